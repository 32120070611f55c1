"""The two-scale composite (methods.two_scale): split, flat limit, energy, reciprocity, auto's choice, and
agreement with full Kirchhoff (methods.kirchhoff, itself exact against direct integration) on a two-scale
relief whose large scale is gentle enough for the tangent plane."""
import warnings

import numpy as np
import pytest

from relief_bsdf.core.fresnel import fresnel_reflectance
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.errors import RequestError
from relief_bsdf.methods import auto, reconstruct
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.bands import BandSpectrum, band_split, two_scale_cut
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import random_relief

N_GLASS = 1.5
MAT = Material(inside=ConstantIndex(N_GLASS))


def two_scale_relief(n=512, pitch=0.25e-6, rms_l=0.5e-6, corr_l=10e-6, rms_f=12e-9, corr_f=1e-6):
    """A lobe plus a haze: a gentle large scale (rms slope 2 s / l = 0.1) and an optically smooth fine scale."""
    big = random_relief(n, pitch, rms_l, corr_l, seed=11)
    fine = random_relief(n, pitch, rms_f, corr_f, seed=12)
    return big.with_heights(big.heights_m + fine.heights_m, "large + fine scale")


def _quiet(fn, *a):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return fn(*a)


# ------------------------------------------------------------------ the split


def test_split_is_the_lowest_cut_with_a_smooth_fine_scale_and_adds_up():
    rel = two_scale_relief(n=256)
    spec = BandSpectrum.of(rel)
    lam, g_cut = 550e-9, 0.05
    f_c = two_scale_cut(spec, lam, 1.0, np.inf, g_cut)
    g = lambda f: (4 * np.pi * np.sqrt(spec.fine_variance(f)) / lam) ** 2   # noqa: E731
    radii = np.unique(spec.f_per_m)
    below = radii[radii < f_c][-1]
    assert g(f_c) <= g_cut < g(below)                       # the lowest such cut
    sp = band_split(rel, f_c)
    h = rel.level(0).heights_m
    np.testing.assert_allclose(sp.large.heights_m + sp.fine.heights_m, h - h.mean(), atol=1e-15)
    # the fine scale's rms from the spectrum equals the map's (periodic tile: Parseval)
    assert sp.fine_rms_m == pytest.approx(np.sqrt(g(f_c)) * lam / (4 * np.pi), rel=1e-6)
    assert np.std(sp.fine.heights_m) == pytest.approx(sp.fine_rms_m, rel=1e-6)


# ------------------------------------------------------------------ physics checks


def test_flat_limit_is_fresnel():
    flat = Relief(np.zeros((64, 64)), 0.25e-6, 0.25e-6, periodic=True)
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside", "inside"), samples=20000,
                  theta_s_edges_deg=tuple(np.arange(0, 91, 5.0)), phi_s_edges_deg=tuple(np.arange(-15, 346, 30.0)),
                  options={"backend": "serial"})
    out_t, in_t = _quiet(reconstruct, flat, MAT, req, "two_scale")
    ci = np.cos(np.radians(req.theta_i_deg))
    for t, (n1, n2) in ((out_t, (1.0, N_GLASS)), (in_t, (N_GLASS, 1.0))):
        F = fresnel_reflectance(ci, n1, n2)
        np.testing.assert_allclose(t.specular_R[0, :, 0], F, atol=2e-3)
        tir = np.isclose(F, 1.0)
        np.testing.assert_allclose(t.specular_T[0, :, 0], np.where(tir, 0.0, 1.0 - F), atol=2e-3)
        h = t.hemispherical()
        assert np.all(h["R"] - t.specular_R < 1e-3) and np.all(h["T"] - t.specular_T < 1e-3)


@pytest.fixture(scope="module")
def small_tables():
    """A 192^2 two-scale tile (pitch 0.25 um: large 0.5 um rms, l 5 um; fine 10 nm rms, l 0.5 um) at 20-65 deg,
    phi_i 0 and 180, both sides; tile_uncertainty off: the reciprocal paths share one tile."""
    rel = two_scale_relief(n=192, rms_l=0.5e-6, corr_l=5e-6, rms_f=10e-9, corr_f=0.5e-6)
    grid = (20.0, 35.0, 50.0, 65.0)
    te = (0.0,) + tuple(x for g in grid for x in (g - 2.5, g + 2.5)) + (90.0,)
    req = Request(theta_i_deg=grid, phi_i_deg=(0.0, 180.0), incident_from=("outside", "inside"), samples=100000,
                  theta_s_edges_deg=te, phi_s_edges_deg=tuple(np.arange(-5.0, 360.0, 10.0)),
                  options={"backend": "serial", "tile_uncertainty": False})
    return _quiet(reconstruct, rel, MAT, req, "two_scale")


