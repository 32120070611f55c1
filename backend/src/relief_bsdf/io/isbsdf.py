"""Zemax / Radiant "IS BSDF" tabulated ASCII files (``.bsdf``): export and import.

The format (BSDF Data Interchange, Radiant Imaging; read by OpticStudio's tabular
BSDF scattering model): ``#`` comment lines, then keyword lines

    Source Measured | Symmetry PlaneSymmetrical|Asymmetrical|ASymmetrical4D
    SpectralContent Monochrome | ScatterType BRDF|BTDF
    SampleRotation n / n values          AngleOfIncidence n / n values
    ScatterAzimuth n / n values          ScatterRadial n / n values
    Monochrome / DataBegin / per sample rotation, per incidence: "TIS t" and
    n_azimuth rows of n_radial BSDF values (1/sr) / DataEnd

Angles are in *specular coordinates*: ScatterRadial is the angle between the
scattered direction and the specular direction (0 = specular), ScatterAzimuth the
azimuth about the specular direction, 0 pointing from the specular direction toward
the sample normal and increasing counter-clockwise seen from above the sample.
PlaneSymmetrical data cover azimuth 0..180 and are mirrored (symmetric about the
plane of incidence).  TIS is the total integrated scatter of the block, i.e. the
hemispherical integral of BSDF cos(theta_s) over the scattered directions (the
specular delta part is not in the data: optical design programs trace it apart).

Choices made here (stated because the published descriptions differ):

- One ScatterType per file (`export_isbsdf`), as OpticStudio expects: a table (one
  incidence side) gives a BRDF file and a BTDF file; one file per wavelength
  (SpectralContent Monochrome).  `export_isbsdf` returns the paths it wrote.  (Older
  combined multi-block files are still read by `read_isbsdf_all` / `import_isbsdf`.)
- BTDF blocks follow OpticStudio by default (``btdf_centre="refracted"``): ScatterRadial is
  measured from the *refracted* direction (T, theta_t, phi_i + 180), sin theta_t =
  n_i sin theta_i / n_t, the indices from the table's `material` at its wavelength; past the
  critical angle (light from inside) there is no refracted ray and the block is centred on
  the grazing direction (theta 90).  ``btdf_centre="undeviated"`` keeps the earlier choice
  (Radiant's original description, "relative to the angle of direct transmission": the
  undeviated direction (T, theta_i, phi_i + 180), no index needed).  At 60 deg into n = 1.5
  the two centres are 25 deg apart.  AngleOfIncidence is the true incidence angle (in the
  medium of incidence) for both blocks.  The centring is recorded in a ``# relief:`` comment;
  a file without it (a measurement) is read as refracted-centred with the indices given to
  `import_isbsdf` (default 1 and 1: a sample measured in air, where refracted = undeviated).
- SampleRotation lists the table's incidence azimuths phi_i (0 for an isotropic table).
- Directions below the horizon (radial > 90 - theta_i toward the far side) hold 0.
- Comment lines ``# relief:`` carry the wavelength, incidence side and method, so an
  import restores them; files from elsewhere need them as arguments.

Values are Nicodemus BSDFs in 1/sr, not cosine-corrected, like BsdfTable.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from relief_bsdf.io.atomic import write_text_atomic
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction, projected_solid_angle
from relief_bsdf.errors import InputError

SIDE_TYPE = {"R": "BRDF", "T": "BTDF"}
TYPE_SIDE = {v: k for k, v in SIDE_TYPE.items()}


@dataclass
class IsBsdfBlock:
    """The content of one .bsdf file (one scatter type, one spectral channel)."""

    scatter_type: str                      # "BRDF" or "BTDF"
    symmetry: str                          # PlaneSymmetrical, Asymmetrical, ASymmetrical4D
    sample_rotation_deg: np.ndarray        # (P,)
    angle_of_incidence_deg: np.ndarray     # (I,)
    azimuth_deg: np.ndarray                # (A,)
    radial_deg: np.ndarray                 # (S,)
    tis: np.ndarray                        # (P, I)
    data_per_sr: np.ndarray                # (P, I, A, S)
    spectral_content: str = "Monochrome"
    comments: list[str] = field(default_factory=list)
    path: Path | None = None

    def relief_tag(self, key: str) -> str | None:
        """Value of a '# relief: key = value' comment, if any."""
        for c in self.comments:
            s = c.strip()
            if s.startswith("relief:") and "=" in s:
                k, v = s[len("relief:"):].split("=", 1)
                if k.strip() == key:
                    return v.strip()
        return None


# ====================================================================== geometry


def specular_frame(theta_i_deg: float, phi_i_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s, e0, e1): specular direction and the azimuth-0 / azimuth-90 unit vectors about it.

    s = w(theta_i, phi_i + 180) (mirror direction; for the BTDF block the same vector
    in the mirrored T frame is the undeviated direction; pass the refracted polar angle as
    `theta_i_deg` to centre on the refracted direction).  e0 is the tangent at s
    pointing toward the normal z (limit value at normal incidence), e1 = s x e0
    (counter-clockwise seen from +z).
    """
    ps = phi_i_deg + 180.0
    s = direction(theta_i_deg, ps)
    t, p = math.radians(theta_i_deg), math.radians(ps)
    # d/d(theta) of w(theta, p) points away from z; toward z is its negative
    e0 = -np.array([math.cos(t) * math.cos(p), math.cos(t) * math.sin(p), -math.sin(t)])
    e1 = np.cross(s, e0)
    return s, e0, e1


