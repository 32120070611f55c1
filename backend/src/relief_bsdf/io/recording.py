"""Goniophotometer recordings (`recording.csv`) and sample descriptions (`sample.toml`).

Both formats are fixed by ../shared/formats.md; the readers here are strict: a file
that breaks the contract raises `InputError` naming the file, the line (CSV) or the
key (TOML) and what was expected.  Nothing is guessed silently.

recording.csv
    UTF-8.  Lines starting with ``#`` are comments; the first line must be exactly
    ``# relief-recording/1``.  Then one header line with exactly the columns
    ``wavelength_nm,theta_i_deg,phi_i_deg,side,theta_s_deg,phi_s_deg,bsdf_sr,sigma_sr``
    and one row per measured point.  Blank lines are ignored.  Checks per row:
    wavelength > 0; theta_i in [0, 90); theta_s in [0, 90]; azimuths in [0, 360);
    side ``R`` or ``T``; bsdf finite and >= 0; sigma empty (unknown -> NaN) or
    finite and >= 0.  Two rows with the same first six columns are an error.

sample.toml
    ``format = "relief-sample/1"`` and the tables ``[plate]``, ``[relief]``,
    ``[instrument]``, ``[recording]``.  Required: ``plate.thickness_mm``, exactly one
    of ``plate.refractive_index`` / ``plate.cauchy``, ``plate.rough_face``,
    ``relief.file``, ``instrument.detector_half_angle_deg``, ``recording.file``.
    Optional with defaults: ``plate.absorption_per_mm`` (None = not known),
    ``instrument.polarization`` ("unpolarized").  File paths are relative to the
    toml file.  UTF-8 with or without a byte-order mark.

    ``recording.file`` is one path or a non-empty list of paths: recording.csv files and / or
    measured plate BSDF files (RPC Photonics text, measured IS-BSDF), each recognised by its
    content and read by io.measured (`Sample.load_recording`).  ``recording.relative_sigma``
    (optional, in (0, 1]): the 1-sigma relative uncertainty of rows whose file states none
    (default: io.measured.DEFAULT_RELATIVE_SIGMA for measured files; recording.csv rows keep
    the fallback of `Recording.with_sigma_fallback`).  ``recording.wavelength_nm`` (optional,
    in [100, 20000] nm): the vacuum wavelength of measured files that do not state theirs
    (RPC Photonics files never do); a file that states another one is an error.

    Plausible ranges (outside them the description is refused as a typo, exit 2, rather
    than simulated into NaN): ``plate.thickness_mm`` in [0.01, 1000] (below 10 um the
    plate is a thin film whose interference the incoherent plate model ignores);
    ``plate.refractive_index`` (and a Cauchy index between 380 and 1000 nm) in
    [1.05, 5] (transparent solids: aerogels ~1.05 up to germanium ~4 in the infrared;
    n = 1 has no boundary at all); ``instrument.detector_half_angle_deg`` in
    [0.01, 45) (a cone below 0.01 deg collects a solid angle below 1e-7 sr: no
    goniophotometer integrates that little light; the plate model's detector takes cones
    below 45 deg).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.io.atomic import write_text_atomic
from relief_bsdf.errors import InputError
from relief_bsdf.core.index import CauchyIndex, ConstantIndex, IndexModel, Material
from relief_bsdf.surface.preparation import ReliefOptions

RECORDING_MAGIC = "# relief-recording/1"
RECORDING_COLUMNS = ("wavelength_nm", "theta_i_deg", "phi_i_deg", "side",
                     "theta_s_deg", "phi_s_deg", "bsdf_sr", "sigma_sr")
SAMPLE_FORMAT = "relief-sample/1"
# unknown sigma_sr -> Recording.with_sigma_fallback(): 3 % of the value plus a floor
SIGMA_FALLBACK_REL = 0.03
SIGMA_FALLBACK_FLOOR_REL = 1e-3
SIGMA_FALLBACK_FLOOR_MIN_SR = 1e-6


# ====================================================================== recording


def sigma_with_fallback(bsdf_sr: Any, sigma_sr: Any, rel: float = SIGMA_FALLBACK_REL,
                        floor_rel: float = SIGMA_FALLBACK_FLOOR_REL,
                        floor_min_sr: float = SIGMA_FALLBACK_FLOOR_MIN_SR) -> np.ndarray:
    """sigma per row with every unknown one (None, NaN, <= 0) replaced by the fallback of
    `Recording.with_sigma_fallback` (the one definition)."""
    y = np.abs(np.asarray(bsdf_sr, float))
    sig = np.full(y.shape, np.nan) if sigma_sr is None else np.asarray(sigma_sr, float).copy()
    bad = ~np.isfinite(sig) | (sig <= 0)
    if bad.any():
        floor = max(floor_rel * float(np.max(y)) if y.size else floor_rel, floor_min_sr)
        sig[bad] = np.sqrt((rel * y[bad]) ** 2 + floor**2)
    return sig


@dataclass
class Recording:
    """Measured (or simulated) BSDF values, one entry per row of recording.csv.

    All arrays have the same length.  Angles in degrees in the frame of formats.md;
    `bsdf_sr` is the Nicodemus BSDF in 1/sr (not cosine-corrected); `sigma_sr` its
    1-sigma uncertainty, NaN where unknown.
    """

    wavelength_nm: np.ndarray
    theta_i_deg: np.ndarray
    phi_i_deg: np.ndarray
    side: np.ndarray
    theta_s_deg: np.ndarray
    phi_s_deg: np.ndarray
    bsdf_sr: np.ndarray
    sigma_sr: np.ndarray
    path: Path | None = None
    comments: list[str] = field(default_factory=list)

    _FLOAT_FIELDS = ("wavelength_nm", "theta_i_deg", "phi_i_deg", "theta_s_deg", "phi_s_deg",
                     "bsdf_sr", "sigma_sr")

    def __post_init__(self) -> None:
        for name in self._FLOAT_FIELDS:
            setattr(self, name, np.asarray(getattr(self, name), dtype=float).reshape(-1))
        self.side = np.asarray(self.side, dtype="<U1").reshape(-1)
        n = len(self.wavelength_nm)
        for name in self._FLOAT_FIELDS + ("side",):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Recording: column {name} has {len(getattr(self, name))} entries, expected {n}")
        if self.path is not None:
            self.path = Path(self.path)

    def __len__(self) -> int:
        return len(self.wavelength_nm)

    def subset(self, mask: Any) -> "Recording":
        """Rows selected by a boolean mask or an index array (same path and comments)."""
        sel = np.asarray(mask)
        return Recording(**{name: getattr(self, name)[sel] for name in self._FLOAT_FIELDS + ("side",)},
                         path=self.path, comments=list(self.comments))

    def with_values(self, bsdf_sr: Any, sigma_sr: Any = None) -> "Recording":
        """Same rows (geometry), new BSDF values; sigma unknown (NaN) unless given."""
        b = np.asarray(bsdf_sr, dtype=float).reshape(-1)
        if len(b) != len(self):
            raise ValueError(f"with_values: {len(b)} values for {len(self)} rows")
        s = np.full(len(self), np.nan) if sigma_sr is None else np.broadcast_to(
            np.asarray(sigma_sr, dtype=float), b.shape).copy()
        fields = {name: getattr(self, name).copy() for name in self._FLOAT_FIELDS + ("side",)}
        fields.update(bsdf_sr=b, sigma_sr=s)
        return Recording(**fields, path=None, comments=list(self.comments))

    def with_sigma_fallback(self, rel: float = SIGMA_FALLBACK_REL,
                            floor_rel: float = SIGMA_FALLBACK_FLOOR_REL,
                            floor_min_sr: float = SIGMA_FALLBACK_FLOOR_MIN_SR) -> "Recording":
        """Same rows, every unknown sigma (NaN, or <= 0) replaced by the documented fallback.

        A fit or a diagnosis weights each row by 1 / sigma^2, so it needs a finite,
        positive sigma everywhere.  Where the recording gives none, the fallback is a
        relative error plus a floor, added in quadrature:
            sigma = sqrt((rel |bsdf|)^2 + floor^2),
            floor = max(floor_rel * max |bsdf| (over all rows), floor_min_sr)
        (defaults 3 %, 1e-3 of the peak, 1e-6 1/sr: a typical goniophotometer's
        relative repeatability, and a dark-signal floor so zero readings keep a finite
        weight).  Known sigmas are kept unchanged; the result is a new Recording (same
        path and comments), this one is not modified.
        """
        sig = sigma_with_fallback(self.bsdf_sr, self.sigma_sr, rel, floor_rel, floor_min_sr)
        fields = {name: getattr(self, name).copy() for name in self._FLOAT_FIELDS + ("side",)}
        fields["sigma_sr"] = sig
        return Recording(**fields, path=self.path, comments=list(self.comments))

    # small conveniences for summaries
    def incidences(self) -> list[tuple[float, float]]:
        """Distinct (theta_i, phi_i) pairs, sorted."""
        pairs = np.unique(np.stack([self.theta_i_deg, self.phi_i_deg], axis=1), axis=0)
        return [(float(a), float(b)) for a, b in pairs]

    def summary(self) -> dict:
        return {"kind": "recording", "path": str(self.path) if self.path else None, "rows": len(self),
                "wavelengths_nm": sorted({float(w) for w in self.wavelength_nm}),
                "incidences_deg": [list(p) for p in self.incidences()],
                "sides": sorted({str(s) for s in self.side}),
                "rows_per_side": {s: int(np.sum(self.side == s)) for s in ("R", "T")},
                "sigma_known_fraction": float(np.mean(np.isfinite(self.sigma_sr))) if len(self) else 0.0,
                "bsdf_range_sr": [float(self.bsdf_sr.min()), float(self.bsdf_sr.max())] if len(self) else None}


def _parse_float(text: str, where: str, column: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(where, f"column {column}: {text.strip()!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(where, f"column {column}: {text.strip()!r} is not a finite number")
    return v


def _read_bytes(path: Path, what: str) -> bytes:
    """The file's bytes, or an InputError naming the file ("<what> file not found", ...)."""
    if path.is_dir():
        raise InputError(path, f"is a folder; expected a {what} file")
    if path.exists() and not path.is_file():
        raise InputError(path, f"not a regular file (a FIFO, socket or device?); expected a {what} file")
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, f"{what} file not found") from None
    except OSError as e:
        raise InputError(path, f"cannot read {what} file: {e.strerror or e}") from None


