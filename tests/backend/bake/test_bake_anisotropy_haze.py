"""Bake: anisotropy in Cycles' conventions, the lobe's aspect ratio from a table, the table's haze."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.bake import closure_anisotropy, reflection_slope_ratio, transmission_haze


def _cycles_ratio(a_signed: float, closure: str) -> float:
    """alpha_x / alpha_y that Cycles 5.0 makes of a signed value (a quarter turn where negative)."""
    a = abs(a_signed)
    if closure == "metallic":
        aspect = np.sqrt(1.0 - 0.9 * a)
        rho = (1.0 / aspect) / aspect
    else:
        rho = (1.0 - a) / (1.0 / (1.0 - a))
    return rho if a_signed >= 0 else 1.0 / rho


@pytest.mark.parametrize("closure", ["metallic", "glossy"])
@pytest.mark.parametrize("rho", [0.2, 0.5, 1.0, 2.0, 4.1, 9.0])
def test_closure_anisotropy_inverts_cycles(closure, rho):
    a = closure_anisotropy(rho, closure)
    assert _cycles_ratio(a, closure) == pytest.approx(rho, rel=1e-9)


def test_closure_anisotropy_limits():
    assert closure_anisotropy(float("nan"), "metallic") == 0.0
    assert closure_anisotropy(50.0, "metallic") == 1.0                     # Cycles' Metallic stops at 10
    assert closure_anisotropy(1.0, "glossy") == 0.0


def _table(values_T, values_R=None, specular_T=0.0):
    from relief_bsdf.bsdf.table import BsdfTable
    te = np.linspace(0.0, 90.0, 46)
    pe = np.arange(-5.0, 360.0, 10.0)
    S, A = te.size - 1, pe.size - 1
    v = np.zeros((1, 1, 1, 2, S, A))
    v[0, 0, 0, 1] = values_T(te, pe)
    if values_R is not None:
        v[0, 0, 0, 0] = values_R(te, pe)
    return BsdfTable(wavelength_nm=np.array([550.0]), theta_i_deg=np.array([0.0]), phi_i_deg=np.array([0.0]),
                     theta_s_edges_deg=te, phi_s_edges_deg=pe, values_per_sr=v,
                     specular_R=np.zeros((1, 1, 1)), specular_T=np.full((1, 1, 1), specular_T))


def test_haze_counts_light_beyond_2_5_degrees():
    # T cells: a uniform 1/sr everywhere, no material (n = 1: the flat face deviates nothing): the bake's
    # haze is the one definition (bsdf.haze), the share beyond 2.5 deg: pi cos^2(2.5) / (pi + specular)
    def uniform(te, pe):
        return np.ones((te.size - 1, pe.size - 1))
    t = _table(uniform, specular_T=0.5)
    want = np.pi * np.cos(np.radians(2.5)) ** 2 / (np.pi + 0.5)
    assert transmission_haze(t) == pytest.approx(want, abs=1e-3)
    flat = _table(lambda te, pe: np.zeros((te.size - 1, pe.size - 1)), specular_T=0.9)
    assert transmission_haze(flat) == 0.0


def test_slope_ratio_of_an_elliptical_lobe():
    # R cells filled with a Gaussian slope density of widths ax, ay over the half-vector slopes
    ax, ay = 0.3, 0.1
    def lobe(te, pe):
        th, ph = np.meshgrid(0.5 * (te[:-1] + te[1:]), 0.5 * (pe[:-1] + pe[1:]), indexing="ij")
        t, p = np.radians(th), np.radians(ph)
        h = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), 1 + np.cos(t)], -1)
        sx, sy = h[..., 0] / h[..., 2], h[..., 1] / h[..., 2]
        return np.exp(-(sx / ax) ** 2 - (sy / ay) ** 2) / np.cos(t)
    t = _table(lambda te, pe: np.zeros((te.size - 1, pe.size - 1)), values_R=lobe)
    # cell quantisation (2 x 10 deg cells) blurs the narrow axis: within 15 %
    assert reflection_slope_ratio(t, 550.0) == pytest.approx(ax / ay, rel=0.15)


def test_tilt_slope_follows_the_ggx_one_axis_marginal():
    """The node group's random facet slope: its distribution is the one-axis marginal of the GGX slope
    density P(s) = 1 / (pi c^2 (1 + |s|^2 / c^2)^2) (Walter et al. 2007 eq. 33 in slope space), here
    integrated over the other axis by quadrature (independent of the closed form the bake inverts)."""
    from scipy.integrate import quad
    from relief_bsdf.bake import tilt_slope
    c = 0.3
    s = tilt_slope((np.arange(400_000) + 0.5) / 400_000, c)          # stratified uniform u
    edges = np.array([-1.0, -0.5, -0.2, -0.05, 0.0, 0.1, 0.3, 0.6, 1.5])
    got = np.histogram(s, edges)[0] / s.size

    def marginal(x):
        return quad(lambda y: 1.0 / (np.pi * c * c * (1.0 + (x * x + y * y) / (c * c)) ** 2), -np.inf, np.inf)[0]
    want = np.array([quad(marginal, a, b)[0] for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-5)


def test_tilt_scale_adds_widths_between_cauchy_and_gauss():
    """c / alpha_narrow for a lobe alpha_wide / alpha_narrow = q: widths of independent slopes add linearly
    for Cauchy-tailed and in quadrature for Gaussian ones; GGX marginals (t with 2 degrees of freedom) lie in
    between, so q - 1 < c / alpha_narrow < sqrt(q^2 - 1); it grows with q and vanishes for a round lobe."""
    from relief_bsdf.bake import MIN_TILT_ASPECT, tilt_scale_ratio
    ratios = [tilt_scale_ratio(q) for q in (1.5, 2.0, 4.0, 8.0)]
    for q, r in zip((1.5, 2.0, 4.0, 8.0), ratios):
        assert q - 1.0 < r < np.sqrt(q * q - 1.0), (q, r)
    assert np.all(np.diff(ratios) > 0)
    assert tilt_scale_ratio(1.0) == 0.0 and tilt_scale_ratio(0.5 * (1.0 + MIN_TILT_ASPECT)) == 0.0
    assert tilt_scale_ratio(float("nan")) == 0.0


def test_transmission_tilt_keeps_the_mean_width_and_points_along_the_wide_axis():
    """alpha_wide alpha_narrow = alpha_mean^2 (the fitted roughness is the lobes' geometric mean), the
    closure keeps the narrow width, the tilt's sign names the wide axis (x: +, y: -); round lobes: no tilt,
    the fitted roughness unchanged."""
    from relief_bsdf.bake import tilt_scale_ratio, transmission_tilt
    r = np.array([0.3, 0.5, 0.7])
    for rho, sign in ((4.0, 1.0), (0.25, -1.0)):
        r_closure, c = transmission_tilt(r, rho)
        np.testing.assert_allclose(r_closure ** 2, r ** 2 / 2.0, rtol=1e-12)          # narrow = mean / sqrt(4)
        np.testing.assert_allclose(c, sign * tilt_scale_ratio(4.0) * r ** 2 / 2.0, rtol=1e-12)
    r_closure, c = transmission_tilt(r, 1.02)
    np.testing.assert_array_equal(r_closure, r)
    np.testing.assert_array_equal(c, 0.0)
