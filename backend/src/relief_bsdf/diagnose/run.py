"""`relief diagnose`: locate the mismatch, name every missing physics, model it, refit, give intervals.

Pipeline
1. Baseline: the plate exactly as sample.toml states it, simulated by the one plate model
   (`forward.build_forward`: relief as measured on the front face, boundary tables by the
   fit's method, `--method`).  What sample.toml states (plate.absorption_per_mm) is in the
   baseline and held fixed: its effect is no candidate (listed as skipped, with the reason).
2. Locate: `mismatch.regions` / `mismatch.classify` on the noise-normalised baseline residual.
3. Candidates and selection: the stepwise search of `stepwise` (add the effect that gains most
   by BIC = chi^2 + k ln n, refit all named effects jointly, stop when no further effect passes
   the bar); an effect that does not apply, or that the plate engine cannot express yet, is
   listed in `candidates` with the reason instead of a number.
4. Closure: the chosen combination must explain the misfit: reach the noise up to the forward
   model's own stated accuracy (`stepwise.adequate`: chi^2 <= 1.2^2 n + 3 sqrt(2 n)), or remove
   at least EXPLAINED_SHARE = 1/2 of the baseline's misfit above the noise, (chi^2_0 - chi^2) /
   (chi^2_0 - n) >= 1/2 (then what remains is reported as an unexplained remainder).  The share
   was set on the seed-1 test cases (an absorption case on a 48 px relief whose `normals` model
   misses by rms 1.8 after the fit: 0.95 explained; absorption + stray light seen through tilt
   and polarisation only: 0.011), any value in 0.02 - 0.9 separating them; it is reported on
   seed 2 by the benchmark.  If even the best combination fails both, no effect is named as the
   cause (`effects` = ["none"]): the explanation says so, says where the unexplained residual
   lives (`mismatch.locate` on the best combination's residual) and which physics its shape
   resembles (`mismatch.SHAPE_PHYSICS`), and the best combination is reported as tried, not as
   found.
5. Intervals: 68 % intervals of every named parameter from the chi^2 curvature
   (`fitting.intervals`); a parameter the data cannot pin down is null with a note.
6. Report: diagnosis.json's document (formats.md schema: `effects` most important first, `effect` =
   effects[0], `parameters` of every named effect, `intervals`; `mismatch` entries say which
   named effect explains each region, `mismatch.attribute`); the job `jobs.run_diagnose` writes it
   and report.html, atomically.

Metric: the project's one metric, rms z = sqrt(chi^2 / n) (`fit.residual.rms_z`; 1 = fits to the noise).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.diagnose.effects import all_effects, get_effect
from relief_bsdf.diagnose.effects.relief_smoothing import derived as smoothing_derived
from relief_bsdf.diagnose.fitting import intervals as fit_intervals
from relief_bsdf.diagnose.forward import DEFAULT_METHOD, DiagnosisForward, build_forward
from relief_bsdf.diagnose.profile import profiling, stage
from relief_bsdf.diagnose.mismatch import SHAPE_PHYSICS, attribute, classify, locate, regions
from relief_bsdf.diagnose.report import shape_against_search
from relief_bsdf.diagnose.stepwise import (BIC_OVERWHELMING, CONSISTENCY_Z, MODEL_ACCURACY_RMS, adequate, alternatives,
                                           consistent_with_noise, first_fits, method_check, overwhelming_bar, passes,
                                           stepwise, steps_record)
from relief_bsdf.errors import InputError
from relief_bsdf.fit.residual import METRIC, metric_of_chi2
from relief_bsdf.criteria import BIC_MARGIN
from relief_bsdf.parallel import current_settings, parallel_settings
from relief_bsdf.plate import TableGrid
from relief_bsdf.parallel.memory import trim_heap
from relief_bsdf.plate.memory import ForwardMemory, MemoryPlan, job_memory_bytes, plan_processes
from relief_bsdf.progress import silent

__all__ = ["BIC_MARGIN", "BIC_OVERWHELMING", "CONSISTENCY_Z", "MODEL_ACCURACY_RMS", "Diagnosis", "candidate_names",
           "diagnosis",
           "explain", "select"]

EXPLAINED_SHARE = 0.5


def select(chi0: float, n: int, fits: list[dict]) -> tuple[str, list[dict], bool]:
    """One step of the selection (`stepwise.passes`) on candidates fitted against the baseline.

    `fits`: {effect, chi2, k, parameters} per candidate (skipped ones carry "skipped" and are
    ignored).  Returns (effect name or "none", candidates best first with score, consistent).
    """
    ln = math.log(max(n, 2))
    cands = [{"effect": "none", "chi2": chi0, "k": 0, "score": chi0, "parameters": {}}]
    for f in fits:
        if f.get("skipped"):
            continue
        cands.append({"effect": f["effect"], "chi2": f["chi2"], "k": f["k"], "score": f["chi2"] + f["k"] * ln,
                      "parameters": f["parameters"]})
    cands.sort(key=lambda c: c["score"])
    best = cands[0]
    if best["effect"] == "none" or not passes(chi0, 0, best["chi2"], best["k"], n):
        return "none", cands, consistent_with_noise(chi0, n)
    return best["effect"], cands, consistent_with_noise(chi0, n)


def closes(chi0: float, chi2: float, n: int) -> bool:
    """Does a model explain the baseline's misfit (module docstring, 4)?"""
    return adequate(chi2, n) or (chi0 > n and (chi0 - chi2) / (chi0 - n) >= EXPLAINED_SHARE)