def read_recording(path: str | Path) -> Recording:
    """Read a recording.csv strictly (see module docstring for every check)."""
    path = Path(path)
    raw = _read_bytes(path, "recording")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(path, f"not UTF-8 text (byte {e.start}); a recording.csv is UTF-8") from None
    lines = text.splitlines()
    if not lines or not text.strip():
        raise InputError(path, f"empty file; expected first line {RECORDING_MAGIC!r}, a header and data rows")
    if lines[0].strip() != RECORDING_MAGIC:
        raise InputError(f"{path}:1", f"first line must be {RECORDING_MAGIC!r}, got {lines[0][:60]!r}")

    comments: list[str] = []
    header_seen = False
    cols: list[list[float]] = [[] for _ in range(7)]
    sides: list[str] = []
    linenos: list[int] = []
    seen: dict[tuple, int] = {}
    expected_header = ",".join(RECORDING_COLUMNS)
    for lineno, line in enumerate(lines[1:], start=2):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s[1:].strip())
            continue
        where = f"{path}:{lineno}"
        if not header_seen:
            got = [c.strip() for c in s.split(",")]
            if tuple(got) != RECORDING_COLUMNS:
                raise InputError(where, f"header must be exactly {expected_header!r}, got {s[:120]!r}")
            header_seen = True
            continue
        cells = s.split(",")
        if len(cells) != 8:
            raise InputError(where, f"expected 8 comma-separated cells ({expected_header}), got {len(cells)}")
        w, ti, pi = (_parse_float(cells[k], where, RECORDING_COLUMNS[k]) for k in range(3))
        side = cells[3].strip()
        if side not in ("R", "T"):
            raise InputError(where, f"column side: {side!r} must be 'R' (reflected) or 'T' (transmitted)")
        ts, ps, f = (_parse_float(cells[k], where, RECORDING_COLUMNS[k]) for k in (4, 5, 6))
        sig_txt = cells[7].strip()
        sig = math.nan if sig_txt == "" else _parse_float(sig_txt, where, "sigma_sr")
        if w <= 0:
            raise InputError(where, f"column wavelength_nm: {w:g} must be > 0 (vacuum wavelength in nm)")
        if not 0 <= ti < 90:
            raise InputError(where, f"column theta_i_deg: {ti:g} outside [0, 90)")
        if not 0 <= ts <= 90:
            raise InputError(where, f"column theta_s_deg: {ts:g} outside [0, 90]")
        for name, v in (("phi_i_deg", pi), ("phi_s_deg", ps)):
            if not 0 <= v < 360:
                raise InputError(where, f"column {name}: {v:g} outside [0, 360)")
        if f < 0:
            raise InputError(where, f"column bsdf_sr: {f:g} is negative (a BSDF is >= 0)")
        if sig == sig and sig < 0:
            raise InputError(where, f"column sigma_sr: {sig:g} is negative (leave empty when unknown)")
        key = (w, ti, pi, side, ts, ps)
        if key in seen:
            raise InputError(where, f"duplicate row: same wavelength, incidence, side and scatter direction "
                                    f"as line {seen[key]}")
        seen[key] = lineno
        for k, v in enumerate((w, ti, pi, ts, ps, f, sig)):
            cols[k].append(v)
        sides.append(side)
        linenos.append(lineno)
    if not header_seen:
        raise InputError(path, f"no header line; expected {expected_header!r}")
    if not sides:
        raise InputError(path, "the recording has a header but no data rows")
    arr = [np.asarray(c, dtype=float) for c in cols]
    return Recording(wavelength_nm=arr[0], theta_i_deg=arr[1], phi_i_deg=arr[2],
                     side=np.asarray(sides, dtype="<U1"), theta_s_deg=arr[3], phi_s_deg=arr[4],
                     bsdf_sr=arr[5], sigma_sr=arr[6], path=path, comments=comments)


