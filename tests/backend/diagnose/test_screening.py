"""The screens evaluate without the inside sector tables and on the intensity-only loop
(`DiagnosisForward.screening`).

A screen needs the change of the model toward a candidate's probes.  On a relief that scatters the
light inside the plate by azimuth, the sector tables (`plate.faces.inside_sectors`) make most of an
evaluation's cost; the screening forward leaves them out for the probes AND the current model, so it
finds the same gain (here within 10 %, measured 1-3 % on the seed-10 reliefs); what is
fitted and named keeps them.  The loop carries intensities only on the screening forward (the tables'
M00, `TableGrid.stokes_loop` False), except for a candidate that acts through the polarisation.
"""
import pickle
import re

from dataclasses import replace

import numpy as np
import pytest

from relief_bsdf.diagnose.effects import get_effect
from relief_bsdf.diagnose.stepwise import Step, _probes, line_gain
from relief_bsdf.plate import current_memory
from relief_bsdf.surface.synth import RandomFieldSpec, random_relief, relief_from_spec


def _anisotropic():
    return relief_from_spec(RandomFieldSpec(64, 64, 1e-6, 0.5e-6, 4e-6, anisotropy=2.5, angle_deg=0.0), 33)


def _recorded(fwd, truth: np.ndarray, seed: int) -> Step:
    """The forward's rows recorded as `truth` with 2 % noise (seeded); the baseline's step against them."""
    rng = np.random.default_rng(seed)
    fwd.rows.sigma_sr = 0.02 * np.abs(truth) + 1e-4
    fwd.rows.bsdf_sr = truth + fwd.rows.sigma_sr * rng.standard_normal(truth.size)
    fwd._memo.clear()
    v0, s0 = fwd.baseline()
    return Step((), {}, fwd.misfit(v0, s0), 0, (v0, s0))


def _sector_keys(keys) -> list:
    from relief_bsdf.plate.faces import SECTORS_KEY
    return [k for k in keys if SECTORS_KEY in k]


def test_the_screening_forward_leaves_out_only_the_sector_tables_and_the_stokes_loop(plate_forward):
    iso = plate_forward(random_relief(48, 1.0e-6, 0.4e-6, 5.0e-6, "gaussian", seed=2), method="ray", samples=4_000)
    assert iso.screening(get_effect("polarization")) is iso     # nothing to leave out for a Stokes effect
    flat = iso.screening(get_effect("relief_scale"))
    assert flat is not iso and not flat.grid.stokes_loop
    assert replace(flat.grid, stokes_loop=True) == iso.grid
    fwd = plate_forward(_anisotropic(), method="ray", samples=4_000)
    fwd.baseline()
    assert _sector_keys(fwd._baseline_keys)
    screen = fwd.screening()
    assert screen is not fwd and fwd.screening() is screen       # made once per process
    assert screen.grid.sector_azimuths_deg() == () and screen.grid.key() == fwd.grid.key()
    stokes = fwd.screening(get_effect("polarization"))
    assert stokes.grid.stokes_loop and stokes.grid.sector_azimuths_deg() == () and stokes is not screen
    with current_memory().recording() as used:
        screen.evaluate(get_effect("relief_scale"), {"height_scale": 1.2})
    assert used and not _sector_keys(used)
    assert screen.model_rel_sigma() is fwd.model_rel_sigma()     # shared, not derived again
    assert not [k for k in pickle.loads(pickle.dumps(fwd)).__dict__ if k.startswith("_screen")]   # a worker's own


def test_an_intensity_only_screen_finds_the_stokes_loops_gain_and_a_polarised_source_keeps_the_stokes_loop(
        plate_forward):
    """The recording: the full forward's rows with the heights 15 % higher and a Beckmann back face of
    alpha 0.1 (2 % noise, seed 7); each candidate's screen gain on the intensity-only loop against the
    Stokes loop (within 10 %); the source's polarisation is screened on the Stokes loop (the intensity-only
    loop cannot carry it: the plate model refuses it)."""
    from relief_bsdf.errors import InputError
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate
    from relief_bsdf.plate.setup import EngineSetup
    from relief_bsdf.core.index import ConstantIndex
    fwd = plate_forward(random_relief(48, 1.0e-6, 0.4e-6, 5.0e-6, "gaussian", seed=2), method="ray", samples=4_000)
    effs = (get_effect("relief_scale"), get_effect("back_face_roughness"))
    _, truth, _ = fwd.evaluate_set(effs, {"height_scale": 1.15, "back_alpha": 0.1})
    cur = _recorded(fwd, truth, 7)
    for e in effs + (get_effect("bulk_absorption"),):
        flat = line_gain(fwd, cur, e, _probes(e, None))
        fwd.__dict__["_screen"] = fwd                             # this candidate's screen on the Stokes loop
        full = line_gain(fwd, cur, e, _probes(e, None))
        del fwd.__dict__["_screen"]
        print(f"{e.name}: chi2 {cur.chi2:.1f}, screen gain {flat:.2f} intensity only, {full:.2f} Stokes loop")
        assert full > 1.0 and abs(flat / full - 1.0) < 0.1, (e.name, flat, full, cur.chi2)
    assert fwd.screening(get_effect("polarization")) is fwd
    with pytest.raises(InputError, match="stokes_loop"):
        EngineSetup(Experiment(Plate(1e-3, ConstantIndex(1.5), FlatFace(), FlatFace()), Instrument(polarization_q=1.0)),
                    stokes_loop=False)


