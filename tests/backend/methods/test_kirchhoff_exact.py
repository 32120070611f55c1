"""Kirchhoff against the direct-integration oracle (kirchhoff_oracle.py): the integral, per order.

Periodic maps at 0.0625 um (every propagating order of both media lies inside the FFT band, so
the oracle's orders and the FFT's are the same frequencies), 550 nm, n = 1.5, light from both
sides at 0 / 30 / 60 deg (inside 60 deg is past the critical angle).  Reliefs: Gaussian
autocorrelation (sigma 60-150 nm, l 1-3 um), exponential autocorrelation and light-guide dots
(surface.synth).  In-lobe: orders binned into 5 x 10 deg cells (edges away from the specular
directions), cells holding > 1 % of the largest, within 3 %; hemispherical totals (diffuse +
coherent) of the *table* (with the project's filtering) within 1 % of the oracle's sum.
"""
import warnings

import numpy as np
import pytest

from kirchhoff_oracle import bin_orders, direct_orders
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import kirchhoff, reconstruct
from relief_bsdf.methods.rayleigh_rice import prepared_heights
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import DotPattern, lgp_dots, random_relief

PITCH = 0.0625e-6
MAT = Material(inside=ConstantIndex(1.5))
# cell edges away from the directions orders share by symmetry (specular, multiples of 45 deg azimuth)
TE = np.concatenate([[0.0], np.arange(2.37, 90, 5.0), [90.0]])
PE = np.arange(-4.3, 360.0, 10.0)
FLOOR = 1e-4          # power fractions below this are compared absolutely (e.g. T of 1e-8 past the critical angle)


def _reliefs(n):
    return {
        "gauss 60 nm / 3 um": random_relief(n, PITCH, 60e-9, 3e-6, seed=11),
        "gauss 150 nm / 1 um": random_relief(n, PITCH, 150e-9, 1e-6, seed=12),
        "exponential 100 nm / 1 um": random_relief(n, PITCH, 100e-9, 1e-6, kind="exponential", seed=13),
        "light-guide dots": lgp_dots(n, PITCH, DotPattern(dot_pitch_m=n * PITCH / 2, dot_radius_m=n * PITCH / 6,
                                                          dot_height_m=0.4e-6), seed=14),
    }


def _compare_orders(rel, fr, theta_i, side):
    """(max in-lobe relative cell error, relative error of the side's total) for one case."""
    h, w = prepared_heights(rel)
    hh = h if fr == "outside" else -h
    n1, n2 = (1.0, 1.5) if fr == "outside" else (1.5, 1.0)
    surf = kirchhoff.Surface(hh, w, (PITCH, PITCH), True)
    inc = kirchhoff.Incidence(550.0, theta_i, 0.0, n1, n2)
    m = kirchhoff.order_powers(surf, inc, kirchhoff.SolveSettings(cells=None, width_dcos=0.0), side)
    o = direct_orders(hh, PITCH, 550.0, theta_i, n1, n2, side)
    ns = n1 if side == "R" else n2
    cells_m = bin_orders(m["alpha"].ravel(), m["beta"].ravel(), m["power"].ravel(), TE, PE)
    spec_a = -n1 * np.sin(np.radians(theta_i)) / ns + 0.0          # never -0.0 (phi 180 instead of 0)
    cells_m += bin_orders(np.array([spec_a]), np.array([0.0]), np.array([m["specular"]]), TE, PE)
    cells_o = bin_orders(o["alpha"], o["beta"], o["power"], TE, PE)
    lobe = cells_o > 0.01 * cells_o.max()
    in_lobe = float(np.max(np.abs(cells_m[lobe] - cells_o[lobe]) / np.maximum(cells_o[lobe], FLOOR)))
    total = (m["power"].sum() + m["specular"] - o["power"].sum()) / max(o["power"].sum(), FLOOR)
    return in_lobe, float(total)


