"""Stepwise selection of every effect present: add the one that gains most, refit all jointly, repeat.

The one information criterion of the project (`criteria`): BIC = chi^2 + k ln n
(Schwarz 1978) over the n recording rows, chi^2 the censored misfit with
s^2 = sigma_recording^2 + sigma_model^2 (`forward.DiagnosisForward.misfit`), k the number of
fitted parameters of the named effects.

Step (current set S, chi^2_S, k_S; S = {} is the baseline):
1. every candidate c not in S that can act together with S (`effects.compatible`) and is not
   held fixed by sample.toml is fitted with S held at its values (`fitting.fit_effect`, the
   conditional fit; at the first step this is the single-effect fit of each candidate) unless
   its screen shows that it can neither pass nor win.
   Screen: every candidate with parameters is first screened by TWO evaluations (`_probes`: its
   value from the first step's fit when it had one, else 10 % into its range; and 10 % to the
   other side of its neutral value, or 30 % into the range when the neutral value is a bound).
   With r the current normalised residual and D the probes' changes of the model in the same
   units, the chi^2 gain of the best linear combination, r.D (D^T D)^+ D^T.r (a linear
   least-squares search in the probes' span: Rao's score test, with the second probe catching
   a change of shape with the amplitude; the changes evaluated without the inside sector tables
   and on the intensity-only loop, `forward.DiagnosisForward.screening`), must pass the same bar
   as a fit (`passes`, with chi^2_S minus that gain as the larger model's chi^2), else the
   candidate is listed as screened out and not fitted.  For an effect linear in its parameter (a
   background, the source's Stokes q) the span holds the whole family, so the screen gain bounds
   the fit's gain from above (a bounded fit gains less); for a smooth one (Beer-Lambert absorption, a tilt, a
   relief scale) it is the linear regime's estimate.  A fit costs 9-19 evaluations, a screen 2:
   on a measured map the cheap fits alone were 40-50 s of a step's worker time.
   The screens and the fits of candidates without parameters run as one round on the worker
   processes, except a screen whose probes' tables this process already holds from an earlier
   step, which runs here beside them (`_step_round`; the rounds of one diagnosis share one pool
   of worker processes, `parallel.kept_workers`, so the workers keep the tables, solvers and
   evaluations of the rounds before); then the candidates that passed are fitted in decreasing
   screen gain, one at a time in this process (a fit's grid points are evaluated together on
   the worker processes, `DiagnosisForward.prefetch`), each only while it could still be the
   step's best or within BIC_MARGIN of it (an `alternatives` entry, item 5): its screened BIC
   gain (gain - k ln n) must exceed the best BIC gain already fitted at this step less
   BIC_MARGIN, else it is listed as outgained.  A screen cannot name an effect, only save the
   fit of one that could not pass or win: what is named is always decided on fitted chi^2;
2. the candidate with the lowest BIC(S + c) is the one that gains most; it passes the bar
   (`passes`) when
   - Delta BIC = BIC(S) - BIC(S + c) > BIC_MARGIN = 10 ("very strong", Kass & Raftery 1995),
   - AND S does not reach the noise within the forward model's stated accuracy (`adequate`:
     chi^2_S > A^2 n + 3 sqrt(2 n), A = MODEL_ACCURACY_RMS = 1.2, the rms z the one plate model is
     required to reach on clean independent recordings; 3 sqrt(2 n) is the 99.9 %
     one-sided spread of a chi^2 with n degrees of freedom, normal approximation), or the gain is
     overwhelming, Delta BIC > max(40, 3 sqrt(2 n)) (a global chi^2 test has little power against
     an effect confined to a few rows; under pure noise a 1-parameter gain of 45 has probability
     ~1e-11).  A baseline that misses the noise only by the model's own stated inaccuracy is
     not evidence of a missing physics: a candidate can always absorb part of a systematic
     model error (a clean 48 px case on `normals` tables, rms 1.34, gained 21 with a relief
     scale of 0.95; test_diagnose.test_clean_case_called_none);
3. if it passes, every parameter of S + c is refitted jointly, starting from S's values and c's
   conditional fit (at the first step the conditional fit is the joint one, and a fit that already
   ended with Gauss-Newton steps, `fitting._polished_fit`, is not polished again): Gauss-Newton steps
   (`fitting.polish`, twice its budget of steps), and where they do not converge the coordinate
   search (`fitting.refit_joint`, on the screening forward model: `_screened_refit`) and the steps
   again, and a named effect that the others now make redundant (removing it and refitting the
   rest jointly does not fail the bar) is dropped (an effect whose removal costs more than ten
   times the overwhelming bar after the rest's linearised refit is kept without the refit,
   `_clearly_needed`);
4. stop when no candidate passes, or at MAX_EFFECTS effects (a dropped effect is not offered
   again, so the search ends).
5. (reporting only) a candidate whose fitted BIC came within BIC_MARGIN of the winner's at the
   step that named an effect, and that is not named itself, is an `alternatives` entry: the
   recording does not decide between them (relief scale and smoothing in geometric optics); so is
   a trading pair's member that the rows do not separate from its partner (`_separate_pair`).
6. every joint refit of step 3 ends with Gauss-Newton steps to the least-chi^2 point
   (`fitting.polish`), and so does the chosen model when a drop changed its set (a joint refit
   that starts with those steps needs the coordinate search only when they do not converge: on
   tilt + blur, seed 10, the search took 11 s and the steps after it 15 s): the
   coordinate search stops where its short grids end, not at the optimum of correlated
   parameters (seed 5, case06: relief smoothing named at step 2 with chi^2 986 for 210 rows,
   then traded for a relief scale of 0.47 plus an absorption), and the bar of the next step is
   judged against that chi^2.  The last polish's Jacobian is the intervals' one.

Rules that keep the search from contradicting its own report:
- the gain a candidate is judged on (`passes`) is the project's one criterion on the
  quasi-likelihood scale (`gain_of`: `criteria.bic_gain` with the larger model's
  overdispersion c = max(1, chi^2 / (n - k)), the fit's QBIC): while the model misses the noise by
  a wide margin a chi^2 difference counts 1 / c as much, so a parameter that only bends the model
  toward its own systematic error is not named (the plain BIC gain is still what ranks
  candidates and what `steps` records as `bic_gain`; the reason words give both);
- a signature (`_signatures`): where one shape template of `mismatch.classify` explains at least
  SIGNATURE_SHARE = 1/2 of the current model's residual chi^2 and names a candidate (an offset is
  stray light, a loss growing with the path in the glass absorption, a displaced lobe a tilt),
  that candidate is fitted at the step whatever its screen, from the start the signature gives
  (the offset's own level for stray light);
- the reach rule: a strongly non-linear candidate (NONLINEAR: back-face roughness, volume
  scattering, blur) that its two-probe screen would leave unfitted is fitted while its screen gain
  is at least REACH = 1/4 of the step's leader's (the best fitted chi^2 gain, or the largest screen
  gain) and that leader passes the bar: the linear screen of such an effect can fall several times
  short of its fit;
- a fit that ends at its null value (0 /mm, alpha 0, 0 um) is refitted from starts spread over its
  range before it is judged (`fitting._restart`);
- trading pairs (TRADING_PAIRS: blur and relief scale, smoothing and relief scale, index and
  scale act alike on a lobe): when the second of a pair is named, the joint refit runs from the
  other start too (`_pair_starts`), and the step records the correlation of the two
  (`_correlations`, diagnosis.json `steps[].correlations`); `_drop_redundant` on the QBIC scale
  removes one that the other makes redundant, and where their correlation exceeds PAIR_CORRELATION
  (0.95) in size a member stays named beside the other only when removing it costs more than the
  overwhelming bar (`_separate_pair`): otherwise the one whose removal costs less is reported as an
  alternative with the correlation, so one is named only where the data separate them;
- boundary methods (METHOD_OF: interreflection is the relief ray traced, diffraction its Kirchhoff
  integral) are fitted at the first step only and never named: `method_check` reports whether one
  fits the baseline better (diagnosis.json `method_check`), a verdict on the method choice.
These thresholds were set on the stand-in forward models of tests/backend/diagnose and the
project's own concealed cases (test_diagnose, seed 1), never on the independent validation set.

7. (record keeping only) every step is recorded for diagnosis.json's `steps` and `stop`
   (`steps_record`, formats.md): the model after the step, its chi^2, the effect added, and what
   each candidate did (fitted, screened out, outgained, skipped, dropped) with its chi^2, BIC gain
   and the reason in words; the last step carries why the search stopped (`Step.stop`).

The effects come out in the order they were added: each was the largest gain of its step,
so the most important is first.  The same thresholds as the single-effect selection of the
blind-diagnosis benchmark (the n-scaled overwhelming bar was set on its seed 1 and checked on
fresh seeds); nothing here was tuned on the compound cases.
"""
from __future__ import annotations

