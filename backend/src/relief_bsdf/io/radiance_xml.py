"""LBNL/WINDOW XML BSDF files (Radiance, WINDOW, EnergyPlus): export and import.

The XML BSDF (schema ``http://windows.lbl.gov`` BSDF-v1.4) describes one layer seen from both
sides: four blocks ``Reflection Front``, ``Transmission Front``, ``Reflection Back``,
``Transmission Back``.  Conventions (WINDOW / Radiance, the LBNL "BSDF" format notes):

- WINDOW's *front* is the side the boundary's normal points to in our frame: the `outside`
  table (light from the lit medium, +z, formats.md) is written as the front blocks, the
  `inside` table (mirrored frame: +z into the dielectric) as the back blocks.  Radiance's own
  BSDF frame reverses WINDOW's sides (its +z, the surface normal of a BSDF material, is the
  back: Radiance's bsdf_t.c / bsdf_m.c "front and back are reversed from WINDOW 6"), so in a
  Radiance scene the material's normal points into the dielectric, away from the lit side.
  We relate the frames by a proper rotation (a half turn about x: x kept, y and z reversed),
  so a Radiance azimuth is the negative of ours (`to_table_phi`).
- Values are BSDFs in 1/sr (not cosine-corrected), radiance leaving over irradiance arriving,
  as in BsdfTable.  Radiance scenes have one medium (n = 1) on both sides, so a boundary
  between air and glass is written power-conserving: a BTDF is tabulated over the directions
  *in the medium the light enters* (theta measured there, as in the table), so that
  sum(f * projected solid angle) is the table's transmittance.  The two transmission blocks
  then differ by n^2 (f(a->b)/n_b^2 = f(b->a)/n_a^2, formats.md): Radiance uses each block only
  for its own incidence side, so both are kept as they are.
- Klems angle basis (``LBNL/Klems Full``, 145 patches): nine theta rings (0-5, 5-15, ..., 65-75,
  75-90 degrees) with 1, 8, 16, 20, 24, 24, 24, 16, 12 azimuth patches centred on
  phi = j * 360 / n.  A *scattered* patch lists the direction away from the layer; an
  *incident* patch lists the direction the light travels, i.e. the direction toward the source
  is the patch's with phi + 180 (so a mirror and a clear pane are diagonal matrices).
  ``IncidentDataStructure Columns``: the ScatteringData text has one line per scattered patch
  with one column per incident patch.  Checked against Radiance itself (pyradiance's
  SDevalBSDF / checkBSDF) in tests/backend/io/test_radiance_xml.py.
- A matrix entry is the patch average of f over the scattered patch, weighted by projected
  solid angle (sampled on an m x m grid uniform in sin^2 theta and phi), for the incidence at
  the incident patch centre (the table interpolated in theta_i; held at the nearest tabulated
  incidence beyond its range).  The table's delta parts (specular_R, specular_T) go into the
  patch holding the mirror / refracted direction (index from `material`), value = power /
  projected solid angle of that patch, so the hemispherical totals R and T are kept.
- Tensor tree option (``TensorTree3`` for an isotropic table, ``TensorTree4`` otherwise,
  Radiance's variable-resolution format): a uniform tree of depth `depth` (2^depth cells per
  dimension) on Shirley-Chiu square-to-disc coordinates of both hemispheres.
- One spectral channel: the table's wavelength nearest `wavelength_nm` (default 555 nm) is
  written as ``Visible`` (photopic) data; the wavelength is recorded in a comment.

Regime of validity: Klems patches are 5-15 degrees wide, so lobes narrower than a patch are
smeared over it (their power is kept); the tensor tree of depth d resolves ~ 90 / 2^d degrees.
"""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.io.atomic import write_text_atomic

NS = "http://windows.lbl.gov"
XSI = "http://www.w3.org/2001/XMLSchema-instance"
KLEMS_FULL_NAME = "LBNL/Klems Full"
# (lower theta, upper theta, number of azimuth patches) per ring of the Klems full basis
KLEMS_FULL = ((0.0, 5.0, 1), (5.0, 15.0, 8), (15.0, 25.0, 16), (25.0, 35.0, 20), (35.0, 45.0, 24),
              (45.0, 55.0, 24), (55.0, 65.0, 24), (65.0, 75.0, 16), (75.0, 90.0, 12))
