"""Compound and non-Gaussian-relief concealed cases: what the generator hides and on what relief."""
import json

import numpy as np
import pytest

from relief_bsdf.validation.conceal import (COMPOUND_CASES, RELIEF_CASES, CaseSpec, _rows, _true_signal, case_relief,
                                            default_cases, generate, measured_tile)


def _tiny(effects, params, seed=11, **kw):
    return CaseSpec(name="t", effects=effects, parameters=params, seed=seed, relief_n=32, photons=20000,
                    theta_i_deg=(0.0, 40.0), theta_s_deg=tuple(float(x) for x in range(0, 90, 10)), **kw)


def test_a_compound_case_carries_both_effects_in_one_photon_run():
    """Same photons (same seed): absorption + background = the absorption-only signal plus the background,
    and the absorption lowers the transmitted lobe by about exp(-a t) at normal incidence."""
    a, b = 0.3, 0.04
    both = _tiny(("bulk_absorption", "stray_light"), {"absorption_per_mm": a, "background_per_sr": b})
    only = _tiny(("bulk_absorption",), {"absorption_per_mm": a})
    clean = _tiny(("none",), {})
    rec = _rows(both)
    h = case_relief(both)
    v2, _ = _true_signal(both, h, rec)
    v1, _ = _true_signal(only, h, rec)
    v0, _ = _true_signal(clean, h, rec)
    assert np.allclose(v2, v1 + b)
    T = (rec.side == "T") & (rec.theta_i_deg == 0.0) & (rec.theta_s_deg == 0.0)
    assert v1[T].mean() / v0[T].mean() == pytest.approx(np.exp(-a * both.thickness_mm), rel=0.1)


def test_the_key_lists_every_effect_and_stays_readable_as_one_effect(tmp_path):
    spec = _tiny(("sample_tilt", "instrument_blur"), {"tilt_deg": 2.0, "blur_deg": 2.5})
    spec.name = "c1"
    generate(tmp_path, [spec])
    key = json.loads((tmp_path / "key.json").read_text())["cases"][0]
    assert key["effects"] == ["sample_tilt", "instrument_blur"] and key["effect"] == "sample_tilt"
    assert key["relief"] == "gaussian"
    assert CaseSpec(name="x", effect="stray_light", parameters={}, seed=1).effects == ("stray_light",)
    with pytest.raises(ValueError):
        CaseSpec(name="x", effects=("none", "stray_light"))
    with pytest.raises(ValueError):
        CaseSpec(name="x", effect="stray_light", effects=("sample_tilt", "instrument_blur"))


def test_default_cases_hold_the_compound_pairs_and_the_relief_kinds():
    cases = default_cases(1, 1, seed=2)
    pairs = {c.effects for c in cases if len(c.effects) == 2}
    assert set(COMPOUND_CASES) <= pairs
    kinds = {(c.relief, c.effect) for c in cases if c.relief != "gaussian"}
    assert kinds == set(RELIEF_CASES)
    for pair in COMPOUND_CASES:                       # the two effects' parameters are both drawn
        c = next(c for c in cases if c.effects == pair)
        assert len(c.parameters) >= 2
    # adding compound and relief cases leaves the single-effect cases of a seed as they were
    old = default_cases(1, 1, seed=2, n_compound=0, relief_cases=False)
    assert [(c.effects, c.parameters) for c in old] == [(c.effects, c.parameters) for c in cases[:len(old)]]


def test_measured_tile_is_a_periodic_mirror_of_the_real_map():
    r = measured_tile(crop_n=48)
    h = r.heights_m
    assert r.periodic and h.shape == (96, 96)
    assert np.allclose(h[:, :48], h[:, 48:][:, ::-1]) and np.allclose(h[:48], h[48:][::-1])
    # the wrap adds no step: the jump across the tile edge is no larger than the map's own largest one
    inner = np.abs(np.diff(h, axis=1)).max()
    assert np.abs(h[:, 0] - h[:, -1]).max() <= inner
    assert r.dx_m != r.dy_m                           # the instrument's own anisotropic pitch is kept


@pytest.mark.parametrize("kind", ["exponential", "anisotropic", "dots"])
def test_non_gaussian_reliefs_are_periodic_tiles_of_their_kind(kind):
    spec = CaseSpec(name="k", effect="none", seed=3, relief=kind)
    r = case_relief(spec)
    assert r.periodic and r.heights_m.shape == (spec.relief_n, spec.relief_n)
    assert np.all(np.isfinite(r.heights_m)) and np.std(r.heights_m) > 0
    if kind == "dots":                                # flat land between the dots
        land = np.median(r.heights_m)
        assert np.mean(np.abs(r.heights_m - land) < 1e-9) > 0.3