import contextvars
import copy
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

from relief_bsdf.diagnose.effects import compatible, get_effect
from relief_bsdf.diagnose.fitting import POLISH_STEPS, fit_effect, polish, refit_joint, why_skipped
from relief_bsdf.diagnose.profile import captured, merge, stage
from relief_bsdf.errors import InputError
from relief_bsdf.criteria import BIC_MARGIN, bic, bic_gain, overdispersion
from relief_bsdf.parallel import kept_workers, map_tasks
from relief_bsdf.parallel.blas import blas_single_thread
from relief_bsdf.progress import silent

BIC_OVERWHELMING = 40.0
CONSISTENCY_Z = 3.0
MAX_EFFECTS = 4
MODEL_ACCURACY_RMS = 1.2
DROP_SHORTCUT = 10.0     # `_clearly_needed`: the safety factor on the linearised refit of the rest
# A residual's signature (`mismatch.classify` on the current model's residual): the shape that
# explains at least SIGNATURE_SHARE of it forces the candidate it names to be fitted at that step,
# from the start the signature gives (`_signatures`).
SIGNATURE_SHARE = 0.5
SIGNATURES = {"offset": "stray_light", "path_deficit": "bulk_absorption", "shift": "sample_tilt"}
# Strongly non-linear candidates: their two-probe linear screen may rank them far below their fit
# (back-face roughness's screen 1.25e5 against absorption's fitted 1.54e5, then never fitted), so
# one is fitted while its screen gain is within REACH of the step's leader (`_fit_step`).
NONLINEAR = ("back_face_roughness", "volume_scattering", "instrument_blur")
REACH = 0.25
# Effects that trade against each other on the rows (both widen, narrow or move a lobe): fitted
# jointly from both starts and reported with their correlation (`_pair_starts`, `Step.correlations`).
TRADING_PAIRS = (("instrument_blur", "relief_scale"), ("relief_smoothing", "relief_scale"),
                 ("refractive_index", "relief_scale"))
# A trading pair named together whose fitted correlation exceeds PAIR_CORRELATION in size is not
# separated by the rows unless removing a member costs more than the overwhelming bar
# (`_separate_pair`).  |r| > 0.95 is a variance inflation 1 / (1 - r^2) > 10, the usual bar of
# collinearity (Marquardt 1970; Kutner et al., Applied Linear Statistical Models): each member's
# interval is then more than 3.2 times what it would be were the other known.
PAIR_CORRELATION = 0.95
# Candidates that are a boundary method, not physics of the sample (`method_check`).
METHOD_OF = {"interreflection": "ray", "diffraction": "kirchhoff"}


def consistent_with_noise(chi2: float, n: int) -> bool:
    """chi^2 <= n + 3 sqrt(2 n): the 99.9 % one-sided bound of a chi^2 with n degrees of freedom."""
    return chi2 <= n + CONSISTENCY_Z * math.sqrt(2 * n)


def adequate(chi2: float, n: int) -> bool:
    """chi^2 <= A^2 n + 3 sqrt(2 n): the noise reached within the forward model's stated accuracy A."""
    return chi2 <= MODEL_ACCURACY_RMS**2 * n + CONSISTENCY_Z * math.sqrt(2 * n)


def overwhelming_bar(n: int) -> float:
    return max(BIC_OVERWHELMING, CONSISTENCY_Z * math.sqrt(2 * n))


def gain_of(chi_cur: float, k_cur: int, chi_new: float, k_new: int, n: int) -> float:
    """The gain a larger model is judged on: the project's one criterion on the quasi-likelihood scale
    (`criteria.bic_gain` with the larger model's overdispersion c = max(1, chi^2 / (n - k)), QBIC):
    while the model misses the noise by a wide margin its chi^2 differences are inflated by c, and a
    parameter that only bends the model toward its own systematic error (an index offset, a small
    polarisation, a 0.01 deg blur) would pass a plain BIC bar.  c = 1 at the noise: plain BIC."""
    return bic_gain(chi_cur, k_cur, chi_new, k_new, n, overdispersion(chi_new, k_new, n))


def passes(chi_cur: float, k_cur: int, chi_new: float, k_new: int, n: int) -> bool:
    """Does the larger model (chi_new, k_new) pass the bar against the current one (module docstring)?
    Judged on the quasi-likelihood scale (`gain_of`)."""
    gain = gain_of(chi_cur, k_cur, chi_new, k_new, n)
    return gain > BIC_MARGIN and (not adequate(chi_cur, n) or gain > overwhelming_bar(n))


@dataclass
class Step:
    """The model after one step: named effects (in order), their values, chi^2, k, simulated rows."""

    effects: tuple
    values: dict
    chi2: float
    k: int
    model: tuple                    # (values per row, model sigma per row)
    added: str = "none"
    gain: float = 0.0               # Delta BIC of this step
    dropped: tuple = ()
    tried: list = field(default_factory=list)     # the conditional fits of the step that led here
    jacobian: Any = None            # `fitting.polish`'s at `values` (for the intervals), or None
    excluded: tuple = ()            # (effect, reason) of candidates not offered at this step
    stop: str = ""                  # on the last step: why the search ended (plain words)
    correlations: list = field(default_factory=list)   # of trading pairs both named (`_correlations`)
    pairs: list = field(default_factory=list)   # trading pairs the rows do not separate (`_separate_pair`)


def _probes(effect, first: dict | None) -> list[dict]:
    """The screening points of a candidate (module docstring, step 1); [] for one without parameters."""
    if not effect.params:
        return []
    out = []
    if first and "parameters" in first and any(first["parameters"][p.name] != p.neutral for p in effect.params):
        out.append(dict(first["parameters"]))

    def toward(p, frac: float, wide: bool) -> float:
        up = p.upper - p.neutral >= p.neutral - p.lower
        end = p.upper if up == wide else p.lower
        return p.neutral + frac * (end - p.neutral)
    out.append({p.name: toward(p, 0.1, True) for p in effect.params})
    out.append({p.name: (toward(p, 0.1, False) if p.lower < p.neutral < p.upper else toward(p, 0.3, True))
                for p in effect.params})
    return out


