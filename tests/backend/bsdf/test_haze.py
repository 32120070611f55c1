"""The one haze (bsdf/haze.py): ASTM D1003 on a plate with a flat clear second face, checked on
cases with a closed form or a one-dimensional quadrature written here (Fresnel from its textbook
formula, not the project's)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from relief_bsdf.bsdf.haze import haze_astm_d1003
from relief_bsdf.bsdf.table import BsdfTable

TE = np.linspace(0.0, 90.0, 91)
PE = np.linspace(0.0, 360.0, 73)
MAT = {"inside": {"model": "constant", "n": 1.5, "k": 0.0}, "outside": {"model": "constant", "n": 1.0, "k": 0.0}}


def _fresnel(cos_i: float, n1: float, n2: float) -> float:
    """Unpolarised reflectance of a flat boundary, medium n1 -> n2 (1 past the critical angle)."""
    sin_t = n1 / n2 * np.sqrt(max(0.0, 1 - cos_i ** 2))
    if sin_t >= 1:
        return 1.0
    cos_t = np.sqrt(1 - sin_t ** 2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (rs ** 2 + rp ** 2)


def _lambertian(frm: str, t_diffuse: float, t_spec: float, theta_i: float = 0.0) -> BsdfTable:
    v = np.zeros((1, 1, 1, 2, TE.size - 1, PE.size - 1))
    v[..., 1, :, :] = t_diffuse / np.pi
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=[theta_i], phi_i_deg=[0.0], theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, specular_T=t_spec, incident_from=frm,
                     specular_R=1 - t_diffuse - t_spec, material=MAT, method="test")


def test_flat_boundary_has_no_haze():
    assert haze_astm_d1003(_lambertian("outside", 0.0, 0.96)) == 0.0
    assert haze_astm_d1003(_lambertian("inside", 0.0, 0.96)) == 0.0


def test_lambertian_exit_face_is_its_share_beyond_2p5_deg():
    """Rough face from inside: the exit directions are the table's (in air); a Lambertian part sends
    T_d sin^2 a into a cone of half-angle a, so haze = T_d cos^2(2.5 deg) / (T_d + T_s)."""
    td, ts = 0.3, 0.6
    want = td * np.cos(np.radians(2.5)) ** 2 / (td + ts)
    assert haze_astm_d1003(_lambertian("inside", td, ts), sub=16) == pytest.approx(want, abs=3e-4)


def test_lambertian_entry_face_through_the_flat_back_face():
    """Rough face lit from outside: light at theta_g in the glass leaves the flat back face at
    sin theta = 1.5 sin theta_g with transmittance 1 - F, trapped past the critical angle."""
    td, ts, n = 0.3, 0.6, 1.5
    crit = np.arcsin(1 / n)
    cut = np.arcsin(np.sin(np.radians(2.5)) / n)
    dens = lambda g: (td / np.pi) * 2 * np.pi * np.cos(g) * np.sin(g) * (1 - _fresnel(np.cos(g), n, 1.0))  # noqa: E731
    wide = quad(dens, cut, crit, limit=200)[0]
    total = quad(dens, 0.0, crit, limit=200)[0] + ts * (1 - _fresnel(1.0, n, 1.0))
    got = haze_astm_d1003(_lambertian("outside", td, ts), sub=16)
    assert got == pytest.approx(wide / total, abs=3e-4)
    # the same scattering seen as the boundary's own share (no plate) would be larger: the plate traps
    # the widest light, which D1003 does not see
    assert got < td * np.cos(np.radians(2.5)) ** 2 / (td + ts)


def test_oblique_only_table_has_no_d1003_haze_and_n_argument_wins():
    assert np.isnan(haze_astm_d1003(_lambertian("outside", 0.3, 0.6, theta_i=30.0)))
    t = _lambertian("outside", 0.3, 0.6)
    assert haze_astm_d1003(t, n=1.0) == pytest.approx(haze_astm_d1003(_lambertian("inside", 0.3, 0.6)), abs=1e-12)
