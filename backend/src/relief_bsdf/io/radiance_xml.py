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
- Energy is projected, not sampled.  A Klems entry is (integral of f cos over the scattered
  patch) / (the patch's projected solid angle), computed exactly: the table is constant over each
  of its cells (cell averages) and both cells and patches are rectangles in (sin^2 theta, phi),
  so the integral is a sum of cell values times overlap areas (`klems_patch_power`).  The delta
  parts (specular_R, specular_T) add power / projected solid angle to the patch holding the
  mirror / refracted direction.  Each column thus integrates to the table's R or T exactly, for
  a lobe of any width: what a 5-15 deg patch cannot hold is the shape below its size, never the
  power (the writer says so in one line).
- Incidence: each incident patch (cell of a tree's incidence axis) carries one incidence's
  distribution: the tabulated incidence it holds, else its centre, linearly interpolated in
  theta_i (`incidence_cells`), so a consumer gets the table's R and T exactly at every
  tabulated incidence and the linear interpolation between them at patch centres (a
  TensorTree4 cell holding a tabulated (theta_i, phi_i) carries it likewise).  Beyond the
  tabulated range the nearest distribution is used with R and T moved as a smooth boundary's
  Fresnel reflectance changes, and a warning line says which incidences (never silently held).
  A delta transmission interpolated past the critical angle is totally reflected (moved to R).
- Tensor trees (``TensorTree3`` for an isotropic table, ``TensorTree4`` otherwise, Radiance's
  variable-resolution format) are written as uniform trees on Shirley-Chiu square-to-disc
  coordinates of both hemispheres; depth from the narrowest lobe (`tree_depth_for`: cells no
  wider than half its rms radius, 4 to 6 for TensorTree3, 4 to 5 for TensorTree4); each cell
  holds the table's mean over its sub-points, scaled to the table's exact R / T per incidence.
- Reciprocity (Radiance's checkBSDF, mean relative difference of f(i->o) and f(o->i) over its
  samples): transmission blocks differ by n^2 by design (radiance BTDFs of a boundary between
  two media, formats.md; a Radiance layer has one medium on both sides), so their figure
  measures n^2, not an error.  Reflection: one incidence per incident patch or cell while the
  scattered side is integrated over patches is not symmetric for lobes comparable to the patch
  size; on an exactly reciprocal Beckmann-like lobe (rms radius 11 deg, incidences every 5 deg)
  checkBSDF reports about 6 % (Klems) and 9 % (tree depth 6) with tabulated incidences kept
  exact, 4.7 % for the tree when every cell carries its centre's incidence
  (``keep_tabulated=False``, which costs exactness at tabulated incidences: up to several per
  cent of R at 60 deg).  Monte-Carlo tables add their own noise to the figure, and a table of
  few incidences (0, 30, 60 deg) is only as reciprocal as the linear interpolation between
  them (checkBSDF then reports 40-55 %); `relief export` prints the figure after writing.
- Reading (`read_radiance_xml`): Klems patches nest whole into the default cells; a tree cell's
  power is spread over the table cells its sub-points fall in; incidences (and azimuths) are
  the writer's when its comments list them; `lost` is 1 - R - T of what the file holds.
- One spectral channel: the table's wavelength nearest `wavelength_nm` (default 555 nm) is
  written as ``Visible`` (photopic) data; the wavelength is recorded in a comment.

Regime of validity: Klems patches are 5-15 degrees wide, so lobes narrower than a patch are
smeared over it (their power is kept); the tensor tree of depth d resolves cells of
2 / 2^d in sin(theta) (1.8 deg near the normal at depth 6) and incidence steps of 2 / 2^d in
sin(theta_i).
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
from relief_bsdf.core.frames import projected_solid_angle
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


def specular_directions(table: BsdfTable, iw: int, theta_i_deg: np.ndarray) -> np.ndarray | None:
    """Polar angle (deg) of the refracted direction for each incidence, NaN beyond the critical
    angle; None when the table does not state its material (indices)."""
    from relief_bsdf.io.isbsdf import refracted_theta_deg, table_indices
    try:
        n1, n2 = table_indices(table, iw)
    except (InputError, KeyError, TypeError, ValueError):
        return None
    return refracted_theta_deg(theta_i_deg, n1, n2, past_critical=np.nan)


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


# ====================================================================== projection (energy kept)


@dataclass(frozen=True)
class IncidenceCells:
    """What the table says for one incidence direction: a weighted sum of tabulated distributions.

    parts: (weight, cells (2, S, A) in 1/sr on the table's scatter grid, azimuth shift_deg):
    direction (theta_s, phi_s) of the table at its tabulated azimuth is (theta_s, phi_s + shift) for
    this incidence (an isotropic table is turned, an anisotropic one is blended, shift 0).
    spec: (specular_R, specular_T) power fractions; held_from: the tabulated polar angle whose
    distribution stands in for an incidence beyond the table (None inside the table)."""

    parts: tuple
    spec: tuple
    held_from: float | None = None


def _fresnel_r(table: BsdfTable, iw: int, theta_deg: float) -> float | None:
    """Smooth-boundary unpolarised Fresnel reflectance for the table's index pair (None: no material)."""
    from relief_bsdf.core.fresnel import fresnel_unpolarized
    from relief_bsdf.io.isbsdf import table_indices
    try:
        n1, n2 = table_indices(table, iw)
    except (InputError, KeyError, TypeError, ValueError):
        return None
    return float(np.real(fresnel_unpolarized(np.cos(np.radians(theta_deg)), n1, n2)))


def incidence_cells(table: BsdfTable, iw: int, theta_i_deg: float, src_phi_deg: float) -> IncidenceCells:
    """The table at an arbitrary incidence (theta_i, phi_i = src_phi, table frame).

    Inside the tabulated range: linear in theta_i (so R and T are the table's, linearly
    interpolated), azimuth turned (isotropic table) or linearly blended between the two nearest
    tabulated phi_i (anisotropic).  Beyond the last tabulated theta_i (or before the first): the
    nearest tabulated distribution, with power moved between R and T as much as a smooth
    boundary's Fresnel reflectance changes between the two angles (R + T kept, so a lossless table
    stays lossless); without a material the distribution is held unchanged.  Callers say which
    incidences were extrapolated (`held_from`).  A delta transmission interpolated to an incidence
    past the critical angle (light from inside) is moved to the delta reflection: total internal
    reflection, R + T kept."""
    ti = table.theta_i_deg
    v = table.values_per_sr[iw]                                           # (I, P, 2, S, A)
    t = float(theta_i_deg)
    held = None
    if ti.size == 1 or t <= ti[0] or t >= ti[-1]:
        k = 0 if (ti.size == 1 or t <= ti[0]) else ti.size - 1
        th = [(k, 1.0)]
        if abs(t - ti[k]) > 1e-6:
            held = float(ti[k])
    else:
        j = int(np.searchsorted(ti, t, side="right"))
        f = (t - ti[j - 1]) / (ti[j] - ti[j - 1])
        th = [(j - 1, 1.0 - f), (j, f)]
    if table.is_isotropic:
        ph = [(0, 1.0, float(src_phi_deg) - float(table.phi_i_deg[0]))]
    else:
        pi = table.phi_i_deg
        order = np.argsort(pi % 360.0)
        grid = (pi % 360.0)[order]
        x = float(src_phi_deg) % 360.0
        ext = np.concatenate([grid, [grid[0] + 360.0]])
        xr = x if x >= grid[0] else x + 360.0
        j = min(int(np.searchsorted(ext, xr, side="right")), grid.size)
        f = (xr - ext[j - 1]) / (ext[j] - ext[j - 1])
        ph = [(int(order[(j - 1) % grid.size]), 1.0 - f, 0.0), (int(order[j % grid.size]), f, 0.0)]
    parts, sR, sT = [], 0.0, 0.0
    for i, wt in th:
        for p, wp, shift in ph:
            w = wt * wp
            if w <= 0:
                continue
            parts.append([w, v[i, p].astype(float), shift])
            sR += w * float(table.specular_R[iw, i, p])
            sT += w * float(table.specular_T[iw, i, p])
    if sT > 0:                                  # an interpolated delta past the critical angle: none is
        tgt = specular_directions(table, iw, np.array([t]))   # transmitted there; it is totally reflected
        if tgt is not None and not np.isfinite(tgt[0]):
            sR, sT = sR + sT, 0.0
    if held is not None:
        F0, F1 = _fresnel_r(table, iw, held), _fresnel_r(table, iw, t)
        if F0 is not None:
            psa = table.projected_solid_angle_sr
            R = sum(w * float(np.sum(c[0] * psa)) for w, c, _ in parts) + sR
            T = sum(w * float(np.sum(c[1] * psa)) for w, c, _ in parts) + sT
            d = float(np.clip(F1 - F0, -R, T))                            # power moved from T to R
            a = 1.0 + d / R if R > 0 else 1.0
            b = 1.0 - d / T if T > 0 else 1.0
            for part in parts:
                part[1] = part[1] * np.array([a, b])[:, None, None]
            sR, sT = sR * a, sT * b
    return IncidenceCells(tuple(tuple(p) for p in parts), (sR, sT), held)


def representative_theta(lo_deg: np.ndarray, hi_deg: np.ndarray, centre_deg: np.ndarray,
                         tabulated_deg: np.ndarray) -> np.ndarray:
    """The incidence each incident cell [lo, hi] stands for: the tabulated incidence it holds (the one
    nearest its centre), else its centre; so a consumer reading a tabulated incidence gets exactly
    the table's distribution there (no interpolation across the cell)."""
    out = np.array(centre_deg, float, copy=True)
    tab = np.asarray(tabulated_deg, float)
    for k in range(out.size):
        inside = tab[(tab >= lo_deg[k] - 1e-9) & (tab < hi_deg[k] - 1e-9)]
        if lo_deg[k] <= 1e-9 and tab.size and tab.min() <= 1e-9:
            inside = tab[tab <= 1e-9]
        if inside.size:
            out[k] = inside[np.argmin(np.abs(inside - centre_deg[k]))]
    return out


def _periodic_overlap_deg(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Length (deg) of the overlap of azimuth intervals [a0, a1] and [b0, b1] on the circle (each <= 360)."""
    s = np.mod(a0, 360.0)
    a1 = s + (a1 - a0)
    a0 = s
    s = np.mod(b0, 360.0)
    b1 = s + (b1 - b0)
    b0 = s
    out = 0.0
    for k in (-360.0, 0.0, 360.0):
        out = out + np.maximum(0.0, np.minimum(a1, b1 + k) - np.maximum(a0, b0 + k))
    return out


def _sin2_overlap(lo_a, hi_a, lo_b, hi_b) -> np.ndarray:
    """Projected-solid-angle factor (sin^2 hi - sin^2 lo) / 2 of the overlap of two theta ranges (deg)."""
    lo = np.radians(np.maximum(lo_a, lo_b))
    hi = np.radians(np.minimum(hi_a, hi_b))
    return np.where(hi > lo, 0.5 * (np.sin(hi) ** 2 - np.sin(lo) ** 2), 0.0)


def klems_patch_power(table: BsdfTable, cells: np.ndarray, shift_deg: float, basis: AngleBasis = KLEMS) -> np.ndarray:
    """Power (fraction of the incident) that one side's cells (S, A) send into each scattered patch
    of the basis: the exact integral of f cos over each patch, the table being constant over each
    cell (a cell average in projected solid angle), its azimuths turned by shift_deg.  Patch
    azimuths are Radiance's (table azimuth = -Radiance azimuth)."""
    p = basis.patches()
    te, pe = table.theta_s_edges_deg, table.phi_s_edges_deg
    oth = _sin2_overlap(te[:-1, None], te[1:, None], p["theta_lo"][None, :], p["theta_hi"][None, :])  # (S, N)
    # patch in the table frame: [-phi_hi, -phi_lo]; table cell turned: [pe_a + shift, pe_a+1 + shift]
    oph = np.radians(_periodic_overlap_deg(pe[:-1, None] + shift_deg, pe[1:, None] + shift_deg,
                                           -p["phi_hi"][None, :], -p["phi_lo"][None, :]))               # (A, N)
    return np.einsum("sa,an,sn->n", cells, oph, oth)


def klems_matrix(table: BsdfTable, side: str, iw: int = 0, basis: AngleBasis = KLEMS, m: int = 8,
                 notes: list | None = None, keep_tabulated: bool = True) -> np.ndarray:
    """(n_out, n_in) Klems matrix (1/sr) of one side of `table` at wavelength index iw (module doc).

    Entry = (integral of f cos over the scattered patch) / (the patch's projected solid angle) for
    the incidence each incident patch stands for (`representative_theta`: the tabulated one it
    holds, else its centre; `incidence_cells`); the delta part adds its power / projected solid
    angle to the patch holding the mirror / refracted direction.  Each column therefore
    integrates to the table's R or T at that incidence exactly.  (Averaging the incidence over the
    incident patch too would make the matrix symmetric for a reciprocal table, but it averages R
    and T over the patch's 10-15 deg of incidence, several per cent off the tabulated values for a
    coarse incidence grid: not done.)  `m` is kept for callers (the projection is exact; it needs
    no samples).  keep_tabulated False: every incident patch at its centre (module doc: the
    reciprocity / exactness trade).  Extrapolated incidences are noted in `notes`."""
    p = basis.patches()
    th_i = (representative_theta(p["theta_lo"], p["theta_hi"], p["theta_c"], table.theta_i_deg)
            if keep_tabulated else p["theta_c"])
    lam = basis.projected_solid_angle_sr()
    k = 0 if side == "R" else 1
    M = np.zeros((basis.size, basis.size))
    held = {}
    for i in range(basis.size):
        t, ph_travel = float(th_i[i]), float(p["phi_c"][i])
        ic = incidence_cells(table, iw, t, float(to_table_phi(ph_travel + 180.0)))
        for w, cells, shift in ic.parts:
            M[:, i] += w * klems_patch_power(table, cells[k], shift, basis) / lam
        sp = ic.spec[k]
        if sp > 0:
            tgt = t if side == "R" else float(_refracted_or_fail(table, iw, np.array([t]), np.array([sp]))[0])
            if np.isfinite(tgt):
                o = int(basis.index(tgt, ph_travel))                # leaves along the travel azimuth
                M[o, i] += sp / lam[o]
        if ic.held_from is not None:
            held[round(t, 2)] = ic.held_from
    if held and notes is not None:
        notes.append(_held_note(table, sorted(held), held))
    return M


def _held_note(table: BsdfTable, angles: list, held: dict) -> str:
    src = sorted(set(held.values()))
    how = ("power moved between R and T as a smooth boundary's Fresnel reflectance changes"
           if _fresnel_r(table, 0, 0.0) is not None else "held unchanged (the table states no refractive index)")
    return (f"warning: the {table.incident_from} table holds theta_i {table.theta_i_deg[0]:g}-"
            f"{table.theta_i_deg[-1]:g} deg; incidences {', '.join(f'{a:g}' for a in angles)} deg are "
            f"extrapolated from {', '.join(f'{a:g}' for a in src)} deg ({how}; lobe directions not moved)")


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
            "relief: theta_i_deg = " + ", ".join(f"{x:g}" for x in t.theta_i_deg),
            "relief: phi_i_deg = " + ", ".join(f"{x:g}" for x in t.phi_i_deg),
            "relief: front = light from outside (table 'outside'), back = light from inside (table 'inside')",
            "relief: values = BSDF in 1/sr; transmission tabulated over directions in the medium entered "
            "(power conserving); delta parts folded into the patch of the mirror / refracted direction"]


def write_radiance_xml(path: str | Path, tables: list[BsdfTable], wavelength_nm: float | None = None,
                       structure: str = "klems", depth: int | None = None, samples_per_patch: int = 4,
                       notes: list | None = None, keep_tabulated: bool = True) -> Path:
    """Write both sides of a boundary as one LBNL/WINDOW XML BSDF (module doc); returns the path.

    structure "klems" (LBNL/Klems Full matrices) or "tensor-tree" (uniform tree; `depth` None:
    chosen from the narrowest lobe, `tree_depth_for`).  Lines for the user (what the basis cannot
    hold, extrapolated incidences) are appended to `notes` when given, each starting with
    "note:" or "warning:".  samples_per_patch: sub-points per table cell side when splatting onto
    a tensor tree.  keep_tabulated (default): an incident patch / cell holding a tabulated
    incidence carries exactly that incidence's distribution (R and T exact there); False: every
    one carries its centre's (more reciprocal, module doc).
    """
    by = _table_pair(tables)
    iw = _nearest_wl(by["outside"], wavelength_nm)
    wl = float(by["outside"].wavelength_nm[iw])
    iw_in = _nearest_wl(by["inside"], wl)
    notes = [] if notes is None else notes
    thick = 0.0                                      # one boundary: no thickness of its own
    name = f"relief-bsdf boundary ({by['outside'].method})"
    width = min(lobe_width_deg(by["outside"], iw), lobe_width_deg(by["inside"], iw_in))
    spec = any(np.any(t.specular_R > 0) or np.any(t.specular_T > 0) for t in by.values())
    lines: list[str] = []
    if structure == "klems":
        head = _header(name, thick, _comments(by, iw, "Klems full basis"),
                       "<IncidentDataStructure>Columns</IncidentDataStructure>\n" + _basis_xml(KLEMS))
        body = []
        for direction, frm, side in BLOCKS:
            t = by[frm]
            M = klems_matrix(t, side, iw if frm == "outside" else iw_in, KLEMS, notes=lines,
                             keep_tabulated=keep_tabulated)
            text = "\n".join(", ".join(f"{v:.6g}" for v in row) for row in M)
            body.append(_block(direction, "BTDF" if side == "T" else "BRDF", text, KLEMS_FULL_NAME))
        if width < 5.0 or spec:
            what = (f"the narrowest lobe (rms radius {width:.2g} deg)" if width < 5.0 else "") + \
                (" and " if width < 5.0 and spec else "") + ("the specular (delta) parts" if spec else "")
            lines.append(f"note: Klems patches are 5-15 deg wide: {what} are spread over one patch each; "
                         "power kept, shape below the patch size lost (--structure tensor-tree resolves finer)")
            lines[-1] = lines[-1].replace("deg) are spread", "deg) is spread")
    elif structure == "tensor-tree":
        iso = by["outside"].is_isotropic and by["inside"].is_isotropic
        kind = "TensorTree3" if iso else "TensorTree4"
        if depth is None:
            depth = tree_depth_for(width, iso)
        cell_deg = float(np.degrees(np.arcsin(2.0 / 2 ** depth)))
        head = _header(name, thick, _comments(by, iw, f"{kind}, uniform depth {depth}"),
                       f"<IncidentDataStructure>{kind}</IncidentDataStructure>")
        body = []
        for direction, frm, side in BLOCKS:
            t = by[frm]
            grid = tensor_tree_grid(t, side, iw if frm == "outside" else iw_in, depth, iso, samples_per_patch,
                                    notes=lines, keep_tabulated=keep_tabulated)
            body.append(_block(direction, "BTDF" if side == "T" else "BRDF", format_tree(grid), None))
        lines.append(f"note: {kind} depth {depth}: cells ~{cell_deg:.2g} deg near the normal, incidence steps "
                     f"{1.0 / 2 ** (depth - 1):.3g} in sin(theta_i); "
                     + (f"the narrowest lobe (rms radius {width:.2g} deg) is below the cell size: shape averaged, "
                        "power kept" if width < 2 * cell_deg else f"narrowest lobe rms radius {width:.2g} deg")
                     + ("; delta parts fill one cell" if spec else ""))
    else:
        raise InputError("radiance-xml", f"structure must be 'klems' or 'tensor-tree', got {structure!r}")
    for line in lines:
        if line not in notes:
            notes.append(line)
    return write_text_atomic(Path(path), head + "".join(body) + "</Layer>\n</Optical>\n</WindowElement>\n")


def checkbsdf_reciprocity(path: str | Path) -> dict | None:
    """Radiance's checkBSDF reciprocity figures of a written file, {component: (min, mean, max) in %},
    or None when Radiance's checkBSDF is not installed (pyradiance bundles it; optional here)."""
    import shutil
    import subprocess
    exe = None
    try:
        import pyradiance  # noqa: F401  (optional: bundles Radiance's tools)
        cand = Path(pyradiance.__file__).parent / "bin" / "checkBSDF"
        exe = str(cand) if cand.exists() else None
    except ImportError:
        pass
    exe = exe or shutil.which("checkBSDF")
    if exe is None:
        return None
    try:
        r = subprocess.run([exe, str(path)], capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.SubprocessError):
        return None
    if r.returncode != 0 or "Reciprocity Error" not in r.stdout:
        return None
    rows = re.findall(r"^(\w[\w >-]*?)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*$",
                      r.stdout.split("Reciprocity Error")[1], flags=re.M)
    return {name.strip(): tuple(float(x) for x in v) for name, *v in rows}


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


def _cell_samples(table: BsdfTable, k: int) -> tuple[np.ndarray, np.ndarray]:
    """sin(theta) and table azimuth (deg) of k x k points per scatter cell, uniform in projected
    solid angle (sin^2 theta and phi): arrays (S, A, k*k)."""
    te, pe = np.radians(table.theta_s_edges_deg), table.phi_s_edges_deg
    u = (np.arange(k) + 0.5) / k
    s2 = np.sin(te[:-1])[:, None] ** 2 + u[None, :] * (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None]
    ph = pe[:-1, None] + u[None, :] * np.diff(pe)[:, None]
    S, A = s2.shape[0], ph.shape[0]
    s = np.broadcast_to(np.sqrt(s2)[:, None, :, None], (S, A, k, k)).reshape(S, A, k * k)
    p = np.broadcast_to(ph[None, :, None, :], (S, A, k, k)).reshape(S, A, k * k)
    return s, p


def tree_gather_index(table: BsdfTable, n: int, table_phi_offset_deg: float, g: int = 4) -> np.ndarray:
    """Flat table-cell index (n, n, g*g) of g x g sub-points of every cell of the n x n concentric
    square (uniform in projected solid angle: the map is area preserving), the table turned by
    `table_phi_offset_deg`; -1 where a point lies beyond the table's theta range."""
    u = (np.arange(n * g) + 0.5) / (n * g)
    x, y = square_to_disc(*np.meshgrid(u, u, indexing="ij"))
    th, ph_rad = _disc_angles(x, y)
    ph = np.mod(to_table_phi(ph_rad) - table_phi_offset_deg, 360.0)
    te, pe = table.theta_s_edges_deg, table.phi_s_edges_deg
    it = np.searchsorted(te, th, side="right") - 1
    it = np.where(th == te[-1], te.size - 2, it)
    ip = np.clip(np.searchsorted(pe, np.mod(ph - pe[0], 360.0) + pe[0], side="right") - 1, 0, pe.size - 2)
    idx = np.where((it >= 0) & (it <= te.size - 2), it * (pe.size - 1) + ip, -1)
    return idx.reshape(n, g, n, g).transpose(0, 2, 1, 3).reshape(n, n, g * g)


def _gather(cells: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Tree-cell values (n, n): the mean of the table's cell values at each tree cell's sub-points."""
    flat = np.concatenate([cells.ravel(), [0.0]])
    return flat[index].mean(axis=-1)


def tensor_tree_grid(table: BsdfTable, side: str, iw: int, depth: int, isotropic: bool, m: int = 4,
                     notes: list | None = None, keep_tabulated: bool = True) -> np.ndarray:
    """Uniform tensor-tree grid (1/sr) of one side: (N, N, N) for TensorTree3 or (N, N, N, N) for
    TensorTree4, N = 2^depth, in Radiance's index order (module doc).

    TensorTree3 (Radiance bsdf_t.c): axis 0 is 0.5 - sin(theta_in) / 2 (only its first half is
    used; the second mirrors it), axes 1-2 the scattered direction on the concentric square,
    rotated so the incident light travels toward azimuth 0.  TensorTree4: axes 0-1 the travel
    direction of the incident light, axes 2-3 the scattered direction.  For the incidence each
    incident cell stands for (`representative_theta`, `incidence_cells`) each tree cell holds the
    mean of the table's cell values at its m x m sub-points (uniform in projected solid angle),
    the whole grid then scaled by the ratio of the table's exact R or T to this quadrature (a
    fraction of a per cent), so each incidence's R and T are the table's exactly; the delta part
    goes into the cell holding its direction as power / (pi / N^2)."""
    n = 2 ** depth
    c = (np.arange(n) + 0.5) / n
    k = 0 if side == "R" else 1
    cache: dict = {}

    def index_for(offset: float) -> np.ndarray:
        key = round(offset % 360.0, 9)
        if key not in cache:
            cache[key] = tree_gather_index(table, n, offset, m)
        return cache[key]

    psa = table.projected_solid_angle_sr

    held = {}

    def grid_at(theta: float, src_phi: float) -> tuple[np.ndarray, float]:
        ic = incidence_cells(table, iw, theta, src_phi)
        g = np.zeros((n, n))
        exact = 0.0
        for w, cells, shift in ic.parts:
            g += w * _gather(cells[k], index_for(shift))
            exact += w * float(np.sum(cells[k] * psa))
        got = float(g.sum()) * np.pi / n ** 2
        if got > 0:
            g *= exact / got                      # the quadrature's small error: power kept exactly
        if ic.held_from is not None:
            held[round(float(theta), 2)] = ic.held_from
        return g, ic.spec[k]

    if isotropic:
        sin_i = np.clip(1.0 - 2.0 * c[: n // 2], 0.0, 1.0)
        edge = np.degrees(np.arcsin(np.clip(1.0 - 2.0 * np.arange(n // 2 + 1) / n, 0.0, 1.0)))
        th_i = np.degrees(np.arcsin(sin_i))
        if keep_tabulated:
            th_i = representative_theta(edge[1:], edge[:-1], th_i, table.theta_i_deg)
        src = float(to_table_phi(180.0))
        res = [grid_at(t, src) for t in th_i]
        half = np.stack([r[0] for r in res])
        _add_tree_specular(half, table, side, iw, th_i, np.zeros_like(th_i), spec=np.array([r[1] for r in res]))
        out = np.concatenate([half, half[::-1]], axis=0)
    else:
        ix, iy = square_to_disc(*np.meshgrid(c, c, indexing="ij"))
        th_i, ph_travel = _disc_angles(ix, iy)
        if keep_tabulated:                       # a cell holding a tabulated (theta_i, phi_i) carries it
            best = np.full((n, n), np.inf)
            for t in table.theta_i_deg:
                for pz in table.phi_i_deg:
                    trav = float(to_table_phi(pz)) + 180.0
                    st = math.sin(math.radians(t))
                    a, b = disc_to_square(st * math.cos(math.radians(trav)), st * math.sin(math.radians(trav)))
                    cand = {(min(max(int(float(a) * n + ea), 0), n - 1), min(max(int(float(b) * n + eb), 0), n - 1))
                            for ea in (-1e-7, 1e-7) for eb in (-1e-7, 1e-7)}   # on a cell edge: both cells
                    for ia, ib in cand:
                        d = math.hypot(float(a) * n - ia - 0.5, float(b) * n - ib - 0.5)
                        if d < best[ia, ib]:
                            best[ia, ib] = d
                            th_i[ia, ib], ph_travel[ia, ib] = t, trav % 360.0
        src = to_table_phi(ph_travel + 180.0)
        out = np.empty((n, n, n, n))
        spec = np.empty((n, n))
        for a in range(n):
            for b in range(n):
                out[a, b], spec[a, b] = grid_at(th_i[a, b], src[a, b])
        _add_tree_specular(out.reshape((n * n, n, n)), table, side, iw, th_i.ravel(), ph_travel.ravel(),
                           spec=spec.ravel())
    if held and notes is not None:
        notes.append(_held_note(table, sorted(held), held))
    return out


def _add_tree_specular(grid: np.ndarray, table: BsdfTable, side: str, iw: int, theta_i_deg: np.ndarray,
                       travel_phi_deg: np.ndarray, spec: np.ndarray) -> None:
    """Fold the delta part (power fractions `spec` per incident cell) into the scattered cell holding
    the mirror / refracted direction, in place.  grid (K, N, N): per incident cell k the scattered
    square; the delta leaves along the incident light's travel azimuth (Radiance frame).  Cell
    value += power / (pi / N^2)."""
    if not np.any(spec > 0):
        return
    tgt = theta_i_deg if side == "R" else _refracted_or_fail(table, iw, theta_i_deg, spec)
    ok = np.isfinite(tgt) & (spec > 0)
    n = grid.shape[-1]
    s = np.sin(np.radians(np.where(ok, tgt, 0.0)))
    a, b = disc_to_square(s * np.cos(np.radians(travel_phi_deg)), s * np.sin(np.radians(travel_phi_deg)))
    ia, ib = np.minimum((a * n).astype(int), n - 1), np.minimum((b * n).astype(int), n - 1)
    kk = np.nonzero(ok)[0]
    grid[kk, ia[kk], ib[kk]] += spec[kk] / (np.pi / n**2)


def lobe_width_deg(table: BsdfTable, iw: int = 0) -> float:
    """The narrowest diffuse lobe of the table: over incidences and sides, the rms angular radius
    (deg, on the projected disc: sin theta) of the cells' power about its centroid; inf if none."""
    s, p = _cell_samples(table, 1)
    x = (s * np.cos(np.radians(p)))[..., 0]
    y = (s * np.sin(np.radians(p)))[..., 0]
    psa = table.projected_solid_angle_sr
    best = np.inf
    v = table.values_per_sr[iw]
    for idx in np.ndindex(v.shape[:3]):
        P = v[idx] * psa
        tot = P.sum()
        if tot <= 1e-9:
            continue
        mx, my = (P * x).sum() / tot, (P * y).sum() / tot
        r2 = (P * ((x - mx) ** 2 + (y - my) ** 2)).sum() / tot
        best = min(best, float(np.degrees(np.arcsin(min(1.0, np.sqrt(r2))))))
    return best


def lobe_anisotropy(table: BsdfTable, iw: int = 0) -> float | None:
    """How far the boundary is from rotation invariance: the ratio of the relief's rms slopes along x
    and y when the table records them (relief "rms_slope_x", "rms_slope_y"), else the ratio of the
    principal rms widths (on the projected disc) of the diffuse lobe at the incidence nearest the
    normal (within 1 deg), the side holding more diffuse power; 1 for a round lobe.  An isotropic
    boundary has a round lobe at normal incidence, so > 1.2 says a table with one incidence
    azimuth misdescribes the boundary.  None: nothing to judge by."""
    rel = table.relief or {}
    sx, sy = rel.get("rms_slope_x"), rel.get("rms_slope_y")
    if isinstance(sx, (int, float)) and isinstance(sy, (int, float)) and min(sx, sy) > 0:
        return float(max(sx, sy) / min(sx, sy))     # the relief's own statement, when the table records it
    it = int(np.argmin(np.abs(table.theta_i_deg)))
    if abs(table.theta_i_deg[it]) > 1.0:
        return None
    s, p = _cell_samples(table, 1)
    x = (s * np.cos(np.radians(p)))[..., 0]
    y = (s * np.sin(np.radians(p)))[..., 0]
    psa = table.projected_solid_angle_sr
    P = [table.values_per_sr[iw, it, 0, k] * psa for k in (0, 1)]
    P = P[int(np.argmax([q.sum() for q in P]))]
    tot = P.sum()
    if tot <= 1e-9:
        return None
    mx, my = (P * x).sum() / tot, (P * y).sum() / tot
    dx, dy = x - mx, y - my
    cov = np.array([[(P * dx * dx).sum(), (P * dx * dy).sum()], [(P * dx * dy).sum(), (P * dy * dy).sum()]]) / tot
    ev = np.linalg.eigvalsh(cov)
    return float(np.sqrt(ev[1] / ev[0])) if ev[0] > 0 else None


def tree_depth_for(width_deg: float, isotropic: bool, max_depth: int | None = None) -> int:
    """Tensor-tree depth for a lobe of rms radius `width_deg` (`lobe_width_deg`): cells (2 / 2^depth
    on the disc) no wider than half of it, between 4 and max_depth (default 6 for TensorTree3, 5
    for TensorTree4: the file grows as 2^(3 or 4 * depth))."""
    top = max_depth or (6 if isotropic else 5)
    if not np.isfinite(width_deg) or width_deg <= 0:
        return 4
    need = int(np.ceil(np.log2(4.0 / np.sin(np.radians(width_deg)))))
    return int(np.clip(need, 4, top))


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


def read_radiance_xml(path: str | Path, wavelength_nm: float | None = None, phi_i_deg: Any = None,
                      theta_s_edges_deg: Any = None, phi_s_edges_deg: Any = None) -> list[BsdfTable]:
    """A WINDOW/Radiance XML BSDF (Klems matrices or tensor trees) as BsdfTables: the front
    blocks become the `outside` table, the back blocks the `inside` table (module doc).

    Incidence: the polar angles and azimuths a `relief:` comment lists (the table the file was
    written from), else the Klems ring centres (0, 10, ..., 70, 82.5 deg) or 16 tensor-tree angles;
    azimuths `phi_i_deg` when given, else the comment's, else 0 (the file taken as isotropic) or
    every 45 deg for a TensorTree4 or a Klems file whose totals change with the incident azimuth
    by more than 1 % (`klems_azimuth_spread`).  Scatter cells default to 2.5 x 0.75 degrees, which nest
    inside Klems patches (1 x 2 degrees for tensor trees, each tree cell's power spread over them),
    so hemispherical totals are the file's.  Delta parts cannot be told apart from the cells:
    specular_R/T are 0.  `lost` is 1 - R - T of what the file holds.  The wavelength comes from a
    relief comment, else `wavelength_nm`, else 555 nm ("Visible").
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
    tagged_t, tagged_p = _comment_list(path, "theta_i_deg"), _comment_list(path, "phi_i_deg")
    if tagged_t is not None:
        th_i = tagged_t
    aniso_klems = klems and getattr(lookup, "azimuth_spread", 0.0) > 0.01
    if phi_i_deg is None:
        phi_i_deg = tagged_p if tagged_p is not None else (
            np.arange(0.0, 360.0, 45.0) if structure == "TensorTree4" or aniso_klems else (0.0,))
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
                    v[0, i, p, k] = (lookup(direction, t, ph, te, pe) if not klems
                                     else lookup(direction, t, ph, TS, PS))
        t = BsdfTable(wavelength_nm=[wl], theta_i_deg=th_i, phi_i_deg=pi, theta_s_edges_deg=te,
                      phi_s_edges_deg=pe, values_per_sr=v, incident_from=frm, method="radiance-xml import",
                      metadata={"imported_from": str(path), "structure": structure,
                                "note": "delta parts are inside the cells (not separable); lost = 1 - R - T"})
        h = t.hemispherical()
        t.lost = 1.0 - h["R"] - h["T"]
        tables.append(t)
    return tables


def _comment_list(path: Path, key: str) -> np.ndarray | None:
    """Numbers of a '<!-- relief: key = a, b, ... -->' comment, or None."""
    m = re.search(rf"relief: {key} = ([^<>\n]*?)\s*-->", path.read_text(encoding="utf-8", errors="replace")[:6000])
    if not m:
        return None
    try:
        return np.array([float(x) for x in m.group(1).split(",") if x.strip()])
    except ValueError:
        return None


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
    lookup.azimuth_spread = klems_azimuth_spread(mats)
    return lookup


def klems_azimuth_spread(mats: dict) -> float:
    """Largest relative spread (max / min - 1) of the directional-hemispherical totals over the incident
    patches of one Klems ring, over rings and blocks: 0 for a rotation-invariant (isotropic) layer."""
    lam = KLEMS.projected_solid_angle_sr()
    worst = 0.0
    for M in mats.values():
        tot = lam @ M                                             # (n_in,) hemispherical total per column
        start = 0
        for _, _, n in KLEMS.rings:
            ring = tot[start:start + n]
            start += n
            if n > 1 and ring.max() > 1e-6:
                worst = max(worst, float(ring.max() / max(ring.min(), 1e-12) - 1.0))
    return worst


def _tree_lookup(blocks: dict, nd: int, path: Path):
    """A function (direction, theta_i, phi_i, te, pe) -> (S, A) cell values (1/sr) of one block:
    every tree cell's power (value * pi / res^2) spread over the table cells its sub-points fall in,
    divided by each table cell's projected solid angle, so the hemispherical totals are the file's."""
    grids = {}
    for d, b in blocks.items():
        tree = _parse_tree(_text(_child(b, "ScatteringData")), nd, path)
        res = 2 ** min(_tree_depth(tree, nd), 7 if nd == 3 else 5)
        grids[d] = _tree_to_grid(tree, nd, res)
    sub: dict = {}

    def points(res: int):                       # (x, y) on the disc of 4 x 4 sub-points per tree cell
        if res not in sub:
            u = (np.arange(4 * res) + 0.5) / (4 * res)
            A, B = np.meshgrid(u, u, indexing="ij")
            sub[res] = square_to_disc(A, B)
        return sub[res]

    def lookup(direction, theta_i, phi_i, te, pe):
        g = grids[direction]
        res = g.shape[-1]
        if nd == 3:
            # the cell whose polar range [lo, hi) holds theta_i (as the writer's representative_theta)
            k0 = int(min(res - 1, max(0, math.ceil((0.5 - 0.5 * math.sin(math.radians(theta_i))) * res - 1e-9) - 1)))
            leaf = g[k0]
            turn = float(to_table_phi(phi_i)) + 180.0                 # travel azimuth, Radiance frame
        else:
            travel = math.radians(float(to_table_phi(phi_i)) + 180.0)
            s_i = math.sin(math.radians(theta_i))
            ia, ib = disc_to_square(s_i * math.cos(travel), s_i * math.sin(travel))
            c = lambda x: int(min(res - 1, max(0, float(x) * res)))  # noqa: E731
            leaf = g[c(ia), c(ib)]
            turn = 0.0
        x, y = points(res)
        th = np.degrees(np.arcsin(np.clip(np.hypot(x, y), 0.0, 1.0)))
        ph = to_table_phi(np.degrees(np.arctan2(y, x)) + turn)
        it = np.clip(np.searchsorted(te, th, side="right") - 1, 0, te.size - 2)
        ip = np.clip(np.searchsorted(pe, np.mod(ph - pe[0], 360.0) + pe[0], side="right") - 1, 0, pe.size - 2)
        power = np.repeat(np.repeat(leaf, 4, axis=0), 4, axis=1) * (np.pi / (16 * res * res))
        cells = np.bincount((it * (pe.size - 1) + ip).ravel(), weights=power.ravel(),
                            minlength=(te.size - 1) * (pe.size - 1)).reshape(te.size - 1, pe.size - 1)
        return cells / projected_solid_angle(te, pe)
    return lookup
