"""Rayleigh-Rice (first-order vector perturbation) against NIST pySCATMECH and physical truths."""
import numpy as np
import pytest

from _wave_reliefs import gaussian_relief, scatmech_psd_bsdf
from relief_bsdf.methods import rayleigh_rice as rr
from relief_bsdf.methods import reconstruct
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request

RMS, CORR, LAM = 5e-9, 1e-6, 550.0
MAT = Material(inside=ConstantIndex(1.5))
# narrow in-plane cells only (1 degree, centred on 0 and 180): fast, and the cell average is
# within 0.2% of the value at the centre that SCATMECH gives
PHI_EDGES = (-0.5, 0.5, 179.5, 180.5)


@pytest.fixture(scope="module")
def relief():
    return gaussian_relief(2048, 0.1e-6, RMS, CORR, seed=3)


def _exact_psd():
    fr = np.linspace(0, 2e7, 200001)
    return rr.Psd(RMS, True, 1.0, radial_f=fr, radial_s=np.pi * RMS**2 * CORR**2 * np.exp(-(np.pi * CORR * fr) ** 2))


def test_formula_matches_scatmech_pointwise():
    """With the exact Gaussian PSD the formula equals SCATMECH in and out of plane, 4 cases."""
    psd = _exact_psd()
    pts = [(0, 10, 180), (30, 20, 180), (30, 25, 240), (60, 30, 300), (20, 5, 270)]
    for kind, (n1, n2, side) in enumerate([(1, 1.5, "R"), (1, 1.5, "T"), (1.5, 1, "R"), (1.5, 1, "T")]):
        for ti, ts, ps in pts:
            ref = scatmech_psd_bsdf(kind, 0.55, 1.5, RMS * 1e6, CORR * 1e6, ti, [ts], [ps])[0]
            surface = rr.RoughInterface(n1, n2, LAM * 1e-9, psd)
            ours = rr.rr_bsdf(np.radians(ti), 0.0, np.radians(ts), np.radians(ps), side, surface)
            assert ours == pytest.approx(ref, rel=1e-6), (kind, ti, ts, ps)


@pytest.mark.oracle
@pytest.mark.parametrize("incident_from", ["outside", "inside"])
@pytest.mark.slow
def test_table_from_estimated_psd_matches_scatmech(relief, incident_from):
    """Median in-lobe ratio within 3% for R and T at 0, 30, 60 degrees (relief's own PSD)."""
    req = Request(wavelengths_nm=(LAM,), theta_i_deg=(0.0, 30.0, 60.0), incident_from=(incident_from,),
                  phi_s_edges_deg=PHI_EDGES)
    (tab,) = reconstruct(relief, MAT, req, "rayleigh-rice")
    assert tab.mueller_per_sr is not None
    ts = tab.theta_s_deg
    for it, ti in enumerate(req.theta_i_deg):
        for k, side in enumerate("RT"):
            kind = (0 if incident_from == "outside" else 2) + k
            if incident_from == "inside" and side == "T" and ti == 60.0:
                continue  # past the critical angle: the transmitted lobe is tiny but checked below
            ours = np.concatenate([tab.values_per_sr[0, it, 0, k, :, a] for a in (0, 2)])
            ref = np.concatenate([scatmech_psd_bsdf(kind, 0.55, 1.5, RMS * 1e6, CORR * 1e6, ti, ts,
                                                    np.full(ts.size, phi)) for phi in (0.0, 180.0)])
            lobe = ref > 0.02 * ref.max()
            assert lobe.sum() >= 10
            ratio = np.median(ours[lobe] / ref[lobe])
            assert abs(ratio - 1) < 0.03, (incident_from, ti, side, ratio)


@pytest.mark.slow
def test_inside_past_critical_scatters_more(relief):
    """From inside the glass, 60 deg (past critical, 41.8 deg) scatters ~5x more than 30 deg."""
    req = Request(wavelengths_nm=(LAM,), theta_i_deg=(30.0, 60.0), incident_from=("inside",))
    (tab,) = reconstruct(relief, MAT, req, "rayleigh-rice")
    d = tab.hemispherical()["diffuse_R"][0, :, 0]
    assert 3.0 < d[1] / d[0] < 8.0
    # and no specular transmission past the critical angle
    assert tab.specular_T[0, 1, 0] == 0.0 and tab.specular_T[0, 0, 0] > 0.9