def test_energy_is_conserved(small_tables):
    """R + T = 1 for the lossless boundary within 1 %: the ray tables close to 0.3 %, and what the fine scale's
    Debye-Waller factors take out of the lobe is its haze to first order (the neglected second order is
    ~ g_F^2 ~ 0.25 % of the lobe)."""
    for t in small_tables:
        h = t.hemispherical()
        tot = h["R"] + h["T"]
        assert np.all(np.abs(tot - 1.0) < 0.01), (t.incident_from, tot)
        np.testing.assert_allclose(t.lost, 1.0 - tot, atol=1e-12)
        haze = [i["haze_R"] for i in t.metadata["incidences"]]
        assert min(haze) > 0                                    # the fine scale does scatter


def test_reciprocity_of_the_brdf(small_tables):
    """f_R(a, 0 -> b, 180) = f_R(b, 180 -> a, 0) on the same tile: z within 4 of the stated sigma (ray Monte
    Carlo times the Debye-Waller factor, which is symmetric in the two directions, plus the haze)."""
    z = []
    for tab in small_tables:
        centres = tab.theta_s_deg
        grid = list(tab.theta_i_deg)

        def cell(ti, pi, ts, ps):
            i, p = grid.index(ti), list(tab.phi_i_deg).index(pi)
            s = int(np.argmin(np.abs(centres - ts)))
            a = int(np.argmin(np.abs(np.mod(tab.phi_s_deg - ps + 180.0, 360.0) - 180.0)))
            return tab.values_per_sr[0, i, p, 0, s, a], tab.sigma_per_sr[0, i, p, 0, s, a]

        for a in grid:
            for b in grid:
                if b > a:
                    f_ab, s_ab = cell(a, 0.0, b, 180.0)
                    f_ba, s_ba = cell(b, 180.0, a, 0.0)
                    if max(f_ab, f_ba) > 1e-4:
                        z.append((f_ab - f_ba) / np.hypot(s_ab, s_ba))
    assert len(z) >= 6
    assert np.max(np.abs(z)) < 4 and abs(np.mean(z)) < 1.5, z


def test_unknown_option_is_an_error_naming_it():
    rel = two_scale_relief(n=64, corr_l=2e-6, corr_f=0.5e-6)
    with pytest.raises(RequestError, match="f_cut_um"):
        reconstruct(rel, MAT, Request(theta_i_deg=(0.0,), options={"f_cut_um": 0.3}), "two_scale")


# ------------------------------------------------------------------ auto


def test_auto_picks_two_scale_for_a_lobe_plus_a_haze_and_says_why_in_one_line():
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside", "inside"))
    c = _quiet(auto.choose, two_scale_relief(), MAT, req)
    assert c.method == "two_scale", c.summary
    assert "\n" not in c.summary and len(c.summary) < 300 and "two scales" in c.summary
    assert c.options["f_cut_per_um"] > 0
    # one scale only (the same large scale without the fine one): not two_scale
    c1 = _quiet(auto.choose, random_relief(512, 0.25e-6, 0.5e-6, 10e-6, seed=11), MAT, req)
    assert c1.method != "two_scale" and "scale separation" in c1.valid["two_scale"][1]


# ------------------------------------------------------------------ against full Kirchhoff