BLOCKS = (("Reflection Front", "outside", "R"), ("Transmission Front", "outside", "T"),
          ("Reflection Back", "inside", "R"), ("Transmission Back", "inside", "T"))


# ====================================================================== Klems basis


@dataclass(frozen=True)
class AngleBasis:
    """A Klems-type angle basis: rings (theta_lo, theta_hi, n_phi); patch j of a ring is
    centred on phi = j * 360 / n_phi.  Patch order: ring by ring, phi increasing."""

    name: str
    rings: tuple

    @property
    def size(self) -> int:
        return sum(n for _, _, n in self.rings)

    def patches(self) -> dict[str, np.ndarray]:
        """Per patch: theta_lo/hi, theta_c (ring centre; 0 for the polar cap), phi_lo/hi/c (deg)."""
        cols: dict[str, list] = {k: [] for k in ("theta_lo", "theta_hi", "theta_c", "phi_lo", "phi_hi", "phi_c")}
        for lo, hi, n in self.rings:
            w = 360.0 / n
            for j in range(n):
                c = j * w
                cols["theta_lo"].append(lo)
                cols["theta_hi"].append(hi)
                cols["theta_c"].append(0.0 if lo == 0.0 else 0.5 * (lo + hi))
                cols["phi_lo"].append(c - 0.5 * w if n > 1 else 0.0)
                cols["phi_hi"].append(c + 0.5 * w if n > 1 else 360.0)
                cols["phi_c"].append(c)
        return {k: np.asarray(v) for k, v in cols.items()}

    def projected_solid_angle_sr(self) -> np.ndarray:
        p = self.patches()
        return (0.5 * (np.sin(np.radians(p["theta_hi"])) ** 2 - np.sin(np.radians(p["theta_lo"])) ** 2)
                * np.radians(p["phi_hi"] - p["phi_lo"]))

    def index(self, theta_deg: Any, phi_deg: Any) -> np.ndarray:
        """Patch index of each direction (theta in [0, 90], phi any)."""
        th = np.asarray(theta_deg, float)
        ph = np.mod(np.asarray(phi_deg, float), 360.0)
        hi = np.array([r[1] for r in self.rings])
        ring = np.minimum(np.searchsorted(hi, th, side="right"), len(self.rings) - 1)
        n = np.array([r[2] for r in self.rings])[ring]
        start = np.concatenate([[0], np.cumsum([r[2] for r in self.rings])])[ring]
        j = np.floor(ph / (360.0 / n) + 0.5).astype(int) % n
        return start + j


KLEMS = AngleBasis(KLEMS_FULL_NAME, KLEMS_FULL)