@pytest.mark.slow
def test_reciprocity_and_energy(relief):
    # incidences 1 degree apart so pairs lie inside the lobe (values at cell centres, no interpolation)
    req = Request(wavelengths_nm=(LAM,), theta_i_deg=(4.5, 8.5, 12.5, 16.5), incident_from=("outside", "inside"),
                  phi_s_edges_deg=PHI_EDGES)
    out, ins = reconstruct(relief, MAT, req, "rayleigh-rice")
    assert rr_rel(out, out, "R") < 0.03
    # radiance BTDF reciprocity: f_T^out(a->b)/n_in^2 = f_T^in(b->a)/n_out^2 (theta inside < critical)
    f_ab = float(out.eval(LAM, 12.5, 0.0, "T", 8.5, 180.0)) / 1.5**2
    f_ba = float(ins.eval(LAM, 8.5, 0.0, "T", 12.5, 180.0)) / 1.0**2
    assert f_ab == pytest.approx(f_ba, rel=0.03)
    req = Request(wavelengths_nm=(LAM,), theta_i_deg=(0.0, 30.0, 60.0))
    (out,) = reconstruct(relief, MAT, req, "rayleigh-rice")
    h = out.hemispherical()
    tot = h["R"] + h["T"]
    assert np.all(np.abs(tot - 1) < 0.02)
    # diffuse part is a small, positive fraction of order (4 pi sigma / lambda)^2 R_F
    assert np.all(h["diffuse_R"] > 0) and np.all(h["diffuse_R"] < 0.04 * (4 * np.pi * RMS / (LAM * 1e-9)) ** 2 * 2)


def rr_rel(a, b, side):
    from relief_bsdf.bsdf.table import reciprocity_error
    return reciprocity_error(a, b, side=side)["max_rel"]


@pytest.mark.slow
def test_redder_is_sharper(relief):
    """Colour: the lobe narrows with wavelength (PSD sampled at f = sin / lambda)."""
    req = Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0,), phi_s_edges_deg=PHI_EDGES)
    (tab,) = reconstruct(relief, MAT, req, "rayleigh-rice")
    ts = tab.theta_s_deg
    widths = []
    for iw in range(2):
        v = tab.values_per_sr[iw, 0, 0, 0, :, 0]
        widths.append(np.sqrt(np.sum(v * np.sin(np.radians(ts)) ** 3) / np.sum(v * np.sin(np.radians(ts)))))
    assert widths[1] > 1.3 * widths[0]   # lobe width scales with lambda (650/450 = 1.44)


def test_mueller_matches_scatmech_and_flat_interface():
    """Full Mueller BSDF: SCATMECH's psps matrices (basis handedness aside) and the specular limit."""
    from pySCATMECH.brdf import BRDF_Model
    from relief_bsdf.core.fresnel import cos_transmitted, mueller_interface
    psd = _exact_psd()
    D = np.diag([1.0, 1.0, -1.0, -1.0])
    for kind, (n1, n2, side) in enumerate([(1, 1.5, "R"), (1, 1.5, "T"), (1.5, 1, "R"), (1.5, 1, "T")]):
        m = BRDF_Model("Microroughness_BRDF_Model", wavelength=0.55, substrate=1.5, type=kind,
                       psd={None: "Gaussian_PSD_Function", "sigma": RMS * 1e6, "length": CORR * 1e6})
        for ti, ts, ps in [(30, 20, 230), (10, 25, 100), (50, 40, 200)]:
            ref = np.array(m.MuellerBRDF(np.radians(ti), np.radians(ts), np.radians(ps - 180)))
            surface = rr.RoughInterface(n1, n2, LAM * 1e-9, psd)
            ours = rr.rr_mueller(np.radians(ti), 0.0, np.radians(ts), np.radians(ps), side, surface)
            if kind < 2:
                ours = D @ ours @ D
            np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-7 * ref[0, 0])
        # towards the specular / undeviated direction the cell Mueller matrix tends to the interface's
        ti = 25.0
        ct = np.real(cos_transmitted(np.cos(np.radians(ti)), n1, n2))
        ts = ti if side == "R" else np.degrees(np.arccos(ct))
        M = rr.rr_mueller(np.radians(ti), 0.0, np.radians(ts), np.pi, side, rr.RoughInterface(n1, n2, LAM * 1e-9, psd))
        F = mueller_interface(np.cos(np.radians(ti)), n1, n2, side)
        np.testing.assert_allclose(M / M[0, 0], F / F[0, 0], atol=1e-9)


@pytest.mark.slow
def test_polarized_request_values(relief):
    base = dict(wavelengths_nm=(LAM,), theta_i_deg=(40.0,), phi_s_edges_deg=PHI_EDGES)
    (u,) = reconstruct(relief, MAT, Request(**base), "rayleigh-rice")
    (s,) = reconstruct(relief, MAT, Request(**base, polarization="s"), "rayleigh-rice")
    (p,) = reconstruct(relief, MAT, Request(**base, polarization="p"), "rayleigh-rice")
    np.testing.assert_allclose(0.5 * (s.values_per_sr + p.values_per_sr), u.values_per_sr, rtol=1e-12)
    assert s.specular_R[0, 0, 0] > p.specular_R[0, 0, 0]            # R_s > R_p at 40 deg
    assert s.hemispherical()["diffuse_R"][0, 0, 0] > p.hemispherical()["diffuse_R"][0, 0, 0]


