"""The one forward model (fit.forward): fit and diagnosis decide the plate in one place; the fit's
search model steers, the model of record answers."""
from dataclasses import replace

import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.errors import InputError
from relief_bsdf.fit.forward import SEARCH_SAMPLES_FRACTION, Forward, PlateForward
from relief_bsdf.fit.optimise import FitSettings, fit_relief, process_relief, relief_rms
from relief_bsdf.plate import Experiment, FlatFace, Plate, ReliefFace, TableGrid, in_plane_rows
from relief_bsdf.surface.synth import random_relief


def _experiment(relief, method="auto", polarization_q=0.0):
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, method, samples=40_000, seed=3), FlatFace()))
    return replace(ex, instrument=replace(ex.instrument, polarization_q=polarization_q))


def _context(relief):
    from relief_bsdf.diagnose.effects import ReliefContext
    from relief_bsdf.surface.operations import scale_and_filter
    return ReliefContext(relief=relief, method="auto", face=None, scale_and_filter=scale_and_filter,
                         wavelengths_nm=(550.0,), detector_half_angle_deg=1.0, samples=40_000, seed=3)


def test_fit_and_diagnosis_decide_rows_and_auto_in_one_place():
    """Both forward models are the one PlateForward: "auto" resolved once on the relief as read (the same
    choice for both), the grid defaulted alike, and rows the plate cannot answer refused by both, naming
    where they came from."""
    from relief_bsdf.diagnose.forward import DiagnosisForward
    relief = random_relief(64, 0.25e-6, 0.3e-6, 2.0e-6, "gaussian", seed=1)
    rows = in_plane_rows(550.0, [0, 30], np.arange(1.0, 89.0, 8.0))
    fit = Forward(relief, _experiment(relief), rows, where="rec.csv")
    diag = DiagnosisForward(_experiment(relief), rows, _context(relief), where="rec.csv")
    assert isinstance(fit, PlateForward) and isinstance(diag, PlateForward)
    assert fit.method == diag.method != "auto" and fit.face.chosen_by == diag.face.chosen_by
    assert fit.grid == diag.grid == TableGrid()
    bad = in_plane_rows(550.0, [0, 95.0], np.arange(1.0, 89.0, 8.0))
    for make in (lambda: Forward(relief, _experiment(relief), bad, where="rec.csv"),
                 lambda: DiagnosisForward(_experiment(relief), bad, _context(relief), where="rec.csv")):
        with pytest.raises(InputError, match="rec.csv"):
            make()


def test_search_model_takes_a_share_of_the_rays_the_intensity_loop_and_the_record_sigma():
    relief = random_relief(64, 0.25e-6, 0.3e-6, 2.0e-6, "gaussian", seed=1)
    rows = in_plane_rows(550.0, [0, 30], np.arange(1.0, 89.0, 8.0))
    fwd = Forward(relief, _experiment(relief, "ray"), rows)
    search = fwd.search_model()
    assert search.face.samples == round(40_000 * SEARCH_SAMPLES_FRACTION) and search.face.seed == 3
    assert not search.grid.stokes_loop and fwd.grid.stokes_loop
    assert replace(search.grid, stokes_loop=True) == fwd.grid
    fwd._rel_sigma = np.full(len(rows), 0.01)               # the record's sigma, as if computed
    assert search.model_rel_sigma() is fwd.model_rel_sigma()
    # a polarised source keeps the Stokes loop (the polarisation is what it carries); a face that does not
    # sample (an analytic surrogate) keeps its tables: nothing to make cheaper, the model of record itself
    pol = Forward(relief, _experiment(relief, "ray", polarization_q=1.0), rows).search_model()
    assert pol.grid.stokes_loop and pol.face.samples == round(40_000 * SEARCH_SAMPLES_FRACTION)
    same = Forward(relief, _experiment(relief, "microfacet+dw", polarization_q=1.0), rows)
    assert same.search_model() is same


