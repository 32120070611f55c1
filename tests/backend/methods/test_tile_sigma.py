"""The wave tables' sigma_per_sr states the finite tile's realisation uncertainty honestly.

Independent check (no circularity): many independently seeded tiles of the same statistics
(surface.synth, exact_rms off, so the rms height varies between tiles as it does between real
samples) are reconstructed; the spread of each cell value over the tiles is compared with the sigma
each table states from its own single tile (speckle / periodogram statistics, methods.realisation).

Tolerances.  With K = 16 tiles the sample standard deviation of one cell is known to
1 / sqrt(2 (K - 1)) = 18 %; the median over the lobe's cells (tens of cells, correlated in
neighbouring groups) to about 6 %.  The closed form approximates a (theta, phi) cell by a rectangle and
the density as smooth over the filter (~10 %).  So the median ratio spread / stated sigma must lie in
[0.8, 1.25].  z-scores use each table's own sigma, which is proportional to its own (noisy) value and
whose cell values are sums of few chi^2_2 grains (skewed): their robust width (median |z| / 0.6745)
must lie in [0.8, 1.4], and 80-99 % of them within |z| < 2.
"""
import warnings
from dataclasses import replace

import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import reconstruct
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec

MAT = Material(inside=ConstantIndex(1.5))
K = 16


def _tiles(method: str, periodic: bool):
    rms = 0.1e-6 if method == "kirchhoff" else 10e-9
    opts = {"backend": "serial", **({"band_limited": True} if method == "kirchhoff" else {})}
    req = Request(theta_i_deg=(30.0,), theta_s_edges_deg=tuple(np.arange(0, 81, 4.0)),
                  phi_s_edges_deg=tuple(np.arange(-15, 346, 30.0)), options=opts)
    vals, sigs = [], []
    for seed in range(K):
        rel = relief_from_spec(RandomFieldSpec(nx=128, ny=128, pitch_m=0.125e-6, rms_height_m=rms,
                                               corr_length_m=1e-6, exact_rms=False), seed)
        if not periodic:
            rel = replace(rel, periodic=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            (t,) = reconstruct(rel, MAT, req, method)
        vals.append(t.values_per_sr[0, 0, 0])
        sigs.append(t.sigma_per_sr[0, 0, 0])
    return np.array(vals), np.array(sigs), t


@pytest.mark.parametrize("periodic", [True, False], ids=["periodic", "hann-windowed"])
@pytest.mark.parametrize("method", ["kirchhoff", "rayleigh-rice"])
def test_stated_sigma_matches_the_spread_over_independent_tiles(method, periodic):
    v, s, last = _tiles(method, periodic)
    assert "realisation" in last.metadata["uncertainty"]["sigma"]
    mean = v.mean(axis=0)
    for k, side in enumerate("RT"):
        lobe = mean[k] > 0.05 * mean[k].max()
        assert lobe.sum() >= 10
        spread = v[:, k].std(axis=0, ddof=1)[lobe]
        stated = np.sqrt(np.mean(s[:, k] ** 2, axis=0))[lobe]
        ratio = float(np.median(spread / stated))
        z = ((v[:, k] - mean[k]) / np.where(s[:, k] > 0, s[:, k], np.inf) * np.sqrt(K / (K - 1)))[:, lobe]
        robust = float(np.median(np.abs(z)) / 0.6745)
        inside2 = float(np.mean(np.abs(z) < 2))
        assert 0.8 <= ratio <= 1.25, (side, ratio)
        assert 0.8 <= robust <= 1.4, (side, robust)
        assert 0.8 <= inside2 <= 0.99, (side, inside2)


def test_too_small_a_tile_for_the_cells_warns():
    """A 96 x 96 tile of 1 um correlation length at 0.125 um pitch holds ~200 correlation areas (1/e length): 4-degree
    cells of its Kirchhoff lobe scatter by far more than 10 % between tiles, and the table says so."""
    rel = relief_from_spec(RandomFieldSpec(nx=96, ny=96, pitch_m=0.125e-6, rms_height_m=0.1e-6,
                                           corr_length_m=1e-6), 1)
    req = Request(theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.arange(0, 61, 4.0)),
                  phi_s_edges_deg=tuple(np.arange(-5, 356, 10.0)), options={"backend": "serial", "band_limited": True})
    with pytest.warns(RuntimeWarning, match="too few for the cells"):
        (t,) = reconstruct(rel, MAT, req, "kirchhoff")
    assert t.metadata["warnings"] and t.metadata["uncertainty"]["lobe_relative_tile_sigma_max"] > 0.1


# ------------------------------------------------------------------ microfacet: lobes fitted to one tile


def _microfacet_tile(seed: int, n: int = 128, **options):
    """A Gaussian tile of rms slope 0.3 per axis (l = 8 px, rms height free between tiles) and its microfacet
    table at 30 deg (lobes fitted to its slopes)."""
    rel = relief_from_spec(RandomFieldSpec(nx=n, ny=n, pitch_m=1e-6, rms_height_m=0.3 * np.sqrt(2) * 4e-6,
                                           corr_length_m=8e-6, exact_rms=False), seed)
    req = Request(theta_i_deg=(30.0,), incident_from=("outside",), theta_s_edges_deg=tuple(np.arange(0, 91, 3.0)),
                  phi_s_edges_deg=tuple(np.arange(-5.0, 356.0, 10.0)), options=options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return reconstruct(rel, MAT, req, "microfacet")[0]


def test_microfacet_table_states_its_tiles_realisation():
    t = _microfacet_tile(0)
    assert t.sigma_per_sr is not None and t.sigma_per_sr.shape == t.values_per_sr.shape
    lobe = t.values_per_sr > 0.05 * t.values_per_sr.max()
    assert np.all(t.sigma_per_sr[lobe] > 0)
    u = t.metadata["uncertainty"]
    assert "realisation" in u["sigma"] and u["subtiles"][0] * u["subtiles"][1] >= 9     # sub-tiles of >= 4 l
    assert _microfacet_tile(0, tile_uncertainty=False).sigma_per_sr is None
    assert "no tile" in _microfacet_tile(0, alpha=0.4).metadata["uncertainty"]["sigma"]


@pytest.mark.slow
def test_microfacet_sigma_matches_the_spread_over_independent_tiles():
    """48 independent 128^2 tiles: the spread of each lobe cell over the tiles against the sigma each table
    states from its own tile (sub-tile refits of the lobe).  Every cell follows the one fitted alpha, so the
    cells are not independent checks: the ratio is one number, known to ~1/sqrt(2 x 47) = 10 % from the
    tiles' spread and ~15 % from each table's batch-means estimate of 9-16 sub-tiles: [0.7, 1.4]
    (measured 0.98; 1.26 on another 48 seeds; a table without the tile part states 0)."""
    tabs = [_microfacet_tile(seed) for seed in range(48)]
    V = np.array([t.values_per_sr[0, 0, 0] for t in tabs])
    S = np.array([t.sigma_per_sr[0, 0, 0] for t in tabs])
    for k in (0, 1):
        mean = V[:, k].mean(axis=0)
        lobe = mean > 0.05 * mean.max()
        ratio = float(np.median(V[:, k].std(axis=0, ddof=1)[lobe] / np.sqrt(np.mean(S[:, k] ** 2, axis=0))[lobe]))
        assert 0.7 <= ratio <= 1.4, (k, ratio)
