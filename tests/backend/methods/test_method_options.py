"""Typed method options, the method registry, the surrogates (microfacet+dw, flat) and auto's one line."""
import dataclasses
import re

import numpy as np
import pytest

from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.errors import InputError, RequestError
from relief_bsdf.methods import (REGISTRY, AutoOptions, KirchhoffOptions, MethodOptions, MicrofacetOptions,
                                 RayOptions, entry, method_names, reconstruct)
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.relief import Relief

GLASS = Material(inside=ConstantIndex(1.5))
SMALL = dict(theta_i_deg=(0.0, 30.0), theta_s_edges_deg=tuple(np.linspace(0, 90, 19)),
             phi_s_edges_deg=tuple(np.arange(-15.0, 360, 30.0)))


def _wavy(n=48, pitch=0.5e-6):
    """A smooth periodic relief (deterministic, no random generator involved)."""
    x = np.arange(n) * pitch
    X, Y = np.meshgrid(x, x)
    h = 60e-9 * np.sin(2 * np.pi * X / 12e-6) * np.cos(2 * np.pi * Y / 8e-6) \
        + 20e-9 * np.cos(2 * np.pi * (X + 2 * Y) / 6e-6)
    return Relief(h, pitch, pitch, periodic=True, source="wavy")


# ------------------------------------------------------------------ typed options


def test_misspelled_option_is_an_error_naming_it_and_the_known_ones():
    with pytest.raises(RequestError) as e:
        KirchhoffOptions.from_mapping({"bandlimted": True}, "kirchhoff")
    msg = str(e.value)
    assert "unknown option 'bandlimted' for method kirchhoff" in msg
    assert "band_limited" in msg and "qz_tolerance" in msg


@pytest.mark.parametrize("cls,key,value", [
    (KirchhoffOptions, "band_limited", "yes"),        # a string where a bool is meant
    (KirchhoffOptions, "max_qz_nodes", 2.5),           # not an integer
    (KirchhoffOptions, "qz_tolerance", True),          # a bool is not a number
    (MicrofacetOptions, "distribution", "phong"),      # not one of the choices
    (RayOptions, "specular_tol_rad", 0.5),             # out of range
    (RayOptions, "max_bounces", 0),
])
def test_mistyped_option_is_an_error_naming_it(cls, key, value):
    with pytest.raises(RequestError) as e:
        cls.from_mapping({key: value})
    assert repr(key) in str(e.value) or key in str(e.value)


def test_defaults_and_conversion():
    k = KirchhoffOptions.from_mapping({})
    assert k == KirchhoffOptions() and k.qz_tolerance == 1e-3 and k.max_qz_nodes == 64 and not k.band_limited
    k = KirchhoffOptions.from_mapping({"max_qz_nodes": 4.0, "qz_tolerance": 1, "band_limited": True})
    assert k.max_qz_nodes == 4 and isinstance(k.max_qz_nodes, int) and k.qz_tolerance == 1.0
    m = MicrofacetOptions.from_mapping({"alpha": [0.1, 0.3], "weights": [1, 2]})
    assert m.alpha == (0.1, 0.3) and m.weights == (1.0, 2.0)
    assert RayOptions.from_mapping({"fill_holes": 3}).fill_holes == 3
    assert KirchhoffOptions.from_mapping(k) is k                    # an options object passes through


def test_every_registered_method_has_documented_typed_options():
    for name, e in REGISTRY.items():
        assert issubclass(e.options, MethodOptions) and e.physics and e.validity
        e.options.from_mapping({}, name)                               # all defaults valid
        docs = e.options.describe()
        assert set(docs) == set(e.options.known()) and all(docs.values())
        with pytest.raises(RequestError, match=re.escape(f"unknown option 'nonsense_key' for method {name}")):
            e.parse_options({"nonsense_key": 1})


def test_request_options_for_and_reconstruct_refuse_a_typo_before_work():
    req = Request(options={"bandlimted": True}, **SMALL)
    with pytest.raises(RequestError, match="bandlimted"):
        req.options_for("kirchhoff")
    with pytest.raises(RequestError, match="unknown option 'bandlimted' for method kirchhoff"):
        reconstruct(_wavy(), GLASS, req, "kirchhoff")
    assert Request(options={"band_limited": True}).options_for("kirchhoff").band_limited


def test_auto_options_forward_only_what_the_chosen_method_knows():
    a = AutoOptions.from_mapping({"quiet": True, "band_limited": True, "max_bounces": 7})
    assert a.quiet
    assert a.for_method(KirchhoffOptions) == {"band_limited": True}
    assert a.for_method(RayOptions) == {"max_bounces": 7}
    with pytest.raises(RequestError, match="unknown option 'bandlimted' for method auto"):
        AutoOptions.from_mapping({"bandlimted": True})
    with pytest.raises(RequestError, match="band_limited"):
        AutoOptions.from_mapping({"band_limited": "yes"})