def line_gain(forward, cur: "Step", effect, probes: list[dict]) -> float:
    """chi^2 gain of the best linear combination of the model changes toward `probes` (module docstring).

    The residual is the current step's (its model, its sigma); the changes are evaluated on the
    screening forward (`DiagnosisForward.screening`: without inside sector tables where the baseline
    has them), the probes against the current model on that same forward."""
    import numpy as np
    held = tuple(get_effect(e) for e in cur.effects)
    from relief_bsdf.fit.residual import misfit_sigma
    m0, s0 = cur.model
    s = misfit_sigma(forward.rows, s0)
    r = (np.asarray(forward.rows.bsdf_sr, float) - m0) / s
    screen = forward.screening(effect) if hasattr(forward, "screening") else forward

    def changes(screen):
        before = screen.evaluations
        ref = m0 if screen is forward else screen.evaluate_set(held, cur.values)[1]
        D = np.stack([(screen.evaluate_set(held + (effect,), {**cur.values, **p})[1] - ref) / s for p in probes],
                     axis=1)
        if screen is not forward:
            forward.evaluations += screen.evaluations - before
        return D
    try:
        D = changes(screen)
    except InputError:
        if screen is forward:
            raise
        D = changes(forward)        # the cheaper loop cannot carry the current model (a polarised source named)
    ok = np.all(np.isfinite(D), axis=0) & (np.abs(D).sum(axis=0) > 0)
    if not ok.any():
        return 0.0
    c = np.linalg.lstsq(D[:, ok], r, rcond=None)[0]
    fit = D[:, ok] @ c
    return float(fit @ fit)


def _plan(forward, names: list[str], first: dict) -> list[tuple]:
    """[(name, probes)] of a step: a candidate's screening points (`_probes`), None for one fitted
    unscreened (no parameters: one evaluation) or listed as skipped by fit_effect, with its reason."""
    plan = []
    for name in names:
        e = get_effect(name)
        probes = _probes(e, first.get(name))
        plan.append((name, probes if probes and not why_skipped(forward, e) else None))
    return plan


def _fit_step(forward, cur: "Step", names: list[str], first: dict, n: int, progress, workers: int | None,
              label: str, held: dict | None = None, forced: dict | None = None
              ) -> tuple[list[dict], list[dict], list[dict]]:
    """(fits, outgained entries, screened-out entries) of a step (module docstring, step 1).

    The screens (and the one-evaluation fits of candidates without parameters) do not depend on
    each other and run as one round (`_step_round`; `held`: which tables each earlier screen used);
    then the candidates that passed are fitted in decreasing screen gain while each could still win
    or be an alternative.  `forced` ({name: (start values, reason)}, `_signatures`): candidates the
    current residual's signature names, fitted whatever their screen, from that start.  A strongly
    non-linear candidate (NONLINEAR) left unfitted by its screen is fitted while its screen gain is at
    least REACH times the step's leader's (the best fitted gain, or the largest screen gain)."""
    ln = math.log(max(n, 2))
    forced = {m: f for m, f in (forced or {}).items() if m in names}
    with stage("screens"):
        fits, screens = _step_round(forward, cur, _plan(forward, names, first), progress, workers, label,
                                    {} if held is None else held)
    passed, screened = [], []
    for r in screens:
        if r["screen"] is None:
            screened.append({"effect": r["effect"], "skipped": r["skipped"]})
        elif r["effect"] in forced:
            continue
        elif passes(cur.chi2, cur.k, cur.chi2 - r["screen"], cur.k + get_effect(r["effect"]).k, n):
            passed.append((r["screen"], r["effect"]))
        else:
            screened.append({"effect": r["effect"], "screened": round(r["screen"], 3)})
    screen_of = {r["effect"]: r["screen"] for r in screens if r["screen"] is not None}
    for m, (start, why) in forced.items():
        if m not in screen_of:
            continue
        with stage("candidate_fits"):
            f = _merged(_step_task(forward, _task(m, None, cur, start)))
        f["forced"] = why
        fits.append(f)
    passed.sort(reverse=True)
    outgained = []
    fitted = 0

    def best() -> tuple[float, str]:
        ok = [f for f in fits if "chi2" in f and f["effect"] not in METHOD_OF]
        if not ok:
            return -math.inf, ""
        f = max(ok, key=lambda f: cur.chi2 - f["chi2"] - f["k"] * ln)
        return cur.chi2 - f["chi2"] - f["k"] * ln, f["effect"]
    while passed:
        top, leader = best()
        can_win = [(g, m) for g, m in passed if g - get_effect(m).k * ln > top - BIC_MARGIN]
        if not can_win:
            outgained += [{"effect": m, "screened": round(g, 3), "outgained_by": leader} for g, m in passed]
            break
        # one at a time, in this process: its grids' points are evaluated together on the kept
        # workers (`DiagnosisForward.prefetch`), and the next is fitted only if it can still win
        # or come within BIC_MARGIN of the winner
        g, m = can_win[0]
        passed.remove((g, m))
        with stage("candidate_fits"):
            fits.append(_merged(_step_task(forward, _task(m, None, cur))))
        fitted += 1
        progress(fitted, fitted + len(passed), label)
    # the reach rule for strongly non-linear candidates
    fitted_gain = max([cur.chi2 - f["chi2"] for f in fits if "chi2" in f and f["effect"] not in METHOD_OF],
                      default=0.0)
    lead = max([fitted_gain] + list(screen_of.values()))
    if not passes(cur.chi2, cur.k, cur.chi2 - lead, cur.k + 1, n):
        return fits, outgained, screened        # no leader past the bar: nothing is within reach of one
    for lst in (outgained, screened):
        for e in list(lst):
            m = e["effect"]
            g = screen_of.get(m)
            if m in NONLINEAR and g is not None and lead > 0 and g >= REACH * lead:
                lst.remove(e)
                with stage("candidate_fits"):
                    f = _merged(_step_task(forward, _task(m, None, cur)))
                f["reach"] = (f"fitted although its linear screen (chi2 gain {g:.4g}) did not ask for it: a strongly "
                              f"non-linear effect within reach of the step's leader (screen >= {REACH:g} x "
                              f"{lead:.4g})")
                fits.append(f)
    return fits, outgained, screened


def _signatures(forward, cur: "Step", names: list[str]) -> dict:
    """{candidate: (start values, reason)} of the current residual's signature (`mismatch.classify` on the
    rows the current model leaves): the best template shape, when it explains at least SIGNATURE_SHARE of
    the residual's chi^2 and names a candidate (SIGNATURES: an offset is stray light, a loss growing with
    the path in the glass is absorption, a displaced lobe a tilt).  The start: an offset's fitted level
    for stray light (the template's own coefficient, 1/sr); the others start from their grid."""
    from relief_bsdf.diagnose.mismatch import classify
    m0, s0 = cur.model
    try:
        shapes = classify(forward.rows, m0, s0)
    except (ValueError, FloatingPointError):
        return {}
    if not shapes or shapes[0]["explained"] < SIGNATURE_SHARE:
        return {}
    top = shapes[0]
    name = SIGNATURES.get(top["shape"])
    if name is None or name not in names:
        return {}
    start = {}
    if name == "stray_light" and top["coefficient"] > 0:
        start = {"background_per_sr": float(top["coefficient"])}
    why = (f"the remainder's signature: {top['shape'].replace('_', ' ')} explains {top['explained']:.0%} of its chi2 "
           f"(>= {SIGNATURE_SHARE:.0%}), so {name} is fitted at this step"
           + (f" from {', '.join(f'{k} {v:.4g}' for k, v in start.items())}" if start else ""))
    return {name: (start, why)}