def candidate_names(requested: list[str] | None) -> list[str]:
    """Every effect module's name, or the requested subset (InputError naming unknown ones)."""
    names = list(all_effects())
    if requested is None:
        return names
    unknown = [e for e in requested if e not in names]
    if unknown:
        raise InputError("--effects", f"unknown effect(s) {unknown}; choose from {sorted(names)}")
    return [e for e in names if e in requested]


def _where(mismatch: list, shapes: list, what: str = "largest misfit") -> str:
    where = ""
    if mismatch:
        m = mismatch[0]
        where = (f" The {what} ({m['share']:.0%} of it) is on the {m['side']} side at theta_i = "
                 f"{m['theta_i_deg']:g} deg, phi_s = {m['phi_s_deg']:g} deg, theta_s {m['theta_s_deg'][0]:g}-"
                 f"{m['theta_s_deg'][1]:g} deg ({m['sign']}).")
    if shapes and shapes[0]["explained"] > 0.3:
        word = shapes[0]["shape"].replace("_", " ")
        where += (f" Its shape is mostly {'an' if word[0] in 'aeiou' else 'a'} {word} "
                  f"({shapes[0]['explained']:.0%} of the misfit).")
    return where


def _resembles(shapes: list) -> str:
    good = [s for s in shapes if s["explained"] > 0.3][:2]
    if not good:
        return " Its shape matches none of the simple templates (offset, gain, shift, broadening, path loss)."
    return " It resembles " + "; or ".join(f"{SHAPE_PHYSICS[s['shape']]} ({s['explained']:.0%} of it)"
                                          for s in good) + "."


def _effects_words(effects: list[str], params: dict) -> str:
    parts = []
    for name in effects:
        e = get_effect(name)
        mine = {p.name: params[p.name] for p in e.params if p.name in params}
        parts.append(f"{name.replace('_', ' ')} ({e.physics}; {e.explain(mine)})")
    return "; ".join(parts)


