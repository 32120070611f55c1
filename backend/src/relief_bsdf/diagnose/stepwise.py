"""Stepwise selection of every effect present: add the one that gains most, refit all jointly, repeat.

The one information criterion of the project (`fit.selection`): BIC = chi^2 + k ln n
(Schwarz 1978) over the n recording rows, chi^2 the censored misfit with
s^2 = sigma_recording^2 + sigma_model^2 (`forward.DiagnosisForward.misfit`), k the number of
fitted parameters of the named effects.

Step (current set S, chi^2_S, k_S; S = {} is the baseline):
1. every candidate c not in S that can act together with S (`effects.compatible`) and is not
   held fixed by sample.toml is fitted with S held at its values (`fitting.fit_effect`, the
   conditional fit; at the first step this is the single-effect fit of each candidate).
   Budget: from the second step on, a candidate that re-derives the boundary tables is first
   screened by ONE evaluation, at its own first-step value (or 10 % into its range when that
   was neutral): the best chi^2 gain along the line from the current model to that probe,
   (r . d)^2 / (d . d) with r the current normalised residual and d the probe's change of the
   model in the same units (a linear least-squares line search, the score-test idea), must
   exceed k ln n + BIC_MARGIN, else it is listed as screened out and not fitted;
2. the candidate with the lowest BIC(S + c) is the one that gains most; it passes the bar
   (`passes`) when
   - Delta BIC = BIC(S) - BIC(S + c) > BIC_MARGIN = 10 ("very strong", Kass & Raftery 1995),
   - AND S does not reach the noise within the forward model's stated accuracy (`adequate`:
     chi^2_S > A^2 n + 3 sqrt(2 n), A = MODEL_ACCURACY_RMS = 1.2, the rms z the one plate model is
     required to reach on clean independent recordings (issue 18); 3 sqrt(2 n) is the 99.9 %
     one-sided spread of a chi^2 with n degrees of freedom, normal approximation), or the gain is
     overwhelming, Delta BIC > max(40, 3 sqrt(2 n)) (a global chi^2 test has little power against
     an effect confined to a few rows; under pure noise a 1-parameter gain of 45 has probability
     ~1e-11).  A baseline that misses the noise only by the model's own stated inaccuracy is
     not evidence of a missing physics: a candidate can always absorb part of a systematic
     model error (a clean 48 px case on `normals` tables, rms 1.34, gained 21 with a relief
     scale of 0.95; test_diagnose.test_clean_case_called_none);
3. if it passes, every parameter of S + c is refitted jointly (`fitting.refit_joint`, starting
   from S's values and c's conditional fit), and a named effect that the others now make
   redundant (removing it and refitting the rest jointly does not fail the bar) is dropped;
4. stop when no candidate passes, or at MAX_EFFECTS effects (a dropped effect is not offered
   again, so the search ends).

The effects come out in the order they were added: each was the largest gain of its step,
so the most important is first.  The same thresholds as the single-effect selection of the
first benchmark (issue 6; the n-scaled overwhelming bar was set on seed 1 and re-checked on
fresh seeds there); nothing here was tuned on the compound benchmark.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from relief_bsdf.diagnose.effects import compatible, get_effect
from relief_bsdf.diagnose.fitting import fit_effect, refit_joint
from relief_bsdf.errors import InputError
from relief_bsdf.fit.selection import BIC_MARGIN, bic, bic_gain
from relief_bsdf.parallel import map_tasks
from relief_bsdf.progress import silent

BIC_OVERWHELMING = 40.0
CONSISTENCY_Z = 3.0
MAX_EFFECTS = 4
MODEL_ACCURACY_RMS = 1.2


def consistent_with_noise(chi2: float, n: int) -> bool:
    """chi^2 <= n + 3 sqrt(2 n): the 99.9 % one-sided bound of a chi^2 with n degrees of freedom."""
    return chi2 <= n + CONSISTENCY_Z * math.sqrt(2 * n)


def adequate(chi2: float, n: int) -> bool:
    """chi^2 <= A^2 n + 3 sqrt(2 n): the noise reached within the forward model's stated accuracy A."""
    return chi2 <= MODEL_ACCURACY_RMS**2 * n + CONSISTENCY_Z * math.sqrt(2 * n)


def overwhelming_bar(n: int) -> float:
    return max(BIC_OVERWHELMING, CONSISTENCY_Z * math.sqrt(2 * n))


def passes(chi_cur: float, k_cur: int, chi_new: float, k_new: int, n: int) -> bool:
    """Does the larger model (chi_new, k_new) pass the bar against the current one (module docstring)?"""
    gain = bic_gain(chi_cur, k_cur, chi_new, k_new, n)
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


def _probe(effect, first: dict | None) -> dict | None:
    """The screening point of a table-changing candidate (module docstring, step 1)."""
    if not effect.params:
        return None
    if first and not first.get("skipped") and any(first["parameters"][p.name] != p.neutral for p in effect.params):
        return dict(first["parameters"])
    return {p.name: p.neutral + 0.1 * (p.upper - p.neutral if p.upper > p.neutral else p.lower - p.neutral)
            for p in effect.params}


