"""The synthesis (infer.synth): a periodic relief whose facet slopes follow a given density."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.infer.slopes import SlopeDensity
from relief_bsdf.infer.synth import cell_widths, density_check, lenslet_relief, plan_for
from relief_bsdf.surface.stats import facet_slopes, rms_slope_xy, slope_histogram


def _density(bins: int = 121, s_max: float = 0.5) -> SlopeDensity:
    """A separable density: a top-hat |sx| <= 0.2 across x, a Gaussian of sigma 0.1 along y."""
    e = np.linspace(-s_max, s_max, bins + 1)
    c = 0.5 * (e[1:] + e[:-1])
    px = (np.abs(c) <= 0.2).astype(float)
    py = np.exp(-0.5 * (c / 0.1) ** 2)
    p = np.outer(px, py)
    return SlopeDensity(e, e.copy(), p / (p.sum() * (e[1] - e[0]) ** 2))


def test_relief_reproduces_the_density():
    d = _density()
    relief, facts = lenslet_relief(d, plan_for(633.0, 512, seed=4))
    assert relief.periodic and relief.shape == (512, 512)
    # the facet slopes (as the ray tracer meets them) against the density: Kolmogorov distance of each
    # axis's distribution from the density's marginal (piecewise-linear CDF on its bins); a cell of m
    # pixels holds the m means of Q over its 1/m quantile shares, a CDF within 1 / (2 m) of the exact one
    sx, sy = facet_slopes(relief)
    px, py = d.marginals()
    ds = d.edges_sx[1] - d.edges_sx[0]
    for got, marginal in ((sx, px), (sy, py)):
        v = np.sort(got.ravel())
        cdf_p = np.interp(v, d.edges_sx, np.concatenate([[0.0], np.cumsum(marginal) * ds]))
        ks = np.max(np.abs(cdf_p - (np.arange(v.size) + 0.5) / v.size))
        assert ks < 1.0 / 64, ks      # the m-point discretisation of a cell: at most 1 / (2 m), m >= 32 px
    check = density_check(relief, d)           # the job's own check agrees
    assert check["ks_x"] < 1.0 / 64 and check["ks_y"] < 1.0 / 64
    assert check["rms_slope_relief"] == pytest.approx(check["rms_slope_density"], rel=0.01)
    rx, ry = rms_slope_xy(relief)
    m = d.moments()          # the binned top-hat reaches the outer edges of its bins: rms ~0.2066 / sqrt 3
    assert rx == pytest.approx(m["rms_slope_x"], rel=0.005) and ry == pytest.approx(m["rms_slope_y"], rel=0.01)
    assert np.nanmax(np.abs(facet_slopes(relief)[0])) < 0.21          # no slope outside the top-hat
    # the joint density: separable, as asked (coarse bins: a few discrete slopes per bin and cell)
    ex, ey, h = slope_histogram(relief, bins=20, max_slope=0.5)
    a = (ex[1] - ex[0]) ** 2
    hx, hy = h.sum(axis=1), h.sum(axis=0)
    tv = 0.5 * np.abs(h * a - np.outer(hx, hy) * a * a).sum()
    assert tv < 0.02, tv
    assert facts["separability_tv"] < 1e-12
    # the lateral scale: mean cell = lambda / 0.002
    assert facts["mean_cell_um"] == pytest.approx(633e-3 / 0.002, rel=1e-9)


def test_seeded_and_periodic_chains():
    d = _density()
    a, _ = lenslet_relief(d, plan_for(633.0, 256, seed=1))
    b, _ = lenslet_relief(d, plan_for(633.0, 256, seed=1))
    c, _ = lenslet_relief(d, plan_for(633.0, 256, seed=2))
    np.testing.assert_array_equal(a.heights_m, b.heights_m)
    assert not np.allclose(a.heights_m, c.heights_m)
    rng = np.random.default_rng(0)
    for n in (100, 256, 512, 777):
        w = cell_widths(n, 64, rng)
        assert sum(w) == n and min(w) >= 32 and max(w) <= 96 + 31