# ------------------------------------------------------------------ registry


def test_registry_lists_methods_surrogates_and_flat():
    names = method_names()
    for n in ("microfacet", "normals", "ray", "kirchhoff", "rayleigh-rice", "auto", "microfacet+dw", "flat"):
        assert n in names
    assert "microfacet+dw" not in method_names(surrogates=False)
    assert entry("microfacet+dw").surrogate and entry("flat").surrogate
    with pytest.raises(RequestError, match="--method"):
        entry("nonsense")
    from relief_bsdf.methods.registry import listing
    text = listing()
    assert all(n in text for n in names)


def test_cli_help_lists_the_registry(capsys):
    from relief_bsdf.cli import main
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert all(n in out for n in method_names())


@pytest.mark.parametrize("method,option", [("kirchhoff", "bandlimted=true"), ("auto", "quite=true"),
                                           ("microfacet", "alpah=0.2")])
def test_cli_misspelled_option_exit_2_naming_it(tmp_path, capsys, method, option):
    from relief_bsdf.cli import main
    src = tmp_path / "r.npz"
    rel = _wavy()
    np.savez(src, heights=rel.heights_m, dx=rel.dx_m, dy=rel.dy_m)
    out = tmp_path / "x.h5"
    rc = main(["reconstruct", str(src), "--method", method, "--n", "1.5", "--option", option, "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert option.split("=")[0] in err and f"for method {method}" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


# ------------------------------------------------------------------ microfacet+dw (the fit's surrogate)


def _old_debye_waller(table, material, sigma_m):
    """The fit's former fit.optimise._debye_waller, verbatim in its arithmetic (the reference)."""
    W, I = table.wavelength_nm.size, table.theta_i_deg.size
    gR, gT = np.zeros((W, I, 1)), np.zeros((W, I, 1))
    sR, sT = np.zeros((W, I, 1, 4, 4)), np.zeros((W, I, 1, 4, 4))
    for w, wl in enumerate(table.wavelength_nm):
        n1, n2 = (float(np.real(x)) for x in material.n_pair(wl, table.incident_from))
        k = 2 * np.pi / (wl * 1e-9)
        ci = np.cos(np.radians(table.theta_i_deg))
        st2 = (n1 / n2) ** 2 * (1 - ci**2)
        ct = np.sqrt(np.clip(1 - st2, 0, 1))
        gR[w, :, 0] = np.exp(-(2 * k * n1 * sigma_m * ci) ** 2)
        gT[w, :, 0] = np.where(st2 < 1, np.exp(-(k * sigma_m * (n1 * ci - n2 * ct)) ** 2), 0.0)
        sR[w, :, 0] = mueller_interface(ci, n1, n2, "R") * gR[w, :, 0, None, None]
        sT[w, :, 0] = mueller_interface(ci, n1, n2, "T") * gT[w, :, 0, None, None]
    v = table.values_per_sr.copy()
    v[:, :, :, 0] *= (1 - gR)[..., None, None]
    v[:, :, :, 1] *= (1 - gT)[..., None, None]
    return v, sR, sT


def _fit_grid_request(theta_i, side):
    te = tuple(np.linspace(0.0, 90.0, 19))
    pe = tuple(np.arange(-7.5, 360.0 - 7.5 + 1e-9, 15.0))
    return Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=tuple(theta_i), incident_from=(side,),
                   theta_s_edges_deg=te, phi_s_edges_deg=pe, samples=200_000, seed=0)


# frozen from the fit's own code path (fit.optimise.derive_tables before the redesign) on _wavy():
# the Debye-Waller delta parts depend on the rms height only
OLD_SPECULAR_R_OUTSIDE = [0.016963717524307847, 0.021821298588495415, 0.026515865999066978, 0.030504870073325124]
OLD_SPECULAR_T_OUTSIDE = [0.9098871843459978, 0.8986569154464067, 0.935646068481463, 0.92932479589844]
OLD_SIGMA_M = 3.3166247903553997e-08


@pytest.mark.slow
def test_microfacet_dw_equals_the_old_fit_path():
    from relief_bsdf.methods.microfacet_dw import relief_sigma_slope
    rel = _wavy()
    for side, theta in (("outside", (0.0, 30.0)), ("inside", (0.0, 30.0, 45.0, 60.0, 75.0, 89.0))):
        req = _fit_grid_request(theta, side)
        (new,) = reconstruct(rel, GLASS, req, "microfacet+dw")
        sigma, slope = relief_sigma_slope(rel)
        old_req = dataclasses.replace(req, options={"alpha": max(slope, 1e-4)})
        (lobe,) = reconstruct(rel, GLASS, old_req, "microfacet")
        v, sR, sT = _old_debye_waller(lobe, GLASS, sigma)
        assert new.method == "microfacet+dw" and new.incident_from == side
        np.testing.assert_array_equal(new.values_per_sr, v)
        np.testing.assert_array_equal(new.specular_mueller_R, sR)
        np.testing.assert_array_equal(new.specular_mueller_T, sT)
        np.testing.assert_array_equal(new.specular_R, sR[..., 0, 0])
        assert new.metadata["debye_waller_sigma_m"] == sigma
        if side == "outside":
            assert sigma == pytest.approx(OLD_SIGMA_M, rel=1e-12)
            np.testing.assert_allclose(new.specular_R.ravel(), OLD_SPECULAR_R_OUTSIDE, rtol=1e-12)
            np.testing.assert_allclose(new.specular_T.ravel(), OLD_SPECULAR_T_OUTSIDE, rtol=1e-12)


@pytest.mark.slow
def test_fit_relief_face_tables_call_the_registered_surrogate():
    from relief_bsdf.plate import ReliefFace, TableGrid
    rel = _wavy()
    out, ins = ReliefFace(rel, method="microfacet+dw").tables(GLASS, TableGrid(10.0, 15.0, 15.0), [450.0, 650.0],
                                                              [0.0, 30.0])
    te = tuple(np.linspace(0.0, 90.0, 10))
    pe = tuple(np.arange(-7.5, 360.0 - 7.5 + 1e-9, 15.0))
    (ref,) = reconstruct(rel, GLASS, Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0, 30.0),
                                             theta_s_edges_deg=te, phi_s_edges_deg=pe, samples=200_000),
                         "microfacet+dw")
    np.testing.assert_array_equal(out.values_per_sr, ref.values_per_sr)
    np.testing.assert_array_equal(out.specular_mueller_T, ref.specular_mueller_T)
    assert ins.incident_from == "inside" and ins.method == "microfacet+dw"