def _screen_id(task: tuple) -> tuple:
    name, probes = task[:2]
    return name, tuple(tuple(sorted((k, round(float(v), 12)) for k, v in p.items())) for p in probes)


def _task(name: str, probes: list | None, cur: Step, start: dict | None = None) -> tuple:
    """A task of `_step_task`: the candidate, its probes (None: fit it), the current step without
    what the task does not read (its fits, its Jacobian), whether the search is coarse, and the start
    of its fit (a signature's, `_signatures`; None: the grid's)."""
    return name, probes, replace(cur, tried=[], jacobian=None), bool(cur.effects), start


def _step_round(forward, cur: Step, plan: list, progress, workers: int | None, label: str,
                held: dict) -> tuple[list[dict], list[dict]]:
    """(fits, screens) of a step's first round, in plan order.

    The round is one batch of tasks on the worker processes (the fits of candidates without parameters first),
    except the screens whose probes' tables this process's memory owner (`plate.memory`)
    held at an earlier step (`held`: the table keys each screen used).  Those run here, beside the
    batch (plate solves only), each inside `TableCache.held_only`: a screen that needs a table this
    process does not hold (the current model changed the tables it builds on: a relief scale or a
    tilt named since; or the cache let it go) stops at that table (`MissingTable`) and goes to the
    workers instead, two or more at a time as they come (a batch of one would run in this process),
    a last single one here after the others.  So a step derives no probe table here, and none that
    an earlier step derived and this cache still holds (otherwise, on a relief scale + absorption
    case, the later rounds derive the re-scaled relief's probe tables here, one after the other,
    while the workers idle).  A worker sends the tables of its screens back to this
    process's cache when they are small enough to be held (`TableCache.worth_sending`).  The
    workers' context is the forward model (pickled once for the diagnosis's kept pool, `stepwise`),
    each task carries the current step; a copy of the forward with its own memo screens here.
    Without worker processes (one worker, another backend, or inside a worker) everything runs
    here, one task after the other.  Where a task runs changes no result (the same tables from
    the same seeds)."""
    import threading
    from collections import deque

    from relief_bsdf.parallel.tasks import current_settings, in_worker, resolve_backend
    from relief_bsdf.plate.memory import MissingTable, current_memory
    settings = current_settings().updated(workers=workers)
    workers_here = (not in_worker() and settings.worker_count() > 1
                    and resolve_backend(None, settings) == "processes")
    here = [_task(*t, cur) for t in plan if t[1] is not None and workers_here
            and current_memory().holds(held.get(_screen_id(t)))]
    there = ([_task(*t, cur) for t in plan if t[1] is None]
             + [_task(*t, cur) for t in plan if t[1] is not None and t[0] not in {h[0] for h in here}])
    if here:
        mine = forward.twin() if hasattr(forward, "twin") else copy.copy(forward)
        missing: deque = deque()        # screens that need a table this process does not hold
        lock, here_done = threading.Lock(), threading.Event()

        def on_workers() -> list:
            out = list(zip(there, map_tasks(_step_task, there, forward, progress=progress, label=label,
                                            workers=workers)))
            while True:
                with lock:
                    batch = [missing.popleft() for _ in range(len(missing))] if len(missing) >= 2 else []
                if batch:
                    out += zip(batch, map_tasks(_step_task, batch, forward, label=label, workers=workers))
                elif here_done.is_set():
                    return out
                else:
                    here_done.wait(0.05)
        with ThreadPoolExecutor(1) as pool:
            pending = pool.submit(contextvars.copy_context().run, on_workers)   # the settings in force travel
            mine_done = []
            try:
                with blas_single_thread():       # beside the workers: one BLAS thread (parallel.blas)
                    _current_on_screens(mine, cur, here)
                    for t in here:
                        try:
                            with current_memory().held_only():
                                mine_done.append((t, _step_task(mine, t)))
                        except MissingTable:
                            with lock:
                                missing.append(t)
            finally:
                here_done.set()
                pairs = pending.result() + mine_done
        pairs += [(t, _step_task(mine, t)) for t in missing]        # at most one left: here
        if hasattr(forward, "_memo"):
            forward._memo.update(mine._memo)
        forward.evaluations = mine.evaluations
    else:
        pairs = list(zip(there, map_tasks(_step_task, there, forward, progress=progress, label=label,
                                          workers=workers)))
    result = {t[0]: _merged(r) for t, r in pairs}
    for t in plan:
        r = result[t[0]]
        for key, table in r.pop("tables", {}).items():
            current_memory().put(key, table)
        if "table_keys" in r:
            held[_screen_id(t)] = r.pop("table_keys")
    return ([result[t[0]] for t in plan if t[1] is None], [result[t[0]] for t in plan if t[1] is not None])


def _current_on_screens(forward, cur: Step, tasks: list) -> None:
    """The current model evaluated on each screening forward model of `tasks` (`DiagnosisForward.screening`),
    tables derived here as needed: every screen starts from it (`line_gain`'s reference), so the held
    screens then stop at a missing table only when their own probes need one (a named relief scale
    changes the screening grid's front tables too, which no earlier round derived here)."""
    if not cur.effects or not hasattr(forward, "screening"):
        return
    named = tuple(get_effect(e) for e in cur.effects)
    done: list = []
    for t in tasks:
        screen = forward.screening(get_effect(t[0]))
        if screen is forward or any(screen is d for d in done):
            continue
        done.append(screen)
        try:
            screen.evaluate_set(named, cur.values)
        except InputError:
            pass                        # the screens report it (`_step_task`)


def _merged(result: dict) -> dict:
    """`result` of `_step_task` with its evaluation counts moved into this process's profile (`profile.merge`)."""
    merge(result.pop("profile", None))
    return result


def _step_task(forward, task: tuple) -> dict:
    """One task of a step: the conditional fit of a candidate (probes None), or its screen (the
    chi^2 gain of its probes, `line_gain`, with the keys of the tables it used and, in a worker
    process, those tables that are not the baseline's when they are small enough to be held there,
    `TableCache.worth_sending`; an InputError of the plate lists it as skipped)."""
    from relief_bsdf.parallel.tasks import in_worker
    name, probes = task[:2]
    kind = "method_check" if name in METHOD_OF else "candidate_fits" if probes is None else "screens"
    if not in_worker():                 # counted in this process's profile as it runs
        with stage(kind):
            return _step_task_counted(forward, task)
    with captured() as p, stage(kind):  # on a worker (or a task of a serial round): the counts travel back
        out = _step_task_counted(forward, task)
    counts = p.counts()
    if counts:
        out["profile"] = counts
    return out


def _step_task_counted(forward, task: tuple) -> dict:
    from relief_bsdf.parallel.tasks import in_worker
    from relief_bsdf.plate.memory import current_memory
    name, probes, cur, coarse = task[:4]
    start = task[4] if len(task) > 4 else None
    if probes is None:
        return fit_effect(forward, get_effect(name), tuple(get_effect(e) for e in cur.effects), cur.values, coarse,
                          start)
    try:
        with current_memory().recording() as used:
            gain = line_gain(forward, cur, get_effect(name), probes)
    except InputError as err:
        return {"effect": name, "screen": None, "skipped": str(err)}
    tables = current_memory().tables(used)
    base = getattr(forward, "_baseline_keys", frozenset())
    new = {k: v for k, v in tables.items() if k not in base} if in_worker() else {}
    return {"effect": name, "screen": gain, "table_keys": tuple(tables),
            "tables": new if current_memory().worth_sending(new) else {}}


