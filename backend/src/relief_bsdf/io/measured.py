"""Measured plate BSDF files read as recording rows (formats.md, "Measured plate BSDF files").

A goniophotometer's own file of a plate (a diffuser, a frosted or structured sheet) is a
recording: the same rows as `recording.csv` (wavelength_nm, theta_i_deg, phi_i_deg, side,
theta_s_deg, phi_s_deg, bsdf_sr, sigma_sr) in the frame of formats.md.  Two kinds are read,
recognised by their content (not their name):

RPC Photonics text (`sniff` -> "rpc")
    Line 1 starts with ``!!`` (product, incidence, vendor, date), line 2 ``!!BSDF Data``,
    line 3 ``theta_i phi_i`` (degrees), then rows ``theta_s phi_s bsdf`` (degrees, 1/sr) over
    the transmitted hemisphere, a full grid (RPC's files: theta_s 0..85, phi_s 0..359 in
    1-degree steps).  RPC's frame describes the incident beam by its direction of travel and
    measures scatter about the axis behind the sample, so the undeviated ray sits at its own
    (theta_s, phi_s) = (theta_i, phi_i).  In this project's frame every direction points away
    from the sample and the undeviated ray of a plate is (T, theta_i, phi_i + 180); the two
    frames differ by a point inversion (x, y, z) -> (-x, -y, -z), so a reading at RPC's
    (theta_s, phi_s) is the row (T, theta_s, phi_s + 180 mod 360), incidence (theta_i, phi_i)
    unchanged.  The data prove it (tests/backend/io/test_measured.py): the lobe's power
    centroid of ``EDS10 5-0.txt`` and ``EDS10 5-45.txt`` lands 0.06 deg from (T, 5, phi_i + 180)
    in both (the test's bar: 0.2 deg); RPC's azimuths taken literally put it 10 deg away, and no
    fixed mirror of the azimuth (phi -> c - phi) puts both files' lobes there.  RPC's files state
    no wavelength: the caller gives it (``--wavelength-nm``, or ``[recording] wavelength_nm`` of
    sample.toml).
    The 360 readings at theta_s = 0 are repeated readings of one direction (one per azimuth
    of the scan); they are kept as rows, each with its share of the pole's solid angle.

Measured IS-BSDF (Zemax / Radiant tabular ``.bsdf``; `sniff` -> "is-bsdf")
    Parsed by io.isbsdf.read_isbsdf_all (its geometry: ScatterRadial / ScatterAzimuth about
    the block's centre).  ``ScatterType BRDF`` -> side R centred on the mirror direction,
    ``BTDF`` -> side T centred on the undeviated direction (T, theta_i, phi_i + 180): a sample
    measured in air, where OpticStudio's refracted direction is the undeviated one; a file
    written by this project keeps the centring its ``# relief:`` comments state, and an
    untagged BTDF is centred on the refracted direction from 1 into `n_transmitted` when that
    is given (the command line's ``--n``).  One incidence block per AngleOfIncidence and
    SampleRotation (the incidence azimuth phi_i).  Each stored point becomes one row at its own
    direction (no interpolation): PlaneSymmetrical data are mirrored about the plane of
    incidence, an azimuth 360 column equal to 0 is dropped, the radial-0 points (one direction
    for every azimuth) become one row (their mean), directions below the horizon are dropped.
    The wavelength is the file's own: a ``# relief: wavelength_nm`` tag or a header comment
    ``#Wavelength (nm) = 550.0``; a file stating none needs ``--wavelength-nm``.

Uncertainty (neither kind states one):
    sigma = sqrt((relative_sigma * f)^2 + floor^2),
    relative_sigma = 0.03 by default (`DEFAULT_RELATIVE_SIGMA`; sample.toml
    ``[recording] relative_sigma``): the EDS10 files' readings inside the lobe's plateau
    scatter by 1.2-1.5 % between neighbouring azimuths (0.05-0.2 deg apart) and by 3.4-5 %
    between neighbouring polar angles 1 deg apart, the pole's 360 repeated readings by
    0.5-0.8 % (rms); 3 % covers the repeatability and the sample-to-sample structure a model
    of the mean diffuser does not hold.
    floor = the file's own noise level (`noise_floor_sr`): the robust spread (1.4826 x the
    median absolute deviation / sqrt 2) of the differences between neighbouring azimuth
    readings on one ring, over the readings below 1 % of the file's peak.  The EDS10 files
    give 0.8-1.2e-3 1/sr there (their far field reads 1-5e-3 1/sr, their plateau ~23 1/sr),
    so far-field rows keep an honest, finite weight, where the generic fallback of
    recording.csv (1e-3 of the peak, 0.024 1/sr) would drown them.  A file with fewer than
    100 such neighbour pairs takes that generic floor (`SIGMA_FALLBACK_FLOOR_REL` of the peak);
    the floor is never below 1e-6 of the peak.

Integrals (`lobe_summary`) use each row's projected solid angle cos(theta_s) dOmega: the cell
it stands for on the file's own grid (RPC: theta_s cells between mid-points, clipped to the
measured range 0..85 deg, azimuth cells between mid-points; IS-BSDF: the same in the block's
radial / azimuth coordinates about its centre, times cos theta_s at the point).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from relief_bsdf.errors import InputError

DEFAULT_RELATIVE_SIGMA = 0.03
#: readings below this fraction of the peak are "dim": their azimuth neighbours give the noise floor
DIM_FRACTION = 0.01
MIN_NOISE_PAIRS = 100
FLOOR_MIN_REL = 1e-6
#: the power centroid of a lobe is taken over the readings at or above this fraction of its peak
LOBE_FRACTION = 0.5
RPC_MAPPING = ("RPC frame -> project frame: (theta_s, phi_s) -> (T, theta_s, phi_s + 180); incidence unchanged "
               "(RPC's undeviated ray (theta_i, phi_i) becomes the project's (T, theta_i, phi_i + 180))")
_ISBSDF_KEYS = ("Source", "Symmetry", "SpectralContent", "ScatterType", "SampleRotation", "AngleOfIncidence")
_WAVELENGTH_RE = re.compile(r"wavelength\s*\(\s*nm\s*\)\s*[=:]\s*([-+0-9.eE]+)", re.I)
WAVELENGTH_OPTION = "--wavelength-nm"


# ====================================================================== data


@dataclass(frozen=True)
class MeasuredIncidence:
    """The readings of one incidence, in the frame of formats.md (one side)."""

    theta_i_deg: float
    phi_i_deg: float
    side: str                         # "R" or "T"
    theta_s_deg: np.ndarray           # (N,)
    phi_s_deg: np.ndarray             # (N,)
    bsdf_sr: np.ndarray               # (N,)
    weight_sr: np.ndarray             # (N,) projected solid angle cos(theta_s) dOmega of each row's cell
    centre_theta_deg: float           # polar angle of the lobe's nominal centre (mirror / undeviated)
    range_deg: tuple[float, float]    # polar range the file covers (theta_s for RPC, radial for IS-BSDF)


@dataclass(frozen=True)
class MeasuredFile:
    """A measured plate BSDF file: what it states, and its readings per incidence."""

    path: Path
    kind: str                         # "rpc" or "is-bsdf"
    title: str                        # RPC's first line / the IS-BSDF header comments
    wavelength_nm: float | None       # stated by the file (None: not stated)
    incidences: tuple[MeasuredIncidence, ...]
    noise_floor_sr: float
    notes: tuple[str, ...] = field(default=())   # the frame mapping and what was done to the points

    @property
    def rows(self) -> int:
        return int(sum(inc.bsdf_sr.size for inc in self.incidences))

    @property
    def peak_sr(self) -> float:
        return float(max(float(inc.bsdf_sr.max()) if inc.bsdf_sr.size else 0.0 for inc in self.incidences))


# ====================================================================== sniffing


def sniff(path: str | Path) -> str | None:
    """What a file holds, from its first bytes: "recording" (recording.csv), "rpc" (RPC Photonics
    text), "is-bsdf" (Zemax / Radiant tabular), or None."""
    try:
        with open(path, "rb") as f:
            head = f.read(8192)
    except OSError:
        return None
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    lines = text.splitlines()
    if not lines:
        return None
    first = lines[0].strip()
    if first.startswith("# relief-recording"):
        return "recording"
    if first.startswith("!!"):
        return "rpc"
    for line in lines:
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        return "is-bsdf" if s.split()[0] in _ISBSDF_KEYS else None
    return None


def is_measured(path: str | Path) -> bool:
    """Whether `path` is a measured plate file this module reads (RPC text, or an IS-BSDF file
    without this project's ``# relief:`` tags)."""
    kind = sniff(path)
    if kind == "rpc":
        return True
    if kind == "is-bsdf":
        with open(path, "rb") as f:
            head = f.read(8192).decode("utf-8", errors="replace")
        return not any(l.strip().lstrip("#").strip().startswith("relief:") for l in head.splitlines())
    return False


# ====================================================================== cells and noise


def _polar_cells(t_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) edges in radians of the polar cells of sorted sample angles: mid-points between
    neighbours, the first and last cells clipped at the first and last sample (the measured range)."""
    t = np.radians(t_deg)
    mid = 0.5 * (t[1:] + t[:-1])
    lo = np.concatenate([[t[0]], mid])
    hi = np.concatenate([mid, [t[-1]]])
    return lo, hi


def _azimuth_widths(a_deg: np.ndarray) -> np.ndarray:
    """Widths in radians of periodic azimuth cells (mid-points between sorted neighbours, wrapping)."""
    a = np.asarray(a_deg, float)
    if a.size == 1:
        return np.array([2 * math.pi])
    nxt = np.roll(a, -1)
    nxt[-1] += 360.0
    prv = np.roll(a, 1)
    prv[0] -= 360.0
    return np.radians(0.5 * (nxt - prv))


def _noise_floor(grids: list[np.ndarray], peak: float) -> float:
    """Robust noise level from neighbouring azimuth readings on rings (module doc); grids are
    (rings, azimuths) arrays of readings."""
    diffs = []
    dim = DIM_FRACTION * peak
    for g in grids:
        if g.shape[1] < 2:
            continue
        a, b = g, np.roll(g, -1, axis=1)
        m = (a < dim) & (b < dim)
        diffs.append((b - a)[m])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    from relief_bsdf.io.recording import SIGMA_FALLBACK_FLOOR_REL
    if d.size < MIN_NOISE_PAIRS:
        est = SIGMA_FALLBACK_FLOOR_REL * peak
    else:
        est = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
    return float(max(est, FLOOR_MIN_REL * peak, 1e-300))


# ====================================================================== RPC Photonics


def _rpc_numbers(line: str, n: int, where: str, what: str) -> list[float]:
    parts = line.split()
    if len(parts) != n:
        raise InputError(where, f"expected {n} numbers ({what}), got {len(parts)}: {line.strip()[:60]!r}"
                         + (" (truncated file?)" if len(parts) < n else ""))
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise InputError(where, f"expected {n} numbers ({what}), got {line.strip()[:60]!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise InputError(where, f"non-finite number in {line.strip()[:60]!r}")
    return vals


def _read_text(path: Path, what: str) -> str:
    from relief_bsdf.io.recording import _read_bytes
    raw = _read_bytes(path, what)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def read_rpc(path: str | Path) -> MeasuredFile:
    """Read an RPC Photonics BSDF text file strictly (module doc); InputError naming the file and line."""
    path = Path(path)
    lines = _read_text(path, "RPC Photonics BSDF").splitlines()
    if not lines or not lines[0].startswith("!!"):
        raise InputError(f"{path}:1", "not an RPC Photonics BSDF file: line 1 must start with '!!'")
    if len(lines) < 2 or not lines[1].startswith("!!") or "bsdf" not in lines[1].lower():
        raise InputError(f"{path}:2", "expected '!!BSDF Data' on line 2 of an RPC Photonics file")
    if len(lines) < 3 or not lines[2].strip():
        raise InputError(f"{path}:3", "expected 'theta_i phi_i' (degrees) on line 3 (truncated file?)")
    ti, pi = _rpc_numbers(lines[2], 2, f"{path}:3", "theta_i phi_i in degrees")
    if not 0 <= ti < 90:
        raise InputError(f"{path}:3", f"theta_i {ti:g} outside [0, 90) deg")
    if not 0 <= pi < 360:
        raise InputError(f"{path}:3", f"phi_i {pi:g} outside [0, 360) deg")
    rows = []
    last = 3
    for lineno, line in enumerate(lines[3:], start=4):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        t, p, f = _rpc_numbers(line, 3, where, "theta_s phi_s BSDF")
        if not 0 <= t <= 90:
            raise InputError(where, f"theta_s {t:g} outside [0, 90] deg")
        if not 0 <= p < 360:
            raise InputError(where, f"phi_s {p:g} outside [0, 360) deg")
        if f < 0:
            raise InputError(where, f"BSDF {f:g} is negative")
        rows.append((t, p, f))
        last = lineno
    if not rows:
        raise InputError(path, "no data rows after line 3 (theta_s phi_s BSDF expected)")
    arr = np.asarray(rows)
    th, ph = np.unique(arr[:, 0]), np.unique(arr[:, 1])
    it = np.searchsorted(th, arr[:, 0])
    ip = np.searchsorted(ph, arr[:, 1])
    count = np.zeros((th.size, ph.size), int)
    np.add.at(count, (it, ip), 1)
    if np.any(count > 1):
        k = int(np.argmax(count[it, ip] > 1))
        second = [j for j in range(len(rows)) if it[j] == it[k] and ip[j] == ip[k]][1]
        raise InputError(path, f"theta_s {arr[second, 0]:g}, phi_s {arr[second, 1]:g} is read twice "
                               f"(data row {second + 1})")
    if np.any(count == 0):
        raise InputError(f"{path}:{last}", f"the scan is not a full grid: {len(rows)} readings for "
                                          f"{th.size} theta_s x {ph.size} phi_s = {th.size * ph.size} "
                                          "(truncated file?)")
    grid = np.zeros((th.size, ph.size))
    grid[it, ip] = arr[:, 2]
    lo, hi = _polar_cells(th)
    proj = 0.5 * (np.sin(hi) ** 2 - np.sin(lo) ** 2)                   # int cos sin dtheta per ring
    w = proj[:, None] * _azimuth_widths(ph)[None, :]
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    inc = MeasuredIncidence(theta_i_deg=ti, phi_i_deg=pi, side="T", theta_s_deg=TH.ravel().copy(),
                            phi_s_deg=((PH + 180.0) % 360.0).ravel(), bsdf_sr=grid.ravel().copy(),
                            weight_sr=w.ravel(), centre_theta_deg=ti, range_deg=(float(th[0]), float(th[-1])))
    peak = float(grid.max())
    return MeasuredFile(path=path, kind="rpc", title=lines[0].lstrip("!").strip(), wavelength_nm=None,
                        incidences=(inc,), noise_floor_sr=_noise_floor([grid], peak),
                        notes=(RPC_MAPPING,))


# ====================================================================== IS-BSDF


def header_wavelength_nm(comments: Sequence[str]) -> float | None:
    """The wavelength an IS-BSDF file's comments state: ``relief: wavelength_nm = w`` or
    ``Wavelength (nm) = w``; None when none does."""
    for c in comments:
        s = c.strip()
        if s.startswith("relief:") and "=" in s:
            k, v = s[len("relief:"):].split("=", 1)
            if k.strip() == "wavelength_nm":
                try:
                    return float(v)
                except ValueError:
                    return None
    for c in comments:
        m = _WAVELENGTH_RE.search(c)
        if m:
            try:
                v = float(m.group(1))
            except ValueError:
                continue
            return v if v > 0 and math.isfinite(v) else None
    return None


def read_measured_isbsdf(path: str | Path, n_transmitted: float | None = None) -> MeasuredFile:
    """Read a measured IS-BSDF file (module doc) with io.isbsdf's parser."""
    from relief_bsdf.io.isbsdf import TYPE_SIDE, from_specular_coords, read_isbsdf_all, refracted_theta_deg
    path = Path(path)
    blocks = read_isbsdf_all(path)
    incs: list[MeasuredIncidence] = []
    grids: list[np.ndarray] = []
    comments = [c for b in blocks for c in b.comments]
    notes = []
    for b in blocks:
        side = TYPE_SIDE[b.scatter_type]
        if b.relief_tag("incident_from") == "inside":
            raise InputError(path, "a table of light arriving from inside the dielectric (# relief: incident_from "
                                   "= inside): not a plate measured from outside")
        az, rad = b.azimuth_deg.astype(float), b.radial_deg.astype(float)
        data = b.data_per_sr
        if np.any(az < 0) or np.any(az > 360) or np.any(rad < 0) or np.any(rad > 180):
            raise InputError(path, "ScatterAzimuth must lie in [0, 360] and ScatterRadial in [0, 180] deg")
        if b.symmetry == "PlaneSymmetrical":
            if az[0] != 0 or az[-1] != 180:
                raise InputError(path, "PlaneSymmetrical data must cover ScatterAzimuth 0 .. 180 deg")
            inner = az[1:-1][::-1]
            az = np.concatenate([az, 360.0 - inner])
            data = np.concatenate([data, data[:, :, 1:-1, :][:, :, ::-1, :]], axis=2)
            note = "PlaneSymmetrical: azimuths 0..180 mirrored to 180..360"
            if note not in notes:
                notes.append(note)
        if az.size > 1 and abs(az[-1] - az[0] - 360.0) < 1e-9:
            data = data.copy()
            data[:, :, 0] = 0.5 * (data[:, :, 0] + data[:, :, -1])     # the same azimuth twice: one column
            az, data = az[:-1], data[:, :, :-1]
        centring = b.relief_tag("btdf_centre")
        n_pair = (1.0, 1.0)
        if side == "T" and centring != "undeviated":
            if b.relief_tag("n_incident") is not None:
                n_pair = (float(b.relief_tag("n_incident")), float(b.relief_tag("n_transmitted")))
            elif n_transmitted is not None:
                n_pair = (1.0, float(n_transmitted))
        lo, hi = _polar_cells(rad)
        ring = np.cos(lo) - np.cos(hi)                     # int sin r dr per radial cell
        daz = _azimuth_widths(az)
        for p, phi_i in enumerate(b.sample_rotation_deg):
            for i, theta_i in enumerate(b.angle_of_incidence_deg):
                centre = float(theta_i) if side == "R" else float(refracted_theta_deg(theta_i, *n_pair))
                vals = data[p, i]                                          # (A, S)
                grids.append(vals.T)                                       # rings x azimuths
                R, A = np.meshgrid(rad, az)
                th, ph, up = from_specular_coords(centre, float(phi_i), R, A)
                w = np.cos(np.radians(th)) * ring[None, :] * daz[:, None]
                th, ph = np.round(th, 9), np.round(ph, 9) % 360.0
                zero = R == 0.0
                th = np.where(zero, centre, th)
                ph = np.where(zero, (float(phi_i) + 180.0) % 360.0, ph)
                keep = up & (th <= 90.0)
                t_s, p_s, f, ww = th[keep], ph[keep], vals[keep], w[keep]
                key = np.stack([t_s, p_s], axis=1)
                uniq, inv = np.unique(key, axis=0, return_inverse=True)
                inv = inv.reshape(-1)
                cnt = np.bincount(inv, minlength=len(uniq))
                fv = np.bincount(inv, weights=f, minlength=len(uniq)) / cnt
                wv = np.bincount(inv, weights=ww, minlength=len(uniq))
                incs.append(MeasuredIncidence(theta_i_deg=float(theta_i), phi_i_deg=float(phi_i) % 360.0, side=side,
                                              theta_s_deg=uniq[:, 0], phi_s_deg=uniq[:, 1], bsdf_sr=fv,
                                              weight_sr=wv, centre_theta_deg=centre,
                                              range_deg=(float(rad[0]), float(rad[-1]))))
        centre_word = ("mirror direction" if side == "R" else
                       "undeviated direction (T, theta_i, phi_i + 180)" if n_pair[0] == n_pair[1] else
                       f"refracted direction from n {n_pair[0]:g} into n {n_pair[1]:g}")
        notes.append(f"{b.scatter_type} -> side {side}, ScatterRadial measured from the {centre_word}; "
                     "radial-0 points merged into one row, points below the horizon dropped")
    peak = float(max(float(i.bsdf_sr.max()) if i.bsdf_sr.size else 0.0 for i in incs)) if incs else 0.0
    title = "; ".join(c for c in comments if c and not c.startswith("relief:"))[:200]
    return MeasuredFile(path=path, kind="is-bsdf", title=title, wavelength_nm=header_wavelength_nm(comments),
                        incidences=tuple(incs), noise_floor_sr=_noise_floor(grids, peak), notes=tuple(notes))


def read_measured_file(path: str | Path, n_transmitted: float | None = None) -> MeasuredFile:
    """An RPC or IS-BSDF measured file (by content); InputError when it is neither."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    kind = sniff(path)
    if kind == "rpc":
        return read_rpc(path)
    if kind == "is-bsdf":
        return read_measured_isbsdf(path, n_transmitted)
    raise InputError(path, "not a measured BSDF file: expected RPC Photonics text (line 1 starting with '!!') "
                           "or a Zemax/Radiant IS-BSDF file (keywords Source, ScatterType, ...)")


# ====================================================================== rows


#: how a sample.toml gives the wavelength of measured files (the command line's is WAVELENGTH_OPTION)
SAMPLE_WAVELENGTH_KEY = "[recording] wavelength_nm = ... in the sample.toml"


def file_wavelength(mf: MeasuredFile, wavelength_nm: float | None, where: str | Path | None = None,
                    ask: str = WAVELENGTH_OPTION) -> float:
    """The wavelength of the file's rows: its own, else `wavelength_nm`; InputError naming the file and
    how to give it (`ask`: the command line's ``--wavelength-nm`` by default, or the sample.toml key)
    when neither is known, or when both are and differ."""
    if mf.wavelength_nm is not None:
        if wavelength_nm is not None and abs(float(wavelength_nm) - mf.wavelength_nm) > 1e-6 * mf.wavelength_nm:
            raise InputError(where or mf.path, f"the file states {mf.wavelength_nm:g} nm but {wavelength_nm:g} nm "
                                               "was given for it")
        return float(mf.wavelength_nm)
    if wavelength_nm is None:
        what = "an RPC Photonics file" if mf.kind == "rpc" else "the IS-BSDF file"
        raise InputError(where or mf.path, f"{what} does not state its wavelength; give it with {ask}")
    if not (math.isfinite(wavelength_nm) and wavelength_nm > 0):
        raise InputError(WAVELENGTH_OPTION, f"wavelength must be > 0 nm, got {wavelength_nm:g}")
    return float(wavelength_nm)


def measured_sigma(mf: MeasuredFile, bsdf_sr: np.ndarray, relative_sigma: float | None = None) -> np.ndarray:
    """sigma = sqrt((relative_sigma f)^2 + floor^2) (module doc)."""
    rel = DEFAULT_RELATIVE_SIGMA if relative_sigma is None else float(relative_sigma)
    return np.sqrt((rel * np.asarray(bsdf_sr, float)) ** 2 + mf.noise_floor_sr ** 2)


def to_recording(mf: MeasuredFile, wavelength_nm: float | None = None, relative_sigma: float | None = None,
                 ask: str = WAVELENGTH_OPTION):
    """The file's rows as a `Recording` (io.recording), sigma by `measured_sigma`; `ask`: how the
    wavelength is given, named when the file states none and none was given."""
    from relief_bsdf.io.recording import Recording
    wl = file_wavelength(mf, wavelength_nm, ask=ask)
    cols = {k: [] for k in ("theta_i_deg", "phi_i_deg", "side", "theta_s_deg", "phi_s_deg", "bsdf_sr")}
    for inc in mf.incidences:
        n = inc.bsdf_sr.size
        cols["theta_i_deg"].append(np.full(n, inc.theta_i_deg))
        cols["phi_i_deg"].append(np.full(n, inc.phi_i_deg))
        cols["side"].append(np.full(n, inc.side, dtype="<U1"))
        cols["theta_s_deg"].append(inc.theta_s_deg)
        cols["phi_s_deg"].append(inc.phi_s_deg)
        cols["bsdf_sr"].append(inc.bsdf_sr)
    arr = {k: np.concatenate(v) for k, v in cols.items()}
    rel = DEFAULT_RELATIVE_SIGMA if relative_sigma is None else float(relative_sigma)
    comments = [f"read from {mf.path.name} ({'RPC Photonics text' if mf.kind == 'rpc' else 'measured IS-BSDF'})",
                f"wavelength {wl:g} nm ({'stated by the file' if mf.wavelength_nm is not None else 'given'})",
                *mf.notes,
                f"sigma_sr = sqrt(({rel:g} bsdf)^2 + {mf.noise_floor_sr:.3g}^2): the file states no uncertainty "
                "(relative part: relative_sigma; floor: the file's noise between neighbouring dim readings)"]
    return Recording(wavelength_nm=np.full(arr["bsdf_sr"].size, wl), sigma_sr=measured_sigma(mf, arr["bsdf_sr"], rel),
                     path=mf.path, comments=comments, **arr)


def read_measured(path: str | Path, wavelength_nm: float | None = None, relative_sigma: float | None = None,
                  n_transmitted: float | None = None, ask: str = WAVELENGTH_OPTION):
    """A measured plate file (RPC text or IS-BSDF, by content) as a `Recording` (module doc)."""
    return to_recording(read_measured_file(path, n_transmitted), wavelength_nm, relative_sigma, ask)


def read_recording_files(paths: Sequence[str | Path], wavelength_nm: float | None = None,
                         relative_sigma: float | None = None, ask: str = SAMPLE_WAVELENGTH_KEY):
    """One `Recording` from recording.csv files and / or measured plate files (each by content).

    Measured files get `measured_sigma`; recording.csv rows keep their sigma, and the unknown
    ones get the recording fallback with `relative_sigma` when it is given (NaN otherwise, for the
    caller's fallback).  Two files holding the same row (first six columns) are an error, and so is
    an IS-BSDF file this project wrote (a boundary table, not a plate's measurement).
    """
    from relief_bsdf.io.recording import Recording, read_recording, sigma_with_fallback
    parts = []
    for p in paths:
        p = Path(p)
        kind = sniff(p)
        if kind == "is-bsdf" and not is_measured(p):
            raise InputError(p, "an IS-BSDF file written by relief from a boundary table (its '# relief:' "
                                "comments say so), not a measured plate; a recording is a plate's measurement")
        if kind in ("rpc", "is-bsdf"):
            rec = read_measured(p, wavelength_nm, relative_sigma, ask=ask)
        else:
            rec = read_recording(p)
            if relative_sigma is not None and np.any(~np.isfinite(rec.sigma_sr)):
                rec = rec.with_values(rec.bsdf_sr, sigma_with_fallback(rec.bsdf_sr, rec.sigma_sr, rel=relative_sigma))
                rec.path = p
        parts.append(rec)
    if len(parts) == 1:
        return parts[0]
    names = Recording._FLOAT_FIELDS + ("side",)
    fields = {k: np.concatenate([getattr(r, k) for r in parts]) for k in names}
    src = np.concatenate([np.full(len(r), k) for k, r in enumerate(parts)])
    key = np.stack([fields["wavelength_nm"], fields["theta_i_deg"], fields["phi_i_deg"],
                    (fields["side"] == "T").astype(float), fields["theta_s_deg"], fields["phi_s_deg"]], axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = first[np.argmax(counts > 1)]
        same = np.nonzero(np.all(key == key[dup], axis=1))[0]
        a, b = (Path(paths[src[j]]).name for j in same[:2])
        raise InputError(paths[src[same[1]]], f"the same row (wavelength {key[dup, 0]:g} nm, incidence "
                                              f"{key[dup, 1]:g}/{key[dup, 2]:g} deg, scatter {key[dup, 4]:g}/"
                                              f"{key[dup, 5]:g} deg) is in {a} and {b}")
    comments = [c for r in parts for c in r.comments]
    return Recording(**fields, path=Path(paths[0]), comments=comments)


# ====================================================================== summaries


def _unit(theta_deg: np.ndarray, phi_deg: np.ndarray) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b)))))


def lobe_summary(inc: MeasuredIncidence) -> dict:
    """The hemispherical integral into the measured range, the lobe's peak and power centroid.

    integral = sum f cos(theta_s) dOmega over the rows (R or T into the file's range); peak = the
    99.5th percentile of the readings (a single hot reading does not set it); the centroid is the
    power-weighted mean direction of the readings at or above half that peak, in the side's own
    frame; `offset_deg` is its angle to the nominal centre (mirror for R, undeviated / refracted for T).
    """
    f, w = inc.bsdf_sr, inc.weight_sr
    integral = float(np.sum(f * w))
    peak = float(np.percentile(f, 99.5)) if f.size else 0.0
    core = f >= LOBE_FRACTION * peak
    d = _unit(inc.theta_s_deg[core], inc.phi_s_deg[core])
    pw = (f * w)[core]
    out = {"theta_i_deg": inc.theta_i_deg, "phi_i_deg": inc.phi_i_deg, "side": inc.side, "rows": int(f.size),
           "range_deg": list(inc.range_deg), "integral": integral, "peak_sr": peak}
    nominal = _unit(inc.centre_theta_deg, (inc.phi_i_deg + 180.0) % 360.0)
    out["nominal_deg"] = [float(inc.centre_theta_deg), float((inc.phi_i_deg + 180.0) % 360.0)]
    if pw.sum() > 0:
        c = (d * pw[:, None]).sum(axis=0)
        c /= np.linalg.norm(c)
        out["centroid_deg"] = [float(np.degrees(np.arccos(np.clip(c[2], -1, 1)))),
                               float(np.degrees(np.arctan2(c[1], c[0])) % 360.0)]
        out["offset_deg"] = _angle_deg(c, nominal)
    else:
        out["centroid_deg"] = None
        out["offset_deg"] = None
    return out


def measured_info(path: str | Path) -> dict:
    """The JSON object of `relief info` for a measured file."""
    mf = read_measured_file(path)
    lobes = [lobe_summary(inc) for inc in mf.incidences]
    return {"kind": "measured", "format": "rpc-photonics" if mf.kind == "rpc" else "is-bsdf",
            "path": str(mf.path), "title": mf.title,
            "wavelength_nm": mf.wavelength_nm,
            "wavelength": ("stated by the file" if mf.wavelength_nm is not None
                           else f"not stated: give it with {WAVELENGTH_OPTION} (or {SAMPLE_WAVELENGTH_KEY})"),
            "sides": sorted({inc.side for inc in mf.incidences}),
            "incidences_deg": [[inc.theta_i_deg, inc.phi_i_deg] for inc in mf.incidences],
            "rows": mf.rows, "peak_sr": mf.peak_sr, "noise_floor_sr": mf.noise_floor_sr,
            "relative_sigma": DEFAULT_RELATIVE_SIGMA, "frame": list(mf.notes), "lobes": lobes}


def print_measured_info(d: dict) -> None:
    """`relief info` text for a measured file."""
    kind = "RPC Photonics text" if d["format"] == "rpc-photonics" else "measured IS-BSDF"
    print(f"measured BSDF {d['path']}  ({kind})")
    if d["title"]:
        print(f"  header     {d['title']}")
    wl = f"{d['wavelength_nm']:g} nm (stated)" if d["wavelength_nm"] is not None else d["wavelength"]
    print(f"  wavelength {wl}")
    print(f"  rows       {d['rows']} (side {', '.join(d['sides'])}), {len(d['incidences_deg'])} incidence(s) "
          f"(theta_i, phi_i) deg: {', '.join(f'({t:g}, {p:g})' for t, p in d['incidences_deg'][:12])}"
          + (" ..." if len(d["incidences_deg"]) > 12 else ""))
    print(f"  sigma      none stated: {d['relative_sigma']:g} x BSDF (+) noise floor {d['noise_floor_sr']:.3g} 1/sr")
    for note in d["frame"]:
        print(f"  frame      {note}")
    print("  per incidence: integral = sum f cos(theta_s) dOmega over the measured range (R or T); lobe = power "
          "centroid of the readings >= half the peak; offset = its angle to the mirror / undeviated direction")
    print(f"    {'theta_i':>7s} {'phi_i':>6s} {'side':>4s} {'range/deg':>10s} {'integral':>8s} {'peak/sr':>9s} "
          f"{'centroid (theta, phi)':>22s} {'offset':>7s}")
    for lb in d["lobes"]:
        c = lb["centroid_deg"]
        cen = f"({c[0]:.2f}, {c[1]:.2f})" if c else "n/a"
        off = f"{lb['offset_deg']:.2f}" if lb["offset_deg"] is not None else "n/a"
        rng = f"{lb['range_deg'][0]:g}-{lb['range_deg'][1]:g}"
        print(f"    {lb['theta_i_deg']:7.4g} {lb['phi_i_deg']:6.4g} {lb['side']:>4s} {rng:>10s} {lb['integral']:8.4f} "
              f"{lb['peak_sr']:9.4g} {cen:>22s} {off:>7s}")


# ====================================================================== tables, plots, export


def measured_table(mf: MeasuredFile, wavelength_nm: float | None = None):
    """An RPC file as a `BsdfTable` (bsdf.table) on 1-degree cells, theta_s 0..90 by phi_s 0..360:
    cell averages of the readings' linear interpolant (periodic in azimuth) in the project's frame
    (side T; side R zero), zero beyond the measured range.  A plate's BSDF, light from
    outside, so it can be plotted beside a reconstruction, exported and baked like any table."""
    from relief_bsdf.bsdf.table import BsdfTable
    if mf.kind != "rpc":
        raise InputError(mf.path, "only RPC Photonics files are turned into tables here (IS-BSDF: io.tables)")
    wl = file_wavelength(mf, wavelength_nm)
    (inc,) = mf.incidences
    th = np.unique(inc.theta_s_deg)
    ph = np.unique(inc.phi_s_deg)
    grid = np.zeros((th.size, ph.size))
    grid[np.searchsorted(th, inc.theta_s_deg), np.searchsorted(ph, inc.phi_s_deg)] = inc.bsdf_sr
    te, pe = np.linspace(0.0, 90.0, 91), np.linspace(0.0, 360.0, 361)
    tc, pc = 0.5 * (te[1:] + te[:-1]), 0.5 * (pe[1:] + pe[:-1])
    # periodic azimuth: close the circle, then interpolate each ring at the cell centres
    php = np.concatenate([ph[-1:] - 360.0, ph, ph[:1] + 360.0])
    gp = np.concatenate([grid[:, -1:], grid, grid[:, :1]], axis=1)
    rings = np.stack([np.interp(pc, php, gp[k]) for k in range(th.size)])           # (theta, pc)
    # cell averages over theta_s (8 sub-points weighted by the projected solid angle sin cos), so the
    # table holds the integral of the readings' linear interpolant; in azimuth the average of the linear
    # interpolant over a cell between two readings is its value at the centre
    inside = tc <= inc.range_deg[1]
    sub = te[:-1, None] + (np.arange(8) + 0.5)[None, :] / 8.0 * np.diff(te)[:, None]     # (cells, 8)
    wsub = np.sin(np.radians(2.0 * sub))
    cells = np.zeros((tc.size, pc.size))
    for j in range(pc.size):
        v = np.interp(sub, th, rings[:, j])
        cells[:, j] = np.sum(v * wsub, axis=1) / np.sum(wsub, axis=1)
    cells[~inside] = 0.0
    values = np.zeros((1, 1, 1, 2, tc.size, pc.size))
    values[0, 0, 0, 1] = cells
    return BsdfTable(wavelength_nm=[wl], theta_i_deg=[inc.theta_i_deg], phi_i_deg=[inc.phi_i_deg],
                     theta_s_edges_deg=te, phi_s_edges_deg=pe, values_per_sr=values, incident_from="outside",
                     method="measured plate (RPC Photonics)",
                     metadata={"imported_from": [str(mf.path)], "frame": RPC_MAPPING,
                               "note": f"a plate's BSDF measured in air; zero beyond theta_s {inc.range_deg[1]:g} deg "
                                       "(not measured)"})


def plot_tables(paths: Sequence[str | Path], wavelength_nm: float | None = None, n: float | None = None,
                incident_from: str | None = None) -> list:
    """The tables `relief plot` draws (io.tables.pick_table of each file).  A file that states no
    wavelength (RPC text, an IS-BSDF file without one) takes `wavelength_nm`, else the first other
    file's first wavelength (it is plotted beside that file); alone and without `wavelength_nm`, an
    IS-BSDF file asks for --wavelength-nm."""
    from relief_bsdf.io.tables import pick_table, read_table_file
    later = [_states_no_wavelength(p) for p in paths]
    got: dict[int, Any] = {}
    for k, p in enumerate(paths):
        if not later[k]:
            got[k] = pick_table(read_table_file(p, wavelength_nm=wavelength_nm, n=n), incident_from, p)
    wl = wavelength_nm
    if wl is None and got:
        wl = float(got[min(got)].wavelength_nm[0])
    for k, p in enumerate(paths):
        if later[k]:
            got[k] = pick_table(read_table_file(p, wavelength_nm=wl, n=n), incident_from, p)
    return [got[k] for k in range(len(paths))]


def _states_no_wavelength(path: str | Path) -> bool:
    """An RPC file, or an IS-BSDF file whose header comments state no wavelength."""
    kind = sniff(path)
    if kind == "rpc":
        return True
    if kind != "is-bsdf":
        return False
    with open(path, "rb") as f:
        head = f.read(8192).decode("utf-8", errors="replace").splitlines()
    comments = [l.strip()[1:].strip() for l in head if l.strip().startswith("#")]
    return header_wavelength_nm(comments) is None


def _cut(inc: MeasuredIncidence, phi_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(signed theta_s, f) of the readings on the half-planes phi and phi + 180 (phi_s nearest on the
    file's grid; the pole's readings once each): positive toward phi, negative toward phi + 180."""
    ph = np.unique(inc.phi_s_deg)
    def nearest(a):
        d = np.abs((ph - a + 180.0) % 360.0 - 180.0)
        return ph[int(np.argmin(d))]
    a, b = nearest(phi_deg % 360.0), nearest((phi_deg + 180.0) % 360.0)
    ma, mb = inc.phi_s_deg == a, inc.phi_s_deg == b
    s = np.concatenate([inc.theta_s_deg[ma], -inc.theta_s_deg[mb]])
    f = np.concatenate([inc.bsdf_sr[ma], inc.bsdf_sr[mb]])
    o = np.argsort(s, kind="stable")
    return s[o], f[o]


def measured_figure(mf: MeasuredFile):
    """The measured lobe of each incidence as the file holds it (its own readings, no
    interpolation): left, the cuts along the sample's axes, phi_s 0 / 180 and 90 / 270 (signed
    theta_s: negative toward 180 resp. 270), log scale, the undeviated / mirror direction marked;
    right, the polar map of the readings (project frame)."""
    import textwrap

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    incs = list(mf.incidences)[:6]
    fig = plt.figure(figsize=(12.0, 4.8 * len(incs) + 0.6))
    gs = fig.add_gridspec(len(incs), 2, width_ratios=[1.6, 1.0])
    for r, inc in enumerate(incs):
        lb = lobe_summary(inc)
        ax = fig.add_subplot(gs[r, 0])
        for phi, col in ((0.0, "C0"), (90.0, "C3")):
            s, f = _cut(inc, phi)
            pos = f > 0
            ax.plot(s[pos], f[pos], ".-", color=col, markersize=3, linewidth=0.8,
                    label=f"phi_s {phi:g} (theta_s > 0) / {phi + 180:g} (theta_s < 0)")
        # the nominal direction (side, centre, phi_i + 180) projected on each cut's plane
        nom = (inc.phi_i_deg + 180.0) % 360.0
        sc_ = math.sin(math.radians(inc.centre_theta_deg))
        for trig, col in ((math.cos, "C0"), (math.sin, "C3")):
            ax.axvline(math.degrees(math.asin(sc_ * trig(math.radians(nom)))), color=col, linestyle=":",
                       linewidth=0.9)
        ax.plot([], [], "k:", label=f"{'mirror' if inc.side == 'R' else 'undeviated'} direction (theta_s "
                                    f"{inc.centre_theta_deg:g}, phi_s {nom:g} deg) projected on each cut")
        ax.set_yscale("log")
        ax.set_xlim(-90, 90)
        ax.set_xlabel("signed scatter angle theta_s (deg)", fontsize=8)
        ax.set_ylabel("BSDF f (1/sr, not cosine-corrected)", fontsize=8)
        c = lb["centroid_deg"]
        ax.set_title(f"{mf.path.name}: theta_i {inc.theta_i_deg:g}, phi_i {inc.phi_i_deg:g} deg, side {inc.side}; "
                     f"{inc.side} into {inc.range_deg[0]:g}-{inc.range_deg[1]:g} deg = {lb['integral']:.4f}"
                     + (f"\nlobe power centroid (theta_s, phi_s) = ({c[0]:.2f}, {c[1]:.2f}) deg, "
                        f"{lb['offset_deg']:.2f} deg from the {'mirror' if inc.side == 'R' else 'undeviated'} "
                        "direction" if c else ""), fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
        pax = fig.add_subplot(gs[r, 1], projection="polar")
        pos = inc.bsdf_sr > 0
        vmax = float(inc.bsdf_sr.max()) if pos.any() else 1.0
        sc = pax.scatter(np.radians(inc.phi_s_deg[pos]), inc.theta_s_deg[pos], c=inc.bsdf_sr[pos], s=2,
                         cmap="magma", norm=LogNorm(vmin=vmax * 1e-5, vmax=vmax))
        pax.set_ylim(0, 90)
        pax.set_yticks([30, 60, 90])
        pax.set_yticklabels(["30", "60", "90"], fontsize=6)
        pax.set_xticks(np.radians([0, 90, 180, 270]))
        pax.set_xticklabels(["0", "90", "180", "270"], fontsize=7)
        pax.set_title(f"side {inc.side}: radius theta_s, angle phi_s (deg)", fontsize=8, pad=12)
        fig.colorbar(sc, ax=pax, fraction=0.046, pad=0.1).set_label("f (1/sr)", fontsize=7)
    wl = f"{mf.wavelength_nm:g} nm" if mf.wavelength_nm is not None else "wavelength not stated"
    fig.suptitle(f"measured BSDF, {'RPC Photonics text' if mf.kind == 'rpc' else 'IS-BSDF'}, {wl}; "
                 "project frame (formats.md)", fontsize=9)
    fig.text(0.01, 0.005, "\n".join(textwrap.wrap("; ".join(mf.notes), 170)), fontsize=7, va="bottom")
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    return fig


def export_rows(path: str | Path, out: str | Path, wavelength_nm: float | None = None,
                n_transmitted: float | None = None, relative_sigma: float | None = None) -> Path:
    """`relief export MEASURED --format recording-csv`: the file's rows as recording.csv (atomically)."""
    from relief_bsdf.io.recording import write_recording
    rec = read_measured(path, wavelength_nm, relative_sigma, n_transmitted)
    out = write_recording(out, rec)
    print(f"wrote {out}: {len(rec)} rows ({len(rec.incidences())} incidence(s), side "
          f"{', '.join(sorted(set(rec.side.tolist())))}, {rec.wavelength_nm[0]:g} nm) read from {Path(path).name}")
    return out