def line_gain(forward, cur: "Step", effect, probe: dict) -> float:
    """Largest chi^2 gain along the line from the current model to `effect` at `probe` (linear)."""
    import numpy as np
    named = tuple(get_effect(e) for e in cur.effects) + (effect,)
    m1 = forward.evaluate_set(named, {**cur.values, **probe})[1]
    m0, s0 = cur.model
    s = np.sqrt(np.asarray(forward.rows.sigma_sr, float) ** 2 + s0**2)
    r = (np.asarray(forward.rows.bsdf_sr, float) - m0) / s
    d = (m1 - m0) / s
    dd = float(d @ d)
    return float(r @ d) ** 2 / dd if dd > 0 else 0.0


def _screen(forward, cur: "Step", names: list[str], first: dict, n: int) -> tuple[list[str], list[dict]]:
    """(candidates to fit, screened-out entries) of a later step (module docstring, step 1)."""
    keep, out = [], []
    for name in names:
        e = get_effect(name)
        probe = None if e.cheap else _probe(e, first.get(name))
        if probe is None:
            keep.append(name)
            continue
        try:
            g = line_gain(forward, cur, e, probe)
        except InputError as err:
            out.append({"effect": name, "skipped": str(err)})
            continue
        if g > e.k * math.log(max(n, 2)) + BIC_MARGIN:
            keep.append(name)
        else:
            out.append({"effect": name, "screened": round(g, 3)})
    return keep, out


def _cond_task(context, name: str) -> dict:
    forward, named, values, coarse = context
    return fit_effect(forward, get_effect(name), tuple(get_effect(e) for e in named), values, coarse)


def _drop_redundant(forward, step: Step, n: int) -> Step:
    """Drop a named effect that the others make redundant: removing it and refitting the rest
    jointly (`fitting.refit_joint`, from their current values) loses less than the bar.  The refit
    matters: a greedy first step may name an effect that mimics two true ones together (volume
    scattering both dims the lobes and lifts the floor, like absorption plus stray light); once
    those are named, they take over its share only if they may move."""
    for name in step.effects[:-1]:
        rest = tuple(get_effect(e) for e in step.effects if e != name)
        eff = get_effect(name)
        vals = {k: v for k, v in step.values.items() if k not in {p.name for p in eff.params}}
        vals, _ = refit_joint(forward, rest, vals)
        chi, v, s = forward.evaluate_set(rest, vals)
        if not passes(chi, step.k - eff.k, step.chi2, step.k, n):
            return Step(tuple(e.name for e in rest), vals, chi, step.k - eff.k, (v, s), step.added, step.gain,
                        step.dropped + (name,), step.tried)
    return step


def stepwise(forward, names: list[str], progress=None, workers: int | None = None) -> list[Step]:
    """Every step of the selection (module docstring), the baseline first, the chosen model last."""
    progress = progress or silent
    n = len(forward.rows)
    v0, s0 = forward.baseline()
    steps = [Step((), {}, forward.misfit(v0, s0), 0, (v0, s0))]
    dropped: set = set()
    while len(steps[-1].effects) < MAX_EFFECTS and len(steps) <= MAX_EFFECTS + 2:
        cur = steps[-1]
        named = tuple(get_effect(e) for e in cur.effects)
        remaining = [m for m in names if m not in cur.effects and m not in dropped
                     and compatible(named + (get_effect(m),))]
        if not remaining:
            break
        screened = []
        if cur.effects:
            first = {f["effect"]: f for f in first_fits(steps)}
            remaining, screened = _screen(forward, cur, remaining, first, n)
        fits = map_tasks(_cond_task, remaining, (forward, cur.effects, cur.values, bool(cur.effects)),
                         progress=progress, label=f"candidate effects, step {len(steps)}", workers=workers)
        ok = [f for f in fits if not f.get("skipped")]
        step_tried = fits + screened
        if not ok:
            steps.append(Step(cur.effects, cur.values, cur.chi2, cur.k, cur.model, "stop", 0.0, (), step_tried))
            break
        best = min(ok, key=lambda f: bic(f["chi2"], cur.k + f["k"], n))
        if not passes(cur.chi2, cur.k, best["chi2"], cur.k + best["k"], n):
            steps.append(Step(cur.effects, cur.values, cur.chi2, cur.k, cur.model, "stop", 0.0, (), step_tried))
            break
        effs = named + (get_effect(best["effect"]),)
        vals, chi = refit_joint(forward, effs, {**cur.values, **best["parameters"]})
        chi, v, s = forward.evaluate_set(effs, vals)
        new = Step(cur.effects + (best["effect"],), vals, chi, cur.k + best["k"], (v, s), best["effect"],
                   bic(cur.chi2, cur.k, n) - bic(chi, cur.k + best["k"], n), (), step_tried)
        steps.append(_drop_redundant(forward, new, n) if len(new.effects) > 1 else new)
        dropped |= set(steps[-1].dropped)           # a dropped effect is not offered again
    return steps


def first_fits(steps: list[Step]) -> list[dict]:
    """The first step's fits: every candidate alone (or skipped with its reason)."""
    return steps[1].tried if len(steps) > 1 else steps[0].tried
