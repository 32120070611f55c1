"""Beer-Lambert and Henyey-Greenstein (core/bulk.py)."""
import numpy as np
import pytest
from scipy import integrate

from relief_bsdf.core.bulk import beer_lambert, hg_phase, sample_hg_cos, scatter_directions, slab_transmittance
from relief_bsdf.core.frames import direction


@pytest.mark.parametrize("g", [0.0, 0.3, 0.85, -0.5])
def test_hg_sampling_has_mean_cosine_g(g):
    u = np.random.default_rng(1).random(400_000)
    c = sample_hg_cos(g, u)
    assert c.min() >= -1 and c.max() <= 1
    assert np.mean(c) == pytest.approx(g, abs=4e-3)


@pytest.mark.parametrize("g", [0.0, 0.6, -0.3])
def test_hg_phase_is_normalised_and_matches_the_samples(g):
    norm = integrate.quad(lambda c: 2 * np.pi * hg_phase(c, g), -1, 1)[0]
    assert norm == pytest.approx(1.0, rel=1e-9)
    c = sample_hg_cos(g, np.random.default_rng(2).random(400_000))
    hist, edges = np.histogram(c, bins=20, range=(-1, 1))
    expect = [integrate.quad(lambda x: 2 * np.pi * hg_phase(x, g), a, b)[0] for a, b in zip(edges[:-1], edges[1:])]
    np.testing.assert_allclose(hist / c.size, expect, atol=3e-3)


def test_scattered_directions_are_unit_with_mean_cosine_g():
    d = np.tile(direction(40.0, 10.0), (200_000, 1))
    out = scatter_directions(d, 0.7, np.random.default_rng(3))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    assert np.mean(out @ d[0]) == pytest.approx(0.7, abs=5e-3)


def test_beer_lambert_and_slab():
    assert beer_lambert(100.0, 0.01) == pytest.approx(np.exp(-1.0))
    np.testing.assert_allclose(slab_transmittance(50.0, 2e-3, np.cos(np.radians([0.0, 60.0]))),
                               np.exp(-50.0 * 2e-3 / np.array([1.0, 0.5])))
    assert slab_transmittance(50.0, 2e-3, 0.0) == 0.0          # grazing: |cos| floored, a very long path