def explain(effects: list[str], params: dict, fit: dict, located: tuple, unexplained: dict | None = None,
            remainder: dict | None = None, alike: list | None = None) -> str:
    """Plain-language account; `fit` = {rms0, rms1, n, chi0, consistent}, `located` = (mismatch, shapes);
    `unexplained` = {tried, rms_tried, mismatch, shapes} when even the best combination misses the noise;
    `remainder` = {mismatch, shapes} of what named effects leave beyond the noise; `alike` =
    `stepwise.alternatives` (candidates the recording cannot tell apart from a named effect)."""
    where = _where(*located)
    if unexplained is not None:
        tried = unexplained["tried"]
        best = (f"The best combination of candidates, {', '.join(tried)}, brings it only to "
                f"{unexplained['rms_tried']:.2f}, still short of the noise, so it is not named as the cause."
                if tried else "No candidate effect improves it by more than the bar.")
        return (f"The simulation of the plate as described misses the recording (metric, rms z {fit['rms0']:.2f})."
                f"{where} {best}{_where(unexplained['mismatch'], [], 'largest unexplained residual')}"
                f"{_resembles(unexplained['shapes'])} The cause may be outside the candidates tried "
                f"or in the relief's own model.")
    if effects == ["none"]:
        within = ("within its noise" if fit["consistent"] else
                  f"within its noise and the forward model's stated accuracy (rms {MODEL_ACCURACY_RMS:g}), and no "
                  f"candidate passes the bar")
        return (f"The simulation of the plate as described agrees with the recording to {within} "
                f"(metric, rms z {fit['rms0']:.2f}, chi2 = {fit['chi0']:.0f} for {fit['n']} "
                f"rows), so no missing physics is named.")
    lead = ("The best explanation is" if len(effects) == 1
            else f"{len(effects)} effects are present, most important first:")
    rest = ""
    if remainder is not None:
        rest = (f" A remainder beyond the noise and the model's stated accuracy is left unexplained."
                f"{_where(remainder['mismatch'], [], 'largest remaining residual')}{_resembles(remainder['shapes'])}")
    weak = "".join(f" The recording barely tells {a['named'].replace('_', ' ')} from "
                   f"{a['alternative'].replace('_', ' ')} ({get_effect(a['alternative']).explain(a['alternative_parameters'])}"
                   f" fits almost as well, BIC {a['bic_difference']:.1f} worse; a difference under {BIC_MARGIN:g} "
                   f"is not strong evidence): treat the choice between them as open."
                   for a in (alike or []) if "correlation" not in a)
    weak += "".join(f" {a['named'].replace('_', ' ')} and {a['alternative'].replace('_', ' ')} trade against each "
                    f"other on these rows (fitted correlation {a['correlation']:+.2f}): "
                    + (f"{a['named'].replace('_', ' ')} is needed, but the rows do not separate "
                       f"{a['alternative'].replace('_', ' ')} from it, so it is not named." if a["separated"] else
                       f"the rows do not separate them; {a['named'].replace('_', ' ')} is kept, and "
                       f"{a['alternative'].replace('_', ' ')} "
                       f"({get_effect(a['alternative']).explain(a['alternative_parameters'])}) would stand in for it "
                       f"(BIC {a['bic_difference']:.1f} worse): treat the choice between them as open.")
                    for a in (alike or []) if "correlation" in a)
    return (f"The baseline simulation misses the recording (metric, rms z {fit['rms0']:.2f}).{where} {lead} "
            f"{_effects_words(effects, params)}. Modelling {'it' if len(effects) == 1 else 'them together'} "
            f"brings the metric down to {fit['rms1']:.2f}.{rest}{weak}")


def _rounded(d: dict) -> dict:
    return {k: round(float(v), 6) for k, v in d.items()}


def _candidate_list(fits: list[dict], chi0: float, n: int) -> list[dict]:
    """Every effect tried alone against the baseline (the first step), best first; screened-out and
    skipped ones last."""
    ln = math.log(max(n, 2))
    out = [{"effect": "none", "rms_after": round(metric_of_chi2(chi0, n), 6), "score": round(chi0, 3),
            "parameters": {}}]
    out += [{"effect": f["effect"], "rms_after": round(metric_of_chi2(f["chi2"], n), 6),
             "score": round(f["chi2"] + f["k"] * ln, 3), "parameters": _rounded(f["parameters"])}
            for f in fits if "chi2" in f]
    out.sort(key=lambda c: c["score"])
    out += [{"effect": f["effect"], "rms_after": None, "score": None, "parameters": {},
             "screened": (f"not fitted: the best linear change toward it (score test, stepwise) gains chi2 "
                          f"{f['screened']:.3g}, "
                          + (f"less than {f['outgained_by']} gained when fitted, by more than the BIC margin"
                             if f.get("outgained_by") else "short of the selection's bar"))}
            for f in fits if "screened" in f]
    out += [{"effect": f["effect"], "rms_after": None, "score": None, "parameters": {}, "skipped": f["skipped"]}
            for f in fits if f.get("skipped")]
    return out


