"""What a user sees through / on a rough boundary: haze, clarity, TIS and the coherent fractions.

From a BsdfTable (cell averages over projected solid angle, plus the specular deltas):

- **haze** (ASTM D1003 on the plate, `bsdf.haze.haze_astm_d1003`, the one definition shown
  everywhere): given on the row of the incidence nearest the normal (within 1 deg), NaN on the
  other rows (D1003 measures at normal incidence only).
- **clarity** (narrow-angle scatter, as the BYK haze-gard defines it, not part of D1003):
  C = (I_C - I_R) / (I_C + I_R), with I_C the transmitted light within 0.1 deg of the regular
  direction and I_R that between 0.1 and 2.5 deg.  With table cells coarser than 0.1 deg, I_C is
  the specular (coherent) part plus the cells' share inside 0.1 deg (cell values are averages,
  taken uniform over each cell) - a statement about the table's resolution, stated in `detail`.
- **TIS** (total integrated scatter, ISO 13696 in spirit): the diffuse (non-specular) share of the
  incident power on each side, R - specular_R and T - specular_T.
- **coherent fractions**: specular_R / R and specular_T / T.

The angular distance of a cell from the regular direction is evaluated on sub-points of each
cell (uniform in projected solid angle, as the table's cells are averages), so the share of a
cell beyond 2.5 deg is exact to the sub-sampling (8 x 8 per cell by default), independent of
how the 2.5 deg circle cuts the grid.  Haze and clarity are per wavelength, so their colour
dependence (sharper in the red for a wave-optics table) is visible row by row.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable

HAZE_ANGLE_DEG = 2.5
CLARITY_ANGLE_DEG = 0.1


@dataclass(frozen=True)
class Appearance:
    """Appearance figures of one incidence (module doc)."""

    wavelength_nm: float
    theta_i_deg: float
    phi_i_deg: float
    incident_from: str
    haze: float
    clarity: float
    tis_R: float
    tis_T: float
    coherent_fraction_R: float
    coherent_fraction_T: float

    def as_dict(self) -> dict:
        return asdict(self)


def _subpoints(table: BsdfTable, m: int):
    """Direction cosines (S, A, m*m) of sub-points uniform in projected solid angle in each cell."""
    te = np.radians(table.theta_s_edges_deg)
    pe = np.radians(table.phi_s_edges_deg)
    f = (np.arange(m) + 0.5) / m
    u = np.sin(te[:-1])[:, None] ** 2 + (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None] * f[None, :]
    ph = pe[:-1, None] + np.diff(pe)[:, None] * f[None, :]
    s = np.sqrt(u)[:, None, :, None]
    a = s * np.cos(ph)[None, :, None, :]
    b = s * np.sin(ph)[None, :, None, :]
    S, A = u.shape[0], ph.shape[0]
    return a.reshape(S, A, m * m), b.reshape(S, A, m * m)


def _angle_from(a, b, a0, b0) -> np.ndarray:
    """Angle (deg) between the directions with direction cosines (a, b) and (a0, b0), same hemisphere."""
    c = np.sqrt(np.clip(1 - a * a - b * b, 0, 1)) * np.sqrt(max(1 - a0 * a0 - b0 * b0, 0.0)) + a * a0 + b * b0
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def appearance(table: BsdfTable, sub: int = 8) -> list[Appearance]:
    """Haze, clarity, TIS and coherent fractions of every incidence of `table` (module doc)."""
    from relief_bsdf.core.index import Material
    mat = Material.from_dict(table.material) if table.material else None
    psa = table.projected_solid_angle_sr
    a, b = _subpoints(table, sub)
    h = table.hemispherical()
    from relief_bsdf.bsdf.haze import haze_astm_d1003
    it0 = int(np.argmin(np.abs(table.theta_i_deg)))
    d1003 = [haze_astm_d1003(table, wavelength_nm=float(w)) for w in table.wavelength_nm]
    out = []
    for iw, wl in enumerate(table.wavelength_nm):
        n1, n2 = (mat.n_pair(wl, table.incident_from) if mat is not None else (1.0, 1.0))
        n1, n2 = float(np.real(n1)), float(np.real(n2))
        for it, ti in enumerate(table.theta_i_deg):
            for ip, pi_ in enumerate(table.phi_i_deg):
                R, T = float(h["R"][iw, it, ip]), float(h["T"][iw, it, ip])
                sR, sT = float(table.specular_R[iw, it, ip]), float(table.specular_T[iw, it, ip])
                s_t = n1 * np.sin(np.radians(ti)) / n2 if n2 > 0 else np.inf
                haze = clarity = float("nan")
                if s_t < 1 and T > 0:
                    a0 = -s_t * np.cos(np.radians(pi_))
                    b0 = -s_t * np.sin(np.radians(pi_))
                    ang = _angle_from(a, b, a0, b0)
                    power = table.values_per_sr[iw, it, ip, 1] * psa                      # (S, A)
                    wide = np.mean(ang > HAZE_ANGLE_DEG, axis=-1)
                    core = np.mean(ang <= CLARITY_ANGLE_DEG, axis=-1)
                    haze = d1003[iw] if ti == table.theta_i_deg[it0] and abs(ti) <= 1.0 else float("nan")
                    i_c = sT + float(np.sum(power * core))
                    i_r = float(np.sum(power * (1 - wide - core)))
                    clarity = (i_c - i_r) / (i_c + i_r) if i_c + i_r > 0 else float("nan")
                out.append(Appearance(float(wl), float(ti), float(pi_), table.incident_from, haze, clarity,
                                      R - sR, T - sT, sR / R if R > 0 else float("nan"),
                                      sT / T if T > 0 else float("nan")))
    return out