@pytest.mark.parametrize("fr,theta_i", [("outside", 60.0), ("inside", 60.0)])
def test_orders_match_direct_integration_fast(fr, theta_i):
    rel = random_relief(64, PITCH, 150e-9, 1e-6, seed=3)
    for side in "RT":
        in_lobe, total = _compare_orders(rel, fr, theta_i, side)
        assert in_lobe < 0.03, (side, in_lobe)
        assert abs(total) < 0.01, (side, total)


@pytest.mark.slow
def test_orders_match_direct_integration_all_reliefs():
    worst = {}
    for name, rel in _reliefs(96).items():
        for fr in ("outside", "inside"):
            for ti in (0.0, 30.0, 60.0):
                for side in "RT":
                    in_lobe, total = _compare_orders(rel, fr, ti, side)
                    worst[(name, fr, ti, side)] = (in_lobe, total)
    bad = {k: v for k, v in worst.items() if v[0] >= 0.03 or abs(v[1]) >= 0.01}
    assert not bad, bad


def _table_vs_oracle(rel, fr, thetas, **options):
    """The table's hemispherical R, T against the oracle's sums over the heights the table diffracted:
    the map itself, or, where kirchhoff band-limited it (metadata height_band_limit, option
    band_limit_heights), the map low-passed at the f_max it states."""
    from relief_bsdf.surface.stats import band_limited
    req = Request(theta_i_deg=tuple(thetas), incident_from=(fr,), theta_s_edges_deg=tuple(np.linspace(0, 90, 19)),
                  phi_s_edges_deg=tuple(np.arange(-5.0, 360.0, 10.0)), options={"backend": "serial", **options})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)       # the energy-defect warning (tested below)
        (tab,) = reconstruct(rel, MAT, req, "kirchhoff")
    hm = tab.hemispherical()
    band = tab.metadata["height_band_limit"]
    h, w = prepared_heights(rel if band is None else band_limited(rel, band["f_max_per_m"]).relief)
    hh = h if fr == "outside" else -h
    n1, n2 = (1.0, 1.5) if fr == "outside" else (1.5, 1.0)
    out = []
    for it, ti in enumerate(thetas):
        for s in "RT":
            o = direct_orders(hh, PITCH, 550.0, ti, n1, n2, s)["power"].sum()
            out.append((ti, s, float((hm[s][0, it, 0] - o) / max(o, FLOOR))))
        out.append((ti, "lost", float(tab.lost[0, it, 0])))
    return tab, out


@pytest.mark.slow
@pytest.mark.parametrize("fr", ["outside", "inside"])
def test_table_totals_match_oracle_within_one_percent(fr):
    """The filtered table's hemispherical R and T (diffuse + coherent) against the oracle's sums:
    the filter keeps the power inside the propagating disc and the cells hold what the grid holds."""
    rel = random_relief(128, PITCH, 100e-9, 1e-6, seed=1)
    tab, rows = _table_vs_oracle(rel, fr, (0.0, 30.0, 60.0))
    for ti, s, err in rows:
        if s != "lost":
            assert abs(err) < 0.01, (ti, s, err)
    hm = tab.hemispherical()
    np.testing.assert_allclose(hm["R"] + hm["T"] + tab.lost, 1.0, atol=1e-12)     # lost is signed


@pytest.mark.slow
@pytest.mark.parametrize("name,options", [("exponential 100 nm / 1 um", {}),
                                          ("exponential 100 nm / 1 um", {"band_limit_heights": False}),
                                          ("light-guide dots", {})])
def test_table_totals_match_oracle_on_non_gaussian_reliefs(name, options):
    """As above on the non-Gaussian reliefs, both sides, 0 / 30 / 60 deg: the filtered table's totals
    within 1 % of the oracle's.  The exponential relief has power beyond the propagating band: by
    default kirchhoff removes it (and says so), and the table equals the integral over the heights
    it kept; with band_limit_heights off it equals the integral over the map as it is."""
    rel = _reliefs(128)[name]
    for fr in ("outside", "inside"):
        tab, rows = _table_vs_oracle(rel, fr, (0.0, 30.0, 60.0), **options)
        for ti, s, err in rows:
            if s != "lost":
                assert abs(err) < 0.01, (fr, ti, s, err)
        removed = (tab.metadata["height_band_limit"] or {}).get("removed_rms_m", 0.0)
        assert (removed > 1e-9) == (name.startswith("exponential") and not options), (fr, removed)


