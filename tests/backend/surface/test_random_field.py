"""ONE random-field generator with the documented autocovariance s^2 exp(-r^2/L^2) (surface/synth.py)."""
import numpy as np
import pytest
from scipy import optimize

from relief_bsdf.surface.stats import acf_2d, radial_average
from relief_bsdf.surface.synth import RandomFieldSpec, gaussian_field, random_heights, random_relief

S_M, L_M, PITCH_M, N = 30e-9, 1.6e-6, 0.1e-6, 512


def _radial_acf(relief):
    lx, ly, acf = acf_2d(relief)
    r, c = radial_average(lx, ly, acf)
    keep = r <= 3 * L_M
    return r[keep], c[keep] / c[0]


def test_acf_is_exp_minus_r2_over_L2():
    rel = random_relief(N, PITCH_M, S_M, L_M, "gaussian", seed=7)
    r, c = _radial_acf(rel)
    (L_fit,), _ = optimize.curve_fit(lambda r, L: np.exp(-(r / L) ** 2), r, c, p0=[L_M])
    assert L_fit == pytest.approx(L_M, rel=0.05)              # tile = 32 L: a few % realisation scatter
    # exp(-r^2 / (2 l^2)) with l = L (the convention that was wrong in one old copy) fits far worse
    good = np.sum((c - np.exp(-(r / L_M) ** 2)) ** 2)
    bad = np.sum((c - np.exp(-(r / L_M) ** 2 / 2)) ** 2)
    assert bad > 20 * good


def test_exponential_acf():
    # the exponential ACF's long tail scatters one realisation's L by ~10 %: average six tiles
    cs = [_radial_acf(random_relief(N, PITCH_M, S_M, L_M, "exponential", seed=s)) for s in range(6)]
    r, c = cs[0][0], np.mean([c for _, c in cs], axis=0)
    k = r <= 1.5 * L_M
    (L_fit,), _ = optimize.curve_fit(lambda r, L: np.exp(-r / L), r[k], c[k], p0=[L_M])
    assert L_fit == pytest.approx(L_M, rel=0.05)


def test_heights_only_helper_is_the_same_field():
    spec = RandomFieldSpec(nx=64, ny=48, pitch_m=PITCH_M, rms_height_m=S_M, corr_length_m=0.5e-6)
    rel = random_relief(64, PITCH_M, S_M, 0.5e-6, seed=3, ny=48)
    np.testing.assert_array_equal(random_heights(spec, seed=3), rel.heights_m)
    z = gaussian_field(spec, np.random.default_rng(0))
    assert z.shape == (48, 64)
    assert np.sqrt(np.mean(z**2)) == pytest.approx(S_M) and abs(z.mean()) < 1e-12 * S_M
