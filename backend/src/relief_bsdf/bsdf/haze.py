"""Haze as ASTM D1003 defines it, for a boundary table (formats.md: one definition everywhere).

ASTM D1003 measures a *plate*: light at normal incidence from outside, haze = the share of the
plate's total transmittance that leaves more than 2.5 deg from the incident direction.  A
boundary table describes one face, so the plate here is that face on a plate of the table's
index with a flat, clear second face:

- table for light from outside (the rough face is lit): the light transmitted into the glass
  in direction theta_g leaves through the flat back face at sin theta_out = n sin theta_g with
  the Fresnel transmittance of that face (unpolarised); theta_g past the critical angle is
  trapped (total internal reflection) and is not transmitted.
- table for light from inside (the rough face is the exit face): the flat front face refracts
  nothing at normal incidence, so the light meets the rough face from inside at 0 deg and the
  table's transmitted directions (in air) are the exit directions; the front face's Fresnel
  factor is common to all of them and cancels in the ratio.

The deviation of an exit direction from the incident (normal) direction is its polar angle.
Each cell's power (value x projected solid angle) is split over m x m sub-points uniform in
projected solid angle, so the 2.5 deg circle cuts cells exactly to the sub-sampling; the delta
part (specular_T) leaves undeviated.  Single pass: light reflected back by the flat face (about
4 % at n = 1.5) and returned through the rough face is not followed, which changes the haze by
a few per cent of its value at most.
"""
from __future__ import annotations

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable

HAZE_ANGLE_DEG = 2.5


def _index(table: BsdfTable, iw: int, n: float | None) -> float:
    if n is not None:
        return float(n)
    if not table.material:
        return 1.0
    from relief_bsdf.core.index import Material
    n_out, n_in = Material.from_dict(table.material).n_pair(float(table.wavelength_nm[iw]), "outside")
    return float(np.real(n_in) / np.real(n_out))


def haze_astm_d1003(table: BsdfTable, n: float | None = None, wavelength_nm: float | None = None,
                    sub: int = 8) -> float:
    """ASTM D1003 haze (fraction, 0..1) of `table`'s boundary on a plate with a flat clear second
    face (module doc), at the tabulated wavelength nearest `wavelength_nm` (default: the first),
    from the incidence nearest the normal (NaN if none within 1 deg), azimuths averaged.  `n`: the
    plate's index relative to the outside medium (default: the table's material; 1 without one).
    NaN when nothing is transmitted."""
    iw = 0 if wavelength_nm is None else int(np.argmin(np.abs(table.wavelength_nm - float(wavelength_nm))))
    it = int(np.argmin(np.abs(table.theta_i_deg)))
    if abs(table.theta_i_deg[it]) > 1.0:
        return float("nan")
    nr = _index(table, iw, n)
    te, pe = np.radians(table.theta_s_edges_deg), np.radians(table.phi_s_edges_deg)
    u = (np.arange(sub) + 0.5) / sub
    s2 = np.sin(te[:-1])[:, None] ** 2 + (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None] * u[None, :]
    sin_s = np.sqrt(s2)                                                   # (S, sub); azimuth does not matter
    if table.incident_from == "outside":
        from relief_bsdf.core.fresnel import fresnel_unpolarized
        sin_out = nr * sin_s
        ok = sin_out < 1.0
        cos_g = np.sqrt(1.0 - s2)
        t_face = np.where(ok, 1.0 - np.real(fresnel_unpolarized(cos_g, nr, 1.0)), 0.0)
        t0 = 1.0 - float(np.real(fresnel_unpolarized(1.0, nr, 1.0)))
    else:
        sin_out, ok = sin_s, np.ones_like(sin_s, bool)
        t_face, t0 = np.ones_like(sin_s), 1.0
    wide = ok & (sin_out > np.sin(np.radians(HAZE_ANGLE_DEG)))
    psa = table.projected_solid_angle_sr                                   # (S, A)
    out = []
    for ip in range(table.phi_i_deg.size):
        power = (table.values_per_sr[iw, it, ip, 1] * psa).sum(axis=1)     # (S,) per theta ring
        through = np.sum(power * t_face.mean(axis=1)) + float(table.specular_T[iw, it, ip]) * t0
        scattered = np.sum(power * (t_face * wide).mean(axis=1))
        out.append(scattered / through if through > 0 else np.nan)
    return float(np.mean(out))