def _fmt(v: float) -> str:
    return repr(float(v))


def write_recording(path: str | Path, rec: Recording, comments: Any = ()) -> Path:
    """Write `rec` as recording.csv (atomically); returns the path.

    Comment lines written after the format line: `comments` if given, else
    `rec.comments`.  Numbers are written with full double precision (shortest
    round-trip representation), so reading back gives identical values.  Rows
    violating the contract (negative BSDF, angles out of range, duplicates) raise
    ValueError: a writer must not produce a file its reader refuses.
    """
    path = Path(path)
    n = len(rec)
    bad = ~np.isfinite(rec.bsdf_sr) | (rec.bsdf_sr < 0)
    if bad.any():
        raise ValueError(f"write_recording: row {int(np.argmax(bad))} has BSDF {rec.bsdf_sr[bad][0]!r} "
                         "(must be finite and >= 0)")
    if not np.all(np.isin(rec.side, ("R", "T"))):
        raise ValueError("write_recording: side must be 'R' or 'T'")
    lines = [RECORDING_MAGIC]
    for c in (list(comments) if comments else list(rec.comments)):
        for part in str(c).splitlines() or [""]:
            lines.append(f"# {part}".rstrip())
    lines.append(",".join(RECORDING_COLUMNS))
    for k in range(n):
        sig = rec.sigma_sr[k]
        lines.append(",".join((_fmt(rec.wavelength_nm[k]), _fmt(rec.theta_i_deg[k]), _fmt(rec.phi_i_deg[k]),
                               str(rec.side[k]), _fmt(rec.theta_s_deg[k]), _fmt(rec.phi_s_deg[k]),
                               _fmt(rec.bsdf_sr[k]), "" if not np.isfinite(sig) else _fmt(sig))))
    keys = np.stack([rec.wavelength_nm, rec.theta_i_deg, rec.phi_i_deg, (rec.side == "T").astype(float),
                     rec.theta_s_deg, rec.phi_s_deg], axis=1) if n else np.zeros((0, 6))
    if n and len(np.unique(keys, axis=0)) != n:
        raise ValueError("write_recording: duplicate rows (same first six columns)")
    return write_text_atomic(path, "\n".join(lines) + "\n")