def _patch_samples(basis: AngleBasis, m: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of m x m sample points per patch, uniform in sin^2 theta and phi: (N, m*m)."""
    p = basis.patches()
    u = (np.arange(m) + 0.5) / m
    s2 = (np.sin(np.radians(p["theta_lo"]))[:, None] ** 2
          + u[None, :] * (np.sin(np.radians(p["theta_hi"])) ** 2 - np.sin(np.radians(p["theta_lo"])) ** 2)[:, None])
    th = np.degrees(np.arcsin(np.sqrt(s2)))
    ph = p["phi_lo"][:, None] + u[None, :] * (p["phi_hi"] - p["phi_lo"])[:, None]
    return np.repeat(th, m, axis=1), np.tile(ph, (1, m))


def specular_directions(table: BsdfTable, iw: int, theta_i_deg: np.ndarray) -> np.ndarray | None:
    """Polar angle (deg) of the refracted direction for each incidence, NaN beyond the critical
    angle; None when the table does not state its material (indices)."""
    from relief_bsdf.io.isbsdf import refracted_theta_deg, table_indices
    try:
        n1, n2 = table_indices(table, iw)
    except (InputError, KeyError, TypeError, ValueError):
        return None
    return refracted_theta_deg(theta_i_deg, n1, n2, past_critical=np.nan)


def klems_matrix(table: BsdfTable, side: str, iw: int = 0, basis: AngleBasis = KLEMS, m: int = 8) -> np.ndarray:
    """(n_out, n_in) Klems matrix (1/sr) of one side of `table` at wavelength index iw (module doc).

    Patch azimuths are Radiance's; the table's azimuth of the same direction is its negative
    (`to_table_phi`)."""
    p = basis.patches()
    th_o, ph_o = _patch_samples(basis, m)                        # (N_out, m*m)
    th_i = p["theta_c"]
    src_phi = to_table_phi(p["phi_c"] + 180.0)                   # toward the source, table frame
    wl = table.wavelength_nm[iw]
    M = np.empty((th_o.shape[0], th_i.size))
    for o in range(th_o.shape[0]):                               # one scattered patch at a time (memory)
        M[o] = table.eval(wl, th_i[:, None], src_phi[:, None], side, np.minimum(th_o[o], 90.0)[None, :],
                          to_table_phi(ph_o[o])[None, :]).mean(axis=-1)
    lam = basis.projected_solid_angle_sr()
    spec = _specular_at(table, side, iw, th_i, src_phi)
    if np.any(spec > 0):
        tgt_theta = th_i if side == "R" else _refracted_or_fail(table, iw, th_i, spec)
        ok = np.isfinite(tgt_theta) & (spec > 0)
        o = basis.index(np.where(ok, tgt_theta, 0.0), p["phi_c"])   # same azimuth as the incident patch
        cols = np.nonzero(ok)[0]
        M[o[cols], cols] += spec[cols] / lam[o[cols]]
    return M


def to_table_phi(radiance_phi_deg: Any) -> np.ndarray:
    """Azimuth in the table frame of a direction with azimuth `radiance_phi_deg` in Radiance's BSDF
    frame (and back: the map is its own inverse).  Radiance's +z is WINDOW's back side, i.e. our
    `inside`; the table frames relate to it by a half turn about x (x kept, y and z reversed)."""
    return np.mod(-np.asarray(radiance_phi_deg, float), 360.0)


def _refracted_or_fail(table: BsdfTable, iw: int, theta_i_deg: np.ndarray, spec: np.ndarray) -> np.ndarray:
    """Refracted polar angles for the delta transmission (NaN past the critical angle, where an
    interpolated delta is dropped: it is zero there); InputError when they cannot be placed."""
    tgt = specular_directions(table, iw, theta_i_deg)
    if tgt is None:
        raise InputError("radiance-xml", "the table has a specular transmitted part but no material "
                         "(refractive indices) to place it; cannot write it")
    tabulated = specular_directions(table, iw, table.theta_i_deg)
    if np.any((table.specular_T[iw] > 1e-12) & ~np.isfinite(tabulated)[:, None]):
        raise InputError("radiance-xml", f"the table (light from {table.incident_from}) has specular transmission "
                         "beyond the critical angle, where no refracted direction exists; inconsistent table")
    return tgt


def _specular_at(table: BsdfTable, side: str, iw: int, theta_deg: np.ndarray, phi_deg: np.ndarray) -> np.ndarray:
    """The delta part (power fraction) of one side, linear in theta_i, nearest in phi_i."""
    s = (table.specular_R if side == "R" else table.specular_T)[iw]        # (I, P)
    ip = np.argmin(np.abs(((phi_deg[:, None] - table.phi_i_deg[None, :]) + 180.0) % 360.0 - 180.0), axis=1)
    if table.theta_i_deg.size == 1:
        return s[0, ip]
    return np.array([np.interp(t, table.theta_i_deg, s[:, k]) for t, k in zip(theta_deg, ip)])


# ====================================================================== writing


def _table_pair(tables: list[BsdfTable]) -> dict[str, BsdfTable]:
    by = {t.incident_from: t for t in tables}
    if "outside" not in by or "inside" not in by:
        missing = "inside" if "outside" in by else "outside"
        raise InputError("radiance-xml", f"the XML BSDF needs both sides of the boundary; no table for light "
                         f"arriving from {missing} (reconstruct with --from both)")
    return by


def _nearest_wl(table: BsdfTable, wavelength_nm: float | None) -> int:
    target = 555.0 if wavelength_nm is None else float(wavelength_nm)
    return int(np.argmin(np.abs(table.wavelength_nm - target)))


def _basis_xml(basis: AngleBasis) -> str:
    out = ["    <AngleBasis>", f"      <AngleBasisName>{basis.name}</AngleBasisName>"]
    for lo, hi, n in basis.rings:
        c = 0.0 if lo == 0.0 else 0.5 * (lo + hi)
        out += ["      <AngleBasisBlock>", f"        <Theta>{c:g}</Theta>", f"        <nPhis>{n}</nPhis>",
                f"        <ThetaBounds><LowerTheta>{lo:g}</LowerTheta><UpperTheta>{hi:g}</UpperTheta></ThetaBounds>",
                "      </AngleBasisBlock>"]
    return "\n".join(out + ["    </AngleBasis>"])


def _header(name: str, thickness_m: float, comments: list[str], data_definition: str) -> str:
    notes = "\n".join(f"<!-- {c.replace('--', '- -')} -->" for c in comments)
    return f"""<?xml version="1.0" encoding="UTF-8"?>
{notes}
<WindowElement xmlns="{NS}" xmlns:xsi="{XSI}" xsi:schemaLocation="{NS}/BSDF-v1.4.xsd">
<WindowElementType>System</WindowElementType>
<FileType>BSDF</FileType>
<Optical>
<Layer>
  <Material>
    <Name>{_esc(name)}</Name>
    <Manufacturer>relief-bsdf</Manufacturer>
    <Thickness unit="Meter">{thickness_m:g}</Thickness>
    <DeviceType>Other</DeviceType>
  </Material>
  <DataDefinition>
    {data_definition}
  </DataDefinition>
"""


def _esc(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _block(direction: str, data_type: str, text: str, basis_name: str | None) -> str:
    bases = (f"      <ColumnAngleBasis>{basis_name}</ColumnAngleBasis>\n"
             f"      <RowAngleBasis>{basis_name}</RowAngleBasis>\n") if basis_name \
        else "      <AngleBasis>LBNL/Shirley-Chiu</AngleBasis>\n"
    return f"""  <WavelengthData>
    <LayerNumber>System</LayerNumber>
    <Wavelength unit="Integral">Visible</Wavelength>
    <SourceSpectrum>CIE Illuminant D65 1nm.ssp</SourceSpectrum>
    <DetectorSpectrum>ASTM E308 1931 Y.dsp</DetectorSpectrum>
    <WavelengthDataBlock>
      <WavelengthDataDirection>{direction}</WavelengthDataDirection>
{bases}      <ScatteringDataType>{data_type}</ScatteringDataType>
      <ScatteringData>
{text}
      </ScatteringData>
    </WavelengthDataBlock>
  </WavelengthData>
"""


def _comments(by: dict[str, BsdfTable], iw: int, extra: str) -> list[str]:
    t = by["outside"]
    return [f"written by relief_bsdf.io.radiance_xml ({extra})",
            f"relief: wavelength_nm = {float(t.wavelength_nm[iw])!r} (one channel, written as Visible)",
            f"relief: method = {t.method}",
            "relief: front = light from outside (table 'outside'), back = light from inside (table 'inside')",
            "relief: values = BSDF in 1/sr; transmission tabulated over directions in the medium entered "
            "(power conserving); delta parts folded into the patch of the mirror / refracted direction"]


def write_radiance_xml(path: str | Path, tables: list[BsdfTable], wavelength_nm: float | None = None,
                       structure: str = "klems", depth: int = 5, samples_per_patch: int = 8) -> Path:
    """Write both sides of a boundary as one LBNL/WINDOW XML BSDF (module doc); returns the path.

    structure "klems" (LBNL/Klems Full matrices) or "tensor-tree" (uniform tree of `depth`).
    """
    by = _table_pair(tables)
    iw = _nearest_wl(by["outside"], wavelength_nm)
    wl = float(by["outside"].wavelength_nm[iw])
    iw_in = _nearest_wl(by["inside"], wl)
    thick = 0.0                                      # one boundary: no thickness of its own
    name = f"relief-bsdf boundary ({by['outside'].method})"
    if structure == "klems":
        head = _header(name, thick, _comments(by, iw, "Klems full basis"),
                       "<IncidentDataStructure>Columns</IncidentDataStructure>\n" + _basis_xml(KLEMS))
        body = []
        for direction, frm, side in BLOCKS:
            t = by[frm]
            M = klems_matrix(t, side, iw if frm == "outside" else iw_in, KLEMS, samples_per_patch)
            text = "\n".join(", ".join(f"{v:.6g}" for v in row) for row in M)
            body.append(_block(direction, "BTDF" if side == "T" else "BRDF", text, KLEMS_FULL_NAME))
    elif structure == "tensor-tree":
        iso = by["outside"].is_isotropic and by["inside"].is_isotropic
        kind = "TensorTree3" if iso else "TensorTree4"
        head = _header(name, thick, _comments(by, iw, f"{kind}, uniform depth {depth}"),
                       f"<IncidentDataStructure>{kind}</IncidentDataStructure>")
        body = []
        for direction, frm, side in BLOCKS:
            t = by[frm]
            grid = tensor_tree_grid(t, side, iw if frm == "outside" else iw_in, depth, iso)
            body.append(_block(direction, "BTDF" if side == "T" else "BRDF", format_tree(grid), None))
    else:
        raise InputError("radiance-xml", f"structure must be 'klems' or 'tensor-tree', got {structure!r}")
    return write_text_atomic(Path(path), head + "".join(body) + "</Layer>\n</Optical>\n</WindowElement>\n")


# ====================================================================== tensor trees


def square_to_disc(a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]:
    """Shirley & Chiu (1997) concentric map of the unit square [0, 1]^2 onto the unit disc.

    Area preserving, so equal square cells are equal projected solid angles when the disc is the
    (x, y) projection of the hemisphere (r = sin theta).  Radiance's tensor trees index
    directions this way (its SDdisk2square is the inverse)."""
    u = 2.0 * np.asarray(a, float) - 1.0
    v = 2.0 * np.asarray(b, float) - 1.0
    first = np.abs(u) > np.abs(v)
    r = np.where(first, u, v)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(first, (np.pi / 4) * v / u, (np.pi / 2) - (np.pi / 4) * u / v)
    phi = np.where(r == 0, 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


def disc_to_square(x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `square_to_disc`."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    r = np.hypot(x, y)
    phi = np.arctan2(y, x)
    phi = np.where(phi < -np.pi / 4, phi + 2 * np.pi, phi)
    sector = np.floor((phi + np.pi / 4) / (np.pi / 2)).astype(int) % 4       # 0: right, 1: top, 2: left, 3: bottom
    centre = sector * (np.pi / 2)
    t = (phi - centre) / (np.pi / 4)                                          # -1 .. 1 within the sector
    a = np.select([sector == 0, sector == 1, sector == 2], [r, -t * r, -r], t * r)
    b = np.select([sector == 0, sector == 1, sector == 2], [t * r, r, -t * r], -r)
    return (a + 1.0) * 0.5, (b + 1.0) * 0.5


def _disc_angles(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta from the hemisphere's own axis, Radiance azimuth) of disc points (deg)."""
    s = np.clip(np.hypot(x, y), 0.0, 1.0)
    return np.degrees(np.arcsin(s)), np.degrees(np.arctan2(y, x)) % 360.0


def tensor_tree_grid(table: BsdfTable, side: str, iw: int, depth: int, isotropic: bool, m: int = 2) -> np.ndarray:
    """Uniform tensor-tree grid (1/sr) of one side: (N, N, N) for TensorTree3 or (N, N, N, N) for
    TensorTree4, N = 2^depth, in Radiance's index order (module doc).

    TensorTree3 (Radiance bsdf_t.c): axis 0 is 0.5 - sin(theta_in) / 2 (only its first half is
    used; the second mirrors it), axes 1-2 the scattered direction on the concentric square,
    rotated so the incident light travels toward azimuth 0.  TensorTree4: axes 0-1 the travel
    direction of the incident light, axes 2-3 the scattered direction.  Each entry is the
    average over the scattered cell (m x m samples) at the incident cell's centre."""
    n = 2 ** depth
    c = (np.arange(n) + 0.5) / n
    sub = (np.arange(m) + 0.5) / (m * n)
    oa = (np.arange(n)[:, None] / n + sub[None, :]).ravel()                    # (n*m,) sample coordinates
    OA, OB = np.meshgrid(oa, oa, indexing="ij")
    ox, oy = square_to_disc(OA, OB)
    th_o, ph_o = _disc_angles(ox, oy)
    wl = table.wavelength_nm[iw]

    def cell_means(v: np.ndarray) -> np.ndarray:                 # (..., n*m, n*m) -> (..., n, n)
        return v.reshape(v.shape[:-2] + (n, m, n, m)).mean(axis=(-3, -1))

    if isotropic:
        sin_i = np.clip(1.0 - 2.0 * c[: n // 2], 0.0, 1.0)
        th_i = np.degrees(np.arcsin(sin_i))
        half = np.stack([cell_means(table.eval(wl, t, to_table_phi(180.0), side, th_o, to_table_phi(ph_o)))
                         for t in th_i])
        _add_tree_specular(half, table, side, iw, th_i, np.zeros_like(th_i))
        return np.concatenate([half, half[::-1]], axis=0)
    ix, iy = square_to_disc(*np.meshgrid(c, c, indexing="ij"))
    th_i, ph_travel = _disc_angles(ix, iy)
    src = to_table_phi(ph_travel + 180.0)
    out = np.empty((n, n, n, n))
    for a in range(n):
        for b in range(n):
            out[a, b] = cell_means(table.eval(wl, th_i[a, b], src[a, b], side, th_o, to_table_phi(ph_o)))
    _add_tree_specular(out.reshape((n * n, n, n)), table, side, iw, th_i.ravel(), ph_travel.ravel(), src.ravel())
    return out


def _add_tree_specular(grid: np.ndarray, table: BsdfTable, side: str, iw: int, theta_i_deg: np.ndarray,
                       travel_phi_deg: np.ndarray, src_phi_deg: np.ndarray | None = None) -> None:
    """Fold the delta part into the scattered cell holding the mirror / refracted direction, in place.

    grid (K, N, N): per incident cell k the scattered square; the delta leaves along the
    incident light's travel azimuth (Radiance frame).  Cell value += power / (pi / N^2)."""
    src = to_table_phi(travel_phi_deg + 180.0) if src_phi_deg is None else src_phi_deg
    spec = _specular_at(table, side, iw, theta_i_deg, src)
    if not np.any(spec > 0):
        return
    tgt = theta_i_deg if side == "R" else _refracted_or_fail(table, iw, theta_i_deg, spec)
    ok = np.isfinite(tgt) & (spec > 0)
    n = grid.shape[-1]
    s = np.sin(np.radians(np.where(ok, tgt, 0.0)))
    a, b = disc_to_square(s * np.cos(np.radians(travel_phi_deg)), s * np.sin(np.radians(travel_phi_deg)))
    ia, ib = np.minimum((a * n).astype(int), n - 1), np.minimum((b * n).astype(int), n - 1)
    k = np.nonzero(ok)[0]
    grid[k, ia[k], ib[k]] += spec[k] / (np.pi / n**2)


def format_tree(grid: np.ndarray) -> str:
    """A uniform tensor tree: one brace-enclosed leaf grid, values in C order (last axis fastest)."""
    flat = grid.ravel()
    lines = [" ".join(f"{v:.5g}" for v in flat[k:k + 16]) for k in range(0, flat.size, 16)]
    return "{\n" + "\n".join(lines) + "\n}"


# ====================================================================== reading


def _child(el: ET.Element, name: str) -> ET.Element | None:
    for c in el:
        if c.tag.split("}")[-1] == name:
            return c
    return None


def _children(el: ET.Element, name: str) -> list[ET.Element]:
    return [c for c in el if c.tag.split("}")[-1] == name]


def _text(el: ET.Element | None) -> str:
    return "" if el is None or el.text is None else el.text.strip()


def _parse_tree(text: str, nd: int, path: Path) -> Any:
    """Nested tensor tree -> nested lists (branch: 2^nd children) or a flat np.ndarray leaf grid."""
    tokens = re.findall(r"[{}]|[^\s,{}]+", text)
    pos = 0

    def node():
        nonlocal pos
        if pos >= len(tokens) or tokens[pos] != "{":
            raise InputError(path, "tensor tree: expected '{'")
        pos += 1
        if pos < len(tokens) and tokens[pos] == "{":
            kids = [node() for _ in range(2 ** nd)]
        else:
            start = pos
            while pos < len(tokens) and tokens[pos] not in "{}":
                pos += 1
            try:
                kids = np.maximum(np.array([float(t) for t in tokens[start:pos]]), 0.0)
            except ValueError as e:
                raise InputError(path, f"tensor tree: {e}") from None
            g = round(kids.size ** (1.0 / nd))
            if g ** nd != kids.size or g & (g - 1):
                raise InputError(path, f"tensor tree: a leaf grid of {kids.size} values is not 2^(k*{nd})")
        if pos >= len(tokens) or tokens[pos] != "}":
            raise InputError(path, "tensor tree: missing '}'")
        pos += 1
        return kids

    tree = node()
    if pos != len(tokens):
        raise InputError(path, "tensor tree: extra characters after the tree")
    return tree


def _tree_to_grid(node: Any, nd: int, res: int) -> np.ndarray:
    """Uniform (res,)*nd grid of a parsed tree (finer leaves averaged, coarser ones repeated).
    Child n of a branch lies in the upper half of axis i when bit i of n is set (Radiance)."""
    if isinstance(node, np.ndarray):
        g = round(node.size ** (1.0 / nd))
        a = node.reshape((g,) * nd)
        if g > res:
            f = g // res
            a = a.reshape(sum(((res, f) for _ in range(nd)), ())).mean(axis=tuple(range(1, 2 * nd, 2)))
        elif g < res:
            for ax in range(nd):
                a = np.repeat(a, res // g, axis=ax)
        return a
    out = np.empty((res,) * nd)
    h = res // 2
    for n, kid in enumerate(node):
        sl = tuple(slice(h, res) if (n >> i) & 1 else slice(0, h) for i in range(nd))
        out[sl] = _tree_to_grid(kid, nd, max(h, 1))
    return out


def _tree_depth(node: Any, nd: int) -> int:
    if isinstance(node, np.ndarray):
        return int(round(math.log2(round(node.size ** (1.0 / nd))))) if node.size > 1 else 0
    return 1 + max(_tree_depth(k, nd) for k in node)


def read_radiance_xml(path: str | Path, wavelength_nm: float | None = None, phi_i_deg: Any = (0.0,),
                      theta_s_edges_deg: Any = None, phi_s_edges_deg: Any = None) -> list[BsdfTable]:
    """A WINDOW/Radiance XML BSDF (Klems matrices or tensor trees) as BsdfTables: the front
    blocks become the `outside` table, the back blocks the `inside` table (module doc).

    Incidence: the Klems ring centres (0, 10, ..., 70, 82.5 deg) or 16 tensor-tree angles, at the
    azimuths `phi_i_deg` (one azimuth = the file is taken as isotropic).  Scatter cells default
    to 2.5 x 0.75 degrees, which nest inside Klems patches, so hemispherical totals are kept
    (1 x 2 degrees for tensor trees, sampled at cell centres).
    Delta parts cannot be told apart from the cells: specular_R/T are 0.  The wavelength comes
    from a relief comment, else `wavelength_nm`, else 555 nm ("Visible").
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "XML BSDF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(path, f"not well-formed XML ({e})") from None
    layer = _child(_child(root, "Optical") or root, "Layer") if _child(root, "Optical") is not None else None
    if root.tag.split("}")[-1] != "WindowElement" or layer is None:
        raise InputError(path, "not a WINDOW XML BSDF (no WindowElement/Optical/Layer)")
    structure = _text(_child(_child(layer, "DataDefinition") or layer, "IncidentDataStructure"))
    blocks: dict[str, ET.Element] = {}
    for wd in _children(layer, "WavelengthData"):
        if _text(_child(wd, "Wavelength")).lower() != "visible":
            continue
        for b in _children(wd, "WavelengthDataBlock"):
            blocks[_text(_child(b, "WavelengthDataDirection"))] = b
    missing = [d for d, _, _ in BLOCKS if d not in blocks]
    if missing:
        raise InputError(path, f"no Visible data block for {', '.join(missing)}")
    wl = _comment_wavelength(path) or (555.0 if wavelength_nm is None else float(wavelength_nm))
    if structure in ("Columns", "Rows"):
        lookup = _klems_lookup(blocks, structure, path)
        th_i = np.array([0.0 if lo == 0 else 0.5 * (lo + hi) for lo, hi, _ in KLEMS.rings])
    elif structure in ("TensorTree3", "TensorTree4"):
        lookup = _tree_lookup(blocks, 3 if structure == "TensorTree3" else 4, path)
        th_i = np.degrees(np.arcsin(np.linspace(0.0, 0.95, 16)))
    else:
        raise InputError(path, f"IncidentDataStructure {structure!r} not supported (Columns, Rows, TensorTree3/4)")
    klems = structure in ("Columns", "Rows")
    te = (np.linspace(0.0, 90.0, 37 if klems else 91) if theta_s_edges_deg is None
          else np.asarray(theta_s_edges_deg, float))
    pe = (np.linspace(0.0, 360.0, 481 if klems else 181) if phi_s_edges_deg is None
          else np.asarray(phi_s_edges_deg, float))
    pi = np.atleast_1d(np.asarray(phi_i_deg, float))
    tc, pc = 0.5 * (te[1:] + te[:-1]), 0.5 * (pe[1:] + pe[:-1])
    TS, PS = np.meshgrid(tc, pc, indexing="ij")
    tables = []
    for frm in ("outside", "inside"):
        v = np.zeros((1, th_i.size, pi.size, 2, tc.size, pc.size))
        for k, side in enumerate(SIDES_RT):
            direction = [d for d, f, s in BLOCKS if f == frm and s == side][0]
            for i, t in enumerate(th_i):
                for p, ph in enumerate(pi):
                    v[0, i, p, k] = lookup(direction, t, ph, TS, PS)
        tables.append(BsdfTable(wavelength_nm=[wl], theta_i_deg=th_i, phi_i_deg=pi, theta_s_edges_deg=te,
                                phi_s_edges_deg=pe, values_per_sr=v, incident_from=frm,
                                method="radiance-xml import",
                                metadata={"imported_from": str(path), "structure": structure,
                                          "note": "delta parts are inside the cells (not separable)"}))
    return tables


SIDES_RT = ("R", "T")


def _comment_wavelength(path: Path) -> float | None:
    m = re.search(r"relief: wavelength_nm = ([0-9.eE+-]+)", path.read_text(encoding="utf-8", errors="replace")[:4000])
    return float(m.group(1)) if m else None


def _klems_lookup(blocks: dict, structure: str, path: Path):
    n = KLEMS.size
    mats = {}
    for d, b in blocks.items():
        for tag in ("ColumnAngleBasis", "RowAngleBasis"):
            name = _text(_child(b, tag))
            if name and name != KLEMS_FULL_NAME:
                raise InputError(path, f"{d}: angle basis {name!r} not supported (only {KLEMS_FULL_NAME})")
        try:
            vals = np.array([float(t) for t in re.split(r"[\s,]+", _text(_child(b, "ScatteringData"))) if t])
        except ValueError as e:
            raise InputError(path, f"{d}: ScatteringData: {e}") from None
        if vals.size != n * n:
            raise InputError(path, f"{d}: {vals.size} values, the Klems full basis needs {n * n}")
        M = vals.reshape(n, n)
        mats[d] = M if structure == "Columns" else M.T            # rows: scattered, columns: incident

    def lookup(direction, theta_i, phi_i, TS, PS):
        i = KLEMS.index(theta_i, to_table_phi(phi_i) + 180.0)     # travel azimuth, Radiance frame
        o = KLEMS.index(TS, to_table_phi(PS))
        return mats[direction][o, i]
    return lookup


def _tree_lookup(blocks: dict, nd: int, path: Path):
    grids = {}
    for d, b in blocks.items():
        tree = _parse_tree(_text(_child(b, "ScatteringData")), nd, path)
        res = 2 ** min(_tree_depth(tree, nd), 7 if nd == 3 else 5)
        grids[d] = _tree_to_grid(tree, nd, res)

    def lookup(direction, theta_i, phi_i, TS, PS):
        g = grids[direction]
        res = g.shape[-1]
        s_o = np.sin(np.radians(TS))
        if nd == 3:
            travel = to_table_phi(phi_i) + 180.0
            rel = np.radians(to_table_phi(PS) - travel)
            a, b = disc_to_square(s_o * np.cos(rel), s_o * np.sin(rel))
            k0 = int(min(res - 1, max(0, (0.5 - 0.5 * math.sin(math.radians(theta_i))) * res)))
            return g[k0, np.minimum((a * res).astype(int), res - 1), np.minimum((b * res).astype(int), res - 1)]
        travel = math.radians(to_table_phi(phi_i) + 180.0)
        s_i = math.sin(math.radians(theta_i))
        ia, ib = disc_to_square(s_i * math.cos(travel), s_i * math.sin(travel))
        a, b = disc_to_square(s_o * np.cos(np.radians(to_table_phi(PS))), s_o * np.sin(np.radians(to_table_phi(PS))))
        c = lambda x: np.minimum((np.asarray(x) * res).astype(int), res - 1)  # noqa: E731
        return g[c(ia), c(ib), c(a), c(b)]
    return lookup
