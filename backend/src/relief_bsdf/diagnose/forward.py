"""The diagnosis's view of the one forward model: baseline Experiment, rows, misfit.

Baseline: the sample exactly as sample.toml states it (`plate.description.Experiment`):
the relief as measured (plane-levelled) on the front face with the boundary method of the
fit (`--method`, default the fit's), the stated index and thickness, the known absorption
(0 when not known), a flat back face, the stated source polarisation and detector cone, no
blur, tilt or background.  A candidate effect is a change of that Experiment
(`effect.apply`), and every evaluation is `PlateForward.run` of the one forward model
(`fit.forward.PlateForward`: the relief levelled and checked, the rows checked, "auto" decided
once, the deterministic engine on the grid, the simulation's own sigma), of which
`DiagnosisForward` is a thin subclass: the simulation, the fit and the diagnosis share the
physics, the detector and the blur.

Misfit: the censored (Tobit) chi^2 of `fit.residual.chi2`, with s^2 = sigma_recording^2 +
sigma_model^2.

Screens (`stepwise.line_gain`) evaluate on `DiagnosisForward.screening`: the same forward model
without the inside sector tables of a relief that scatters trapped light by azimuth
(`plate.faces.inside_sectors`; the grid's `sector_step_deg` NO_SECTORS_DEG), its loop
azimuth-circulant.  A screen needs the CHANGE of the model toward a candidate's probes, not the
model: both the probes and the current model are evaluated on that grid, so the sectors' correction,
a few per cent of the rows' values (up to a factor 2-3 in the few rows where trapped light leaves near
the normal, the dots at theta_i 60: the grid's doc), enters the screen only as a change of a change.
On a concealed case's measured map an evaluation of a relief operation costs 2.6 s instead of 13.5 s
(the sector tables' rays and the loop's sector operators; one process), and the
screens' gains there and on the dots agree within 1-3 % (the tilt's within 0.64-0.93, both far above
the bar).  The screening forward's loop also carries intensities only (`TableGrid.stokes_loop` False:
the polarised tables' M00, matrices 4x smaller a side; the model itself then misses the polarisation
of the second pass, R 4.7 % on a Gaussian plate, which cancels in the change), except for a candidate
that acts through the source's polarisation (`Effect.stokes`) or when the stated source is polarised: the Mueller loop's
operators and solves were most of a screen's plate time (a concealed tilt + blur case, py-spy:
the operators 65 s and the LU factorisations 17 s of 260 s of CPU); the gains agree within 0.1-8 %
(tests/backend/diagnose/test_screening.py).  What is named, fitted and reported is always evaluated
with the sectors and the Stokes loop.
"""
from __future__ import annotations

import contextlib
import copy
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from relief_bsdf.diagnose.effects import Effect, ReliefContext, apply_all, get_effect
from relief_bsdf.diagnose.profile import note_evaluations
from relief_bsdf.errors import InputError
from relief_bsdf.fit.forward import SIGMA_DRAWS, PlateForward
from relief_bsdf.fit.residual import chi2
from relief_bsdf.parallel.blas import blas_single_thread
from relief_bsdf.plate import DEFAULT_METHOD, Experiment, ReliefFace, TableGrid
from relief_bsdf.plate.grid import NO_SECTORS_DEG

__all__ = ["DEFAULT_METHOD", "DiagnosisForward", "build_forward", "face_options", "known_effects"]

MEMO_SIZE = 400        # evaluations kept (each holds two row-length arrays)