# ====================================================================== sample.toml

#: plausible ranges of sample.toml values (see the module doc for why)
THICKNESS_RANGE_MM = (0.01, 1000.0)
INDEX_RANGE = (1.05, 5.0)
DETECTOR_HALF_ANGLE_RANGE_DEG = (0.01, 45.0)


@dataclass
class PlateSpec:
    """The solid plate: thickness, bulk index, which face carries the relief, absorption."""

    thickness_mm: float
    index: IndexModel
    rough_face: str                     # "front" (lit face) or "back"
    absorption_per_mm: float | None     # None = not known


@dataclass
class InstrumentSpec:
    """Goniophotometer: detector acceptance half-angle and source polarisation."""

    detector_half_angle_deg: float
    polarization: str                   # "unpolarized", "s" or "p"

    @property
    def detector_solid_angle_sr(self) -> float:
        """Solid angle of the detector's acceptance cone, 2 pi (1 - cos a)."""
        return 2 * math.pi * (1 - math.cos(math.radians(self.detector_half_angle_deg)))


@dataclass
class Sample:
    """A sample description: plate, relief file, instrument and recording file."""

    path: Path
    plate: PlateSpec
    relief_path: Path
    instrument: InstrumentSpec
    recording_path: Path
    #: [relief] periodic / fill_holes (surface.preparation): what to do to the map before use
    relief_options: ReliefOptions = field(default_factory=ReliefOptions)
    #: every recording file ([recording] file: one path or a list); the first is `recording_path`
    recording_paths: tuple[Path, ...] = ()
    #: [recording] relative_sigma (None: each reader's documented default)
    relative_sigma: float | None = None
    #: [recording] wavelength_nm: wavelength of measured files that state none (None: not given)
    recording_wavelength_nm: float | None = None

    def __post_init__(self) -> None:
        if not self.recording_paths:
            self.recording_paths = (Path(self.recording_path),)
        self.recording_paths = tuple(Path(p) for p in self.recording_paths)
        self.recording_path = self.recording_paths[0]

    def load_recording(self) -> Recording:
        """The rows of every recording file (recording.csv and / or measured plate files, by content;
        io.measured.read_recording_files), with the sample's relative_sigma and wavelength."""
        from relief_bsdf.io.measured import read_recording_files
        return read_recording_files(self.recording_paths, wavelength_nm=self.recording_wavelength_nm,
                                    relative_sigma=self.relative_sigma)

    @property
    def material(self) -> Material:
        """Air (n = 1) outside, the plate's index inside."""
        return Material(inside=self.plate.index)

    def summary(self) -> dict:
        return {"kind": "sample", "path": str(self.path),
                "plate": {"thickness_mm": self.plate.thickness_mm, "index": self.plate.index.describe(),
                          "rough_face": self.plate.rough_face, "absorption_per_mm": self.plate.absorption_per_mm},
                "relief": str(self.relief_path),
                "relief_options": {"periodic": self.relief_options.periodic,
                                   "fill_holes": self.relief_options.fill_holes},
                "instrument": {"detector_half_angle_deg": self.instrument.detector_half_angle_deg,
                               "detector_solid_angle_sr": self.instrument.detector_solid_angle_sr,
                               "polarization": self.instrument.polarization},
                "recording": str(self.recording_path) if len(self.recording_paths) == 1
                else [str(p) for p in self.recording_paths],
                "recording_files": [_recording_file_summary(p) for p in self.recording_paths],
                "relative_sigma": self.relative_sigma, "recording_wavelength_nm": self.recording_wavelength_nm}