def _clearly_needed(forward, step: Step, name: str, rest: tuple, vals: dict, n: int) -> bool:
    """Does removing `name` from `step` cost far more than the bar, whatever the rest's refit?  One
    evaluation instead of a refit (`_drop_redundant`): the rest at their current values without
    `name`, chi^2_0 (exact, the effect removed in full), less the best the rest can regain by the
    linearised refit from there, |P_J r|^2 with J the rest's columns of the polish's Jacobian (the
    Gauss-Newton model of the refit); needed when what remains exceeds DROP_SHORTCUT times the
    overwhelming bar plus the effect's BIC penalty.  The factor holds the linearisation of the rest's
    move: a refit that regains ten times more than its linear model is not a refit near an optimum.
    No Jacobian (the polish ran out of steps): not decided here."""
    import numpy as np
    from relief_bsdf.fit.residual import misfit_sigma, signed_residuals
    if step.jacobian is None:
        return False
    order = [p.name for e in step.effects for p in get_effect(e).params]
    cols = [order.index(p.name) for e in rest for p in e.params]
    chi0, v, s0 = forward.evaluate_set(rest, vals)
    r = signed_residuals(forward.rows.bsdf_sr, v, misfit_sigma(forward.rows, s0))
    J = np.asarray(step.jacobian, float)[:, cols]
    regained = 0.0
    if J.size:
        fit = J @ np.linalg.lstsq(J, -r, rcond=1e-10)[0]
        regained = float(r @ r - (r + fit) @ (r + fit))
    bar = overwhelming_bar(n) + get_effect(name).k * math.log(max(n, 2))
    return chi0 - regained - step.chi2 > DROP_SHORTCUT * bar


def _screened_refit(forward, effs: tuple, vals: dict) -> tuple[dict, float, Any]:
    """(values, chi^2, J) of `effs` refitted jointly from `vals`: the coordinate search (`fitting.refit_joint`,
    three to eleven evaluations per parameter and pass) on the screening forward model
    (`DiagnosisForward.screening`, with the Stokes loop where an effect of the set acts through the
    polarisation), then Gauss-Newton steps on the full model from its answer (`fitting.polish`): the search
    finds the basin, the full model's steps its optimum, and the chi^2 is always the full model's (the
    reasoning of `fitting._screened_fit`).  Without a screening model (a stand-in), or where the cheaper
    loop cannot carry the set, the coordinate search runs on the full model."""
    screen = forward
    if hasattr(forward, "screening"):
        stokes = next((e for e in effs if e.stokes), None)
        try:
            screen = forward.screening(stokes)
        except InputError:
            screen = forward
    if screen is not forward:
        from relief_bsdf.diagnose.fitting import OnWorkers
        before = screen.evaluations
        try:
            vals, _ = refit_joint(OnWorkers(screen, forward, stokes), effs, vals)
        except InputError:
            vals, _ = refit_joint(forward, effs, vals)
        forward.evaluations += screen.evaluations - before
    else:
        vals, _ = refit_joint(forward, effs, vals)
    return polish(forward, effs, vals)


def _drop_redundant(forward, step: Step, n: int) -> Step:
    """Drop a named effect that the others make redundant: removing it and refitting the rest
    jointly (`_screened_refit`: the coordinate search of `fitting.refit_joint` on the screening model,
    Gauss-Newton steps on the full one, from their current values) loses less than the bar.  The refit
    matters: a greedy first step may name an effect that mimics two true ones together (volume
    scattering both dims the lobes and lifts the floor, like absorption plus stray light); once
    those are named, they take over its share only if they may move.  An effect whose removal
    costs far more than the bar even after the linearised refit (`_clearly_needed`, one evaluation)
    is kept without the refit (10 evaluations of a relief operation: 20 s on a Gaussian tile)."""
    for name in step.effects[:-1]:
        rest = tuple(get_effect(e) for e in step.effects if e != name)
        eff = get_effect(name)
        vals = {k: v for k, v in step.values.items() if k not in {p.name for p in eff.params}}
        if _clearly_needed(forward, step, name, rest, vals, n):
            continue
        vals, chi, _ = _screened_refit(forward, rest, vals)
        chi, v, s = forward.evaluate_set(rest, vals)
        if not passes(chi, step.k - eff.k, step.chi2, step.k, n):
            return Step(tuple(e.name for e in rest), vals, chi, step.k - eff.k, (v, s), step.added, step.gain,
                        step.dropped + (name,), step.tried, excluded=step.excluded)
    return step


def stepwise(forward, names: list[str], progress=None, workers: int | None = None) -> list[Step]:
    """Every step of the selection (module docstring), the baseline first, the chosen model last."""
    progress = progress or silent
    n = len(forward.rows)
    v0, s0 = forward.baseline()
    steps = [Step((), {}, forward.misfit(v0, s0), 0, (v0, s0))]
    dropped: set = set()
    held: dict = {}                 # the table keys of each screen so far (`_step_round`)
    with kept_workers(forward):     # one pool of worker processes for every round
        _steps(forward, names, steps, dropped, held, n, progress, workers)
    return steps