@dataclass
class DiagnosisForward(PlateForward):
    """The diagnosis's forward model: the one forward model of the sample's plate (fit.forward.PlateForward:
    relief, rows, physics, grid and the simulation's own sigma decided there) with candidate effects applied
    (`effects.apply_all`), and what a search over many candidates adds: a memo of evaluations, the
    screening forward (`screening`) and evaluations ahead on worker processes (`prefetch`).

    experiment: the baseline Experiment (fit.baseline); rows: a Recording with finite sigma
    (Recording.with_sigma_fallback); context: the relief context of the effects; grid: the plate's table
    grid (None: the plate's default); where: the rows' name in errors."""

    experiment: Experiment
    rows: object
    context: ReliefContext
    grid: TableGrid | None = None
    evaluations: int = 0
    where: str = "recording"
    _baseline: tuple | None = field(default=None, repr=False)
    _memo: dict = field(default_factory=dict, repr=False)
    _rel_sigma: np.ndarray | None = field(default=None, repr=False)
    _rel_dev: np.ndarray | None = field(default=None, repr=False)
    _baseline_keys: frozenset = field(default=frozenset(), repr=False)

    def __post_init__(self) -> None:
        # the one forward model's decisions (PlateForward); the model sigma a copy carries is kept
        rel_sigma, rel_dev = self._rel_sigma, self._rel_dev
        PlateForward.__init__(self, self.experiment, self.rows, self.grid, self.where, SIGMA_DRAWS)
        self._rel_sigma, self._rel_dev = rel_sigma, rel_dev

    def __getstate__(self) -> dict:
        """Pickled for worker processes (the candidate fits) with the baseline's boundary tables: a
        worker puts them in its own table cache (`__setstate__`) instead of deriving them again
        (seconds per worker and pool; the numbers are the same: the tables are data)."""
        from relief_bsdf.plate.memory import current_memory
        state = {k: v for k, v in self.__dict__.items() if not k.startswith("_screen")}   # made where used
        return {**state, "_baseline_tables": current_memory().tables(self._baseline_keys)}

    def __setstate__(self, state: dict) -> None:
        from relief_bsdf.plate.memory import current_memory
        for key, table in state.pop("_baseline_tables", {}).items():
            current_memory().put(key, table)
        self.__dict__.update(state)

    def twin(self) -> "DiagnosisForward":
        """A shallow copy with its own memo: it evaluates in this process while another thread pickles
        the original for worker processes (`stepwise._fits_beside_screens`)."""
        t = copy.copy(self)
        t._memo = dict(self._memo)
        return t

    def screening(self, effect: Effect | None = None) -> "DiagnosisForward":
        """The forward model the screens evaluate on (module doc): this one without inside sector tables
        when its baseline uses them, and with the intensity-only loop (`TableGrid.stokes_loop` False)
        unless `effect` acts through the polarisation (`Effect.stokes`) or the stated source is
        polarised; this one when neither applies.  Made once per process and kind, with its own memo
        and the model sigma of this one (a screen divides by the current step's sigma anyway)."""
        from relief_bsdf.plate.faces import SECTORS_KEY
        stokes = bool(effect is not None and effect.stokes) or float(self.experiment.instrument.polarization_q) != 0.0
        name = "_screen_stokes" if stokes else "_screen"
        screen = self.__dict__.get(name)
        if screen is None:
            self.baseline()
            own = grid = self.grid
            if any(SECTORS_KEY in key for key in self._baseline_keys):
                grid = replace(grid, sector_step_deg=NO_SECTORS_DEG)
            if not stokes:
                grid = replace(grid, stokes_loop=False)
            # the model sigma's arrays are shared (the baseline made them): nothing is derived again
            screen = self if grid == own else replace(
                self, grid=grid, evaluations=0, _baseline=None, _memo={}, _baseline_keys=frozenset())
            self.__dict__[name] = screen
        return screen

    def simulate(self, experiment: Experiment) -> tuple[np.ndarray, np.ndarray]:
        """(values, model sigma): the sigma is the baseline's relative 1-sigma (its tables' Monte-Carlo
        noise and tile realisation through the plate, plate.uncertainty, computed once) times the values."""
        from relief_bsdf.methods.realisation import tile_warnings_quiet
        from relief_bsdf.plate.faces import ISOTROPY_WARNING
        self.evaluations += 1
        note_evaluations(self.grid)         # the diagnosis's profile (diagnose.profile), per stage
        # the baseline warns about the tile and an anisotropic relief; an effect's experiment (the same tile
        # scaled, filtered, at another index) would repeat it, with other numbers, once per probe and worker
        with contextlib.ExitStack() as quiet:
            if experiment is not self.experiment:
                quiet.enter_context(tile_warnings_quiet())
                quiet.enter_context(warnings.catch_warnings())
                warnings.filterwarnings("ignore", message=ISOTROPY_WARNING, category=RuntimeWarning)
            sim = self.run(experiment)
        return sim.values_per_sr, self.model_rel_sigma() * np.abs(sim.values_per_sr)

    def model_deviations_at(self, effects, values: dict) -> np.ndarray:
        """The simulation's table draws at `values` of `effects` as deviations per row (INTERVAL_DRAWS x rows,
        PlateForward.deviations): the intervals' shared model noise, made where they are asked."""
        _, vals = _memo_key(effects, values)
        return self.deviations(apply_all(self.experiment, self.context, effects, vals))

    def baseline(self) -> tuple[np.ndarray, np.ndarray]:
        """(values, model sigma) of the sample as stated (computed once)."""
        if self._baseline is None:
            from relief_bsdf.plate.memory import current_memory
            with current_memory().recording() as used:
                self._baseline = self.simulate(self.experiment)
            self._baseline_keys = frozenset(used)
        return self._baseline

    def with_effect(self, effect: Effect, values: dict) -> Experiment:
        return effect.apply(self.experiment, self.context, values)

    def evaluate(self, effect: Effect, values: dict) -> tuple[float, np.ndarray, np.ndarray]:
        """(chi^2, values, model sigma) with `effect` at `values`; the neutral values are the baseline."""
        return self.evaluate_set((effect,), values)

    def evaluate_set(self, effects, values: dict) -> tuple[float, np.ndarray, np.ndarray]:
        """(chi^2, values, model sigma) with every effect of `effects` acting together at `values`
        (`effects.apply_all`); all at their neutral values is the baseline.  Memoised on the effect
        names and parameter values (a joint refit and the intervals revisit the points of the
        single fits)."""
        key, vals = _memo_key(effects, values)
        if key is None:
            v, s = self.baseline()
            return self.misfit(v, s), v, s
        if key not in self._memo:            # the simulation is memoised, the misfit computed against the rows now
            self._remember(key, self.simulate(apply_all(self.experiment, self.context, effects, vals)))
        v, s = self._memo[key]
        return self.misfit(v, s), v, s

    def _remember(self, key: tuple, result: tuple) -> None:
        self._memo[key] = result
        if len(self._memo) > MEMO_SIZE:
            self._memo.pop(next(iter(self._memo)))

    def prefetch(self, effects, points: list[dict], workers: int | None = None) -> None:
        """Evaluate those of `points` (values of `effects`) not yet memoised at once on the worker
        processes this forward model keeps (`parallel.kept_workers`, the stepwise diagnosis's pool),
        into the memo, so that the calls of `evaluate_set` that follow find them.  A search's grid, a
        Jacobian's differences are independent points: two workers evaluate them in about half the
        time.  Without kept workers (or fewer than two missing points) it does nothing: each point is
        then evaluated when asked, with the same result (the simulation is a function of its inputs).

        Points that share their boundary tables (they differ only in parameters of `cheap` effects:
        `_tables_of`) are one group.  When the points fall in several groups and one holds two or more,
        this process evaluates that group beside the workers (its tables derived once, then plate
        solves only) while the workers take the rest (two or more): a Jacobian of a relief scale and an
        absorption at a new scale is the scale's two differences (new tables each) and the absorption's
        two (the centre's tables); on two workers the absorption's two waited for the scale's and each
        derived the centre's tables again."""
        from relief_bsdf.parallel import has_kept_workers, map_tasks
        todo: dict = {}
        for values in points:
            key, vals = _memo_key(effects, values)
            if key is not None and key not in self._memo:
                todo.setdefault(key, vals)
        if len(todo) < 2 or not has_kept_workers(self, workers):
            return
        names = tuple(e.name for e in effects)
        groups: dict = {}
        for key, vals in todo.items():
            groups.setdefault(_tables_of(effects, vals), []).append(key)
        mine = max(groups.values(), key=len) if len(groups) > 1 else []
        if len(mine) < 2 or len(todo) - len(mine) < 2:     # (a single task would run in this process)
            mine = []
        here = set(mine)
        there = [k for k in todo if k not in here]
        if not mine:
            got = map_tasks(_evaluate_task, [(names, todo[k]) for k in there], self, label="evaluations",
                            workers=workers)
        else:
            import contextvars
            from concurrent.futures import ThreadPoolExecutor
            twin = self.twin()          # evaluates here while the worker call runs in a thread
            with ThreadPoolExecutor(1) as pool:
                on_workers = pool.submit(contextvars.copy_context().run, map_tasks, _evaluate_task,
                                         [(names, todo[k]) for k in there], self, label="evaluations", workers=workers)
                with blas_single_thread():       # beside the workers: one BLAS thread (parallel.blas)
                    for k in mine:
                        twin.evaluate_set(effects, todo[k])
                got = on_workers.result()
            for k in mine:
                self._remember(k, twin._memo[k])
            self.evaluations += len(mine)
        self.evaluations += len(there)
        note_evaluations(self.grid, len(there))     # evaluated on the workers: counted here
        for key, result in zip(there, got):
            self._remember(key, result)

    def misfit(self, values: np.ndarray, model_sigma: np.ndarray) -> float:
        return chi2(self.rows, values, model_sigma)