def _recording_file_summary(path: Path) -> dict:
    """{"path", "kind"}: what a recording file holds, by content (io.measured.sniff)."""
    from relief_bsdf.io.measured import sniff
    kind = sniff(path) if Path(path).is_file() else None
    return {"path": str(path), "kind": {"recording": "recording.csv", "rpc": "RPC Photonics text",
                                        "is-bsdf": "measured IS-BSDF"}.get(kind, "unknown")}


_SAMPLE_KEYS = {
    "plate": {"thickness_mm", "refractive_index", "cauchy", "rough_face", "absorption_per_mm"},
    "relief": {"file", "periodic", "fill_holes"},
    "instrument": {"detector_half_angle_deg", "polarization"},
    "recording": {"file", "relative_sigma", "wavelength_nm"},
}
#: plausible range of [recording] wavelength_nm (UV to thermal infrared)
RECORDING_WAVELENGTH_RANGE_NM = (100.0, 20000.0)


def _number(d: dict, table: str, key: str, where: Path, required: bool = True) -> float | None:
    if key not in d:
        if required:
            raise InputError(where, f"missing required key {table}.{key}")
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(where, f"key {table}.{key}: expected a number, got {type(v).__name__} {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise InputError(where, f"key {table}.{key}: expected a finite number, got {v!r}")
    return v


def _string(d: dict, table: str, key: str, where: Path, default: str | None = None) -> str:
    if key not in d:
        if default is None:
            raise InputError(where, f"missing required key {table}.{key}")
        return default
    v = d[key]
    if not isinstance(v, str):
        raise InputError(where, f"key {table}.{key}: expected a string, got {type(v).__name__} {v!r}")
    return v


def _sample_from_doc(doc: dict, path: Path, check_files: bool) -> Sample:
    unknown = set(doc) - {"format"} - set(_SAMPLE_KEYS)
    if unknown:
        raise InputError(path, f"unknown key(s) {sorted(unknown)}; expected format, "
                               f"{', '.join('[' + t + ']' for t in _SAMPLE_KEYS)}")
    if "format" not in doc:
        raise InputError(path, f"missing key format (expected format = {SAMPLE_FORMAT!r})")
    if doc["format"] != SAMPLE_FORMAT:
        raise InputError(path, f"key format: expected {SAMPLE_FORMAT!r}, got {doc['format']!r}")
    tables = {}
    for t, allowed in _SAMPLE_KEYS.items():
        if t not in doc:
            raise InputError(path, f"missing table [{t}]")
        if not isinstance(doc[t], dict):
            raise InputError(path, f"key {t}: expected a table [{t}], got {type(doc[t]).__name__}")
        extra = set(doc[t]) - allowed
        if extra:
            raise InputError(path, f"unknown key(s) {', '.join(t + '.' + k for k in sorted(extra))}; "
                                   f"[{t}] accepts {', '.join(sorted(allowed))}")
        tables[t] = doc[t]

    plate = tables["plate"]
    thickness = _number(plate, "plate", "thickness_mm", path)
    lo, hi = THICKNESS_RANGE_MM
    if not lo <= thickness <= hi:
        raise InputError(path, f"key plate.thickness_mm: {thickness:g} is outside the plausible range [{lo:g}, {hi:g}] "
                               "mm of a plate")
    has_n, has_c = "refractive_index" in plate, "cauchy" in plate
    if has_n and has_c:
        raise InputError(path, "keys plate.refractive_index and plate.cauchy are both given; use one")
    if not (has_n or has_c):
        raise InputError(path, "missing required key plate.refractive_index (or plate.cauchy = [A, B_nm2, C_nm4])")
    if has_n:
        n = _number(plate, "plate", "refractive_index", path)
        _check_index(n, path, "plate.refractive_index")
        index: IndexModel = ConstantIndex(n)
    else:
        c = plate["cauchy"]
        if (not isinstance(c, list) or len(c) not in (2, 3)
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in c)):
            raise InputError(path, f"key plate.cauchy: expected [A, B_nm2, C_nm4] (2 or 3 numbers), got {c!r}")
        try:
            index = CauchyIndex(float(c[0]), float(c[1]), float(c[2]) if len(c) == 3 else 0.0)
        except InputError as e:
            raise InputError(path, f"key plate.cauchy: {e.message}") from None
        for wl in (380.0, 1000.0):
            _check_index(float(np.real(index.n(wl))), path, f"plate.cauchy (n at {wl:g} nm)")
    rough = _string(plate, "plate", "rough_face", path)
    if rough not in ("front", "back"):
        raise InputError(path, f"key plate.rough_face: expected \"front\" or \"back\", got {rough!r}")
    absorption = _number(plate, "plate", "absorption_per_mm", path, required=False)
    if absorption is not None and absorption < 0:
        raise InputError(path, f"key plate.absorption_per_mm: must be >= 0, got {absorption:g}")

    inst = tables["instrument"]
    half = _number(inst, "instrument", "detector_half_angle_deg", path)
    lo, hi = DETECTOR_HALF_ANGLE_RANGE_DEG
    if not lo <= half < hi:
        raise InputError(path, f"key instrument.detector_half_angle_deg: {half:g} is outside [{lo:g}, {hi:g}) deg "
                               f"(a detector cone; below {lo:g} deg it collects almost no light)")
    pol = _string(inst, "instrument", "polarization", path, default="unpolarized")
    if pol not in ("unpolarized", "s", "p"):
        raise InputError(path, f"key instrument.polarization: expected \"unpolarized\", \"s\" or \"p\", got {pol!r}")

    base = path.parent
    files = {}
    for t in ("relief", "recording"):
        given = tables[t].get("file")
        if t == "recording" and isinstance(given, list):
            if not given or not all(isinstance(x, str) for x in given):
                raise InputError(path, f"key recording.file: expected a path or a non-empty list of paths, got {given!r}")
            names = given
        else:
            names = [_string(tables[t], t, "file", path)]
        paths = []
        for f in names:
            if not f.strip():
                raise InputError(path, f"key {t}.file: empty path")
            p = Path(f)
            p = p if p.is_absolute() else base / p
            if check_files and not p.is_file():
                what = ("is a folder, not a file" if p.is_dir() else "is not a regular file" if p.exists()
                        else "not found")
                raise InputError(path, f"key {t}.file: {f!r} {what} (looked for {p})")
            paths.append(p)
        files[t] = paths
    rec = tables["recording"]
    rel = _number(rec, "recording", "relative_sigma", path, required=False)
    if rel is not None and not 0 < rel <= 1:
        raise InputError(path, f"key recording.relative_sigma: {rel:g} must be in (0, 1] (a 1-sigma relative "
                               "uncertainty, 0.03 = 3 %)")
    wl = _number(rec, "recording", "wavelength_nm", path, required=False)
    lo, hi = RECORDING_WAVELENGTH_RANGE_NM
    if wl is not None and not lo <= wl <= hi:
        raise InputError(path, f"key recording.wavelength_nm: {wl:g} is outside [{lo:g}, {hi:g}] nm (a vacuum "
                               "wavelength in nm)")
    return Sample(path=path, plate=PlateSpec(thickness, index, rough, absorption), relief_path=files["relief"][0],
                  instrument=InstrumentSpec(half, pol), recording_path=files["recording"][0],
                  recording_paths=tuple(files["recording"]), relative_sigma=rel, recording_wavelength_nm=wl,
                  relief_options=_relief_options(tables["relief"], path))