def _steps(forward, names: list[str], steps: list, dropped: set, held: dict, n: int, progress,
           workers: int | None) -> None:
    """The steps after the baseline, appended to `steps` (`stepwise`)."""
    while len(steps[-1].effects) < MAX_EFFECTS and len(steps) <= MAX_EFFECTS + 2:
        cur = steps[-1]
        named = tuple(get_effect(e) for e in cur.effects)
        # a boundary method (METHOD_OF) is judged once, on the baseline (`method_check`), never named
        methods_later = [m for m in names if m in METHOD_OF and len(steps) > 1]
        remaining = [m for m in names if m not in cur.effects and m not in dropped and m not in methods_later
                     and compatible(named + (get_effect(m),))]
        excluded = tuple((m, f"cannot act together with {', '.join(cur.effects)} in the plate model")
                         for m in names if m not in cur.effects and m not in dropped and m not in remaining
                         and m not in methods_later)
        excluded += tuple((m, f"a boundary method ({METHOD_OF[m]}), not physics of the sample: judged once on the "
                              "baseline (method_check), never named") for m in methods_later)
        if not [m for m in remaining if m not in METHOD_OF]:
            cur.stop = ("no candidate left to try: every effect is named, dropped as redundant, or cannot act "
                        "together with the named ones")
            break
        first = {f["effect"]: f for f in first_fits(steps)} if cur.effects else {}
        forced = _signatures(forward, cur, remaining)
        fits, outgained, screened = _fit_step(forward, cur, remaining, first, n, progress, workers,
                                              f"candidate effects, step {len(steps)}", held, forced)
        ok = [f for f in fits if not f.get("skipped") and f["effect"] not in METHOD_OF]
        step_tried = fits + outgained + screened
        if not ok:
            steps.append(Step(cur.effects, cur.values, cur.chi2, cur.k, cur.model, "stop", 0.0, (), step_tried,
                              cur.jacobian, excluded,
                              f"step {len(steps)}: no candidate was fitted (every one was screened out or "
                              f"skipped), so none can pass the bar ({bar_words(cur.chi2, n)})"))
            break
        best = min(ok, key=lambda f: bic(f["chi2"], cur.k + f["k"], n))
        if not passes(cur.chi2, cur.k, best["chi2"], cur.k + best["k"], n):
            gain = gain_of(cur.chi2, cur.k, best["chi2"], cur.k + best["k"], n)
            steps.append(Step(cur.effects, cur.values, cur.chi2, cur.k, cur.model, "stop", 0.0, (), step_tried,
                              cur.jacobian, excluded,
                              f"step {len(steps)}: the best fitted candidate, {best['effect']}, gains "
                              f"{gain_words(cur.chi2, cur.k, best['chi2'], cur.k + best['k'], n)}, short of the bar "
                              f"({bar_words(cur.chi2, n)})"))
            break
        effs = named + (get_effect(best["effect"]),)
        vals = {**cur.values, **best["parameters"]}
        # Gauss-Newton from the conditional fit (the first effect's is its joint fit: nothing else
        # moves), twice the polish's steps when the held effects move too (a start further from the
        # optimum); the coordinate refit only where those steps do not reach the optimum (step 3)
        with stage("joint_refit"):
            if not named and best.get("jacobian") is not None:
                chi, J = best["chi2"], best["jacobian"]     # its own fit was this polish (`fitting.fit_effect`)
            else:
                vals, chi, J = polish(forward, effs, vals, steps=2 * POLISH_STEPS if named else POLISH_STEPS)
            if named and J is None:
                vals, chi, J = _screened_refit(forward, effs, vals)
        with stage("pair_starts"):
            vals, chi, J = _pair_starts(forward, effs, vals, chi, J, first, best["effect"])
        with stage("joint_refit"):
            chi, v, s = forward.evaluate_set(effs, vals)
        new = Step(cur.effects + (best["effect"],), vals, chi, cur.k + best["k"], (v, s), best["effect"],
                   bic(cur.chi2, cur.k, n) - bic(chi, cur.k + best["k"], n), (), step_tried, J, excluded)
        if len(new.effects) > 1:
            with stage("redundancy"):
                new = _drop_redundant(forward, new, n)
            with stage("joint_refit"):
                new = _polished(forward, new)
        new.correlations = _correlations(new)
        if any(c["correlation"] is not None and abs(c["correlation"]) > PAIR_CORRELATION for c in new.correlations):
            with stage("pair_starts"):
                new = _separate_pair(forward, new, n)
        steps.append(new)
        dropped |= set(steps[-1].dropped)           # a dropped effect is not offered again
    if not steps[-1].stop:
        steps[-1].stop = (f"{MAX_EFFECTS} effects named, the most the search names"
                          if len(steps[-1].effects) >= MAX_EFFECTS else
                          f"the search ends after {len(steps) - 1} steps, the most it takes")


def _partners(name: str) -> list[str]:
    return [b if a == name else a for a, b in TRADING_PAIRS if name in (a, b)]


def _pair_starts(forward, effs: tuple, vals: dict, chi: float, J, first: dict, added: str) -> tuple:
    """The joint refit of a step that adds one of a trading pair while its partner is named, from the
    other start too: the added effect at its own first-step fit (alone on the baseline) and the partner
    back at its neutral value, polished jointly; the lower chi^2 of the two is kept (a blur may widen
    the lobe where a larger relief scale does, and a search from one side settles on its own side).

    The second polish runs only where the other start may lie in another basin (`_same_basin`): one
    full evaluation at the other start is compared with the quadratic model of chi^2 about the answer
    found (its polish's Jacobian); where the rise to the other start is at least BASIN_SHARE of what that
    model predicts, the surface between them is the one bowl and Gauss-Newton steps from there come back
    to this answer (a second start's polish costs 2k + 1 full evaluations per step, k parameters)."""
    names = [e.name for e in effs]
    partners = [p for p in _partners(added) if p in names]
    if not partners or added not in first or "parameters" not in first[added]:
        return vals, chi, J
    other = dict(vals)
    other.update(first[added]["parameters"])
    for p in partners:
        other.update(get_effect(p).neutral)
    try:
        if _same_basin(forward, effs, vals, J, other):
            return vals, chi, J
        v2, c2, J2 = polish(forward, effs, other, steps=2 * POLISH_STEPS)
    except InputError:
        return vals, chi, J
    if c2 < chi - 1e-9 * max(1.0, chi) and J2 is not None:
        return v2, c2, J2
    return vals, chi, J


BASIN_SHARE = 0.75


def _same_basin(forward, effs: tuple, vals: dict, J, other: dict) -> bool:
    """Is the other start of a trading pair (`_pair_starts`) in the basin of the answer `vals`?  With r the
    residuals at `vals` and J their Jacobian (`fitting.polish`'s, r(x + d) ~ r + J d), the quadratic model
    predicts chi^2(other) ~ |r + J d|^2, d = other - vals.  The start is in the same basin when its actual
    chi^2 rises from the answer's by at least BASIN_SHARE of the predicted rise: the bowl holds out to the
    start, so the steps from there descend to this answer.  A start whose chi^2 lies well below the
    prediction (the surface bends down toward another valley), or no Jacobian, is polished."""
    import numpy as np
    from relief_bsdf.fit.residual import misfit_sigma, signed_residuals
    if J is None:
        return False
    order = [p.name for e in effs for p in e.params]
    J = np.asarray(J, float)
    if J.ndim != 2 or J.shape[1] != len(order):
        return False
    chi, v, s = forward.evaluate_set(effs, vals)
    r = signed_residuals(forward.rows.bsdf_sr, v, misfit_sigma(forward.rows, s))
    d = np.array([other[p] - vals[p] for p in order], float)
    predicted = float(np.sum((r + J @ d) ** 2))
    actual = forward.evaluate_set(effs, other)[0]
    rise = predicted - chi
    return rise > 0 and actual - chi >= BASIN_SHARE * rise


def _correlations(step: "Step") -> list[dict]:
    """[{pair, parameters, correlation}] of the trading pairs named together in `step`: the correlation of
    their parameters from the polish's Jacobian (cov = (J^T J)^-1, Gauss-Newton); |r| near 1 means the
    rows cannot tell them apart."""
    import numpy as np
    if step.jacobian is None:
        return []
    order = [p.name for e in step.effects for p in get_effect(e).params]
    J = np.asarray(step.jacobian, float)
    if J.ndim != 2 or J.shape[1] != len(order):
        return []
    try:
        cov = np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return []
    out = []
    for a, b in TRADING_PAIRS:
        if a in step.effects and b in step.effects:
            pa, pb = get_effect(a).params[0].name, get_effect(b).params[0].name
            i, j = order.index(pa), order.index(pb)
            d = math.sqrt(max(cov[i, i] * cov[j, j], 0.0))
            r = float(cov[i, j] / d) if d > 0 else float("nan")
            out.append({"pair": [a, b], "parameters": [pa, pb],
                        "correlation": round(r, 4) if math.isfinite(r) else None})
    return out


