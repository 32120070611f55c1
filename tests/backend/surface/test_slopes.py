"""ONE slope definition: relief info, the fit, the microfacet alpha and the mesh facets agree (surface/stats.py)."""
import json

import numpy as np
import pytest

from relief_bsdf.surface.mesh import build_tile_mesh
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import facet_slopes, relief_stats, rms_height_and_slope, rms_slope
from relief_bsdf.surface.synth import random_relief

S_M, L_M, PITCH_M, N = 40e-9, 2e-6, 0.1e-6, 512


@pytest.fixture(scope="module")
def gaussian():
    return random_relief(N, PITCH_M, S_M, L_M, "gaussian", seed=11)


def test_relief_info_prints_the_one_rms_slope_equal_to_2s_over_L(gaussian, tmp_path, capsys):
    from relief_bsdf.cli import main
    from relief_bsdf.io.heightmaps import write_relief
    path = write_relief(tmp_path / "g.npz", gaussian)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["rms_slope"] == pytest.approx(rms_slope(gaussian), rel=1e-12)
    assert info["rms_slope"] == pytest.approx(relief_stats(gaussian).rms_slope, rel=1e-12)
    # 2 s / L for s^2 exp(-r^2/L^2); a 256 L^2 tile scatters the slope by ~ L / T = 4 %, the
    # forward difference at L = 20 d is low by d^2 / (4 L^2) = 0.06 %
    assert info["rms_slope"] == pytest.approx(2 * S_M / L_M, rel=0.08)


def test_mesh_facets_carry_the_same_rms_slope(gaussian):
    sx, sy = facet_slopes(gaussian)
    assert np.sqrt(np.mean(sx**2 + sy**2)) == pytest.approx(rms_slope(gaussian), rel=1e-12)
    # and they are the slopes of the triangles surface.mesh builds for the ray tracer
    mesh = build_tile_mesh(gaussian)
    n = mesh.triangle_normals().astype(float)
    slope_sq = (n[:, 0] ** 2 + n[:, 1] ** 2) / n[:, 2] ** 2
    assert np.sqrt(np.mean(slope_sq)) == pytest.approx(rms_slope(gaussian), rel=1e-4)


def test_methods_use_the_same_figures(gaussian):
    from relief_bsdf.methods.microfacet import relief_slopes
    from relief_bsdf.methods.microfacet_dw import relief_sigma_slope
    from relief_bsdf.methods.normals import triangle_slopes
    from relief_bsdf.methods.rayleigh_rice import relief_sigma_slope as rr_sigma_slope
    sigma, slope = rms_height_and_slope(gaussian)
    assert sigma == pytest.approx(S_M, rel=1e-12)            # exact_rms synthesis, mean-levelled tile
    for f in (relief_sigma_slope, rr_sigma_slope):
        assert f(gaussian) == pytest.approx((sigma, slope), rel=1e-12)
    for sx, sy in (relief_slopes(gaussian), triangle_slopes(gaussian)):
        assert np.sqrt(np.mean(sx**2 + sy**2)) == pytest.approx(slope, rel=1e-9)


def test_the_fit_uses_the_same_rms_slope(gaussian):
    from relief_bsdf.fit.optimise import process_relief, relief_rms
    assert relief_rms(gaussian) == pytest.approx(rms_height_and_slope(gaussian), rel=1e-12)
    a = process_relief(gaussian, 1.7, 0.3)
    b = scale_and_filter(gaussian, 1.7, 0.3e-6)
    np.testing.assert_array_equal(a.heights_m, b.heights_m)


def test_scale_and_filter_keeps_holes_and_wraps_periodic_tiles():
    rng = np.random.default_rng(0)
    h = rng.normal(0, 1e-8, (64, 64))
    periodic = Relief(h, 1e-7, 1e-7, periodic=True)
    shifted = Relief(np.roll(h, 20, axis=1), 1e-7, 1e-7, periodic=True)
    a = scale_and_filter(periodic, 2.0, 0.4e-6).heights_m
    b = scale_and_filter(shifted, 2.0, 0.4e-6).heights_m
    np.testing.assert_allclose(np.roll(a, 20, axis=1), b, atol=1e-22)     # wrap-around: shift-equivariant
    h2 = h.copy()
    h2[10:14, 30:33] = np.nan
    out = scale_and_filter(Relief(h2, 1e-7, 1e-7), 3.0, 0.2e-6)
    assert np.array_equal(np.isnan(out.heights_m), np.isnan(h2))           # holes stay holes, none filled
    assert len(out.history) == 2
    # linear: the order of scaling and filtering does not matter
    np.testing.assert_allclose(out.heights_m, 3.0 * Relief(h2, 1e-7, 1e-7).gaussian_filtered(0.2e-6).heights_m,
                               rtol=1e-12, atol=1e-20, equal_nan=True)
