"""Normal-density Monte Carlo (paper sec. 2.2): flat limit, energy, agreement with Walter, heuristic."""
import numpy as np
import pytest

from relief_bsdf.core.frames import direction, projected_solid_angle
from relief_bsdf.errors import InputError
from relief_bsdf.methods.microfacet import Roughness, cell_average, walter_bsdf
from relief_bsdf.methods.normals import NormalsBeam, SlopeSet, reconstruct, trace_normals, triangle_slopes
from relief_bsdf.methods.options import NormalsOptions
from relief_bsdf.core.fresnel import fresnel_unpolarized
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.surface.relief import Relief
from relief_bsdf.methods.request import Request

TE = np.linspace(0, 90, 46)
PE = np.arange(-5.0, 360.0, 10.0)
PSA = projected_solid_angle(TE, PE)


def _gauss_slopes(rng, alpha, n=400_000):
    """Slopes of a Beckmann surface of roughness alpha: per-axis normal with std alpha / sqrt(2)."""
    return SlopeSet(rng.normal(0, alpha / np.sqrt(2), n), rng.normal(0, alpha / np.sqrt(2), n))


@pytest.mark.parametrize("n_a,n_b", [(1.0, 1.5), (1.5, 1.0)])
def test_flat_relief_is_fresnel(n_a, n_b):
    rng = np.random.default_rng(1)
    flat = SlopeSet(np.zeros(64), np.zeros(64))
    N = 400_000
    for theta in (0.0, 30.0, 60.0):
        r = trace_normals(flat, NormalsBeam(direction(theta, 0.0), n_a, n_b, N), rng, TE, PE)
        F = float(fresnel_unpolarized(np.cos(np.radians(theta)), n_a, n_b))
        sigma = np.sqrt(F * (1 - F) / N)
        assert r["counts"].sum() == 0                       # everything is in the delta parts
        assert r["specular_R"] + r["specular_T"] == N
        assert r["specular_R"] / N == pytest.approx(F, abs=max(4 * sigma, 1e-9))
        assert abs(r["specular_R"] / N - F) < 1e-3


@pytest.mark.parametrize("n_a,n_b,thetas", [(1.0, 1.5, (0.0, 30.0, 50.0)), (1.5, 1.0, (0.0, 25.0))])
def test_small_slopes_agree_with_walter_incident_shadowing(n_a, n_b, thetas):
    """Single scattering with visible-normal sampling = Walter with G = G1(wi) (module doc of normals)."""
    rng = np.random.default_rng(2)
    alpha = np.sqrt(2) * 0.1                                # rms slope 0.1 per axis
    slopes = _gauss_slopes(rng, alpha)
    N = 300_000
    for theta in thetas:
        wi = direction(theta, 0.0)
        r = trace_normals(slopes, NormalsBeam(wi, n_a, n_b, N), rng, TE, PE)
        rough = Roughness(alpha, shadowing="incident")
        ref = np.stack([cell_average(lambda wo: walter_bsdf(wi[None], wo, n_a, n_b, rough),
                                     TE, PE, s, 6) for s in "RT"])
        expected = ref * PSA * N
        cnt = r["counts"]
        m = expected > 200
        assert m.sum() > 15
        z = (cnt[m] - expected[m]) / np.sqrt(expected[m])
        assert np.max(np.abs(z)) < 5.0                      # cell by cell within Monte-Carlo noise
        assert np.all(np.abs(cnt[m] / expected[m] - 1) < 0.3)
        for k in (0, 1):
            tot, tot_ref = cnt[k].sum() / N, expected[k].sum() / N
            assert tot == pytest.approx(tot_ref, abs=4 * np.sqrt(tot_ref * (1 - tot_ref) / N) + 2e-3)
        # nothing lost in a lossless medium, every path scattered at least once
        assert r["absorbed"] == r["max_bounces"] == r["no_facet"] == 0
        assert cnt.sum() == N


def test_energy_conserved_at_high_slope_and_rescattering_happens():
    rng = np.random.default_rng(3)
    slopes = _gauss_slopes(rng, 0.8)
    N = 100_000
    for n_a, n_b in ((1.0, 1.5), (1.5, 1.0)):
        r = trace_normals(slopes, NormalsBeam(direction(70.0, 30.0), n_a, n_b, N), rng, TE, PE)
        lost = r["absorbed"] + r["max_bounces"] + r["no_facet"]
        assert r["counts"].sum() + r["specular_R"] + r["specular_T"] + lost == N
        assert lost <= 1e-3 * N
        assert r["events_per_path"] > 1.01                  # invalid directions are re-scattered


def test_grazing_heuristic_changes_grazing_only():
    rng = np.random.default_rng(4)
    slopes = _gauss_slopes(rng, 0.3)
    N = 100_000
    base = trace_normals(slopes, NormalsBeam(direction(0.0, 0.0), 1.0, 1.5, N), rng, TE, PE)
    heur = trace_normals(slopes, NormalsBeam(direction(0.0, 0.0), 1.0, 1.5, N), rng, TE, PE,
                         NormalsOptions(grazing_heuristic="smith"))
    assert heur["events_per_path"] > base["events_per_path"]
    # near the normal the exit probability is untouched (p = 0 there): the first rings agree within noise
    a, b = base["counts"][1, :10].sum(), heur["counts"][1, :10].sum()
    assert abs(a - b) < 5 * np.sqrt(a) + 0.02 * a
    g_base = trace_normals(slopes, NormalsBeam(direction(80.0, 0.0), 1.0, 1.5, N), rng, TE, PE)
    g_heur = trace_normals(slopes, NormalsBeam(direction(80.0, 0.0), 1.0, 1.5, N), rng, TE, PE,
                           NormalsOptions(grazing_heuristic="cosine"))
    assert g_heur["events_per_path"] > g_base["events_per_path"] + 0.05


