"""Concealed-case generator: files, secrecy of the effect, and the ray-traced relief's physics."""
import json
import tomllib

import numpy as np
import pytest

from relief_bsdf.validation.conceal import CaseSpec, HeightFieldFace, default_cases, make_case
from relief_bsdf.validation.photon import NormalsFace, PlatePhysics, detect, run_photons
from relief_bsdf.io.recording import read_recording, read_sample


def _tiny(effect, params, seed=11):
    return CaseSpec(name="t", effect=effect, parameters=params, seed=seed, relief_n=32, photons=20000,
                    theta_i_deg=(0.0, 40.0), theta_s_deg=tuple(float(x) for x in range(0, 90, 10)))


def test_flat_height_field_equals_fresnel_plate():
    hf = HeightFieldFace(np.zeros((8, 8)), 1e-6, 1e-6)
    ex = run_photons(hf, PlatePhysics(), 40.0, 0.0, (1, 0, 0, 0), 20000, np.random.default_rng(0))
    fl = run_photons(NormalsFace(np.array([[0, 0, 1.0]])), PlatePhysics(), 40.0, 0.0, (1, 0, 0, 0), 20000,
                     np.random.default_rng(0))
    R = np.mean(ex.d[:, 2] > 0) * len(ex.d) / 20000
    Rf = np.mean(fl.d[:, 2] > 0) * len(fl.d) / 20000
    assert R == pytest.approx(Rf, abs=0.006)
    assert ex.lost == 0


def test_height_field_conserves_energy_and_agrees_with_facet_normals_for_gentle_relief(gaussian_relief):
    h = gaussian_relief(48, 1e-6, 0.25e-6, 5e-6, 2).heights_m
    hf = HeightFieldFace(h, 1e-6, 1e-6)
    nf = NormalsFace.from_heights(h, 1e-6, 1e-6)
    th = np.arange(0.0, 40.0, 5.0)
    side = np.array(["T"] * th.size)
    a = run_photons(hf, PlatePhysics(), 20.0, 0.0, (1, 0, 0, 0), 60000, np.random.default_rng(1))
    b = run_photons(nf, PlatePhysics(), 20.0, 0.0, (1, 0, 0, 0), 60000, np.random.default_rng(2))
    assert (len(a.d) + a.lost) == 60000          # every photon is accounted for (no absorption)
    assert a.lost < 60
    va, sa = detect(a, side, th, np.full(th.size, 180.0), 3.0)
    vb, sb = detect(b, side, th, np.full(th.size, 180.0), 3.0)
    ok = va > 0.5
    z = (va[ok] - vb[ok]) / np.sqrt(sa[ok] ** 2 + sb[ok] ** 2)
    assert np.mean(z**2) < 4.0


def test_case_files_are_readable_and_do_not_reveal_the_effect(tmp_path):
    key = make_case(_tiny("bulk_absorption", {"absorption_per_mm": 0.3}), tmp_path / "a")
    key0 = make_case(_tiny("none", {}), tmp_path / "b")
    assert key["effect"] == "bulk_absorption" and key0["effect"] == "none"
    for d in ("a", "b"):
        s = read_sample(tmp_path / d / "sample.toml")
        rec = read_recording(s.recording_path)
        assert np.all(np.isfinite(rec.sigma_sr)) and np.all(rec.sigma_sr > 0)
        assert s.plate.absorption_per_mm is None
        assert not (tmp_path / d / "key.json").exists()
    ta = tomllib.loads((tmp_path / "a" / "sample.toml").read_text())
    tb = tomllib.loads((tmp_path / "b" / "sample.toml").read_text())
    assert ta == tb                                 # identical descriptions, whatever is concealed
    ra = read_recording(tmp_path / "a" / "recording.csv")
    rb = read_recording(tmp_path / "b" / "recording.csv")
    T = (ra.side == "T") & (ra.theta_i_deg == 0.0) & (ra.theta_s_deg == 0.0)
    # absorption shows up in the data as a loss of about exp(-a t)
    assert ra.bsdf_sr[T].mean() / rb.bsdf_sr[T].mean() == pytest.approx(np.exp(-0.6), rel=0.15)


def test_noise_is_consistent_with_sigma(tmp_path, gaussian_relief):
    """Recorded values scatter about an independent high-photon truth as their sigma says."""
    from dataclasses import replace

    from relief_bsdf.validation.conceal import _true_signal
    spec = _tiny("none", {}, seed=5)
    make_case(spec, tmp_path / "x")
    rec = read_recording(tmp_path / "x" / "recording.csv")
    heights = gaussian_relief(spec.relief_n, spec.pitch_um * 1e-6, spec.rms_um * 1e-6, spec.corr_um * 1e-6,
                              spec.seed).heights_m
    truth, tsig = _true_signal(replace(spec, seed=999, photons=80000), heights, rec)
    z = (rec.bsdf_sr - truth) / np.sqrt(rec.sigma_sr**2 + tsig**2)
    assert 0.6 < np.mean(z**2) < 1.6
    assert rec.sigma_sr.min() >= spec.floor_sr


def test_default_cases_cover_every_effect_twice_and_none_thrice():
    cases = default_cases()
    names = [c.effect for c in cases]
    assert len(cases) >= 24
    for e in set(names) - {"none"}:
        assert names.count(e) >= 2
    assert names.count("none") >= 3
    assert len({c.seed for c in cases}) == len(cases)
    assert all(len(c.wavelengths_nm) > 1 for c in cases if c.effect == "dispersion")
    json.dumps([c.parameters for c in cases])


