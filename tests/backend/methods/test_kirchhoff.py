"""Scalar Kirchhoff (tangent-plane) solver: limits, energy, coherence, colour, sampling checks."""
import numpy as np
import pytest

from _wave_reliefs import gaussian_relief
from relief_bsdf.core.frames import direction, projected_solid_angle
from relief_bsdf.errors import RequestError
from relief_bsdf.methods import kirchhoff, reconstruct
from relief_bsdf.methods.microfacet import Roughness, walter_bsdf
from relief_bsdf.core.fresnel import fresnel_unpolarized
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.surface.relief import Relief
from relief_bsdf.methods.request import Request

MAT = Material(inside=ConstantIndex(1.5))
EDGES60 = tuple(np.linspace(0, 60, 61))


def _dcos(tab):
    ts, ps = np.meshgrid(np.radians(tab.theta_s_deg), np.radians(tab.phi_s_deg), indexing="ij")
    return np.sin(ts) * np.cos(ps), np.sin(ts) * np.sin(ps)


def _rms_width(f, tab):
    """RMS radius of a lobe in direction cosines about its centroid (projected-solid-angle weights)."""
    a, b = _dcos(tab)
    w = f * tab.projected_solid_angle_sr
    a0, b0 = (w * a).sum() / w.sum(), (w * b).sum() / w.sum()
    return np.sqrt((w * ((a - a0) ** 2 + (b - b0) ** 2)).sum() / w.sum())


@pytest.fixture(scope="module")
def smooth():
    return gaussian_relief(1024, 0.1e-6, 5e-9, 1e-6, seed=3)


def test_small_roughness_matches_rayleigh_rice(smooth):
    """sigma = 5 nm << lambda: diffuse part agrees with first-order perturbation theory."""
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 30.0), theta_s_edges_deg=EDGES60)
    (k,) = reconstruct(smooth, MAT, req, "kirchhoff")
    (r,) = reconstruct(smooth, MAT, req, "rayleigh-rice")
    hk, hr = k.hemispherical(), r.hemispherical()
    for key in ("diffuse_R", "diffuse_T"):
        np.testing.assert_allclose(hk[key], hr[key], rtol=0.05)
    np.testing.assert_allclose(hk["specular_R"], hr["specular_R"], rtol=1e-3)
    for it in range(2):
        for s in range(2):
            a, b = k.values_per_sr[0, it, 0, s], r.values_per_sr[0, it, 0, s]
            lobe = b > 0.05 * b.max()
            assert abs(np.median(a[lobe] / b[lobe]) - 1) < 0.10


@pytest.mark.slow
def test_large_roughness_matches_microfacet_lobe():
    """sigma = 1 um ~ 2 lambda, Beckmann slope 0.2: lobe width equals Walter's (G = 1) within 10%."""
    rel = gaussian_relief(2048, 0.1e-6, 1.0e-6, 10e-6, seed=5)
    h = rel.heights_m
    gx = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / (2 * rel.dx_m)
    gy = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / (2 * rel.dy_m)
    alpha = np.sqrt(np.mean(gx**2 + gy**2))        # the realisation's rms slope = Beckmann alpha
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 20.0), theta_s_edges_deg=EDGES60)
    (k,) = reconstruct(rel, MAT, req, "kirchhoff")
    ts, ps = np.meshgrid(k.theta_s_deg, k.phi_s_deg, indexing="ij")
    for it, ti in enumerate(req.theta_i_deg):
        wi = np.broadcast_to(direction(ti, 0.0), ts.shape + (3,)).reshape(-1, 3)
        for s, side in enumerate("RT"):
            wo = direction(ts, ps)
            if side == "T":
                wo[..., 2] *= -1
            rough = Roughness(alpha, "beckmann", shadowing="none")
            fm = walter_bsdf(wi, wo.reshape(-1, 3), 1.0, 1.5, rough).reshape(ts.shape)
            fk = k.values_per_sr[0, it, 0, s]
            assert _rms_width(fk, k) == pytest.approx(_rms_width(fm, k), rel=0.10)
            pk = (fk * k.projected_solid_angle_sr).sum()
            pm = (fm * k.projected_solid_angle_sr).sum()
            assert pk == pytest.approx(pm, rel=0.05)


def test_energy_lossless_boundary():
    """R + T (cells + specular) within 2% of 1 where the tangent plane holds (moderate slopes)."""
    rel = gaussian_relief(512, 0.1e-6, 0.15e-6, 4e-6, seed=2)
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 20.0), incident_from=("outside", "inside"),
                  theta_s_edges_deg=tuple(np.linspace(0, 90, 46)), options={"band_limited": True})
    for tab in reconstruct(rel, MAT, req, "kirchhoff"):
        h = tab.hemispherical()
        assert np.all(np.abs(h["R"] + h["T"] - 1) < 0.02), (tab.incident_from, h["R"] + h["T"])
        assert np.all(h["specular_R"] > 0) and np.all(h["diffuse_R"] > h["specular_R"] * 0.01)