def _relief_options(relief: dict, path: Path) -> ReliefOptions:
    """[relief] periodic (optional: true / false; omitted = the file's statement, else the wrap-around
    test) and fill_holes (optional, default false): booleans, anything else is an error."""
    for key in ("periodic", "fill_holes"):
        if key in relief and not isinstance(relief[key], bool):
            raise InputError(path, f"key relief.{key}: expected true or false, got {relief[key]!r}")
    return ReliefOptions(fill_holes=relief.get("fill_holes", False), periodic=relief.get("periodic"),
                         stated_by=f"[relief] periodic of {path.name}")


def _check_index(n: float, path: Path, key: str) -> None:
    lo, hi = INDEX_RANGE
    if not lo <= n <= hi:
        raise InputError(path, f"key {key}: refractive index {n:g} is outside the plausible range [{lo:g}, {hi:g}] "
                               "of a transparent plate" + (" (n = 1 is no boundary at all)" if n <= 1 else ""))


def read_sample_doc(path: str | Path) -> dict:
    """The TOML document of a sample.toml as read (not yet validated); InputError naming the file if it
    cannot be read or is not UTF-8 TOML."""
    path = Path(path)
    raw = _read_bytes(path, "sample")
    try:
        return tomllib.loads(raw.decode("utf-8-sig"))
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text; a sample.toml is UTF-8 TOML") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, f"not valid TOML: {e}") from None