def _relief(n=96, slope_axis=0.1, seed=0):
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n)
    kx, ky = np.meshgrid(k, k)
    h = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-(np.pi * 6) ** 2 * (kx**2 + ky**2) / 2)))
    sy, sx = np.gradient(h)
    h *= slope_axis / np.sqrt(0.5 * np.mean(sx**2 + sy**2))
    return Relief(h * 1e-6, 1e-6, 1e-6, periodic=True, source="test relief")


def test_reconstruct_tables_both_sides_and_seed():
    relief = _relief()
    mat = Material(inside=ConstantIndex(1.5))
    req = Request(theta_i_deg=(0.0, 60.0), incident_from=("outside", "inside"), samples=40_000, seed=5,
                  theta_s_edges_deg=tuple(TE), phi_s_edges_deg=tuple(PE))
    tables = reconstruct(relief, mat, req)
    assert [t.incident_from for t in tables] == ["outside", "inside"]
    for t in tables:
        h = t.hemispherical()
        np.testing.assert_allclose(h["R"] + h["T"] + h["lost"], 1.0, atol=1e-12)
        assert t.sigma_per_sr is not None and t.method == "normals"
    # same seed, same table; other seed, other noise
    again = reconstruct(relief, mat, req)
    np.testing.assert_array_equal(again[0].values_per_sr, tables[0].values_per_sr)
    other = reconstruct(relief, mat, Request(**{**req.__dict__, "seed": 6}))
    assert not np.array_equal(other[0].values_per_sr, tables[0].values_per_sr)
    # triangle slopes of the relief carry its rms slope (about sqrt(2) * 0.1 in magnitude)
    sx, sy = triangle_slopes(relief)
    assert np.sqrt(np.mean(sx**2 + sy**2)) == pytest.approx(np.sqrt(2) * 0.1, rel=0.1)


def test_bad_requests_fail_early():
    relief = _relief(16)
    mat = Material(inside=ConstantIndex(1.5))
    with pytest.raises(InputError):
        reconstruct(relief, mat, Request(theta_i_deg=(90.0,)))
    with pytest.raises(InputError):
        reconstruct(Relief(np.full((8, 8), np.nan), 1e-6, 1e-6), mat, Request())
    with pytest.raises(InputError):
        reconstruct(Relief(np.zeros((4, 4)), 1e-6, 1e-6), mat, Request())       # 18 facets: too few
    with pytest.raises(InputError):
        reconstruct(relief, mat, Request(options={"grazing_heuristic": "sometimes"}))
    metal = Material(inside=ConstantIndex(0.2, 3.0))
    with pytest.raises(InputError):
        reconstruct(relief, metal, Request(incident_from=("inside",)))


def test_metal_absorbs_what_it_does_not_reflect():
    rng = np.random.default_rng(6)
    n_metal = complex(0.2, 3.0)
    flat = SlopeSet(np.zeros(64), np.zeros(64))
    N = 100_000
    r = trace_normals(flat, NormalsBeam(direction(45.0, 0.0), 1.0, n_metal, N), rng, TE, PE)
    F = float(fresnel_unpolarized(np.cos(np.radians(45.0)), 1.0, n_metal))
    assert r["specular_T"] == 0 and r["counts"][1].sum() == 0
    assert r["specular_R"] / N == pytest.approx(F, abs=4 * np.sqrt(F * (1 - F) / N))
    assert r["specular_R"] + r["absorbed"] == N


def test_sigma_covers_the_scatter_between_two_tile_realisations():
    """Issue 13 item 2: two independent 256^2 tiles of the same statistics (rms slope 0.3 per axis,
    l = 8 px), 30 deg, T lobe: with Monte-Carlo sigma alone their cells disagree at z ~ 3 (the tile's
    own realisation); with the sub-tile batch means of the first facet in sigma at z ~ 1.  The values
    themselves do not change (same random stream), only sigma."""
    import warnings
    from relief_bsdf.surface.synth import random_relief
    te, pe = tuple(np.linspace(0.0, 90.0, 46)), tuple(np.arange(-5.0, 360.0, 10.0))
    glass = Material(inside=ConstantIndex(1.5))
    z_std, tabs = {}, {}
    for tu in (True, False):
        pair = []
        for s in (11, 12):
            req = Request(theta_i_deg=(30.0,), samples=200_000, seed=s, theta_s_edges_deg=te, phi_s_edges_deg=pe,
                          options={"tile_uncertainty": tu})
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                pair.append(reconstruct(random_relief(256, 1e-6, 0.3 * np.sqrt(2) * 4e-6, 8e-6, seed=s), glass, req)[0])
        a, b = pair
        f, g = a.values_per_sr[0, 0, 0, 1], b.values_per_sr[0, 0, 0, 1]
        lobe = (f > 0.2 * f.max()) & (g > 0.2 * g.max())
        z = ((f - g) / np.hypot(a.sigma_per_sr[0, 0, 0, 1], b.sigma_per_sr[0, 0, 0, 1]))[lobe]
        assert z.size > 40
        z_std[tu], tabs[tu] = (float(z.std()), float(z.mean())), a
    assert 0.7 < z_std[True][0] < 1.3 and abs(z_std[True][1]) < 0.4, z_std
    assert z_std[False][0] > 2.5, z_std
    np.testing.assert_array_equal(tabs[True].values_per_sr, tabs[False].values_per_sr)
    u = tabs[True].metadata["uncertainty"]
    assert u["subtiles"] == [7, 7] and "realisation" in u["sigma"]
    assert tabs[False].metadata["uncertainty"]["sigma"].startswith("Monte-Carlo only")