def test_specular_is_separated_flat():
    """A flat boundary: all power in the specular parts, equal to Fresnel, nothing in the cells."""
    rel = Relief(np.zeros((128, 128)), 0.2e-6, 0.2e-6, periodic=True)
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 50.0), incident_from=("outside", "inside"),
                  theta_s_edges_deg=tuple(np.linspace(0, 40, 11)), options={"band_limited": True})
    out, ins = reconstruct(rel, MAT, req, "kirchhoff")
    np.testing.assert_allclose(out.specular_R[0, :, 0], fresnel_unpolarized(np.cos(np.radians([0.0, 50.0])), 1.0, 1.5),
                               rtol=1e-5)
    np.testing.assert_allclose(out.specular_R + out.specular_T, 1.0, atol=1e-5)
    assert np.abs(out.values_per_sr).max() < 1e-6
    assert ins.specular_R[0, 1, 0] == pytest.approx(1.0, abs=1e-6)      # past the critical angle
    assert ins.specular_T[0, 1, 0] == 0.0


def test_partial_coherence_phong_lobe_and_weaker_interference():
    lam = 550.0
    rel = gaussian_relief(512, 0.2e-6, 0.02e-6, 2e-6, seed=4)
    req = Request(wavelengths_nm=(lam,), theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.linspace(0, 20, 41)),
                  options={"band_limited": True})
    (coh,) = reconstruct(rel, MAT, req, "kirchhoff")
    lc = 5e-6
    import dataclasses
    (pc,) = reconstruct(rel, MAT, dataclasses.replace(req, coherence_length_m=lc,
                                                      options={"band_limited": True, "coherence_instances": 8}),
                        "kirchhoff")
    hc, hp = coh.hemispherical(), pc.hemispherical()
    # the delta specular is gone, its power sits in a lobe in the cells: same total reflectance
    assert hp["specular_R"][0, 0, 0] == 0.0 and hc["specular_R"][0, 0, 0] > 0.02
    assert hp["R"][0, 0, 0] == pytest.approx(hc["R"][0, 0, 0], rel=0.02)
    # the lobe: the extra power near the specular direction, of rms radius ~ lambda / (pi Lc)
    extra = pc.values_per_sr[0, 0, 0, 0] - coh.values_per_sr[0, 0, 0, 0]
    a, b = _dcos(pc)
    near = np.hypot(a, b) < 0.2
    p_extra = (extra * pc.projected_solid_angle_sr)[near].sum()
    assert p_extra == pytest.approx(hc["specular_R"][0, 0, 0], rel=0.1)
    w = pc.metadata["smoothing_dcos"]
    expect = np.sqrt((lam * 1e-9 / (np.pi * lc)) ** 2 + 2 * w**2)
    got = _rms_width(np.where(near, np.clip(extra, 0, None), 0.0), pc)
    assert got == pytest.approx(expect, rel=0.2)
    info = pc.metadata["incidences"][0]
    assert 0 < info["coherence_rel_error_R"] < 0.2
    assert pc.metadata["coherence_instances"] == 8


def test_partial_coherence_washes_out_grating_orders():
    """A sinusoidal grating: sharp diffraction orders when coherent, blurred with Lc < period."""
    n, dx, period = 512, 0.2e-6, 10.24e-6
    x = np.arange(n) * dx
    h = np.broadcast_to(0.1e-6 * np.sin(2 * np.pi * x / period), (n, n)).copy()   # orders 1-3 strong
    rel = Relief(h, dx, dx, periodic=True)
    edges = tuple(np.linspace(0, 15, 31))
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0,), theta_s_edges_deg=edges, options={"band_limited": True})
    (coh,) = reconstruct(rel, MAT, req, "kirchhoff")
    import dataclasses
    (pc,) = reconstruct(rel, MAT, dataclasses.replace(req, coherence_length_m=3e-6), "kirchhoff")
    # contrast of the 2nd diffraction order against the mid-points to its neighbours
    th = np.degrees(np.arcsin(np.array([1.5, 2.0, 2.5]) * 550e-9 / period))

    def contrast(t):
        f = t.eval(550.0, 0.0, 0.0, "R", th, 0.0)
        return f[1] / np.sqrt(f[0] * f[2])

    c_coh, c_pc = contrast(coh), contrast(pc)
    assert c_coh > 5.0
    assert c_pc < 1.5 and c_pc < 0.2 * c_coh