def test_windowed_map_is_consistent_flat_limit():
    """A non-periodic (Hann-windowed) nearly flat map: coherent + diffuse = Fresnel R + T = 1; the mean
    field uses the same squared-window weights as the power (no spurious gain)."""
    rng = np.random.default_rng(5)
    h = 3e-9 * rng.standard_normal((256, 256)) + 2e-9 * np.linspace(-1, 1, 256)[None, :]
    rel = Relief(h, 0.1e-6, 0.1e-6, periodic=False, source="flat test")
    req = Request(theta_i_deg=(0.0, 45.0), theta_s_edges_deg=tuple(np.linspace(0, 90, 31)),
                  phi_s_edges_deg=tuple(PE), options={"backend": "serial", "band_limited": True})
    (tab,) = reconstruct(rel, MAT, req, "kirchhoff")
    hm = tab.hemispherical()
    np.testing.assert_allclose(hm["R"] + hm["T"], 1.0, atol=2e-3)
    assert np.all(np.abs(tab.lost) < 2e-3)
    assert tab.metadata["energy_defect"]["meaning"] == "tangent-plane energy defect"


def test_energy_defect_is_signed_and_warned():
    """Past the critical angle the tangent-plane model does not conserve energy: lost is stored with its
    sign (R + T + lost = 1 exactly), and a warning names it."""
    rel = random_relief(128, PITCH, 150e-9, 1e-6, seed=2)
    req = Request(theta_i_deg=(60.0,), incident_from=("inside",), theta_s_edges_deg=tuple(np.linspace(0, 90, 19)),
                  phi_s_edges_deg=tuple(PE), options={"backend": "serial"})
    with pytest.warns(RuntimeWarning, match="tangent-plane"):
        (tab,) = reconstruct(rel, MAT, req, "kirchhoff")
    hm = tab.hemispherical()
    np.testing.assert_allclose(hm["R"] + hm["T"] + tab.lost, 1.0, atol=1e-12)
    assert abs(tab.metadata["energy_defect"]["worst_signed"]) > 0.01


def test_heights_band_limited_to_the_propagating_band_with_a_statement():
    """Profilometer-like white noise (3 nm) on a smooth 20 nm relief at 50 nm pitch: kirchhoff removes
    the components finer than the propagating band, says how much (metadata height_band_limit), and
    its coherent reflection then matches the noise-free relief's instead of being lowered by the
    noise (3 nm rms lowers exp(-(4 pi sigma / lambda)^2) by ~0.5 %; ~7 % of white noise's variance
    lies inside the band)."""
    rng = np.random.default_rng(8)
    base = random_relief(512, 0.05e-6, 20e-9, 2e-6, seed=6)
    noisy = Relief(base.heights_m + 3e-9 * rng.standard_normal(base.shape), 0.05e-6, 0.05e-6, periodic=True,
                   source="noisy")
    req = Request(theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.linspace(0, 60, 31)),
                  phi_s_edges_deg=tuple(PE), options={"backend": "serial"})
    (kb,) = reconstruct(noisy, MAT, req, "kirchhoff")
    (kr,) = reconstruct(noisy, MAT, Request(**{**req.__dict__, "options": {"backend": "serial",
                                                                             "band_limit_heights": False}}), "kirchhoff")
    (k0,) = reconstruct(base, MAT, req, "kirchhoff")
    band = kb.metadata["height_band_limit"]
    assert 1.5e-9 < band["removed_rms_m"] < 3e-9 and "removed" in band["statement"]
    assert kr.metadata["height_band_limit"] is None
    loss_b = 1 - kb.specular_R[0, 0, 0] / k0.specular_R[0, 0, 0]
    loss_r = 1 - kr.specular_R[0, 0, 0] / k0.specular_R[0, 0, 0]
    assert abs(loss_b) < 0.001 and 0.003 < loss_r < 0.007