# ------------------------------------------------------------------ flat


def test_flat_method_is_fresnel_in_the_delta_parts():
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0, 30.0, 45.0, 60.0), incident_from=("outside", "inside"),
                  theta_s_edges_deg=SMALL["theta_s_edges_deg"], phi_s_edges_deg=SMALL["phi_s_edges_deg"])
    out, ins = reconstruct(None, GLASS, req, "flat")
    for t in (out, ins):
        assert t.method == "flat" and not np.any(t.values_per_sr)
        n1, n2 = GLASS.n_pair(550.0, t.incident_from)
        ci = np.cos(np.radians(t.theta_i_deg))
        np.testing.assert_array_equal(t.specular_mueller_R[0, :, 0], mueller_interface(ci, n1, n2, "R"))
        np.testing.assert_array_equal(t.specular_mueller_T[0, :, 0], mueller_interface(ci, n1, n2, "T"))
    assert out.specular_R[0, 0, 0] == pytest.approx(0.04, rel=1e-12)                 # ((n - 1) / (n + 1))^2
    np.testing.assert_allclose(out.specular_R + out.specular_T, 1.0, rtol=1e-12)
    assert ins.specular_R[0, 3, 0] == pytest.approx(1.0) and ins.specular_T[0, 3, 0] == 0.0   # past 41.8 deg


# ------------------------------------------------------------------ auto: one short line, once


def test_auto_prints_its_reason_once_and_short(capsys):
    from _wave_reliefs import gaussian_relief
    rel = gaussian_relief(512, 0.1e-6, 5e-9, 1e-6, seed=1)
    (tab,) = reconstruct(rel, GLASS, Request(theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.linspace(0, 60, 31)),
                                             phi_s_edges_deg=tuple(np.arange(-5, 360, 10.0))), "auto")
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("auto: rayleigh-rice: ") and len(err[0]) < 200
    assert tab.metadata["auto_summary"] in err[0] and "Rayleigh parameter" in tab.metadata["auto_reason"]


def test_auto_quiet_prints_nothing(capsys):
    from _wave_reliefs import gaussian_relief
    rel = gaussian_relief(512, 0.1e-6, 5e-9, 1e-6, seed=1)
    reconstruct(rel, GLASS, Request(theta_i_deg=(0.0,), theta_s_edges_deg=tuple(np.linspace(0, 60, 31)),
                                    phi_s_edges_deg=tuple(np.arange(-5, 360, 10.0)), options={"quiet": True}), "auto")
    assert capsys.readouterr().err.strip() == ""


def test_request_error_is_an_input_error():
    assert issubclass(RequestError, InputError)        # the CLI's exit 2