def _selection_doc(n: int, steps: list, closed: bool) -> dict:
    path = [{"effects": list(s.effects) or ["none"], "added": s.added, "chi2": round(s.chi2, 3), "k": s.k,
             "bic_gain": round(s.gain, 3), "dropped": list(s.dropped)} for s in steps if s.added != "stop"]
    return {"criterion": (f"stepwise: add the candidate with the lowest BIC = chi2 + k ln n given the effects named "
                          f"so far, refit all jointly; it is named if it beats the current model by more than "
                          f"{BIC_MARGIN:g} (chi2 divided by the larger model's reduced chi2 where that exceeds 1: "
                          f"QBIC) and the current model has chi2 > {MODEL_ACCURACY_RMS:g}^2 n + "
                          f"{CONSISTENCY_Z:g} sqrt(2n) (noise plus the forward model's stated accuracy), or by more "
                          f"than max({BIC_OVERWHELMING:g}, {CONSISTENCY_Z:g} sqrt(2n)) = {overwhelming_bar(n):.1f} "
                          f"whatever its chi2; stop when none passes. The named set must then reach that bound or "
                          f"remove at least {EXPLAINED_SHARE:g} of the baseline's misfit above n, else nothing is "
                          f"named"),
            "n_rows": n, "chi2_baseline": round(steps[0].chi2, 3),
            "consistent_with_noise": bool(consistent_with_noise(steps[0].chi2, n)),
            "best_combination_explains": bool(closed), "path": path}


def _known(forward: DiagnosisForward, fits: list[dict]) -> list[dict]:
    """Held-fixed effects as skipped candidates (they were never offered to the search)."""
    have = {f["effect"] for f in fits}
    return [{"effect": name, "skipped": why} for name, why in forward.context.known if name not in have]


def _result(forward: DiagnosisForward, steps: list, located: tuple, n_glass: float) -> tuple[dict, tuple]:
    """diagnosis.json's dict and the (values, sigma) of the chosen model."""
    n = len(forward.rows)
    rows = forward.rows
    final, base = steps[-1], steps[0]
    rms0 = metric_of_chi2(base.chi2, n)
    closed = closes(base.chi2, final.chi2, n)
    chain = [("none",) + base.model] + [(s.added,) + s.model for s in steps[1:] if s.added != "stop"]
    mismatch = attribute(rows, located[0], chain)
    unexplained = remainder = None
    if final.effects and closed:
        effects, params, (v1, s1), rms1 = list(final.effects), final.values, final.model, metric_of_chi2(final.chi2, n)
        with stage("intervals"):
            ivals, notes = fit_intervals(forward, tuple(get_effect(e) for e in final.effects), final.values,
                                         final.jacobian)
        if "relief_smoothing" in effects:     # the slope ratio the fitted smoothing implies, beside its filter
            extra, extra_iv = smoothing_derived(forward.context, params, ivals)
            params, ivals = {**params, **extra}, {**ivals, **extra_iv}
        if not adequate(final.chi2, n):
            remainder = {"mismatch": locate(rows, v1, s1, n_glass=n_glass),
                         "shapes": classify(rows, v1, s1, n_glass=n_glass)}
    else:
        effects, params, (v1, s1), rms1, ivals, notes = ["none"], {}, base.model, rms0, {}, {}
        if not adequate(base.chi2, n):
            v, s = final.model
            unexplained = {"tried": list(final.effects), "rms_tried": metric_of_chi2(final.chi2, n),
                           "mismatch": locate(rows, v, s, n_glass=n_glass),
                           "shapes": classify(rows, v, s, n_glass=n_glass)}
    fits = first_fits(steps)
    record, stop = steps_record(steps, n)
    alike = alternatives(steps, n) if effects != ["none"] else []
    ctx = forward.context
    facts = {"rms0": rms0, "rms1": rms1, "n": n, "chi0": base.chi2, "consistent": consistent_with_noise(base.chi2, n)}
    result = {
        "format": "relief-diagnosis/1", "metric": METRIC,
        "rms_before": round(rms0, 6), "rms_after": round(rms1, 6),
        "effect": effects[0], "parameters": _rounded(params),
        "mismatch": mismatch,
        "candidates": _candidate_list(fits + _known(forward, fits), base.chi2, n),
        "explanation": explain(effects, params, facts, ([e for e, _ in located[0]], located[1]), unexplained,
                               remainder, alike),
        "effects": effects, "alternatives": alike, "intervals": ivals, "interval_notes": notes,
        "shape": located[1][:3],
        "selection": _selection_doc(n, steps, closed),
        "steps": record, "stop": stop, "method_check": method_check(steps, n, ctx.method),
        "forward_model": {"engine": "deterministic", "method": ctx.method, "samples": ctx.samples, "seed": ctx.seed,
                          "rough_face_model": f"boundary tables of the measured relief by method {ctx.method}",
                          "method_reason": ctx.method_reason, "evaluations": forward.evaluations,
                          "grid": (forward.grid or TableGrid()).describe()},
    }
    left = (remainder or unexplained or {}).get("shapes") or []
    result["explanation"] += shape_against_search(left, record, effects)      # the shapes never contradict the steps
    if unexplained is not None:
        result["unexplained"] = {"best_combination": unexplained["tried"],
                                 "rms_best_combination": round(unexplained["rms_tried"], 6),
                                 "residual": unexplained["mismatch"], "shape": unexplained["shapes"][:3],
                                 "resembles": [SHAPE_PHYSICS[s["shape"]] for s in unexplained["shapes"][:2]
                                               if s["explained"] > 0.3]}
    return result, (v1, s1)