def test_a_screen_without_the_sector_tables_finds_the_gain_with_them(plate_forward):
    """The recording: the full forward's rows with the heights 15 % higher (2 % noise, seed 5); the
    screen's gain toward relief_scale with and without the sectors (and on the intensity-only loop)."""
    fwd = plate_forward(_anisotropic(), method="ray", samples=4_000)
    _, truth, _ = fwd.evaluate(get_effect("relief_scale"), {"height_scale": 1.15})
    cur = _recorded(fwd, truth, 5)
    scale = get_effect("relief_scale")
    screened = line_gain(fwd, cur, scale, _probes(scale, None))
    assert fwd.screening() is not fwd
    fwd.__dict__["_screen"] = fwd                                 # the screen on the full forward
    full = line_gain(fwd, cur, scale, _probes(scale, None))
    print(f"chi2 {cur.chi2:.1f}: screen gain {screened:.1f} without the sectors, {full:.1f} with them")
    assert full > 0.5 * cur.chi2 and abs(screened / full - 1.0) < 0.1, (screened, full, cur.chi2)


def test_the_isotropy_warning_comes_with_the_baseline_not_with_every_probe(plate_forward):
    """An anisotropic relief is said once, with the baseline; a probe's experiment (the same tile
    scaled: the same warning with other numbers) would repeat it for every probe and worker."""
    import warnings
    from relief_bsdf.plate.faces import ISOTROPY_WARNING
    fwd = plate_forward(_anisotropic(), method="ray", samples=4_000)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        fwd.baseline()
        said = [w for w in seen if re.match(ISOTROPY_WARNING, str(w.message))]
        fwd.evaluate(get_effect("relief_scale"), {"height_scale": 1.3})
        again = [w for w in seen if re.match(ISOTROPY_WARNING, str(w.message))]
    assert len(said) >= 1 and len(again) == len(said)


@pytest.mark.parametrize("effect, truth", [("bulk_absorption", {"absorption_per_mm": 0.2}),
                                           ("stray_light", {"background_per_sr": 0.02})])
def test_a_candidate_searched_on_the_screening_forward_ends_where_the_full_search_does(plate_forward, effect, truth,
                                                                                        monkeypatch):
    """`fitting._screened_fit`: the grid and Brent steps on the screening forward (intensity-only loop), then
    Gauss-Newton steps on the full one.  Oracle: the same fit with the search on the full forward model
    (`_screening` returning it): the same parameter within a tenth of its 68 % interval, the same chi^2
    within 0.5, and fewer full evaluations (the screening ones are counted apart, on the screening forward)."""
    from relief_bsdf.diagnose import fitting
    relief = random_relief(48, 1.0e-6, 0.4e-6, 5.0e-6, "gaussian", seed=2)
    fwd = plate_forward(relief, method="ray", samples=4_000)
    e = get_effect(effect)
    _recorded(fwd, fwd.evaluate(e, truth)[1], 5)
    full_before = fwd.evaluations - (fwd.screening(e).evaluations)
    quick = fitting.fit_effect(fwd, e)
    quick_full = fwd.evaluations - fwd.screening(e).evaluations - full_before
    assert fwd.screening(e) is not fwd and fwd.screening(e).evaluations > 0
    slow = plate_forward(relief, method="ray", samples=4_000)
    _recorded(slow, fwd.rows.bsdf_sr, 5)
    slow.rows.bsdf_sr, slow.rows.sigma_sr = fwd.rows.bsdf_sr, fwd.rows.sigma_sr
    monkeypatch.setattr(fitting, "_screening", lambda forward, effect: forward)
    start = slow.evaluations
    full = fitting.fit_effect(slow, e)
    full_evals = slow.evaluations - start
    (name,) = truth
    iv, _ = fitting.intervals(slow, (e,), full["parameters"])
    half = (iv[name][1] - iv[name][0]) / 2
    assert abs(quick["parameters"][name] - full["parameters"][name]) < 0.1 * half
    assert quick["chi2"] == pytest.approx(full["chi2"], abs=0.5)
    assert quick_full < full_evals