def _separate_pair(forward, step: "Step", n: int) -> "Step":
    """A trading pair named together with |r| > PAIR_CORRELATION (`_correlations`): neither member is named on
    its own strength.  Each member is removed in turn and the rest polished jointly from their values
    (`fitting.polish`, Gauss-Newton: the partner takes over what it can); a member is *separated* by the rows
    when its removal costs more than the overwhelming bar, max(40, 3 sqrt(2 n)), on the QBIC scale
    (`gain_of`): the bar a gain must pass where a model already reaches the noise, since the two differ
    only in the small part of their signatures that does not trade, which is where the forward model's own
    error lives.  Both separated: both stay named (with their correlation).  Otherwise the member whose
    removal costs less is dropped, the other stays (named: it is needed, or it fits better alone), and the
    pair is recorded (`Step.pairs`, diagnosis.json `alternatives` with the correlation and whether the
    kept one is separated).  The model after a drop is the rest's polished fit (its Jacobian the intervals')."""
    for c in list(step.correlations):
        r = c["correlation"]
        if r is None or abs(r) <= PAIR_CORRELATION or not all(m in step.effects for m in c["pair"]):
            continue
        without = {}
        for m in c["pair"]:
            eff = get_effect(m)
            rest = tuple(get_effect(e) for e in step.effects if e != m)
            vals = {k: v for k, v in step.values.items() if k not in {p.name for p in eff.params}}
            try:
                vals, chi, J = polish(forward, rest, vals, steps=2 * POLISH_STEPS)
            except InputError:
                continue
            without[m] = (vals, chi, J, gain_of(chi, step.k - eff.k, step.chi2, step.k, n))
        if len(without) < 2:
            continue
        a, b = c["pair"]
        separated = {m: without[m][3] > overwhelming_bar(n) for m in (a, b)}
        if all(separated.values()):
            continue
        drop = a if without[a][3] < without[b][3] else b        # its removal costs less
        keep = b if drop == a else a
        vals, chi, J, _ = without[drop]
        eff = get_effect(drop)
        rest = tuple(get_effect(e) for e in step.effects if e != drop)
        _, v, s = forward.evaluate_set(rest, vals)
        other = without[keep][0]            # the model with `drop` in place of `keep`
        note = {"pair": [a, b], "parameters": c["parameters"], "correlation": r, "named": keep,
                "alternative": drop, "separated": bool(separated[keep]),
                "cost_of_removal": {m: round(float(without[m][3]), 3) for m in (a, b)},
                "bic_difference": round(float(bic(without[keep][1], step.k - get_effect(keep).k, n)
                                              - bic(chi, step.k - eff.k, n)), 3),
                "alternative_parameters": {p.name: round(float(other.get(p.name, step.values[p.name])), 6)
                                           for p in eff.params}}
        step = replace(step, effects=tuple(e.name for e in rest), values=vals, chi2=chi, k=step.k - eff.k,
                       model=(v, s), dropped=step.dropped + (drop,), jacobian=J, pairs=step.pairs + [note])
        step = _polished(forward, step)
        step.correlations = _correlations(step)
    return step


def gain_words(chi_cur: float, k_cur: int, chi_new: float, k_new: int, n: int) -> str:
    """The gain in words: BIC, and the quasi-likelihood (QBIC) gain it is judged on when c > 1 (`gain_of`)."""
    g = bic_gain(chi_cur, k_cur, chi_new, k_new, n)
    c = overdispersion(chi_new, k_new, n)
    if c <= 1.0:
        return f"BIC {g:.1f}"
    return f"BIC {g:.1f}, QBIC {gain_of(chi_cur, k_cur, chi_new, k_new, n):.1f} (chi2 / {c:.3g}: the model misses the noise)"


def method_check(steps: list["Step"], n: int, method: str) -> dict:
    """diagnosis.json's `method_check`: does another boundary method fit the baseline better?  The
    candidates that are a method (METHOD_OF: interreflection is the relief ray traced, diffraction its
    Kirchhoff integral) fitted at the first step, each against the baseline by the same criterion as an
    effect (`passes`, k = 0).  A method choice, never an effect of the sample."""
    tried = [f for f in (steps[1].tried if len(steps) > 1 else []) if f["effect"] in METHOD_OF]
    fitted = [f for f in tried if "chi2" in f and not f.get("skipped")]
    base = steps[0].chi2
    if not fitted:
        why = "; ".join(f"{METHOD_OF[f['effect']]}: {f['skipped']}" for f in tried if f.get("skipped"))
        return {"method": method, "better": None,
                "verdict": f"no other boundary method was tried on this baseline{': ' + why if why else ''}"}
    f = min(fitted, key=lambda f: f["chi2"])
    alt = METHOD_OF[f["effect"]]
    words = (f"the baseline by {alt} has chi2 {f['chi2']:.1f} against {base:.1f} by {method} ("
             f"{gain_words(base, 0, f['chi2'], 0, n)})")
    if passes(base, 0, f["chi2"], 0, n):
        return {"method": method, "better": alt,
                "verdict": f"the boundary method {alt} fits this recording better than {method}: {words}. This is a "
                           f"verdict on the method choice, not an effect of the sample: rerun with --method {alt}"}
    return {"method": method, "better": None,
            "verdict": f"{method} stands: {words}, not past the bar ({bar_words(base, n)})"}


def bar_words(chi_cur: float, n: int) -> str:
    """The bar a candidate must pass against a current model of misfit `chi_cur` (`passes`), in words."""
    if adequate(chi_cur, n):
        return (f"gain above {overwhelming_bar(n):.1f}: the current model already reaches the noise within "
                f"the forward model's stated accuracy, chi2 {chi_cur:.1f} <= {MODEL_ACCURACY_RMS:g}^2 n + "
                f"{CONSISTENCY_Z:g} sqrt(2 n), so only an overwhelming gain counts")
    return f"gain above {BIC_MARGIN:g} on the QBIC scale (BIC with chi2 divided by the larger model's reduced chi2)"