@pytest.mark.slow
@pytest.mark.parametrize("theta_i,pol,q", [(30.0, "unpolarized", 0.0), (55.0, "s", 1.0), (55.0, "p", -1.0)])
def test_generator_agrees_with_the_independent_plate_mc(theta_i, pol, q, gaussian_relief):
    """Cross-check against relief_bsdf.plate.photon (another team's code: ReliefTracer, own Stokes frames,
    flat-face and detection code): the concealed-data physics must match it to the Monte-Carlo noise."""
    from types import SimpleNamespace

    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, simulate
    from relief_bsdf.surface.relief import Relief
    h = gaussian_relief(48, 1e-6, 0.3e-6, 5e-6, 4).heights_m
    th = np.arange(0.0, 90.0, 5.0)
    side = np.array(["R"] * 36 + ["T"] * 36)
    ts = np.concatenate([th] * 4)
    ps = np.concatenate([np.zeros(18), np.full(18, 180.0)] * 2)
    n = ts.size
    rows = SimpleNamespace(wavelength_nm=np.full(n, 550.0), theta_i_deg=np.full(n, theta_i), phi_i_deg=np.zeros(n),
                           side=side, theta_s_deg=ts, phi_s_deg=ps)
    face = ReliefFace(Relief(h, 1e-6, 1e-6, periodic=True), method="ray")
    exp = Experiment(Plate(2e-3, ConstantIndex(1.5), front=face, back=FlatFace()),
                     Instrument(detector_half_angle_deg=3.0, polarization_q=q))
    sim = simulate(exp, rows, engine="photon", photons=80000, seed=3)
    v1, e1 = sim.values_per_sr, sim.sigma_per_sr
    ex = run_photons(HeightFieldFace(h, 1e-6, 1e-6), PlatePhysics(), theta_i, 0.0, (1, q, 0, 0), 80000,
                     np.random.default_rng(5))
    v2, e2 = detect(ex, side, ts, ps, 3.0)
    ok = (e1 > 0) & (e2 > 0)
    assert ok.sum() >= 15
    z = (v1 - v2)[ok] / np.sqrt(e1**2 + e2**2)[ok]
    assert np.mean(z**2) < 2.5


def test_wave_case_key_and_secrecy(tmp_path):
    """A small diffraction case (phase-screen face): its key, identical sample.toml to a ray case's,
    and the coherent transmitted peak the wave physics puts in the specular row."""
    from dataclasses import replace

    from relief_bsdf.validation.conceal import WAVE_RELIEF
    spec = replace(_tiny("diffraction", {"coherent_scale": 1.0}), relief_n=64, pitch_um=WAVE_RELIEF["pitch_um"],
                   rms_um=0.14, corr_um=WAVE_RELIEF["corr_um"], photons=20000)
    key = make_case(spec, tmp_path / "w")
    key0 = make_case(replace(spec, effect="none", parameters={}), tmp_path / "r")
    assert key["effect"] == "diffraction" and key["parameters"] == {"coherent_scale": 1.0}
    assert not (tmp_path / "w" / "key.json").exists()
    tw = tomllib.loads((tmp_path / "w" / "sample.toml").read_text())
    tr = tomllib.loads((tmp_path / "r" / "sample.toml").read_text())
    assert tw == tr
    assert "diffraction" not in (tmp_path / "w" / "sample.toml").read_text()
    assert "diffraction" not in (tmp_path / "w" / "recording.csv").read_text()
    rw = read_recording(tmp_path / "w" / "recording.csv")
    rr = read_recording(tmp_path / "r" / "recording.csv")
    spec_row = (rw.side == "T") & (rw.theta_i_deg == 0.0) & (rw.theta_s_deg == 0.0)
    # ray optics spreads the transmitted lobe (~3 deg) beyond the 2.5 deg detector; the coherent
    # (Debye-Waller ~0.5) part of the wave case stays in it: the specular row is brighter
    assert rw.bsdf_sr[spec_row].mean() > 1.3 * rr.bsdf_sr[spec_row].mean()


def test_default_cases_include_the_wave_effects_on_a_thin_screen_relief():
    from relief_bsdf.validation.conceal import WAVE_RELIEF
    cases = [c for c in default_cases() if c.effect in ("diffraction", "partial_coherence")]
    assert sorted({c.effect for c in cases}) == ["diffraction", "partial_coherence"] and len(cases) == 4
    for c in cases:
        assert c.relief_n * c.pitch_um >= 100.0                     # tile >~ 100 um
        assert 2 * c.rms_um / c.corr_um < 0.2                       # small slopes
        k0s = 2 * np.pi / 0.55 * c.rms_um
        for t in c.theta_i_deg:
            ci = np.cos(np.radians(t))
            ct = np.sqrt(1 - (1 - ci**2) / 1.5**2)
            assert 0.15 < np.exp(-(k0s * (1.5 * ct - ci)) ** 2) < 0.7  # transmitted coherent fraction
            assert np.exp(-(2 * k0s * ci) ** 2) < 0.1                   # reflection mostly diffuse
        if c.effect == "partial_coherence":
            width_deg = np.degrees(0.55 / (2 * np.pi * c.parameters["coherence_length_um"]))
            assert width_deg > c.half_angle_deg
        else:
            assert c.parameters == {"coherent_scale": 1.0}
