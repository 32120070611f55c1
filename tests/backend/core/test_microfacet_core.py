"""Microfacet distributions and their slope sampling (core/microfacet.py)."""
import numpy as np
import pytest
from scipy import integrate

from relief_bsdf.core.microfacet import distribution_D, normals_from_slopes, sample_normals, sample_slopes, smith_G1


@pytest.mark.parametrize("dist", ["beckmann", "ggx"])
@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_projected_area_normalisation(dist, alpha):
    val = integrate.quad(lambda t: 2 * np.pi * distribution_D(np.cos(t), alpha, dist) * np.cos(t) * np.sin(t),
                         0, np.pi / 2, limit=200)[0]
    assert val == pytest.approx(1.0, rel=1e-6)


def test_beckmann_slopes_have_rms_magnitude_alpha_and_ggx_median_alpha():
    rng = np.random.default_rng(4)
    s = sample_slopes(0.3, 400_000, rng, "beckmann")
    assert np.sqrt(np.mean(np.sum(s * s, axis=1))) == pytest.approx(0.3, rel=5e-3)
    g = sample_slopes(0.3, 400_000, rng, "ggx")
    assert np.median(np.hypot(g[:, 0], g[:, 1])) == pytest.approx(0.3, rel=1e-2)   # CDF r^2 / (a^2 + r^2)


def test_sampled_normals_follow_D():
    n = sample_normals(0.4, 400_000, np.random.default_rng(5), "beckmann")
    # the normals' cos(theta_m) histogram is D(m) cos(theta_m) dw (projected-area weighting)
    hist, edges = np.histogram(n[:, 2], bins=10, range=(np.cos(np.radians(70)), 1.0))
    expect = [integrate.quad(lambda c: 2 * np.pi * distribution_D(c, 0.4) * c, a, b)[0]
              for a, b in zip(edges[:-1], edges[1:])]
    np.testing.assert_allclose(hist / n.shape[0], expect, atol=2e-3)
    np.testing.assert_allclose(normals_from_slopes(0.0, 0.0), [0, 0, 1.0])


def test_smith_g1_limits():
    assert smith_G1(1.0, 0.3) == pytest.approx(1.0)
    assert smith_G1(1e-6, 0.3) < 1e-3