def steps_record(steps: list[Step], n: int) -> tuple[list[dict], str]:
    """diagnosis.json's `steps` and `stop` (formats.md): what every step of the search did.

    One entry per step after the baseline: `model` (the named effects after the step), `chi2` (its
    misfit), `added` (the effect named at the step, None when none passed) and every candidate with
    its `status`: "fitted" (its conditional fit with the named effects held, `chi2` and `bic_gain`
    = BIC(model before the step) - BIC(with it) from that fit), "screened" and "outgained" (not
    fitted: `chi2` and `bic_gain` are the linear screen's estimates, the model before the step less
    the screen's gain), "skipped" (not tried: held fixed by sample.toml, not applicable, or unable
    to act with the named effects), "dropped" (named at an earlier step, redundant now).  Records
    the search; it decides nothing."""
    ln = math.log(max(n, 2))
    out = []
    for prev, step in zip(steps, steps[1:]):
        added = None if step.added in ("stop", "none") else step.added
        fitted = [f for f in step.tried if "chi2" in f and not f.get("skipped")]
        gains = {f["effect"]: prev.chi2 - f["chi2"] - f["k"] * ln for f in fitted}
        effect_gains = {k: g for k, g in gains.items() if k not in METHOD_OF}
        lead = max(effect_gains, key=effect_gains.get) if effect_gains else None
        cands = []
        for f in step.tried:
            name = f["effect"]
            if f.get("skipped"):
                cands.append(_entry(name, "skipped", None, None, str(f["skipped"])))
            elif name in METHOD_OF:
                why = (f"a boundary method ({METHOD_OF[name]}), not physics of the sample: the baseline by it has "
                       f"chi2 {f['chi2']:.1f} ({gain_words(prev.chi2, prev.k, f['chi2'], prev.k, n)}); reported in "
                       f"method_check, never named")
                cands.append(_entry(name, "fitted", f["chi2"], gains[name], why))
            elif name in gains:
                g = gains[name]
                said = gain_words(prev.chi2, prev.k, f["chi2"], prev.k + f["k"], n)
                if name == added:
                    why = f"named: the largest BIC gain of the step ({said}), past the bar ({bar_words(prev.chi2, n)})"
                elif added is None and name == lead:
                    why = f"the best of the step ({said}), short of the bar ({bar_words(prev.chi2, n)})"
                else:
                    ref = added or lead
                    why = f"fitted ({said}); gains less than {ref} (BIC gain {gains[ref]:.1f})"
                why += _fit_notes(f)
                cands.append(_entry(name, "fitted", f["chi2"], g, why))
            else:
                screen = float(f.get("screened", 0.0))
                k = get_effect(name).k
                if f.get("outgained_by"):
                    by = f["outgained_by"]
                    why = (f"not fitted: its linear screen (two probes) gains at most about chi2 {screen:.4g} (BIC "
                           f"gain {screen - k * ln:.1f}), more than {BIC_MARGIN:g} below {by}'s fitted BIC gain "
                           f"{gains.get(by, float('nan')):.1f}, so it could neither win nor come close")
                    status = "outgained"
                else:
                    why = (f"not fitted: its linear screen (two probes) gains at most about chi2 {screen:.4g} ("
                           f"{gain_words(prev.chi2, prev.k, prev.chi2 - screen, prev.k + k, n)}), short of the bar "
                           f"({bar_words(prev.chi2, n)})")
                    status = "screened"
                cands.append(_entry(name, status, prev.chi2 - screen, screen - k * ln, why))
        cands += [_entry(name, "skipped", None, None, why) for name, why in step.excluded]
        unseparated = {p["alternative"]: p for p in step.pairs}
        cands += [_entry(name, "dropped", None, None,
                         f"named at an earlier step; with {added or 'the others'} named, removing it and refitting "
                         f"the rest jointly loses less than the bar, so it is redundant and not offered again")
                  for name in step.dropped if name not in unseparated and name != added]
        cands += [_entry(name, "dropped", None, None, pair_words(p, n) + "; not offered again")
                  for name, p in unseparated.items() if name != added]
        for c in cands:
            if c["effect"] == added and added in unseparated:
                c["reason"] += "; then " + pair_words(unseparated[added], n)
        order = {"fitted": 0, "outgained": 1, "screened": 2, "dropped": 3, "skipped": 4}
        cands.sort(key=lambda c: (order[c["status"]], -(c["bic_gain"] if c["bic_gain"] is not None else -math.inf)))
        entry = {"model": list(step.effects), "chi2": round(float(step.chi2), 3), "added": added,
                 "candidates": cands}
        if step.correlations and added is not None:
            entry["correlations"] = step.correlations
        if step.pairs:
            entry["pairs"] = [pair_words(p, n) for p in step.pairs]
        out.append(entry)
    return out, steps[-1].stop or "the search ended"


def _fit_notes(f: dict) -> str:
    """What a fit's record adds to its reason: forced by a signature, fitted by the reach rule, restarted
    from its null value (with the numbers)."""
    out = ""
    if f.get("forced"):
        out += f"; {f['forced']}"
    if f.get("reach"):
        out += f"; {f['reach']}"
    r = f.get("restart")
    if r:
        pts = ", ".join(f"{t:g}: {c:.1f}" for t, c in zip(r["fractions"], r["chi2"]))
        on = " on the screening forward model" if r.get("forward") == "screening" else ""
        out += (f"; its fit ended at its null value (chi2 {r['chi2_null']:.1f}{on}) and was refitted from starts "
                f"spread over its range (fraction of the range: chi2 {pts})"
                + ("" if r.get("moved") else ", none better than the null"))
    return out


def _entry(effect: str, status: str, chi2: float | None, gain: float | None, reason: str) -> dict:
    r = (lambda x: None if x is None or not math.isfinite(x) else round(float(x), 3))
    return {"effect": effect, "status": status, "chi2": r(chi2), "bic_gain": r(gain), "reason": reason}


def _polished(forward, step: Step) -> Step:
    """`step` at its least-chi^2 point (`fitting.polish`) when a drop changed its set (no Jacobian yet)."""
    if step.jacobian is not None or not step.effects:
        return step
    effs = tuple(get_effect(e) for e in step.effects)
    vals, chi, J = polish(forward, effs, step.values)
    _, v, s = forward.evaluate_set(effs, vals)
    return replace(step, values=vals, chi2=chi, model=(v, s), jacobian=J)


def pair_words(p: dict, n: int) -> str:
    """A trading pair the rows did not separate (`_separate_pair`), in words."""
    a, b = p["named"], p["alternative"]
    cost = p["cost_of_removal"]
    why = (f"{a} is needed (removing it costs QBIC {cost[a]:.1f}, above the overwhelming bar "
           f"{overwhelming_bar(n):.1f})" if p["separated"] else
           f"neither is separated (removing {a} costs QBIC {cost[a]:.1f}, {b} {cost[b]:.1f}, both under the "
           f"overwhelming bar {overwhelming_bar(n):.1f}); {a} is kept as the one whose removal costs more")
    return (f"{b} and {a} trade against each other on these rows (correlation {p['correlation']:+.3f}, past "
            f"{PAIR_CORRELATION:g}): {why}, and {b} (removing it costs QBIC {cost[b]:.1f}) is not separated from "
            f"it, so it is not named (alternatives)")


def alternatives(steps: list[Step], n: int) -> list[dict]:
    """Effects the recording cannot tell apart from a named one: at the step that added a named
    effect, another candidate whose fitted BIC came within BIC_MARGIN of the winner's (no "very
    strong" evidence between them, Kass & Raftery 1995) and that is not named itself.  In
    geometric optics, for example, relief_scale and relief_smoothing both act on the slopes, so
    one can stand for the other; the user should know that the choice between them is weak."""
    final = steps[-1].effects
    out = []
    for prev, step in zip(steps, steps[1:]):
        if step.added in ("stop", "none") or step.added not in final:
            continue
        fitted = [f for f in step.tried if "chi2" in f and not f.get("skipped")]
        won = next((f for f in fitted if f["effect"] == step.added), None)
        if won is None:
            continue
        b0 = bic(won["chi2"], prev.k + won["k"], n)
        for f in fitted:
            d = bic(f["chi2"], prev.k + f["k"], n) - b0
            if (f["effect"] != step.added and f["effect"] not in final and f["effect"] not in METHOD_OF
                    and d < BIC_MARGIN):
                out.append({"named": step.added, "alternative": f["effect"], "bic_difference": round(d, 3),
                            "alternative_parameters": {k: round(float(v), 6) for k, v in f["parameters"].items()}})
    for step in steps[1:]:          # trading pairs the rows do not separate (`_separate_pair`)
        for p in step.pairs:
            if p["named"] in final and p["alternative"] not in final:
                out.append({"named": p["named"], "alternative": p["alternative"],
                            "bic_difference": p["bic_difference"],
                            "alternative_parameters": p["alternative_parameters"],
                            "correlation": p["correlation"], "separated": p["separated"]})
    return out


def first_fits(steps: list[Step]) -> list[dict]:
    """The first step's fits: every candidate alone (or skipped with its reason)."""
    return steps[1].tried if len(steps) > 1 else steps[0].tried