def _memory_plan(memory: ForwardMemory, workers: int | None) -> MemoryPlan:
    """How many workers the search may run with the job's memory (`plate.memory.plan_processes`: one
    evaluation holds what the baseline left held), this process's owner held to its share; `workers`
    (the caller's) is the most.  A plan that does not fit even alone is said in a warning."""
    most = workers if workers is not None else current_settings().worker_count()
    plan = plan_processes(memory.budget_bytes, memory.held_bytes, most)
    memory.budget_bytes = plan.main_budget_bytes
    memory.refresh(None)
    trim_heap()          # what the baseline's stage freed goes back before the workers allocate (parallel.memory)
    if not plan.fits:
        import warnings
        warnings.warn(f"one evaluation of the forward model holds {plan.evaluation_bytes / 1e9:.1f} GB, more than the "
                      f"job's memory ({plan.total_bytes / 1e9:.1f} GB, --memory-gb) allows beside it: going on in one "
                      "process, keeping no more than one evaluation", RuntimeWarning, stacklevel=3)
    return plan


@dataclass
class Diagnosis:
    """What a diagnosis found: `doc`, diagnosis.json's document (formats.md schema), and the arrays its
    report draws: the recording's `rows`, the baseline's (values, model sigma) and the chosen model's."""

    doc: dict
    rows: Any
    baseline: tuple
    chosen: tuple


def diagnosis(sample_path: str | Path, progress=None, *, method: str = DEFAULT_METHOD, photons: int = 200_000,
              seed: int = 0, effects: list[str] | None = None, workers: int | None = None,
              sectors: str = "auto") -> Diagnosis:
    """The whole diagnosis of one sample (module doc, 1-5); writes nothing (the job, `jobs.run_diagnose`,
    writes diagnosis.json and report.html).

    `photons`: Monte-Carlo samples per incidence of a sampling boundary method (ray, normals).
    `sectors`: the plate grid's `TableGrid.sectors` ("always": the inside sector tables for every
    ray-traced relief; the screens still go without, `DiagnosisForward.screening`).
    """
    from relief_bsdf.parallel.memory import small_pages
    small_pages()           # here and in its workers (parallel.memory)
    progress = progress or silent
    names = candidate_names(effects)
    memory = ForwardMemory(job_memory_bytes())         # the job's one memory owner: everything the forward keeps
    with memory.active(), profiling() as profile:
        with stage("baseline"):
            forward, sample = build_forward(sample_path, method, photons, seed, sectors=sectors)
            rows = forward.rows
            v0, s0 = forward.baseline()
            plan = _memory_plan(memory, workers)
        with stage("report"):
            n_mid = float(np.real(sample.plate.index.n(float(np.median(rows.wavelength_nm)))))
            located = (regions(rows, v0, s0, n_glass=n_mid), classify(rows, v0, s0, n_glass=n_mid))
        # the plan in force for every task the search starts (a pool anywhere below takes its worker count)
        with parallel_settings(workers=plan.workers, worker_memory_bytes=plan.worker_budget_bytes):
            with stage("search"):
                steps = stepwise(forward, names, progress, plan.workers)
            with stage("report"):
                result, (v1, s1) = _result(forward, steps, located, n_mid)
    result["memory"] = {**plan.describe(), "main_process": memory.report()}
    result["profile"] = profile.doc()          # where the time went (diagnose.profile)
    return Diagnosis(result, rows, (v0, s0), (v1, s1))