def sample_from_doc(doc: dict, path: str | Path, check_files: bool = True) -> Sample:
    """Validate a sample.toml document (`read_sample_doc`) read from `path` into a `Sample`."""
    return _sample_from_doc(doc, Path(path), check_files)


def read_sample(path: str | Path, check_files: bool = True) -> Sample:
    """Read and validate a sample.toml; with `check_files` the relief and recording must exist."""
    path = Path(path)
    return _sample_from_doc(read_sample_doc(path), path, check_files)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (str, Path)):
        s = str(v).replace("\\", "\\\\").replace('"', '\\"')
        return f'"{s}"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ValueError(f"write_sample: cannot write {type(v).__name__} {v!r} as TOML")


def _sample_to_doc(sample: Sample, toml_path: Path) -> dict:
    idx = sample.plate.index
    plate: dict[str, Any] = {"thickness_mm": sample.plate.thickness_mm}
    if isinstance(idx, ConstantIndex):
        if idx.imag:
            raise ValueError("write_sample: sample.toml holds a real refractive index only")
        plate["refractive_index"] = idx.real
    elif isinstance(idx, CauchyIndex):
        plate["cauchy"] = [idx.A, idx.B_nm2, idx.C_nm4]
    else:
        raise ValueError(f"write_sample: index model {type(idx).__name__} has no sample.toml form")
    plate["rough_face"] = sample.plate.rough_face
    if sample.plate.absorption_per_mm is not None:
        plate["absorption_per_mm"] = sample.plate.absorption_per_mm

    def rel(p: Path) -> str:
        p = Path(p)
        try:
            return Path(p).resolve().relative_to(toml_path.parent.resolve()).as_posix()
        except ValueError:
            return str(p.resolve())

    relief: dict[str, Any] = {"file": rel(sample.relief_path)}
    if sample.relief_options.periodic is not None:
        relief["periodic"] = sample.relief_options.periodic
    if sample.relief_options.fill_holes:
        relief["fill_holes"] = True
    return {"format": SAMPLE_FORMAT, "plate": plate, "relief": relief,
            "instrument": {"detector_half_angle_deg": sample.instrument.detector_half_angle_deg,
                           "polarization": sample.instrument.polarization},
            "recording": _recording_doc(sample, rel)}