def _memo_key(effects, values: dict) -> tuple[tuple | None, dict]:
    """(memo key, full values) of `effects` at `values` (a missing parameter at its neutral value);
    the key is None when every effect is at its neutral values (the baseline)."""
    vals = {p.name: float(values.get(p.name, p.neutral)) for e in effects for p in e.params}
    if all(vals[p.name] == p.neutral for e in effects for p in e.params) and all(e.params for e in effects):
        return None, vals
    names = tuple(sorted(e.name for e in effects))
    return (names, tuple(sorted((k, round(x, 12)) for k, x in vals.items()))), vals


def _tables_of(effects, vals: dict) -> tuple:
    """What decides a point's boundary tables: the values of the parameters of the effects that are not
    `cheap` (a relief scale, a tilt traced into the tables); points equal in them share their tables."""
    return tuple((p.name, round(float(vals[p.name]), 12)) for e in effects if not e.cheap for p in e.params)


def _evaluate_task(forward: DiagnosisForward, task: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(values, model sigma) of the named effects at `vals`, on a worker (`DiagnosisForward.prefetch`)."""
    names, vals = task
    _, v, s = forward.evaluate_set(tuple(get_effect(n) for n in names), vals)
    return v, s


@dataclass(frozen=True)
class _FaceBuilder:
    """face(relief, method, **options) -> the plate's ReliefFace (picklable, for worker processes).

    Tables carry Mueller matrices wherever the method can fill them (option `polarized`): a
    source polarisation, Fresnel at the flat back face and the relief's own polarisation then
    all reach the rows (a depolarising table would hide the `polarization` effect).
    """

    samples: int
    seed: int

    def __call__(self, relief, method: str, coherence_length_m: float | None = None, **options):
        return ReliefFace(relief, method, self.samples, self.seed, options={**face_options(method), **options},
                          coherence_length_m=coherence_length_m)


def face_options(method: str) -> dict:
    """The relief face's method options in the diagnosis: Mueller matrices wherever the method fills them."""
    from relief_bsdf.errors import RequestError
    from relief_bsdf.methods import entry
    try:
        entry(method).parse_options({"polarized": True})
    except RequestError:         # a scalar method (or no such option): its tables depolarise
        return {}
    return {"polarized": True}


def known_effects(sample) -> tuple:
    """((effect, reason), ...) for the effects whose value sample.toml states: held fixed, not candidates."""
    known = []
    a = sample.plate.absorption_per_mm
    if a is not None:
        known.append(("bulk_absorption", f"held fixed: sample.toml states plate.absorption_per_mm = {a:g} "
                                         f"(what the user knows is not a candidate)"))
    return tuple(known)


def _scale_and_filter():
    from relief_bsdf.surface.operations import scale_and_filter
    return scale_and_filter


def build_forward(sample_path: str | Path, method: str = DEFAULT_METHOD, samples: int = 200_000,
                  seed: int = 0, sectors: str = "auto") -> tuple[DiagnosisForward, object]:
    """The baseline forward model of a sample.toml (and the Sample), on the default grid with
    TableGrid.sectors = `sectors`: the sample's plate as `fit.baseline` prepares it for every forward
    model (relief levelled and checked, rows checked, "auto" decided once), with Mueller tables
    wherever the method fills them (`face_options`)."""
    from relief_bsdf.fit.baseline import baseline
    from relief_bsdf.io.recording import read_sample
    sample = read_sample(sample_path)
    if sample.plate.rough_face != "front":
        raise InputError(sample.path, "key plate.rough_face: diagnose models a relief on the lit (front) face only")
    grid = TableGrid(sectors=sectors)                   # the plate's default grid, but for `sectors`
    b = baseline(sample, method=method, samples=samples, seed=seed, grid=grid, face_options=face_options(method))
    if len(b.recording) < 4:
        raise InputError(sample.recording_path, f"only {len(b.recording)} rows; a diagnosis needs a scan")
    rows = b.recording.with_sigma_fallback()   # unknown sigma: documented fallback (recording.py)
    front = b.experiment.plate.front
    context = ReliefContext(relief=b.relief, method=front.method, face=_FaceBuilder(samples, seed),
                            scale_and_filter=_scale_and_filter(),
                            wavelengths_nm=tuple(float(w) for w in np.unique(rows.wavelength_nm)),
                            detector_half_angle_deg=float(sample.instrument.detector_half_angle_deg),
                            samples=samples, seed=seed, method_reason=front.chosen_by, known=known_effects(sample))
    return DiagnosisForward(b.experiment, rows, context, grid=grid, where=b.where), sample
