"""Physics of the validation's own photon engine (validation/photon.py, the physics of `relief conceal`).

Moved unchanged from the diagnosis's test_effects.py when the diagnosis stopped using this
engine: the tests check the engine itself (Fresnel series of a flat plate,
Brewster angle, tilt, Henyey-Greenstein sampling, volume scattering, rough back face, blur).
The Henyey-Greenstein sampler now lives in core.bulk (`sample_hg_cos`).
"""
import numpy as np
import pytest

from relief_bsdf.core.bulk import sample_hg_cos as _hg_cos
from relief_bsdf.core.fresnel import fresnel_power
from relief_bsdf.validation.photon import NormalsFace, PlatePhysics, beckmann_normals, detect, run_photons

FLAT = NormalsFace(np.array([[0.0, 0.0, 1.0]]))
N = 20000


def _plate_RT(theta_deg, n, t_mm, a_per_mm, pol):
    """Incoherent flat plate (Stokes channel s or p): multiple reflections summed exactly."""
    ci = np.cos(np.radians(theta_deg))
    Rs, Rp, _, _ = fresnel_power(ci, 1.0, n)
    R = float(Rs if pol == "s" else Rp)
    ct = np.sqrt(1 - (np.sin(np.radians(theta_deg)) / n) ** 2)
    att = np.exp(-a_per_mm * t_mm / ct)
    T = (1 - R) ** 2 * att / (1 - R**2 * att**2)
    Rt = R + (1 - R) ** 2 * R * att**2 / (1 - R**2 * att**2)
    return Rt, T


def _fractions(ex):
    up = ex.d[:, 2] > 0
    return ex.w[up].sum() / ex.n_launched, ex.w[~up].sum() / ex.n_launched


@pytest.mark.parametrize("pol,stokes", [("s", (1, 1, 0, 0)), ("p", (1, -1, 0, 0))])
@pytest.mark.parametrize("theta", [0.0, 56.31, 70.0])
def test_flat_plate_matches_incoherent_fresnel_series(pol, stokes, theta):
    ex = run_photons(FLAT, PlatePhysics(thickness_mm=2.0, n_glass=1.5, absorption_per_mm=0.2), theta, 0.0,
                     stokes, N, np.random.default_rng(1))
    R, T = _fractions(ex)
    Rt, Tt = _plate_RT(theta, 1.5, 2.0, 0.2, pol)
    tol = 4 * np.sqrt(Rt * (1 - Rt) / N) + 1e-4
    assert R == pytest.approx(Rt, abs=tol)
    assert T == pytest.approx(Tt, abs=4 * np.sqrt(Tt * (1 - Tt) / N) + 1e-4)


def test_brewster_angle_p_source_reflects_almost_nothing():
    tb = np.degrees(np.arctan(1.5))
    ex_p = run_photons(FLAT, PlatePhysics(), tb, 0.0, (1, -1, 0, 0), N, np.random.default_rng(2))
    ex_s = run_photons(FLAT, PlatePhysics(), tb, 0.0, (1, 1, 0, 0), N, np.random.default_rng(2))
    assert _fractions(ex_p)[0] < 2e-3
    assert _fractions(ex_s)[0] > 0.2


def test_tilt_rotates_the_specular_reflection_by_twice_the_tilt():
    ex = run_photons(FLAT, PlatePhysics(tilt_deg=3.0), 30.0, 0.0, (1, 0, 0, 0), 2000, np.random.default_rng(3))
    up = ex.d[ex.d[:, 2] > 0]
    th = np.degrees(np.arccos(up[:, 2]))
    assert np.allclose(th, 30.0 + 6.0, atol=1e-6) or np.allclose(th, 30.0 - 6.0, atol=1e-6)
    # transmission through a tilted parallel plate stays undeviated
    dn = ex.d[ex.d[:, 2] < 0]
    assert np.allclose(np.degrees(np.arccos(-dn[:, 2])), 30.0, atol=1e-6)


def test_henyey_greenstein_sampler_mean_cosine_is_g():
    u = np.random.default_rng(4).random(200000)
    for g in (0.0, 0.5, 0.9):
        assert np.mean(_hg_cos(g, u)) == pytest.approx(g, abs=5e-3)


def test_volume_scattering_removes_the_direct_beam_as_exp_minus_mu_t():
    mu, t = 0.3, 2.0
    ex = run_photons(FLAT, PlatePhysics(thickness_mm=t, scatter_per_mm=mu, hg_g=0.5), 0.0, 0.0, (1, 0, 0, 0), N,
                     np.random.default_rng(5))
    direct = np.sum(ex.d[:, 2] < -1 + 1e-9) / N
    T0 = _plate_RT(0.0, 1.5, t, 0.0, "s")[1]
    # first-pass direct transmission dominates T0; multiple passes add (R^2 e^{-2 mu t}) corrections
    expect = (1 - 0.04) ** 2 * np.exp(-mu * t)
    assert direct == pytest.approx(expect, abs=0.02)
    assert direct < T0


def test_rough_back_face_spreads_transmission_with_roughness():
    spread = []
    for alpha in (0.05, 0.15):
        ex = run_photons(FLAT, PlatePhysics(back_alpha=alpha), 0.0, 0.0, (1, 0, 0, 0), 5000, np.random.default_rng(6))
        dn = ex.d[ex.d[:, 2] < 0]
        spread.append(np.sqrt(np.mean(np.arccos(-dn[:, 2]) ** 2)))
    assert spread[1] > 2.0 * spread[0]
    # Beckmann normals: mean square slope = alpha^2
    m = beckmann_normals(0.2, 100000, np.random.default_rng(0))
    assert np.mean((m[:, 0] ** 2 + m[:, 1] ** 2) / m[:, 2] ** 2) == pytest.approx(0.04, rel=0.03)


def test_detector_blur_keeps_the_integral_and_lowers_a_sharp_peak():
    ex = run_photons(NormalsFace(beckmann_normals(0.05, 20000, np.random.default_rng(1))), PlatePhysics(), 0.0, 0.0,
                     (1, 0, 0, 0), N, np.random.default_rng(7))
    th = np.array([0.0])
    sharp, _ = detect(ex, np.array(["T"]), th, th, 2.0)
    wide, _ = detect(ex, np.array(["T"]), th, th, 2.0, blur_sigma_deg=3.0)
    assert wide[0] < 0.8 * sharp[0]