class _Lobe:
    """A stand-in forward model (milliseconds): a lobe whose width follows the processed relief's rms
    slope and a specular peak whose weight follows its rms height; `search_model()` the same lobe
    through a model that misses it by a tilt of 4 % across the angles and by ripples of 0.5 % (a quarter
    of the recording's noise) that move smoothly with the parameters (the search model's extra table
    noise under common random numbers)."""

    def __init__(self, log=None, biased=False):
        self.relief = random_relief(32, 0.125e-6, 30e-9, 0.5e-6, "gaussian", seed=0)
        self.x = np.linspace(-30, 30, 61)
        self.log = [] if log is None else log
        self.biased = biased

    def simulate(self, s, g):
        self.log.append((self.biased, s, g))
        sigma, slope = relief_rms(process_relief(self.relief, s, g))
        w = np.degrees(slope) + 0.1
        spec = np.exp(-(sigma / 30e-9) ** 2)
        v = (1 - spec) * np.exp(-0.5 * (self.x / w) ** 2) / w + spec * np.exp(-0.5 * (self.x / 1.0) ** 2) + 1e-3
        if self.biased:
            v = v * (1 + 0.04 * self.x / 30) * (1 + 0.005 * np.sin(0.7 * self.x + 25 * s + 5 * g))
        return v

    def search_model(self):
        return _Lobe(self.log, biased=True)


def test_fit_steers_on_the_search_model_and_answers_on_the_record(tmp_path):
    """The search runs on the biased search model; the criterion's points, the polish, the response
    surface, the answer and its intervals on the model of record: the answer is the record-only fit's
    within a fifth of its half-width, and an interrupted fit resumes to the same answer."""
    truth = _Lobe().simulate(1.3, 0.3)          # a filter of 2.4 pitches: within the ridge scan's reach
    sigma = 0.02 * truth
    meas = truth + sigma * np.random.default_rng(3).standard_normal(truth.size)

    class _RecordOnly(_Lobe):
        search_model = None
    alone = fit_relief(_RecordOnly(), meas, sigma, FitSettings(max_iter=40))
    log = []
    res = fit_relief(_Lobe(log), meas, sigma, FitSettings(max_iter=40))
    models = [it["model"] for it in res.iterations]
    assert models[0] == "record" and "search" in models and set(models) == {"record", "search"}
    assert res.computed_by_model["search"] == models.count("search") == sum(b for b, *_ in log)
    assert res.computed_by_model["record"] == models.count("record") == res.computed - models.count("search")
    assert list(res.stage_seconds) == ["baseline and the model sigma", "search", "criterion", "polish",
                                       "response surface", "intervals", "ridge probe"]
    # everything after the search is the model of record's: the criterion's points, the polish, the design,
    # the answer, the ridge probe
    last_search = max(k for k, m in enumerate(models) if m == "search")
    assert models[last_search + 1:] == ["record"] * (len(models) - last_search - 1)
    assert len(models) - last_search - 1 >= res.surface["design_points"] + 2
    for name in ("height_scale", "filter_sigma_um"):
        lo, hi = alone.intervals[name]
        assert abs(getattr(res, name) - getattr(alone, name)) <= 0.2 * (hi - lo) / 2, name
    ck = tmp_path / "checkpoint.json"

    def interrupt(n):
        if n == 15:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        fit_relief(_Lobe(), meas, sigma, FitSettings(max_iter=40), checkpoint=ck, on_eval=interrupt)
    again = []
    resumed = fit_relief(_Lobe(again), meas, sigma, FitSettings(max_iter=40), checkpoint=ck)
    assert (resumed.height_scale, resumed.filter_sigma_um, resumed.rms_after) == \
        (res.height_scale, res.filter_sigma_um, res.rms_after)
    assert len(again) == len(log) - 15


def test_the_ridge_scan_stops_past_its_valley():
    from relief_bsdf.fit.optimise import _past_the_valley

    class _O:
        model = "search"
        iterations = []

    o = _O()
    for g, v in ((0.0, 5.0), (0.5, 2.0), (1.0, 2.5)):
        o.iterations.append({"parameters": {"filter_sigma_um": g}, "search": v, "model": "search"})
    assert not _past_the_valley(o)                     # one rise: the valley may still be ahead
    o.iterations.append({"parameters": {"filter_sigma_um": 2.0}, "search": 4.0, "model": "search"})
    assert _past_the_valley(o)
    o.iterations.append({"parameters": {"filter_sigma_um": 4.0}, "search": 1.0, "model": "record"})
    assert _past_the_valley(o)                         # another model's evaluations are not the scan's