@pytest.mark.parametrize("side_from", ["outside", "inside"])
@pytest.mark.slow
def test_agrees_with_full_kirchhoff_where_both_apply(side_from):
    """The 512^2 two-scale relief (large: 0.5 um rms, l 10 um, slope 0.1, k R_c ~ 500: tangent plane valid and
    no coherent part left in the large scale; fine: 12 nm rms, l 1 um, g_F ~ 0.05) at 0 / 30 / 60 deg.
    Kirchhoff is filtered narrowly (0.006 in direction cosines, about the lobe's ray-tracing resolution; its
    default filter of half a cell would widen the 0.024-wide transmitted lobe).

    Tolerances, stated from the physics each model leaves out:
    - hemispherical totals (diffuse + specular) per side within 2 % relative or 1e-3 of the incident power:
      the large scale is ray-traced (the stationary-phase limit; R + T of both within 0.3 %), the fine scale
      to first order;
    - the lobe's power (cells above 10 % of Kirchhoff's peak) within 3 %: at the transmitted side's phase
      roughness (nu_z sigma_L)^2 ~ 8 the wave lobe is a Poisson mixture of Gaussians (kurtosis 3 (1 + 1/g))
      whose wings hold ~ 1-2 % more than the geometric lobe;
    - in-lobe cells: median relative difference within 15 % (speckle of Kirchhoff's tile and the ray Monte
      Carlo: 5-12 % per 2 x 10 deg cell);
    - the haze where the large scale sends nothing (cells where Kirchhoff of the large scale alone is below
      1e-3 of its peak): the composite's power there against what the fine scale adds to Kirchhoff,
      K(h_L + h_F) - K(h_L), within 40 % + 1e-4 of the incident power (the composite evaluates the
      polarisation factor Q on the mean plane and spreads the haze by a Gaussian of the rms facet tilt,
      whose tails set the wide-angle haze; measured 0-37 %)."""
    rel = two_scale_relief()
    base = dict(theta_i_deg=(0.0, 30.0, 60.0), incident_from=(side_from,),
                theta_s_edges_deg=tuple(np.arange(0, 91, 2.0)), phi_s_edges_deg=tuple(np.arange(-5, 356, 10.0)),
                samples=1_000_000)
    (tk,) = _quiet(reconstruct, rel, MAT, Request(**base, options={"backend": "serial", "band_limited": True,
                                                                   "smoothing_dcos": 0.006}), "kirchhoff")
    (ts,) = _quiet(reconstruct, rel, MAT, Request(**base, options={"backend": "serial"}), "two_scale")
    from relief_bsdf.methods.two_scale import split_for
    large = split_for(rel, MAT, Request(**base)).large
    (tl,) = _quiet(reconstruct, large, MAT, Request(**base, options={"backend": "serial", "band_limited": True,
                                                                     "smoothing_dcos": 0.006}), "kirchhoff")
    te, pe = np.radians(base["theta_s_edges_deg"]), np.radians(base["phi_s_edges_deg"])
    psa = 0.5 * (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None] * np.diff(pe)[None, :]
    hk, hs = tk.hemispherical(), ts.hemispherical()
    checked = 0
    for it in range(3):
        for k, side in enumerate("RT"):
            a, b = tk.values_per_sr[0, it, 0, k], ts.values_per_sr[0, it, 0, k]
            tot_k, tot_s = hk[side][0, it, 0], hs[side][0, it, 0]
            assert abs(tot_s - tot_k) <= max(0.02 * tot_k, 1e-3), (side, it, tot_k, tot_s)
            if tot_k < 0.01:                      # transmission past the critical angle: nothing to compare
                continue
            lobe = a > 0.1 * a.max()
            lk, ls = (a * psa)[lobe].sum(), (b * psa)[lobe].sum()
            assert ls == pytest.approx(lk, rel=0.03), (side, it)
            assert np.median(np.abs(b[lobe] / a[lobe] - 1.0)) < 0.15, (side, it)
            lg = tl.values_per_sr[0, it, 0, k]
            far = lg < 1e-3 * lg.max()
            added, haze = ((a - lg) * psa)[far].sum(), (b * psa)[far].sum()
            assert abs(haze - added) <= 0.4 * added + 1e-4, (side, it, added, haze)
            checked += 1
    assert checked >= 5
    assert np.all(np.abs(hs["R"] + hs["T"] - 1.0) < 0.01)


@pytest.mark.slow
def test_real_maps_coherent_specular_of_autos_choice_within_ten_percent_of_the_wave_methods():
    """Every area map of tests/data/topography (outside and inside, 0-60 deg): the coherent specular
    fraction auto's choice carries is within 0.1 of the wave methods' |<exp(-i nu h)>|^2 at normal incidence
    (the tangent-plane mean field of the map's own heights, the least coherent incidence): ray carries
    none, two_scale only its large scale's (times the fine scale's Debye-Waller factor <= 1), the wave
    methods the figure itself."""
    from pathlib import Path

    from relief_bsdf.io.heightmaps import read_relief
    topo = Path(__file__).resolve().parents[2] / "data" / "topography"
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside", "inside"))
    seen = 0
    for p in sorted(topo.glob("ST_*")):
        try:
            rel = read_relief(p)
        except Exception:                      # the 1-D profile
            continue
        c = _quiet(auto.choose, rel, MAT, req)
        wave = c.figures["coherent_max"]
        carried = {"ray": 0.0, "two_scale": c.figures["ts_large_coherent"]}.get(c.method, wave)
        assert abs(carried - wave) <= 0.1, (p.name, c.method, carried, wave)
        seen += 1
    assert seen >= 8
