"""Cross-method consistency: the reconstruction methods must agree where physics says they must.

One frame (formats.md), one normalisation (BsdfTable: cell averages in projected solid angle,
delta parts apart, `lost` for what is not scattered), everywhere.  Each block below runs
every method concerned on the SAME relief realisation, so the relief's own statistical
scatter (finite tile) cancels and what is left are model differences, stated per check:

- geometric regime (rms slope ~0.17, correlation length >> lambda): `ray` (real geometry,
  shadowing and inter-reflections), `normals` (facet-normal density, G1(wi) only, no exit
  masking), `microfacet` (Walter 2007, Beckmann fitted to the relief's slopes, Smith G,
  single scattering) agree to a few % in R and T; normals' R lobe is sparse (Russian
  roulette gives it ~4 % of the paths) so it is compared through integrals and centroids.
- large roughness (sigma ~ 2 lambda): `kirchhoff` tends to geometric optics, so its lobe
  centroid and width match `ray` / `microfacet`.
- small roughness (5 nm): `kirchhoff` (tangent plane, small-roughness limit) and
  `rayleigh-rice` (first-order vector perturbation) agree in the diffuse integrals; both
  specular parts equal Fresnel x Debye-Waller.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from relief_bsdf.surface import synth
from relief_bsdf.bsdf.table import reciprocity_error
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.cli import main as cli_main
from relief_bsdf.methods import reconstruct
from relief_bsdf.core.fresnel import fresnel_unpolarized, mueller_interface
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.io.recording import read_recording
from relief_bsdf.surface.relief import Relief
from relief_bsdf.methods.request import Request

N_GLASS = 1.5
WL_NM = 550.0
MAT = Material(inside=ConstantIndex(N_GLASS))
TH_EDGES = tuple(np.linspace(0.0, 90.0, 31))            # 3 degree rings
PH_EDGES = tuple(np.arange(-5.0, 360.0, 10.0))          # 10 degree sectors centred on 0, 10, ...
BOTH = ("outside", "inside")


def _run(relief, method, options=None, **kw):
    base = dict(wavelengths_nm=(WL_NM,), theta_s_edges_deg=TH_EDGES, phi_s_edges_deg=PH_EDGES,
                incident_from=BOTH, seed=11)
    base.update(kw)
    tables = reconstruct(relief, MAT, Request(options=dict(options or {}), **base), method)
    return {t.incident_from: t for t in tables}


def _n_pair(frm):
    return (1.0, N_GLASS) if frm == "outside" else (N_GLASS, 1.0)


def _lobe_moments(table, i, p, k):
    """Power-weighted centroid (x, y) and rms widths of a lobe, in direction cosines."""
    th = np.radians(table.theta_s_deg)[:, None]
    ph = np.radians(table.phi_s_deg)[None, :]
    x, y = np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph)
    w = table.values_per_sr[0, i, p, k] * table.projected_solid_angle_sr
    w = w / w.sum()
    cx, cy = (w * x).sum(), (w * y).sum()
    return cx, cy, np.sqrt((w * (x - cx) ** 2).sum()), np.sqrt((w * (y - cy) ** 2).sum())


def _along(cx, cy, phi_deg):
    """Centroid component along the azimuth phi, and across it."""
    c, s = np.cos(np.radians(phi_deg)), np.sin(np.radians(phi_deg))
    return cx * c + cy * s, -cx * s + cy * c


# ====================================================================== fixtures (one run per module)

THETA_GEO = (0.0, 30.0, 60.0)
PHI_GEO = (0.0, 40.0)


@pytest.fixture(scope="module")
def geo():
    """Moderate slopes (per-axis rms slope sqrt(2) s / L = 0.12), geometric regime; 128 um tile."""
    rel = synth.random_relief(256, 0.5e-6, 0.34e-6, 4e-6, seed=3)
    kw = dict(theta_i_deg=THETA_GEO, phi_i_deg=PHI_GEO, samples=100_000)
    return {"relief": rel,
            "ray": _run(rel, "ray", {"polarized": True}, **kw),
            "normals": _run(rel, "normals", {}, **kw),
            "microfacet": _run(rel, "microfacet", {"polarized": True, "subsamples": 4}, **kw)}


@pytest.fixture(scope="module")
def rough():
    """Large roughness: sigma = 1.2 um (~2.2 lambda), L = 16 um, slope per axis 0.106."""
    rel = synth.random_relief(512, 0.25e-6, 1.2e-6, 16e-6, seed=5)
    kw = dict(theta_i_deg=(0.0, 30.0), phi_i_deg=(0.0,), samples=100_000,
              theta_s_edges_deg=tuple(np.linspace(0.0, 90.0, 46)))
    kir = {"band_limited": True, "polarized": True, "smoothing_dcos": 0.009}
    return {"kirchhoff": _run(rel, "kirchhoff", kir, **kw),
            "ray": _run(rel, "ray", {"polarized": True}, **kw),
            "microfacet": _run(rel, "microfacet", {"polarized": True}, **kw)}


@pytest.fixture(scope="module")
def smooth():
    """Small roughness: sigma = 5 nm, L = 1 um; pitch 80 nm resolves every direction."""
    rel = synth.random_relief(256, 0.08e-6, 5e-9, 1.0e-6, seed=7)
    kw = dict(theta_i_deg=(0.0, 30.0, 60.0), phi_i_deg=(0.0, 40.0))
    return {"relief": rel,
            "kirchhoff": _run(rel, "kirchhoff", {"polarized": True}, **kw),
            "rayleigh-rice": _run(rel, "rayleigh-rice", {"polarized": True}, **kw)}


# ====================================================================== 1. geometric regime


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_geometric_methods_hemispherical_agree(geo):
    """R and T of ray, normals and microfacet agree per incidence, azimuth and side.

    Model difference allowed: microfacet is single scattering, so its deficit `lost` is light
    that ray / normals send out after a second bounce; everything else within 0.006 absolute
    (MC noise of 1e5 paths on R ~ 0.04 - 1 is < 0.002; slope-statistics of the fitted Beckmann
    lobe vs the real slopes shift R by a few 1e-3 at 60 deg).
    """
    for frm in BOTH:
        h = {m: geo[m][frm].hemispherical() for m in ("ray", "normals", "microfacet")}
        for m in ("ray", "normals"):
            assert np.all(np.abs(h[m]["lost"]) < 2e-3), (m, frm, h[m]["lost"])
        for key in ("R", "T"):
            assert np.all(np.abs(h["normals"][key] - h["ray"][key]) < 0.006), (frm, key, h["normals"][key],
                                                                               h["ray"][key])
            slack = 0.006 + h["microfacet"]["lost"]
            assert np.all(np.abs(h["microfacet"][key] - h["ray"][key]) < slack), (frm, key, h["microfacet"][key],
                                                                                  h["ray"][key])
        # energy: every path of ray / normals is accounted for
        for m in ("ray", "normals"):
            tot = h[m]["R"] + h[m]["T"] + h[m]["lost"]
            assert np.allclose(tot, 1.0, atol=1e-9), (m, frm, tot)


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_geometric_lobes_cellwise(geo):
    """In-lobe cells (>= 30 % of ray's peak): microfacet vs ray median relative difference <= 15 %,
    normals vs ray <= 10 % for T (dense), and lobe centroids agree to 0.02 in direction cosines.

    Excluded: light from inside at 60 deg, T (past the critical angle: only multiply scattered or
    steep-facet light escapes, a grazing residue where the models differ by design) and normals'
    R cells (about 4 % of its paths; compared by centroid only).
    """
    for frm in BOTH:
        ray, mf, nm = geo["ray"][frm], geo["microfacet"][frm], geo["normals"][frm]
        for i, ti in enumerate(THETA_GEO):
            for p in range(len(PHI_GEO)):
                for k, side in enumerate("RT"):
                    if frm == "inside" and ti == 60.0 and side == "T":
                        continue
                    vr = ray.values_per_sr[0, i, p, k]
                    mask = vr >= 0.3 * vr.max()
                    med = np.median(np.abs(mf.values_per_sr[0, i, p, k][mask] - vr[mask]) / vr[mask])
                    # inside R at 30 deg: the lobe straddles the critical angle (41.8 deg), where F jumps
                    # to 1 and a caustic-like ridge forms at 52-58 deg whose height depends on the
                    # realisation's slopes in that direction (ray and normals both move ~20 % between
                    # phi_i = 0 and 40, the isotropic microfacet cannot): 0.2 there
                    lim = 0.2 if (frm == "inside" and ti == 30.0 and side == "R") else 0.15
                    assert med < lim, (frm, ti, p, side, med)
                    if side == "T":
                        medn = np.median(np.abs(nm.values_per_sr[0, i, p, k][mask] - vr[mask]) / vr[mask])
                        assert medn < 0.10, (frm, ti, p, side, medn)
                    cr = _lobe_moments(ray, i, p, k)
                    for other in (mf, nm):
                        if other is nm and side == "R" and ti == 60.0:
                            continue      # normals has no exit masking: its grazing R lobe is heavier by design
                        co = _lobe_moments(other, i, p, k)
                        assert abs(co[0] - cr[0]) < 0.02 and abs(co[1] - cr[1]) < 0.02, (frm, ti, p, side,
                                                                                          other.method, co, cr)


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_incidence_azimuth_rotates_the_lobe(geo):
    """Both sides, every method: the R and T lobes lie in the plane of incidence, on the far side
    (phi_i + 180, formats.md), and T obeys Snell at the centroid: n_s sin(theta_s) ~ n_1 sin(theta_i)
    within the lobe's own width (rough-surface centroids shift slightly toward the normal)."""
    for m in ("ray", "normals", "microfacet"):
        for frm in BOTH:
            t = geo[m][frm]
            n1, n2 = _n_pair(frm)
            for i, ti in enumerate(THETA_GEO):
                if ti == 0.0:
                    continue
                for p, pi in enumerate(PHI_GEO):
                    for k, side in enumerate("RT"):
                        if frm == "inside" and ti == 60.0 and side == "T":
                            continue
                        cx, cy, sx, sy = _lobe_moments(t, i, p, k)
                        along, across = _along(cx, cy, pi + 180.0)
                        assert abs(across) < 0.01, (m, frm, ti, pi, side, across)
                        assert along > 0.2, (m, frm, ti, pi, side, along)
                        if side == "T" and n1 * np.sin(np.radians(ti)) < n2:
                            expect = n1 * np.sin(np.radians(ti)) / n2
                            assert abs(along - expect) < max(sx, 0.02), (m, frm, ti, along, expect, sx)
                # the table for phi_i = 40 is the phi_i = 0 table rotated by 40 deg (one relief
                # realisation is not exactly isotropic: compare integrals, not cells)
                h = t.hemispherical()
                assert np.allclose(h["R"][0, i, 0], h["R"][0, i, 1], rtol=0.05, atol=2e-3), (m, frm, ti)


@pytest.mark.slow
def test_microfacet_smooth_lobe_at_normal_incidence_keeps_its_energy():
    """A nearly flat boundary (alpha 0.01, 5 nm / 1 um relief) at normal incidence: the T lobe
    (~0.2 deg) sits on the pole inside the first 3 degree cell.  Light is neither absorbed nor
    multiply scattered there, so R + T = 1 within the cell quadrature (2e-3), as ray, normals,
    kirchhoff and rayleigh-rice give (benchmarks/compare_methods.py).  Before the polar-cap
    quadrature fix microfacet reported lost = 0.13 (0.96 at alpha 0.003)."""
    for alpha in (0.003, 0.01):
        tabs = _run(None, "microfacet", {"alpha": alpha}, theta_i_deg=(0.0, 5.0))
        for frm, t in tabs.items():
            h = t.hemispherical()
            assert np.all(np.abs(h["R"] + h["T"] - 1.0) < (2e-3 if alpha == 0.01 else 1.5e-2)), (alpha, frm,
                                                                                               h["R"] + h["T"])


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_inside_frame_mirrored(geo):
    """Light from inside at 60 deg (past the 41.8 deg critical angle): R stays in the glass and
    takes nearly everything; at 30 deg the T lobe leaves at asin(1.5 sin 30) = 48.6 deg in air."""
    for m in ("ray", "normals", "microfacet"):
        h = geo[m]["inside"].hemispherical()
        assert np.all(h["R"][0, 2] > 0.97), (m, h["R"][0, 2])
        assert np.all(h["T"][0, 2] < 0.01), (m, h["T"][0, 2])
        t = geo[m]["inside"]
        cx, cy, sx, _ = _lobe_moments(t, 1, 0, 1)
        assert abs(-cx - np.sin(np.radians(48.59))) < max(sx, 0.02), (m, cx)


# ====================================================================== 2. wave methods


@pytest.mark.slow
def test_kirchhoff_large_roughness_is_geometric(rough):
    """sigma ~ 2 lambda: the Kirchhoff lobe has the ray / microfacet centroid (within 0.005) and
    rms width (within 12 %: kirchhoff's values are Gaussian-filtered in direction cosines on top of
    the cell average; its default width, half the finest cell = 0.017 here, alone widens the 0.041-wide
    T lobe by 9 %, so it is set to 2 speckle grains, 0.009, and what is left is cell quantisation);
    R and T within 0.01 + kirchhoff's `lost` (its band limit)."""
    for frm in BOTH:
        kr = rough["kirchhoff"][frm]
        hk = kr.hemispherical()
        # energy: the tangent-plane model without shadowing gains ~0.4 % at oblique incidence; the
        # narrow normal-incidence T lobe lost 0.8 % to the cell quadrature before wave_filter 7e54a98
        assert np.all(np.abs(hk["R"] + hk["T"] - 1.0) < 0.006), (frm, hk["R"] + hk["T"])
        for ref in (rough["ray"][frm], rough["microfacet"][frm]):
            hr = ref.hemispherical()
            for key in ("R", "T"):
                assert np.all(np.abs(hk[key] - hr[key]) < 0.01 + hk["lost"] + hr["lost"]), (frm, ref.method, key)
            for i in range(2):
                for k in range(2):
                    ck, cr = _lobe_moments(kr, i, 0, k), _lobe_moments(ref, i, 0, k)
                    assert abs(ck[0] - cr[0]) < 0.005 and abs(ck[1] - cr[1]) < 0.005, (frm, ref.method, i, k, ck, cr)
                    for a, b in ((ck[2], cr[2]), (ck[3], cr[3])):
                        assert abs(a / b - 1.0) < 0.12, (frm, ref.method, i, "RT"[k], a, b)


def test_kirchhoff_energy_narrow_lobe_default_filter():
    """Default filter (half the finest cell) and 3 degree cells: the ~2 degree wide T lobe at
    normal incidence sits in the polar cells; R + T = 1 within the model's 0.6 % (was 0.982: cell
    quadrature with one radial sub-point per filter width, fixed in wave_filter)."""
    rel = synth.random_relief(512, 0.25e-6, 1.2e-6, 16e-6, seed=5)
    t = _run(rel, "kirchhoff", {"band_limited": True}, theta_i_deg=(0.0, 10.0), incident_from=("outside",))["outside"]
    h = t.hemispherical()
    assert np.all(np.abs(h["R"] + h["T"] - 1.0) < 0.006), h["R"] + h["T"]


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_kirchhoff_vs_rayleigh_rice_small_roughness(smooth):
    """5 nm: diffuse R and T of kirchhoff and rayleigh-rice within 15 % (tangent-plane scalar vs
    first-order vector polarisation factors, which differ far from specular); both specular parts
    equal Fresnel x Debye-Waller, exp(-(4 pi sigma n1 cos / lambda)^2) for R."""
    sigma = 5e-9
    for frm in BOTH:
        n1, n2 = _n_pair(frm)
        hk = smooth["kirchhoff"][frm].hemispherical()
        hr = smooth["rayleigh-rice"][frm].hemispherical()
        for i, ti in enumerate((0.0, 30.0, 60.0)):
            for key in ("diffuse_R", "diffuse_T"):
                a, b = hk[key][0, i, 0], hr[key][0, i, 0]
                if b < 1e-4:
                    assert a < 1e-4, (frm, ti, key, a, b)
                    continue
                assert abs(a / b - 1) < 0.15, (frm, ti, key, a, b)
            ci = np.cos(np.radians(ti))
            spec = fresnel_unpolarized(ci, n1, n2) * np.exp(-(4 * np.pi * sigma * n1 * ci / (WL_NM * 1e-9)) ** 2)
            for h in (hk, hr):
                assert abs(h["specular_R"][0, i, 0] - spec) < 1e-4 * spec + 1e-9, (frm, ti, h["specular_R"], spec)
    # light from inside scatters strongly past the critical angle (the evanescent-field enhancement)
    for m in ("kirchhoff", "rayleigh-rice"):
        dR = smooth[m]["inside"].hemispherical()["diffuse_R"][0, :, 0]
        assert dR[2] > 3 * dR[1], (m, dR)


# ====================================================================== 3. reciprocity across sides


def _btdf_reciprocity(tables, tol):
    """f_T^out(i -> o) / n_in^2 == f_T^in(o -> i) / n_out^2 on in-lobe pairs (formats.md).

    Exact partners: light from outside at (a, phi 0) leaving at (T, b, 180) is reversed by light
    from inside arriving along that direction; in the mirrored inside frame (z -> -z) that is
    (b, phi 180), leaving at (T, a, 0); `bsdf.reciprocity_error` uses the same pairing.
    """
    out, ins = tables["outside"], tables["inside"]
    rows = []
    for a in out.theta_i_deg:
        for b in ins.theta_i_deg:
            f_ab = float(out.eval(WL_NM, a, 0.0, "T", b, 180.0)) / N_GLASS**2
            f_ba = float(ins.eval(WL_NM, b, 180.0, "T", a, 0.0)) / 1.0**2
            rows.append((a, b, f_ab, f_ba))
    peak = max(max(r[2], r[3]) for r in rows)
    used = [r for r in rows if min(r[2], r[3]) > 0.2 * peak]
    assert len(used) >= 2, rows
    worst = max(abs(r[2] - r[3]) / (0.5 * (r[2] + r[3])) for r in used)
    assert worst < tol, (tables["outside"].method, worst, used)
    return worst


@pytest.mark.slow
def test_btdf_reciprocity_across_methods():
    """Each method's outside-T and inside-T tables obey the radiance-BTDF reciprocity.

    Every incidence angle sits on a 1 degree cell centre of the other table, so the pairs are
    compared cell average to cell average with no interpolation in theta (linear interpolation
    on a lobe flank is not symmetric between the two frames and would dominate the error);
    outside 15.5, 35.5 deg, inside 5.5, 9.5 (~ Snell image of 15.5), 17.5, 22.5 (~ of 35.5).
    Tolerances: analytic microfacet / rayleigh-rice 3 % (cell averaging in two frames);
    ray 8 % (MC, 3e5 paths, in-lobe cells only); kirchhoff 10 % (one realisation's speckle).
    """
    rel = synth.random_relief(256, 0.5e-6, 0.6e-6, 4e-6, seed=9)     # slope per axis 0.21: broad T lobe
    fine = tuple(np.linspace(0.0, 90.0, 91))
    t_out, t_in = (15.5, 35.5), (5.5, 9.5, 17.5, 22.5)
    for method, opts, tol in (("microfacet", {}, 0.03), ("ray", {"polarized": False}, 0.08)):
        tabs = {"outside": _run(rel, method, opts, theta_i_deg=t_out, incident_from=("outside",),
                                samples=300_000, theta_s_edges_deg=fine)["outside"],
                "inside": _run(rel, method, opts, theta_i_deg=t_in, phi_i_deg=(180.0,), incident_from=("inside",),
                               samples=300_000, theta_s_edges_deg=fine)["inside"]}
        _btdf_reciprocity(tabs, tol)
        if method == "microfacet":      # rotation invariant: the core helper applies as well
            rep = reciprocity_error(tabs["outside"], tabs["inside"], n_a=1.0, n_b=N_GLASS, side="T")
            assert max(r["rel"] for r in rep["pairs"] if r["f_ab"] > 0.05) < tol, rep
    small = synth.random_relief(512, 0.08e-6, 5e-9, 1.0e-6, seed=2)
    # 0.75 degree cells (tile 41 um); pairs away from the pole: a cell of the same angular size spans
    # 1.5x more spatial frequency in glass than in air, so where the cells are not small against the
    # pair's spatial frequency |f| the two frames' cell averages of the PSD differ (8 % with 3 degree
    # cells at 1.5 deg, 5 % with 1.5 degree cells at 9.75 deg: quadrature, not physics)
    for method, tol, edges, th in (("rayleigh-rice", 0.03, np.linspace(0.0, 90.0, 121),
                                    (9.375, 20.625, 30.375, 40.125)),
                                   ("kirchhoff", 0.10, fine, (9.5, 20.5, 30.5, 40.5))):   # its speckle: >= 0.77 deg
        tabs = {frm: _run(small, method, {}, theta_i_deg=th, incident_from=(frm,), theta_s_edges_deg=tuple(edges),
                          phi_i_deg=(0.0 if frm == "outside" else 180.0,))[frm]
                for frm in BOTH}
        _btdf_reciprocity(tabs, tol)


# ====================================================================== 4. Mueller


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_mueller_m00_is_values_everywhere(geo, rough, smooth):
    for group in (geo, rough, smooth):
        for m, tabs in group.items():
            if m in ("relief", "normals"):
                continue
            for t in tabs.values():
                assert t.mueller_per_sr is not None, m
                assert np.allclose(t.mueller_per_sr[..., 0, 0], t.values_per_sr, rtol=1e-6, atol=1e-12), m


def _norm_mueller(t, i, p, k, mask):
    M = t.mueller_per_sr[0, i, p, k][mask]
    return M / M[:, :1, :1]


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_mueller_ray_vs_microfacet_in_lobe(geo):
    """Geometric regime: the normalised cell Mueller matrices M / M00 of ray and microfacet agree
    element-wise to 0.06 in-lobe (same s/p frames, same sign conventions; the residue is MC noise
    and the near-pole cells where the s/p basis turns fast with phi)."""
    for frm in BOTH:
        a, b = geo["ray"][frm], geo["microfacet"][frm]
        for i, ti in enumerate(THETA_GEO):
            for p in range(len(PHI_GEO)):
                for k in range(2):
                    if frm == "inside" and ti == 60.0 and k == 1:
                        continue
                    v = a.values_per_sr[0, i, p, k]
                    mask = v >= 0.3 * v.max()
                    d = np.abs(_norm_mueller(a, i, p, k, mask) - _norm_mueller(b, i, p, k, mask)).max()
                    assert d < 0.06, (frm, ti, p, "RT"[k], d)


# kirchhoff filters each Mueller element with a Gaussian in direction cosines (wave_filter) after
# referring every FFT sample to the s/p basis of ITS OWN direction, so near the pole, where that
# basis turns by ~ filter width / sin(theta_s) across the filter, the linear-polarisation block is
# depolarised (e.g. M11 0.52 -> 0.41 at theta_s = 3 deg); cells with theta_s < 10 deg are left out.
KIRCHHOFF_MIN_THETA_DEG = 10.0


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_mueller_kirchhoff_vs_ray_large_roughness(rough):
    """sigma ~ 2 lambda, oblique incidence: kirchhoff's facet Mueller matrices equal ray's in-lobe
    (both are the stationary-phase facet's Fresnel matrix in the bsdf.py frames) to 0.06."""
    for frm in BOTH:
        a, b = rough["ray"][frm], rough["kirchhoff"][frm]
        for k in range(2):
            v = a.values_per_sr[0, 1, 0, k]
            mask = (v >= 0.3 * v.max()) & (a.theta_s_deg[:, None] >= KIRCHHOFF_MIN_THETA_DEG)
            if frm == "inside" and k == 0:
                mask = (v >= 0.1 * v.max()) & (a.theta_s_deg[:, None] >= KIRCHHOFF_MIN_THETA_DEG)
                # facets met at the critical angle (local incidence (30 + theta_s) / 2 = 41.8 deg): the TIR
                # retardance (M23) rises steeply there and the filter smears it (0.097 vs 0.032)
                mask &= np.abs(0.5 * (30.0 + a.theta_s_deg[:, None]) - 41.81) > 3.0
            assert mask.sum() >= 4
            d = np.abs(_norm_mueller(a, 1, 0, k, mask) - _norm_mueller(b, 1, 0, k, mask)).max()
            assert d < 0.06, (frm, "RT"[k], d)


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_mueller_kirchhoff_vs_rayleigh_rice_near_specular(smooth):
    """5 nm, 30 deg: within 6 degrees of the specular / undeviated direction, where both tend to the
    flat interface, every element of M / M00 agrees to 0.1 and no element of magnitude > 0.1 changes
    sign (a flipped S2/S3 or S1 convention would).  Farther out the two polarisation models differ
    by design (first-order vector theory vs tangent-plane facet Fresnel)."""
    for frm in BOTH:
        a, b = smooth["rayleigh-rice"][frm], smooth["kirchhoff"][frm]
        n1, n2 = _n_pair(frm)
        th = a.theta_s_deg[:, None]
        ph = a.phi_s_deg[None, :]
        for k, side in enumerate("RT"):
            ts = 30.0 if side == "R" else np.degrees(np.arcsin(n1 * 0.5 / n2))
            near = (np.abs(th - ts) < 6.0) & (np.abs(((ph - 180.0 + 180.0) % 360.0) - 180.0) < 6.0)
            near = near & (a.values_per_sr[0, 1, 0, k] > 0) & (th >= KIRCHHOFF_MIN_THETA_DEG)
            assert near.sum() >= 2
            ma, mb = _norm_mueller(a, 1, 0, k, near), _norm_mueller(b, 1, 0, k, near)
            assert np.abs(ma - mb).max() < 0.1, (frm, side, np.abs(ma - mb).max())
            big = np.abs(ma) > 0.1
            assert np.all(np.sign(ma[big]) == np.sign(mb[big])), (frm, side)


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_mueller_follows_incidence_azimuth(geo, smooth):
    """Rotating the incidence azimuth by 40 deg rotates the whole table (values and Mueller cells,
    whose s/p bases are defined from z and the directions, so rotate with them): exact for the
    rotation-invariant models (microfacet; rayleigh-rice with its annulus-averaged PSD), within one
    realisation's anisotropy / speckle / MC noise for ray (0.05) and kirchhoff (0.1) in-lobe."""
    shift = 4                                          # 40 deg in 10 degree phi cells
    cases = [(geo["microfacet"], 1e-9), (geo["ray"], 0.05), (smooth["rayleigh-rice"], 1e-9),
             (smooth["kirchhoff"], 0.1)]
    for tabs, tol in cases:
        for frm, t in tabs.items():
            for i in range(t.theta_i_deg.size):
                if t.theta_i_deg[i] == 0.0:
                    continue                   # same physical incidence: checked in the next test
                v0 = t.values_per_sr[0, i, 0]
                v1 = np.roll(t.values_per_sr[0, i, 1], -shift, axis=-1)
                M0 = t.mueller_per_sr[0, i, 0]
                M1 = np.roll(t.mueller_per_sr[0, i, 1], -shift, axis=-3)
                mask = (v0 >= 0.3 * v0.max(axis=(1, 2), keepdims=True)) & (v1 > 0)
                if t.method == "kirchhoff":
                    mask &= t.theta_s_deg[None, :, None] >= KIRCHHOFF_MIN_THETA_DEG
                d = np.abs(M1[mask] / M1[mask][:, :1, :1] - M0[mask] / M0[mask][:, :1, :1]).max()
                assert d < tol, (t.method, frm, i, d)
                for name in ("specular_mueller_R", "specular_mueller_T"):
                    sm = getattr(t, name)
                    if sm is not None:
                        assert np.allclose(sm[0, i, 0], sm[0, i, 1], atol=1e-12), (t.method, name)


def _stokes_rotation(psi_rad):
    c, s = np.cos(2 * psi_rad), np.sin(2 * psi_rad)
    return np.array([[1, 0, 0, 0], [0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1.0]])


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_normal_incidence_azimuth_only_turns_the_incident_basis(geo, smooth):
    """At theta_i = 0, phi_i = 0 and 40 are the same light; only the incident basis
    s = (-sin phi_i, cos phi_i, 0) turns, so M(40) = M(0) R(-40 deg) cell by cell (R the Stokes
    rotation, S1' = cos 2psi S1 + sin 2psi S2) with the same scattered cells.  Every method agrees on
    this sign; exact for the deterministic ones, MC noise (0.06) for ray."""
    R = _stokes_rotation(np.radians(-40.0))
    for tabs, tol in ((geo["microfacet"], 1e-9), (geo["ray"], 0.06), (smooth["rayleigh-rice"], 1e-9),
                      (smooth["kirchhoff"], 1e-9)):
        for frm, t in tabs.items():
            assert t.theta_i_deg[0] == 0.0
            v0 = t.values_per_sr[0, 0, 0]
            if t.method != "ray":
                assert np.allclose(t.values_per_sr[0, 0, 1], v0, rtol=1e-9, atol=0), (t.method, frm)
            mask = v0 >= 0.3 * v0.max(axis=(1, 2), keepdims=True)
            M0, M1 = t.mueller_per_sr[0, 0, 0][mask], t.mueller_per_sr[0, 0, 1][mask]
            d = np.abs(M1 / M1[:, :1, :1] - (M0 @ R) / M0[:, :1, :1]).max()
            assert d < tol, (t.method, frm, d)


@pytest.mark.slow
def test_flat_limit_equals_mueller_interface():
    """A flat boundary: every method's delta parts (ray, kirchhoff, rayleigh-rice) are exactly
    fresnel.mueller_interface; microfacet with a tiny alpha has its in-lobe cells at the specular
    direction equal to it (normalised by M00) to 0.01."""
    flat = Relief(np.zeros((256, 256)), 0.08e-6, 0.08e-6, periodic=True, source="flat")
    th = (0.0, 30.0, 60.0)
    for method, opts in (("ray", {"polarized": True}), ("kirchhoff", {"polarized": True}),
                         ("rayleigh-rice", {"polarized": True})):
        tabs = _run(flat, method, opts, theta_i_deg=th, samples=2000)
        for frm, t in tabs.items():
            n1, n2 = _n_pair(frm)
            for i, ti in enumerate(th):
                ci = np.cos(np.radians(ti))
                for side, sm, sp in (("R", t.specular_mueller_R, t.specular_R),
                                     ("T", t.specular_mueller_T, t.specular_T)):
                    ref = np.nan_to_num(mueller_interface(ci, n1, n2, side))
                    assert sm is not None, (method, side)
                    assert np.allclose(sm[0, i, 0], ref, atol=1e-9), (method, frm, ti, side, sm[0, i, 0], ref)
                    assert np.isclose(sp[0, i, 0], ref[0, 0], atol=1e-9), (method, frm, ti, side)
                assert float(t.hemispherical()["diffuse_R"][0, i, 0]) < 1e-9
    centred = tuple(np.concatenate([[0.0], np.arange(0.5, 90.0, 1.0), [90.0]]))     # 30 deg is a cell centre
    tabs = _run(flat, "microfacet", {"alpha": 0.004, "polarized": True}, theta_i_deg=(30.0,),
                theta_s_edges_deg=centred)
    for frm, t in tabs.items():
        n1, n2 = _n_pair(frm)
        for k, side in enumerate("RT"):
            ts = 30.0 if side == "R" else np.degrees(np.arcsin(n1 * 0.5 / n2))
            s = int(np.argmin(np.abs(t.theta_s_deg - ts)))
            a = int(np.argmin(np.abs(t.phi_s_deg - 180.0)))
            M = t.mueller_per_sr[0, 0, 0, k, s, a]
            ref = mueller_interface(np.cos(np.radians(30.0)), n1, n2, side)
            assert np.abs(M / M[0, 0] - ref / ref[0, 0]).max() < 0.01, (frm, side, M / M[0, 0], ref / ref[0, 0])


# ====================================================================== 5. plumbing


@pytest.mark.slow   # physics-long: the module's 100 000-path tables of three methods
def test_every_method_table_through_files_and_cli(tmp_path, capsys, geo, rough, smooth):
    """HDF5 round trip, `relief info --json` albedo rows, recording-csv rows == table.eval at the
    cell centre, and IS-BSDF export read back near the lobe, for one table of every method."""
    from relief_bsdf.io.isbsdf import export_isbsdf, import_isbsdf
    picks = [geo["ray"], geo["normals"], geo["microfacet"], rough["kirchhoff"], smooth["rayleigh-rice"]]
    for n, tabs in enumerate(picks):
        path = tmp_path / f"t{n}.h5"
        save_tables(path, list(tabs.values()))
        back = {t.incident_from: t for t in load_tables(path)}
        for frm, t in tabs.items():
            b = back[frm]
            assert b.method == t.method
            for name in ("values_per_sr", "specular_R", "specular_T", "lost", "mueller_per_sr",
                         "specular_mueller_R", "specular_mueller_T", "sigma_per_sr"):
                x, y = getattr(t, name), getattr(b, name)
                assert (x is None) == (y is None), (t.method, name)
                if x is not None:
                    assert np.allclose(x, y, rtol=1e-6, atol=1e-30), (t.method, name)   # float32 on disk
        capsys.readouterr()
        assert cli_main(["info", str(path), "--json"]) == 0
        out = capsys.readouterr().out
        info = json.loads(out)
        rows = info["albedo"] if "albedo" in info else [r for tb in info["tables"] for r in tb["albedo"]]
        for frm, t in tabs.items():
            h = t.hemispherical()
            mine = [r for r in rows if r["from"] == frm]
            assert len(mine) == t.theta_i_deg.size * t.phi_i_deg.size, (t.method, frm)
            for r in mine:
                i = int(np.argmin(np.abs(t.theta_i_deg - r["theta_i_deg"])))
                p = int(np.argmin(np.abs(t.phi_i_deg - r["phi_i_deg"])))
                for key in ("R", "T", "specular_R", "specular_T", "lost"):
                    assert np.isclose(r[key], h[key][0, i, p], rtol=1e-6, atol=1e-12), (t.method, frm, key)
            csv = tmp_path / f"t{n}_{frm}.csv"
            assert cli_main(["export", str(path), "--format", "recording-csv", "--from", frm, "-o", str(csv)]) == 0
            rec = read_recording(csv)
            assert len(rec.bsdf_sr) == t.values_per_sr.size
            k = int(np.argmax(rec.bsdf_sr))
            for j in (k, len(rec.bsdf_sr) // 3):
                ev = t.eval(rec.wavelength_nm[j], rec.theta_i_deg[j], rec.phi_i_deg[j], rec.side[j],
                            rec.theta_s_deg[j], rec.phi_s_deg[j])
                assert np.isclose(rec.bsdf_sr[j], ev, rtol=1e-5, atol=1e-9), (t.method, frm, j, rec.bsdf_sr[j], ev)
        t = tabs["outside"]
        paths = export_isbsdf(t, tmp_path / f"t{n}.bsdf")
        imp = import_isbsdf(paths, t.theta_s_edges_deg, t.phi_s_edges_deg)
        hi, ht = imp.hemispherical(), t.hemispherical()
        for key in ("diffuse_R", "diffuse_T"):
            assert np.allclose(hi[key], ht[key], rtol=0.08, atol=2e-4), (t.method, key, hi[key], ht[key])