# ------------------------------------------------------------------ regime of validity

def _rr_tables(rms_m, incident_from=("outside",), wavelengths=(450.0, 650.0), corr_m=CORR):
    small = gaussian_relief(256, 0.1e-6, rms_m, corr_m, seed=5)
    req = Request(wavelengths_nm=wavelengths, theta_i_deg=(0.0, 60.0), incident_from=incident_from,
                  theta_s_edges_deg=tuple(np.arange(0.0, 91.0, 10.0)), phi_s_edges_deg=PHI_EDGES)
    return small, reconstruct(small, MAT, req, "rayleigh-rice")


def test_validity_metadata_inside_the_regime_and_no_warning():
    import warnings
    from relief_bsdf.surface.stats import relief_stats
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # any warning fails the test
        small, (tab,) = _rr_tables(5e-9)
    v = tab.metadata["validity"]
    st = relief_stats(small)
    assert v["valid"] and v["rayleigh_ok"] and v["slope_ok"]
    assert v["rms_height_m"] == pytest.approx(st.rms_height_m, rel=1e-9)
    assert v["rms_slope"] == pytest.approx(st.rms_slope, rel=1e-9)
    # g = (4 pi n1 sigma cos theta_i / lambda)^2 per [wavelength][incidence], from outside n1 = 1
    g = np.array(v["rayleigh_parameter"])
    expect = (4 * np.pi * 5e-9 * np.cos(np.radians([[0.0, 60.0]])) / (np.array([[450e-9], [650e-9]]))) ** 2
    np.testing.assert_allclose(g, expect, rtol=1e-9)
    assert g[0, 0] > g[1, 0] and g[0, 0] == pytest.approx(4 * g[0, 1])      # bluer and more normal is worse
    assert tab.metadata["rayleigh_parameter_max"] == pytest.approx(g.max())
    assert np.all(v["valid_per_incidence"])


def test_validity_flags_the_pairs_outside_the_regime_and_warns():
    # sigma = 12 nm: g = 0.112 at 450 nm, normal incidence (>= 0.1); 0.028 at 60 deg; 0.054 at 650 nm
    with pytest.warns(RuntimeWarning, match=r"outside its regime.*450 nm, theta_i = 0 deg") as rec:
        small, (tab,) = _rr_tables(12e-9)
    regime = [r for r in rec if "outside its regime" in str(r.message)]      # (the energy defect warns apart)
    assert len(regime) == 1 and "1 of 4" in str(regime[0].message)
    v = tab.metadata["validity"]
    assert not v["valid"] and not v["rayleigh_ok"] and v["slope_ok"]
    assert v["valid_per_incidence"] == [[False, True], [True, True]]
    assert v["rayleigh_parameter"][0][0] == pytest.approx((4 * np.pi * v["rms_height_m"] / 450e-9) ** 2)
    # the same relief lit from inside the glass (n1 = 1.5): the phase variance is 1.5^2 larger
    with pytest.warns(RuntimeWarning, match="light from inside"):
        _, (ins,) = _rr_tables(12e-9, incident_from=("inside",))
    gi = np.array(ins.metadata["validity"]["rayleigh_parameter"])
    np.testing.assert_allclose(gi, 2.25 * np.array(v["rayleigh_parameter"]), rtol=1e-9)
    assert ins.metadata["validity"]["valid_per_incidence"] == [[False, True], [False, True]]


def test_relief_info_shows_the_validity_of_a_saved_table(tmp_path, capsys):
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.cli import main
    with pytest.warns(RuntimeWarning):
        _, (bad,) = _rr_tables(12e-9)
    _, (good,) = _rr_tables(3e-9)
    for name, t, needle in (("bad.h5", bad, "OUTSIDE the method's regime at 450 nm / 0 deg"),
                            ("good.h5", good, "within the method's regime")):
        save_tables(tmp_path / name, [t])
        assert main(["info", str(tmp_path / name)]) == 0
        assert needle in capsys.readouterr().out


def test_validity_flags_steep_slopes():
    # 3 nm rms over a 30 nm correlation length: tiny Rayleigh parameter (0.005), rms slope 2 s / L = 0.2
    small = gaussian_relief(256, 5e-9, 3e-9, 30e-9, seed=2)
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.arange(0.0, 91.0, 10.0)),
                  phi_s_edges_deg=PHI_EDGES)
    with pytest.warns(RuntimeWarning, match="rms slope"):
        (tab,) = reconstruct(small, MAT, req, "rayleigh-rice")
    v = tab.metadata["validity"]
    assert v["rayleigh_ok"] and not v["slope_ok"] and not v["valid"] and v["rms_slope"] > 0.15