def to_specular_coords(theta_i_deg: float, phi_i_deg: float, theta_s_deg: Any, phi_s_deg: Any
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(radial_deg, azimuth_deg in [0, 360)) of directions w(theta_s, phi_s) about the specular one."""
    s, e0, e1 = specular_frame(theta_i_deg, phi_i_deg)
    d = direction(theta_s_deg, phi_s_deg)
    radial = np.degrees(np.arccos(np.clip(d @ s, -1.0, 1.0)))
    az = np.degrees(np.arctan2(d @ e1, d @ e0)) % 360.0
    return radial, az


def from_specular_coords(theta_i_deg: float, phi_i_deg: float, radial_deg: Any, azimuth_deg: Any
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_s_deg, phi_s_deg, above_horizon) of the directions at (radial, azimuth)."""
    s, e0, e1 = specular_frame(theta_i_deg, phi_i_deg)
    r = np.radians(np.asarray(radial_deg, float))[..., None]
    a = np.radians(np.asarray(azimuth_deg, float))[..., None]
    d = np.cos(r) * s + np.sin(r) * (np.cos(a) * e0 + np.sin(a) * e1)
    theta = np.degrees(np.arccos(np.clip(d[..., 2], -1.0, 1.0)))
    phi = np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360.0
    return theta, phi, d[..., 2] >= 0.0


# ====================================================================== export


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _plane_symmetric(table: BsdfTable, k: int, w: int) -> bool:
    """True if the side-k values are mirror symmetric about every plane of incidence."""
    if not table.is_isotropic:
        return False
    phi = table.phi_s_deg
    mirrored = (2 * table.phi_i_deg[0] - phi) % 360.0
    if not np.allclose(np.sort(mirrored), np.sort(phi % 360.0), atol=1e-9):
        return False
    order = np.argsort(phi % 360.0)
    back = np.empty_like(order)
    back[np.argsort(mirrored)] = order
    v = table.values_per_sr[w, :, :, k]
    scale = max(float(np.abs(v).max()), 1e-300)
    return bool(np.max(np.abs(v - v[..., back])) <= 1e-9 * scale)


def _grids(table: BsdfTable, symmetric: bool, max_centre_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Radial and azimuth lists: the table's cell centres and edges (so sampling is exact at
    normal incidence and twice as fine as the table elsewhere), radial out to 90 + the largest
    block centre's polar angle (the far horizon seen from the centre)."""
    te, tc = table.theta_s_edges_deg, table.theta_s_deg
    step = 0.5 * float(np.mean(np.diff(te)))
    top = min(180.0, 90.0 + float(max_centre_deg))
    ext = np.arange(te[-1] + step, top + step, step)
    radial = np.unique(np.round(np.concatenate([[0.0], tc, te, ext[ext <= top], [top]]), 9))
    radial = radial[radial <= top]
    phi0 = table.phi_i_deg[0]
    az = np.unique(np.round(np.concatenate([[0.0, 360.0], (table.phi_s_deg - phi0) % 360.0,
                                            (table.phi_s_edges_deg - phi0) % 360.0]), 9))
    if symmetric:
        az = np.unique(np.concatenate([az[az <= 180.0], [180.0]]))
    return radial, az


BTDF_CENTRES = ("refracted", "undeviated")


def refracted_theta_deg(theta_i_deg: Any, n_incident: float, n_transmitted: float,
                        past_critical: float = 90.0) -> np.ndarray:
    """Polar angle of the refracted direction (Snell, core.fresnel.cos_transmitted);
    `past_critical` (default 90, grazing) where there is none (total internal reflection)."""
    from relief_bsdf.core.fresnel import cos_transmitted
    ct = cos_transmitted(np.cos(np.radians(np.asarray(theta_i_deg, float))), n_incident, n_transmitted)
    tir = np.abs(np.imag(ct)) > 1e-12
    return np.where(tir, past_critical, np.degrees(np.arccos(np.clip(np.real(ct), -1.0, 1.0))))


def table_indices(table: BsdfTable, iw: int = 0) -> tuple[float, float]:
    """(n of the medium of incidence, n of the other medium) from the table's `material`."""
    from relief_bsdf.core.index import Material
    if not table.material:
        raise InputError("is-bsdf", "the table does not state its material (refractive indices), needed to centre "
                         "the BTDF on the refracted direction: give the index (--n or --cauchy), or "
                         "--btdf-centre undeviated")
    n1, n2 = Material.from_dict(table.material).n_pair(float(table.wavelength_nm[iw]), table.incident_from)
    return float(np.real(n1)), float(np.real(n2))


def _centres(table: BsdfTable, side: str, iw: int, btdf_centre: str) -> np.ndarray:
    """Polar angle of each incidence's block centre: mirror (R), refracted or undeviated (T)."""
    if side == "R" or btdf_centre == "undeviated":
        return table.theta_i_deg.copy()
    return refracted_theta_deg(table.theta_i_deg, *table_indices(table, iw))


def block_from_table(table: BsdfTable, side: str, iw: int = 0, btdf_centre: str = "refracted") -> IsBsdfBlock:
    """One IS-BSDF block (side 'R' -> BRDF, 'T' -> BTDF) of the table at wavelength index iw;
    a BTDF centred on the refracted (OpticStudio, default) or the undeviated direction."""
    if side not in SIDE_TYPE:
        raise ValueError(f"side must be 'R' or 'T', got {side!r}")
    if btdf_centre not in BTDF_CENTRES:
        raise InputError("is-bsdf", f"btdf_centre must be one of {BTDF_CENTRES}, got {btdf_centre!r}")
    centre = _centres(table, side, iw, btdf_centre)
    k = 0 if side == "R" else 1
    symmetric = _plane_symmetric(table, k, iw)
    radial, az = _grids(table, symmetric, float(np.max(centre)))
    wl = float(table.wavelength_nm[iw])
    P, I = table.phi_i_deg.size, table.theta_i_deg.size
    data = np.zeros((P, I, az.size, radial.size))
    R, A = np.meshgrid(radial, az)
    for p, phi_i in enumerate(table.phi_i_deg):
        for i, theta_i in enumerate(table.theta_i_deg):
            th, ph, up = from_specular_coords(centre[i], phi_i, R, A)
            v = table.eval(wl, theta_i, phi_i, side, np.minimum(th, 90.0), ph)
            data[p, i] = np.where(up, v, 0.0)
    hemi = table.hemispherical()["diffuse_" + side][iw]          # (I, P)
    comments = ["relief: written by relief_bsdf.io.isbsdf",
                f"relief: wavelength_nm = {wl!r}",
                f"relief: incident_from = {table.incident_from}",
                f"relief: method = {table.method}",
                f"relief: btdf_centre = {btdf_centre}" if side == "T" else "relief: brdf_centre = mirror",
                "relief: values = Nicodemus BSDF in 1/sr (not cosine-corrected); specular part excluded"]
    spec = (table.specular_R if side == "R" else table.specular_T)[iw]          # (I, P)
    comments += [f"relief: specular = {theta_i:g} {phi_i:g} {spec[i, p]!r}"
                 for p, phi_i in enumerate(table.phi_i_deg) for i, theta_i in enumerate(table.theta_i_deg)
                 if spec[i, p] > 0]
    if side == "T" and btdf_centre == "refracted":
        n1, n2 = table_indices(table, iw)
        comments += [f"relief: n_incident = {n1!r}", f"relief: n_transmitted = {n2!r}"]
    return IsBsdfBlock(scatter_type=SIDE_TYPE[side], symmetry="PlaneSymmetrical" if symmetric else "Asymmetrical",
                       sample_rotation_deg=table.phi_i_deg.copy(), angle_of_incidence_deg=table.theta_i_deg.copy(),
                       azimuth_deg=az, radial_deg=radial, tis=hemi.T.copy(), data_per_sr=data,
                       comments=comments)


def format_block(block: IsBsdfBlock) -> str:
    """The text of one .bsdf file."""
    out = [f"# {c}" for c in block.comments]
    out += ["Source  Measured", f"Symmetry  {block.symmetry}", f"SpectralContent  {block.spectral_content}",
            f"ScatterType  {block.scatter_type}"]
    for key, arr in (("SampleRotation", block.sample_rotation_deg), ("AngleOfIncidence", block.angle_of_incidence_deg),
                     ("ScatterAzimuth", block.azimuth_deg), ("ScatterRadial", block.radial_deg)):
        out.append(f"{key}  {arr.size}")
        out.append("\t".join(_fmt(a) for a in arr))
    out += ["", block.spectral_content, "DataBegin"]
    row_fmt = "\t".join(["%.6e"] * block.data_per_sr.shape[-1])     # one C-level format per row
    for p in range(block.sample_rotation_deg.size):
        for i in range(block.angle_of_incidence_deg.size):
            out.append(f"TIS  {_fmt(block.tis[p, i])}")
            out.extend(row_fmt % tuple(row) for row in block.data_per_sr[p, i].tolist())
    out += ["DataEnd", ""]
    return "\n".join(out)


def export_isbsdf(table: BsdfTable, path: str | Path, sides: Sequence[str] = ("R", "T"),
                  wavelength_nm: float | None = None, btdf_centre: str = "refracted") -> list[Path]:
    """Write the table as IS-BSDF file(s), one scatter type each; returns the paths written (atomically).

    One file per side and wavelength.  With a single side and wavelength the file is
    `path` itself; otherwise `path`'s stem gets _BRDF / _BTDF and, for several
    wavelengths, _<wavelength>nm (e.g. out_BRDF_550nm.bsdf).  `wavelength_nm` picks
    the nearest tabulated wavelength only.
    """
    path = Path(path)
    wls = range(table.wavelength_nm.size)
    if wavelength_nm is not None:
        wls = [int(np.argmin(np.abs(table.wavelength_nm - wavelength_nm)))]
    wls = list(wls)
    written = []
    for side in sides:
        for iw in wls:
            if len(sides) == 1 and len(wls) == 1:
                target = path
            else:
                tag = f"_{SIDE_TYPE[side]}" + (f"_{table.wavelength_nm[iw]:g}nm" if len(wls) > 1 else "")
                target = path.with_name(path.stem + tag + (path.suffix or ".bsdf"))
            written.append(write_text_atomic(target, format_block(block_from_table(table, side, iw, btdf_centre))))
    return written


# ====================================================================== import


def _numbers(tokens: list[str], n: int, where: str, what: str) -> np.ndarray:
    if len(tokens) < n:
        raise InputError(where, f"{what}: expected {n} numbers, found {len(tokens)} (truncated file?)")
    try:
        return np.array([float(t) for t in tokens[:n]])
    except ValueError as e:
        raise InputError(where, f"{what}: {e}") from None


def read_isbsdf_all(path: str | Path) -> list[IsBsdfBlock]:
    """Every block of a .bsdf file: one for standard files, several for combined files
    (blocks follow one another, each ending with DataEnd; written by earlier versions)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise InputError(path, "IS-BSDF file not found") from None
    except UnicodeDecodeError:
        try:
            text = path.read_text(encoding="latin-1")
        except OSError as e:  # pragma: no cover
            raise InputError(path, f"cannot read: {e}") from None
    chunks: list[list[str]] = [[]]
    for line in text.splitlines():
        chunks[-1].append(line)
        if line.strip() == "DataEnd":
            chunks.append([])
    if len(chunks) > 1 and not any(l.strip() and not l.strip().startswith("#") for l in chunks[-1]):
        chunks.pop()                                   # trailing comments / blank lines only
    return [_parse_block(c, path) for c in chunks]


def read_isbsdf(path: str | Path) -> IsBsdfBlock:
    """Parse a Monochrome IS-BSDF file strictly (InputError naming the file and the problem).

    Returns the first block (the only one in a standard file); see `read_isbsdf_all`.
    """
    return read_isbsdf_all(path)[0]


def _parse_block(lines: list[str], path: Path) -> IsBsdfBlock:
    comments, body = [], []
    for line in lines:
        s = line.strip()
        if s.startswith("#"):
            comments.append(s[1:].strip())
        elif s:
            body.append(s)
    if not body:
        raise InputError(path, "empty IS-BSDF file (no keywords)")
    tokens = " ".join(body).split()
    hdr: dict[str, Any] = {}
    lists: dict[str, np.ndarray] = {}
    pos = 0
    while pos < len(tokens) and tokens[pos] not in ("DataBegin",):
        key = tokens[pos]
        if key in ("Source", "Symmetry", "SpectralContent", "ScatterType"):
            if pos + 1 >= len(tokens):
                raise InputError(path, f"keyword {key} has no value")
            hdr[key] = tokens[pos + 1]
            pos += 2
        elif key in ("SampleRotation", "AngleOfIncidence", "ScatterAzimuth", "ScatterRadial"):
            try:
                n = int(tokens[pos + 1])
            except (IndexError, ValueError):
                raise InputError(path, f"{key} must be followed by a count") from None
            if n < 1:
                raise InputError(path, f"{key} count must be >= 1, got {n}")
            lists[key] = _numbers(tokens[pos + 2:], n, str(path), key)
            pos += 2 + n
        elif key in ("Monochrome", "TristimulusX", "TristimulusY", "TristimulusZ"):
            if key != "Monochrome":
                raise InputError(path, "only Monochrome IS-BSDF data are supported (one file per wavelength)")
            pos += 1
        else:
            raise InputError(path, f"unexpected keyword {key!r} in the header")
    if pos >= len(tokens):
        raise InputError(path, "no DataBegin line")
    pos += 1
    st = hdr.get("ScatterType")
    if st not in TYPE_SIDE:
        raise InputError(path, f"ScatterType must be BRDF or BTDF, got {st!r}")
    sym = hdr.get("Symmetry", "Asymmetrical")
    if sym not in ("PlaneSymmetrical", "Asymmetrical", "ASymmetrical", "ASymmetrical4D", "Asymmetrical4D"):
        raise InputError(path, f"unknown Symmetry {sym!r}")
    if hdr.get("SpectralContent", "Monochrome") != "Monochrome":
        raise InputError(path, f"SpectralContent {hdr['SpectralContent']!r} not supported (Monochrome only)")
    for key in ("AngleOfIncidence", "ScatterAzimuth", "ScatterRadial"):
        if key not in lists:
            raise InputError(path, f"missing {key}")
    rot = lists.get("SampleRotation", np.zeros(1))
    aoi, az, rad = lists["AngleOfIncidence"], lists["ScatterAzimuth"], lists["ScatterRadial"]
    for key, arr in (("ScatterAzimuth", az), ("ScatterRadial", rad), ("AngleOfIncidence", aoi)):
        if np.any(np.diff(arr) <= 0):
            raise InputError(path, f"{key} values must increase strictly")
    P, I, A, S = rot.size, aoi.size, az.size, rad.size
    from relief_bsdf.io.heightmaps import check_declared_size
    check_declared_size(path, (P, I, A, S), "IS-BSDF data block grid")     # before allocating (io.heightmaps)
    tis = np.zeros((P, I))
    data = np.zeros((P, I, A, S))
    for p in range(P):
        for i in range(I):
            if pos >= len(tokens) or tokens[pos] != "TIS":
                raise InputError(path, f"expected 'TIS' before the block of rotation {rot[p]:g}, "
                                       f"incidence {aoi[i]:g} (truncated file?)")
            tis[p, i] = _numbers(tokens[pos + 1:], 1, str(path), "TIS")[0]
            vals = _numbers(tokens[pos + 2:], A * S, str(path), f"data block for incidence {aoi[i]:g} deg")
            if np.any(vals < 0) or not np.all(np.isfinite(vals)):
                raise InputError(path, f"negative or non-finite BSDF in the block for incidence {aoi[i]:g} deg")
            data[p, i] = vals.reshape(A, S)
            pos += 2 + A * S
    if pos >= len(tokens) or tokens[pos] != "DataEnd":
        raise InputError(path, "missing DataEnd after the data (extra or missing values?)")
    return IsBsdfBlock(scatter_type=st, symmetry=sym, sample_rotation_deg=rot, angle_of_incidence_deg=aoi,
                       azimuth_deg=az, radial_deg=rad, tis=tis, data_per_sr=data, comments=comments, path=path)


def _interp_block(block: IsBsdfBlock, p: int, i: int, radial: np.ndarray, az: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of one (azimuth x radial) block; 0 beyond the last radial."""
    A = block.azimuth_deg
    V = block.data_per_sr[p, i]
    a = az % 360.0
    if block.symmetry == "PlaneSymmetrical":
        a = np.where(a > 180.0, 360.0 - a, a)
    else:
        # close the azimuth circle so interpolation wraps
        if A[-1] < 360.0 - 1e-9:
            A = np.concatenate([A, [A[0] + 360.0]])
            V = np.concatenate([V, V[:1]], axis=0)
        if A[0] > 1e-9:
            A = np.concatenate([[A[-2] - 360.0], A])
            V = np.concatenate([V[-2:-1], V], axis=0)
    ia = np.clip(np.searchsorted(A, a, side="right") - 1, 0, len(A) - 2)
    fa = np.clip((a - A[ia]) / (A[ia + 1] - A[ia]), 0.0, 1.0)
    Rg = block.radial_deg
    ir = np.clip(np.searchsorted(Rg, radial, side="right") - 1, 0, max(len(Rg) - 2, 0))
    if len(Rg) == 1:
        fr = np.zeros_like(radial)
        ir1 = ir
    else:
        fr = np.clip((radial - Rg[ir]) / (Rg[ir + 1] - Rg[ir]), 0.0, 1.0)
        ir1 = ir + 1
    v = ((1 - fa) * (1 - fr) * V[ia, ir] + fa * (1 - fr) * V[ia + 1, ir]
         + (1 - fa) * fr * V[ia, ir1] + fa * fr * V[ia + 1, ir1])
    return np.where(radial <= Rg[-1] + 1e-9, v, 0.0)


def import_isbsdf(paths: str | Path | Sequence[str | Path], theta_s_edges_deg: Any = None,
                  phi_s_edges_deg: Any = None, wavelength_nm: float | None = None,
                  incident_from: str | None = None, method: str | None = None,
                  n_incident: float | None = None, n_transmitted: float | None = None) -> BsdfTable:
    """Build a BsdfTable from IS-BSDF files: one BRDF and/or one BTDF block per wavelength
    (standard one-block files, or older combined files).  A BTDF is read with the centring
    its '# relief: btdf_centre' comment states, else as OpticStudio's (refracted) with the
    indices n_incident / n_transmitted (tags first, then the arguments, then 1 and 1).

    The scatter grid defaults to 1-degree theta cells (0..90) and 5-degree phi cells;
    values are interpolated in specular coordinates at the cell centres.  A block written by `export_isbsdf` is then scaled to its TIS line, which that writer sets to the
    table's exact hemispherical integral (the sampled grid only carries the shape; the factors
    are kept in metadata "tis_scale"); a measured block is taken as its data say.  Specular parts
    come back from the writer's '# relief: specular' lines (else zero); `lost` is 1 - R - T.  Wavelength,
    incidence side and method come from the '# relief:' comments when the file was
    written by `export_isbsdf`, else from the arguments (wavelength is then required).
    A side without a file is zero.  The specular parts are unknown (zero).
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    blocks = [b for p in paths for b in read_isbsdf_all(p)]
    if wavelength_nm is not None and any(b.relief_tag("wavelength_nm") is not None for b in blocks):
        tagged = [b for b in blocks if b.relief_tag("wavelength_nm") is not None
                  and abs(float(b.relief_tag("wavelength_nm")) - wavelength_nm) < 1e-6]
        if not tagged:
            raise InputError(blocks[0].path, f"no block for wavelength {wavelength_nm:g} nm")
        blocks = tagged
    wl_tags = sorted({b.relief_tag("wavelength_nm") or "" for b in blocks}, key=lambda t: float(t) if t else 0.0)
    if len(wl_tags) > 1:
        # several wavelengths: one table per wavelength, then stacked along the wavelength axis
        parts = [import_isbsdf_blocks([b for b in blocks if (b.relief_tag("wavelength_nm") or "") == t],
                                      theta_s_edges_deg, phi_s_edges_deg, None, incident_from, method,
                                      (n_incident, n_transmitted))
                 for t in wl_tags]
        return _stack_wavelengths(parts)
    return import_isbsdf_blocks(blocks, theta_s_edges_deg, phi_s_edges_deg, wavelength_nm, incident_from, method,
                                (n_incident, n_transmitted))


def _stack_wavelengths(parts: list[BsdfTable]) -> BsdfTable:
    base = parts[0]
    for t in parts[1:]:
        if not (np.array_equal(t.theta_i_deg, base.theta_i_deg) and np.array_equal(t.phi_i_deg, base.phi_i_deg)):
            raise InputError("is-bsdf", "blocks of different wavelengths have different incidence angles")
    return BsdfTable(wavelength_nm=np.concatenate([t.wavelength_nm for t in parts]), theta_i_deg=base.theta_i_deg,
                     phi_i_deg=base.phi_i_deg, theta_s_edges_deg=base.theta_s_edges_deg,
                     phi_s_edges_deg=base.phi_s_edges_deg,
                     values_per_sr=np.concatenate([t.values_per_sr for t in parts], axis=0),
                     incident_from=base.incident_from, method=base.method, metadata=base.metadata)


def import_isbsdf_blocks(blocks: list[IsBsdfBlock], theta_s_edges_deg: Any = None, phi_s_edges_deg: Any = None,
                         wavelength_nm: float | None = None, incident_from: str | None = None,
                         method: str | None = None, indices: tuple = (None, None)) -> BsdfTable:
    """`import_isbsdf` for already parsed blocks of one wavelength (at most one BRDF, one BTDF)."""
    by_side: dict[str, IsBsdfBlock] = {}
    for b in blocks:
        side = TYPE_SIDE[b.scatter_type]
        if side in by_side:
            raise InputError(b.path, f"two {b.scatter_type} blocks for one wavelength; pass one BRDF and/or one BTDF")
        by_side[side] = b
    first = blocks[0]
    for b in blocks[1:]:
        if not (np.array_equal(b.angle_of_incidence_deg, first.angle_of_incidence_deg)
                and np.array_equal(b.sample_rotation_deg, first.sample_rotation_deg)):
            raise InputError(b.path, "BRDF and BTDF blocks have different incidence angles / sample rotations")
    for b in blocks:
        if b.relief_tag("btdf_centre") not in (None,) + BTDF_CENTRES:
            raise InputError(b.path, f"unknown btdf_centre {b.relief_tag('btdf_centre')!r} (expected {BTDF_CENTRES})")
    wl = wavelength_nm
    if wl is None:
        tag = first.relief_tag("wavelength_nm")
        if tag is None:
            raise InputError(first.path, "the file does not state its wavelength; pass wavelength_nm")
        wl = float(tag)
    inc = incident_from or first.relief_tag("incident_from") or "outside"
    meth = method or first.relief_tag("method") or "is-bsdf import"
    te = np.linspace(0.0, 90.0, 91) if theta_s_edges_deg is None else np.asarray(theta_s_edges_deg, float)
    pe = np.linspace(0.0, 360.0, 73) if phi_s_edges_deg is None else np.asarray(phi_s_edges_deg, float)
    tc = 0.5 * (te[1:] + te[:-1])
    pc = 0.5 * (pe[1:] + pe[:-1])
    TH, PH = np.meshgrid(tc, pc, indexing="ij")
    psa = projected_solid_angle(te, pe)
    rot, aoi = first.sample_rotation_deg, first.angle_of_incidence_deg
    values = np.zeros((1, aoi.size, rot.size, 2, tc.size, pc.size))
    tis_scale = {}
    for side, b in by_side.items():
        k = 0 if side == "R" else 1
        own = any(c.strip() == "relief: written by relief_bsdf.io.isbsdf" for c in b.comments)
        for p, phi_i in enumerate(rot):
            centre = _block_centres(b, side, aoi, indices)
            for i, theta_i in enumerate(aoi):
                radial, az = to_specular_coords(centre[i], phi_i, TH, PH)
                v = _interp_block(b, p, i, radial, az)
                got = float(np.sum(v * psa))
                if own and got > 0 and b.tis[p, i] > 0:       # our TIS is the table's exact integral
                    tis_scale[(side, float(theta_i), float(phi_i))] = float(b.tis[p, i]) / got
                    v = v * (float(b.tis[p, i]) / got)
                values[0, i, p, k] = v
    specular = {k: np.zeros((1, aoi.size, rot.size)) for k in ("R", "T")}
    for side, b in by_side.items():
        for c in b.comments:
            parts = c.split("=", 1)[1].split() if c.startswith("relief: specular =") else []
            if len(parts) == 3:
                i = np.nonzero(np.isclose(aoi, float(parts[0])))[0]
                p = np.nonzero(np.isclose(rot % 360.0, float(parts[1]) % 360.0))[0]
                if i.size and p.size:
                    specular[side][0, i[0], p[0]] = float(parts[2])
    t = BsdfTable(wavelength_nm=[wl], theta_i_deg=aoi, phi_i_deg=rot, theta_s_edges_deg=te,
                  phi_s_edges_deg=pe, values_per_sr=values, incident_from=inc, method=meth,
                  specular_R=specular["R"], specular_T=specular["T"],
                  metadata={"imported_from": [str(b.path) for b in blocks],
                            "tis": {b.scatter_type: b.tis.tolist() for b in blocks},
                            "tis_scale": [[*k, v] for k, v in tis_scale.items()],
                            "lost": "1 - R - T of what the file(s) hold (a side without a file counts as 0)"})
    h = t.hemispherical()
    t.lost = 1.0 - h["R"] - h["T"]
    return t


def _block_centres(block: IsBsdfBlock, side: str, aoi: np.ndarray, indices: tuple) -> np.ndarray:
    """Polar angle of each block's centre when read: mirror, or the BTDF's stated centring."""
    if side == "R" or block.relief_tag("btdf_centre") == "undeviated":
        return aoi
    n = []
    for tag, arg in zip(("n_incident", "n_transmitted"), indices):
        t = block.relief_tag(tag)
        n.append(float(t) if t is not None else (1.0 if arg is None else float(arg)))
    return refracted_theta_deg(aoi, n[0], n[1])