def test_colour_sharper_in_red():
    """Paper sec. 2.4: the specular share grows with wavelength, the BSDF is sharper in the red."""
    rel = gaussian_relief(512, 0.1e-6, 0.05e-6, 3e-6, seed=6)
    req = Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.linspace(0, 40, 41)),
                  options={"band_limited": True})
    (k,) = reconstruct(rel, MAT, req, "kirchhoff")
    h = k.hemispherical()
    share = h["specular_R"][:, 0, 0] / h["R"][:, 0, 0]
    assert share[1] > 1.5 * share[0]
    a, b = _dcos(k)
    near = np.hypot(a, b) < np.sin(np.radians(3))
    cone = [(k.values_per_sr[iw, 0, 0, 0] * k.projected_solid_angle_sr)[near].sum() + h["specular_R"][iw, 0, 0]
            for iw in range(2)]
    assert cone[1] / h["R"][1, 0, 0] > cone[0] / h["R"][0, 0, 0]


def test_sampling_limits_raise_before_work():
    rel = gaussian_relief(256, 0.5e-6, 0.05e-6, 3e-6, seed=1)
    with pytest.raises(RequestError, match="resolves"):
        reconstruct(rel, MAT, Request(theta_i_deg=(30.0,)), "kirchhoff")          # pitch too coarse for 90 deg
    small = gaussian_relief(64, 0.1e-6, 0.01e-6, 1e-6, seed=1)                       # 6.4 um tile, 1 deg cells
    with pytest.raises(RequestError, match="tile"):
        reconstruct(small, MAT, Request(theta_i_deg=(0.0,), theta_s_edges_deg=EDGES60), "kirchhoff")
    with pytest.raises(RequestError, match="coherence"):
        reconstruct(rel, MAT, Request(theta_i_deg=(0.0,), coherence_length_m=100e-6, theta_s_edges_deg=(0, 10, 20),
                                      options={"band_limited": True}), "kirchhoff")
    steep = gaussian_relief(256, 0.5e-6, 2e-6, 2e-6, seed=1)
    with pytest.raises(RequestError, match="steep"):
        reconstruct(steep, MAT, Request(theta_i_deg=(0.0,), theta_s_edges_deg=(0, 10, 20),
                                        options={"band_limited": True}), "kirchhoff")
    with pytest.raises(RequestError):
        reconstruct(rel, MAT, Request(theta_i_deg=(90.0,)), "kirchhoff")
    metal = Material(inside=ConstantIndex(0.2, 3.0))
    for method in ("kirchhoff", "rayleigh-rice"):
        with pytest.raises(RequestError, match="absorbing"):
            reconstruct(rel, metal, Request(theta_i_deg=(0.0,), incident_from=("inside",)), method)


def test_metal_reflects_fresnel_and_absorbs_the_rest():
    rel = gaussian_relief(256, 0.1e-6, 10e-9, 2e-6, seed=1)
    metal = Material(inside=ConstantIndex(0.2, 3.0))
    req = Request(wavelengths_nm=(650.0,), theta_i_deg=(0.0, 45.0), theta_s_edges_deg=tuple(np.linspace(0, 90, 31)),
                  phi_s_edges_deg=tuple(np.arange(-7.5, 360, 15.0)), options={"band_limited": True})
    (t,) = reconstruct(rel, metal, req, "kirchhoff")
    h = t.hemispherical()
    np.testing.assert_allclose(h["R"][0, :, 0], fresnel_unpolarized(np.cos(np.radians([0.0, 45.0])), 1.0, 0.2 + 3j),
                               rtol=0.01)
    assert np.all(h["T"] == 0) and np.all(t.lost > 0.05)


def test_qz_expansion_order_follows_height_range_and_tolerance():
    """Fewer nodes where q_z sigma is small; more for a wider nu_z span, rougher map or tighter tolerance."""
    from relief_bsdf.methods.qz_expansion import HeightMoments, expansion_order
    rng = np.random.default_rng(0)
    k = 2 * np.pi / 550e-9
    n_of = lambda sig, half, tol=1e-3: expansion_order(half, HeightMoments.of(sig * rng.standard_normal((64, 64)),  # noqa: E731
                                                                             None), 1.0, tol, 64)[0]
    assert n_of(2e-9, 0.5 * k) <= 3
    assert n_of(50e-9, 0.5 * k) < n_of(150e-9, 0.5 * k) < n_of(150e-9, 1.25 * k)
    assert n_of(100e-9, k, 1e-2) < n_of(100e-9, k, 1e-6)