def _recording_doc(sample: Sample, rel: Any) -> dict:
    """The [recording] table of a Sample (a list of files only when there are several)."""
    paths = [rel(p) for p in sample.recording_paths]
    doc: dict[str, Any] = {"file": paths[0] if len(paths) == 1 else paths}
    if sample.relative_sigma is not None:
        doc["relative_sigma"] = sample.relative_sigma
    if sample.recording_wavelength_nm is not None:
        doc["wavelength_nm"] = sample.recording_wavelength_nm
    return doc


def write_sample(path: str | Path, sample: "Sample | dict") -> Path:
    """Write a sample.toml (atomically) from a `Sample` or a dict shaped like the file.

    The dict form mirrors the TOML: {"plate": {...}, "relief": {"file": ...},
    "instrument": {...}, "recording": {"file": ...}} ("format" is added if absent).
    The content is validated with the reader's rules before writing (the referenced
    files need not exist yet).
    """
    path = Path(path)
    if isinstance(sample, Sample):
        doc = _sample_to_doc(sample, path)
    else:
        doc = {"format": SAMPLE_FORMAT, **{k: (dict(v) if isinstance(v, dict) else v) for k, v in sample.items()}}
        for t in ("relief", "recording"):
            if isinstance(doc.get(t), dict) and isinstance(doc[t].get("file"), Path):
                doc[t]["file"] = doc[t]["file"].as_posix()
            if isinstance(doc.get(t), dict) and isinstance(doc[t].get("file"), (list, tuple)):
                doc[t]["file"] = [f.as_posix() if isinstance(f, Path) else f for f in doc[t]["file"]]
    lines = [f"format = {_toml_value(doc['format'])}"]
    for t in ("plate", "relief", "instrument", "recording"):
        if t not in doc:
            continue
        lines.append("")
        lines.append(f"[{t}]")
        for k, v in doc[t].items():
            lines.append(f"{k} = {_toml_value(v)}")
    extra = set(doc) - {"format", *_SAMPLE_KEYS}
    if extra:
        raise InputError(path, f"unknown key(s) {sorted(extra)} in sample description")
    text = "\n".join(lines) + "\n"
    _sample_from_doc(tomllib.loads(text), path, check_files=False)  # validate before writing
    return write_text_atomic(path, text)