def test_expansion_converges_to_its_tolerance():
    """order_powers at the default tolerance against a 1e-8 tolerance (many more nodes)."""
    rel = gaussian_relief(64, 0.0625e-6, 0.15e-6, 1e-6, seed=4)
    from relief_bsdf.methods.rayleigh_rice import prepared_heights
    h, w = prepared_heights(rel)
    surf = kirchhoff.Surface(h, w, (rel.dx_m, rel.dy_m), True)
    inc = kirchhoff.Incidence(550.0, 60.0, 0.0, 1.0, 1.5)
    for side in "RT":
        a = kirchhoff.order_powers(surf, inc, kirchhoff.SolveSettings(cells=None, width_dcos=0.0), side)
        b = kirchhoff.order_powers(surf, inc, kirchhoff.SolveSettings(cells=None, width_dcos=0.0, tau=1e-8), side)
        assert b["qz_nodes"] > a["qz_nodes"] + 3
        big = b["power"] > 1e-3 * b["power"].max()
        assert np.max(np.abs(a["power"][big] / b["power"][big] - 1)) < 0.01
        assert abs(a["power"].sum() / b["power"].sum() - 1) < 1e-3


@pytest.mark.slow
def test_measured_tile_windowed_like_periodic(smooth):
    """A cropped, tilted (non-periodic) tile: Hann window + levelling give the periodic result."""
    h = smooth.heights_m[:900, :1000] + 1e-11 * np.arange(1000)[None, :]
    meas = Relief(h, smooth.dx_m, smooth.dy_m, periodic=False)
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 30.0), theta_s_edges_deg=EDGES60)
    for method in ("kirchhoff", "rayleigh-rice"):
        (a,) = reconstruct(smooth, MAT, req, method)
        (b,) = reconstruct(meas, MAT, req, method)
        ha, hb = a.hemispherical(), b.hemispherical()
        for key in ("diffuse_R", "diffuse_T"):
            np.testing.assert_allclose(hb[key], ha[key], rtol=0.05)
        np.testing.assert_allclose(hb["R"] + hb["T"], 1.0, atol=0.01)
        if method == "kirchhoff":
            assert b.metadata["window"] == "2-D Hann"


@pytest.mark.slow
def test_polarized_mueller_consistent_with_walter():
    """--polarized: M00 equals the scalar table; lobe-averaged Mueller elements match W07's facet Mueller."""
    from relief_bsdf.methods.microfacet import Roughness, walter_mueller
    rel = gaussian_relief(1024, 0.1e-6, 1.0e-6, 10e-6, seed=5)
    base = dict(wavelengths_nm=(550.0,), theta_i_deg=(40.0,), theta_s_edges_deg=tuple(np.linspace(0, 80, 41)),
                phi_s_edges_deg=tuple(np.arange(-5, 360, 10.0)))
    (sc,) = reconstruct(rel, MAT, Request(**base, options={"band_limited": True}), "kirchhoff")
    (po,) = reconstruct(rel, MAT, Request(**base, options={"band_limited": True, "polarized": True}), "kirchhoff")
    np.testing.assert_allclose(po.mueller_per_sr[..., 0, 0], sc.values_per_sr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(po.values_per_sr, sc.values_per_sr, rtol=1e-9, atol=1e-12)
    assert po.specular_mueller_R.shape == (1, 1, 1, 4, 4)
    h = rel.heights_m
    gx = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / (2 * rel.dx_m)
    gy = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / (2 * rel.dy_m)
    alpha = np.sqrt(np.mean(gx**2 + gy**2))
    ts, ps = np.meshgrid(po.theta_s_deg, po.phi_s_deg, indexing="ij")
    psa = po.projected_solid_angle_sr[..., None, None]
    for s, side in enumerate("RT"):
        wo = direction(ts, ps)
        if side == "T":
            wo[..., 2] *= -1
        wi = np.broadcast_to(direction(40.0, 0.0), wo.shape).reshape(-1, 3)
        Mw = walter_mueller(wi, wo.reshape(-1, 3), 1.0, 1.5, Roughness(alpha, "beckmann", shadowing="none"),
                            phi_o_rad=np.radians(ps).ravel()).reshape(ts.shape + (4, 4))
        Mk = po.mueller_per_sr[0, 0, 0, s]
        avg_k = (Mk * psa).sum(axis=(0, 1)) / (Mk[..., 0, 0:1, None] * psa).sum(axis=(0, 1))
        avg_w = (Mw * psa).sum(axis=(0, 1)) / (Mw[..., 0, 0:1, None] * psa).sum(axis=(0, 1))
        np.testing.assert_allclose(avg_k, avg_w, atol=0.03)
        if side == "R":
            assert abs(avg_w[0, 1]) > 0.3 and avg_w[2, 2] < -0.2    # strongly polarising: not a trivial check
