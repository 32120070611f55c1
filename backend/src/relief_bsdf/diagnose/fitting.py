"""Fit candidate effects' parameters by least censored chi^2 on the plate model; their 68 % intervals.

One effect (`fit_effect`), possibly on top of effects already named and held at their values
(`fixed`, the conditional fit of a stepwise step): per parameter, within its bounds or the
effect's data-driven bracket, a coarse grid that always contains the neutral value (the
model without the effect, so a fit never ends worse than no effect), then a bounded Brent
refinement between the best grid point's neighbours (scipy.optimize.minimize_scalar).  A
log-scale parameter (a width ~ 1 / value) is searched on log10 and compared with its neutral
value; a parameter with a search coordinate (`Effect.coordinate`: the relief filter, searched on the
rms slope it leaves) on that coordinate.  Several parameters: one coordinate pass per parameter, then the first again in a
narrowed interval.  Cheap effects (tables re-used, evaluations under a second) get a finer
grid than `budgeted` ones (that re-derive the boundary tables, or are slow: `Effect.slow`); a
budgeted effect with one parameter is refined by Gauss-Newton steps on its residuals (`polish`,
the effects already named held) instead of Brent (`_polished_fit`).

Several effects together (`refit_joint`): coordinate descent over every parameter of the
set, starting from the values found so far (each effect's own fit), each coordinate searched
in an interval around its current value by a short grid + Brent; at most `JOINT_PASSES`
passes, stopping when a pass gains less than one unit of chi^2 (or, for a single parameter, when
it ends inside its window: the next pass would search the same curve).  Budgeted: a `budgeted`
coordinate gets a 3-point grid and 3 Brent steps, a cheap one 5 and 6.  A grid's points and a
Jacobian's differences are independent: they are handed to the forward model first
(`DiagnosisForward.prefetch`), which evaluates them together on the diagnosis's worker processes.

Intervals (`intervals`): the curvature of chi^2 at the best point in the Gauss-Newton form,
widened for correlated residuals (fit.covariance, one definition with `relief fit`).  With
the residual vector r = (y - m) / s (s^2 = sigma_recording^2 + sigma_model^2, the s of the
chi^2 the selection uses) and its Jacobian J (central differences), cov = (J^T J)^-1 is the
covariance for Delta chi^2 = 1 (Press et al., Numerical Recipes 15.6); when the best model
still misses the noise (chi^2 / (n - k) > 1) it is inflated by that reduced chi^2 (Birge
ratio), and each parameter's variance is raised to the Newey-West (HAC) estimate when that is
larger: a forward model's error runs with the angle along a scan, and rows whose residuals
are correlated carry less information than their number; the forward model's stated per-side
level accuracy (plate.uncertainty.FORWARD_LEVEL_SD, measured against the independent photon
Monte Carlo) is marginalised as a nuisance, which widens what acts as a level (absorption in T,
the index or the polarisation in R).  A parameter is *not determined*
(no interval, a note instead) when moving it across its whole search range changes chi^2
by less than 1 (the rows do not respond to it, e.g. a source polarisation seen through
depolarising tables), when J^T J of the responding parameters is singular (their effects
cannot be told apart), or when its 1-sigma reaches past its whole search range.  An
interval is clipped to the parameter's bounds.

An effect the plate model cannot express for this sample (an InputError of the plate or a
method's RequestError, such as Kirchhoff's sampling limits on this relief) comes back as
skipped, with the reason, never as a number; an effect whose value sample.toml states is
skipped as held fixed (`ReliefContext.known`).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from relief_bsdf.diagnose.effects import Effect, Param
from relief_bsdf.diagnose.profile import stage
from relief_bsdf.errors import InputError
from relief_bsdf.fit import gauss_newton
from relief_bsdf.fit.covariance import level_nuisance, parameter_covariance, scans_of, shared_columns
from relief_bsdf.fit.residual import misfit_sigma, signed_residuals

GRID_CHEAP, REFINE_CHEAP = 9, 10
GRID_TABLES, REFINE_TABLES = 5, 5
JOINT_PASSES = 2
POLISH_STEPS = 3


def _fit_1d(f, lo: float, hi: float, grid: int, refine: int, extra: tuple = (), prefetch=None) -> tuple[float, float]:
    """Grid (plus `extra` points) then bounded Brent between the best grid point's neighbours;
    `prefetch(xs)`, when given, is told the grid first (its points are independent)."""
    xs = np.unique(np.concatenate([np.linspace(lo, hi, grid), np.asarray(extra, float)]))
    xs = xs[(xs >= lo) & (xs <= hi)]
    if prefetch is not None:
        prefetch(list(xs))
    ys = [f(x) for x in xs]
    k = int(np.argmin(ys))
    best_x, best_y = float(xs[k]), float(ys[k])
    a, b = xs[max(k - 1, 0)], xs[min(k + 1, len(xs) - 1)]
    if refine > 0 and b > a:
        r = optimize.minimize_scalar(f, bounds=(a, b), method="bounded",
                                     options={"maxiter": refine, "xatol": (hi - lo) * 1e-3})
        if r.fun < best_y:
            best_x, best_y = float(r.x), float(r.fun)
    return best_x, best_y


def _fit_param(cost, p: Param, lo: float, hi: float, grid: int, refine: int, start: float | None = None,
               coord: tuple | None = None, prefetch=None) -> float:
    """Best value of one parameter (the others held) for cost(value); `start` (default the neutral
    value) unless beaten.  `coord` = (to_u, from_u): search on the effect's monotone coordinate u
    (`Effect.coordinate`) instead of the value.  `prefetch(values)`: told the start and the grid's
    values before they are asked for (`DiagnosisForward.prefetch`).

    A parameter the data do not constrain (a flat cost, e.g. the source polarisation seen through
    depolarising tables) stays where it is instead of taking whichever grid end comes first.
    """
    x0 = p.neutral if start is None else float(start)
    if coord is not None:
        to_u, from_u = coord
    elif p.log_scale:
        to_u, from_u = math.log10, (lambda u: 10.0**u)
    else:
        to_u = from_u = None
    ask = None if prefetch is None else (lambda us: prefetch([x0] + [from_u(u) if from_u else u for u in us]))
    if coord is not None:
        ua, ub = sorted((to_u(lo), to_u(hi)))
        u, cx = _fit_1d(lambda u: cost(from_u(u)), ua, ub, grid, refine,
                        tuple(to_u(v) for v in (p.neutral, x0) if lo <= v <= hi), ask)
        x = from_u(u)
    elif p.log_scale:
        u, cu = _fit_1d(lambda u: cost(from_u(u)), np.log10(lo), np.log10(hi), grid, refine,
                        (math.log10(x0),) if x0 > 0 else (), ask)
        x, cx = from_u(u), cu
    else:
        extra = tuple(v for v in (p.neutral, x0) if lo <= v <= hi)
        x, cx = _fit_1d(cost, lo, hi, grid, refine, extra, ask)
    c0 = cost(x0)
    return x if cx < c0 - 1e-9 * max(1.0, abs(c0)) else x0


def search_bounds(forward, effect: Effect) -> dict:
    """{param: (lo, hi)}: the parameter bounds, narrowed by the effect's data-driven bracket."""
    bounds = {p.name: (p.lower, p.upper) for p in effect.params}
    if effect.bracket is not None:
        bounds.update(effect.bracket(forward.context, forward))
    return {k: (min(lo, hi), max(lo, hi)) for k, (lo, hi) in bounds.items()}


def _search(forward, effect: Effect, fixed: tuple = (), fixed_values: dict | None = None,
            coarse: bool = False, start: dict | None = None) -> dict:
    grid, refine = (GRID_TABLES, REFINE_TABLES) if effect.budgeted else (GRID_CHEAP, REFINE_CHEAP)
    if coarse and effect.budgeted:           # a later stepwise step: the costly search is budgeted
        grid, refine = 4, 3
    if _polished_fit(effect):                # the grid only: Gauss-Newton refines it (`fit_effect`)
        refine = 0
    bounds = search_bounds(forward, effect)
    held_all = dict(fixed_values or {})
    effects = tuple(fixed) + (effect,)
    values = effect.neutral
    starts = {k: float(v) for k, v in (start or {}).items() if k in values}
    if len(effect.params) > 1:        # coupled parameters: coarser passes, one more for the first
        grid, refine = max(3, grid - 1), max(2, refine - 2)
    order = list(effect.params) + ([effect.params[0]] if len(effect.params) > 1 else [])
    coords = effect.coordinate(forward.context) if effect.coordinate else {}
    for j, p in enumerate(order):
        lo, hi = bounds[p.name]
        if j == len(effect.params) and values[p.name] != p.neutral:   # second pass: narrowed interval
            lo, hi = max(lo, 0.5 * values[p.name]), min(hi, 1.5 * values[p.name])
        held = {**held_all, **values}

        def cost(x, name=p.name, held=held):
            return forward.evaluate_set(effects, {**held, name: float(x)})[0]
        x0 = starts.pop(p.name, None)
        if x0 is not None:
            x0 = min(max(x0, min(lo, hi)), max(lo, hi))
        values[p.name] = float(_fit_param(cost, p, min(lo, hi), max(lo, hi), grid, refine, start=x0,
                                          coord=coords.get(p.name), prefetch=_prefetch(forward, effects, held, p)))
    return values


def _prefetch(forward, effects: tuple, held: dict, p: Param):
    """prefetch(xs) for `_fit_param`: the points `held` with p at each x, evaluated together where the
    forward model can (`DiagnosisForward.prefetch`); None for a forward model without it."""
    if not hasattr(forward, "prefetch"):
        return None
    return lambda xs: forward.prefetch(effects, [{**held, p.name: float(x)} for x in xs])


def why_skipped(forward, effect: Effect) -> str | None:
    """Why `effect` is not fitted for this sample: held fixed by sample.toml, or its own skip reason."""
    return dict(forward.context.known).get(effect.name) or effect.skip_reason(forward.context)


def fit_effect(forward, effect: Effect, fixed: tuple = (), fixed_values: dict | None = None,
               coarse: bool = False, start: dict | None = None) -> dict:
    """{effect, parameters, chi2, k, values, model_sigma} or {effect, skipped: reason}.

    `fixed`/`fixed_values`: effects already named, held at their values (chi2 and values are then
    those of all of them together, k counts this effect's parameters only).  `coarse`: a later stepwise
    step's conditional fit (the search budgeted, the polish rough: it ranks candidates, the joint polish
    follows).  `start`: values the search starts from besides the neutral ones (a residual's signature,
    `stepwise`).  A fit that ends at its null value (`at_null`) is refitted from starts spread over the
    range (`_restart`) before it is judged; the entry then carries `restart` (the points tried, the best
    chi^2 among them and the null's chi^2).
    """
    reason = why_skipped(forward, effect)
    if reason:
        return {"effect": effect.name, "skipped": reason}
    held = dict(fixed_values or {})
    if effect.forms and not any(k in held for form in effect.forms for k in form):
        return _best_form(forward, effect, fixed, held, coarse, start)
    effects = tuple(fixed) + (effect,)
    jacobian = None
    restart = None
    try:
        screen = _screening(forward, effect)
        if screen is not forward:
            values, jacobian, restart = _screened_fit(forward, screen, effect, fixed, fixed_values, coarse, start)
        else:
            values = _search(forward, effect, fixed, fixed_values, coarse, start) if effect.params else {}
            if _polished_fit(effect):
                values, jacobian = _polish_own(forward, effect, effects, fixed_values, values, coarse)
            if effect.params and at_null(effect, values) and not _form_acts(effect, fixed_values):
                with stage("null_restarts"):
                    values, jac, restart = _restart(forward, effect, effects, fixed_values, values, coarse)
                jacobian = jac if jac is not None else jacobian
        c, v, s = forward.evaluate_set(effects, {**(fixed_values or {}), **values})
    except InputError as e:
        return {"effect": effect.name, "skipped": str(e)}
    out = {"effect": effect.name, "parameters": {k: float(x) for k, x in values.items()}, "chi2": c,
           "k": effect.k, "values": v, "model_sigma": s}
    if restart is not None:
        out["restart"] = restart
    if start:
        out["start"] = {k: float(x) for k, x in start.items()}
    if jacobian is not None and not fixed:
        out["jacobian"] = jacobian          # the whole model's: `stepwise` names it without a second polish
    return out


class OnWorkers:
    """The screening forward model `screen` of `full` (`DiagnosisForward.screening(effect)`), whose independent
    points (a grid, a Jacobian's differences, the restarts' starts) are evaluated together on the worker
    processes that `full` keeps (`parallel.kept_workers`: the diagnosis's pool, whose context is the full
    model; each worker makes the same screening model from it, `_screen_task`).  Everything else is the
    screening model's own.  Without kept workers it is the screening model."""

    def __init__(self, screen, full, effect: Effect | None):
        self._screen, self._full, self._effect = screen, full, effect

    def __getattr__(self, name):
        return getattr(self._screen, name)

    def prefetch(self, effects, points: list[dict], workers: int | None = None) -> None:
        from relief_bsdf.diagnose.forward import _memo_key
        from relief_bsdf.diagnose.profile import note_evaluations
        from relief_bsdf.parallel import has_kept_workers, map_tasks
        screen = self._screen
        todo: dict = {}
        for values in points:
            key, vals = _memo_key(effects, values)
            if key is not None and key not in screen._memo:
                todo.setdefault(key, vals)
        if len(todo) < 2 or not has_kept_workers(self._full, workers):
            return
        names = tuple(e.name for e in effects)
        me = self._effect.name if self._effect is not None else None
        got = map_tasks(_screen_task, [(me, names, todo[k]) for k in todo], self._full, label="evaluations",
                        workers=workers)
        for key, result in zip(todo, got):
            screen._remember(key, result)
        screen.evaluations += len(todo)
        note_evaluations(screen.grid, len(todo))


def _screen_task(forward, task: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(values, model sigma) of the named effects at `vals` on the screening model of the worker's context
    (`OnWorkers.prefetch`)."""
    from relief_bsdf.diagnose.effects import get_effect
    me, names, vals = task
    screen = forward.screening(get_effect(me) if me else None)
    _, v, s = screen.evaluate_set(tuple(get_effect(n) for n in names), vals)
    return v, s


def _screening(forward, effect: Effect):
    """The forward model a candidate's search runs on: the screening one (`DiagnosisForward.screening`: no
    inside sector tables, the intensity-only loop unless the effect acts through the polarisation) where it
    differs from `forward`, else `forward` (a stand-in forward model has none)."""
    if not effect.params or not hasattr(forward, "screening"):
        return forward
    try:
        return forward.screening(effect)
    except InputError:
        return forward


def _screened_fit(forward, screen, effect: Effect, fixed: tuple, fixed_values: dict | None, coarse: bool,
                  start: dict | None) -> tuple[dict, np.ndarray | None, dict | None]:
    """(values, jacobian, restart record) of a candidate searched on the screening forward model and
    finished on the full one.

    The search (grid, Brent, and the restarts of a fit that ends at its null value) only has to find the
    optimum's basin, and the screening model's optimum lies within a few of the full model's
    finite-difference steps of the full one's (they differ by the inside sector tables and the Stokes loop
    only: the trapped light's azimuthal and polarisation detail, not the lobe the parameters move): there
    one evaluation costs a plate solve on the screening grid, 0.2-3 s where a full one, whose solver the
    table changes of other candidates have evicted, costs 14-19 s.  From that point Gauss-Newton steps on
    the full model (`polish`, the effect's parameters moving, the named effects held) reach the full
    model's optimum; only they and the final point are full evaluations (about 5 for one parameter,
    against 19 for the grid and Brent of a cheap effect).  A search that ends at the null value on the
    screening model is the null value on the full one too (no polish: the bound's one-sided slope is
    zero there).  The full model's chi^2 at the answer is never worse than at the null value (the model of
    the effects held, memoised): else the null value stands.  The chi^2 a candidate is judged on is
    always the full model's.  An InputError of the cheaper loop (a polarised source named) falls back to
    the search on the full model."""
    effects = tuple(fixed) + (effect,)
    held = dict(fixed_values or {})
    restart = None
    before = screen.evaluations
    screen = OnWorkers(screen, forward, effect)
    try:
        values = _search(screen, effect, fixed, fixed_values, coarse, start)
        if at_null(effect, values) and not _form_acts(effect, fixed_values):
            with stage("null_restarts"):
                values, _, restart = _restart(screen, effect, effects, fixed_values, values, coarse)
            restart["forward"] = "screening"
    except InputError:
        values = _search(forward, effect, fixed, fixed_values, coarse, start)
    if screen is not forward:
        forward.evaluations += screen.evaluations - before     # the diagnosis's count holds every evaluation
    if at_null(effect, values) and not _form_acts(effect, fixed_values):
        return values, None, restart
    values, jacobian = _polish_own(forward, effect, effects, fixed_values, values, coarse)
    if not _form_acts(effect, fixed_values):
        c_null = (forward.evaluate_set(tuple(fixed), held)[0] if fixed else forward.evaluate_set((), {})[0])
        if forward.evaluate_set(effects, {**held, **values})[0] > c_null:
            return effect.neutral, None, restart
    return values, jacobian, restart


def _form_acts(effect: Effect, held: dict | None) -> bool:
    """Does the effect's form (`Effect.forms`) act by itself at the neutral parameter values (a form other
    than the first: the noise removal of relief_smoothing)?  Its null value is then not 'no effect'."""
    return bool(effect.forms) and any(held and k in held and held[k] != v for k, v in effect.forms[0].items())


def _best_form(forward, effect: Effect, fixed: tuple, held: dict, coarse: bool, start: dict | None) -> dict:
    """The effect fitted in each of its forms (`Effect.forms`, held fixed like a named effect's values): the
    forms have the same parameters, so the information criterion (chi^2 + k ln n) compares their chi^2;
    the first form (the default: the paper's Gaussian for relief_smoothing) is kept unless another is
    lower by more than BIC_MARGIN (where the rows do not tell the forms apart, the default stands).  The
    form's values join `parameters` (held, not fitted: k is the effect's); `forms` records each form's chi^2."""
    from relief_bsdf.criteria import BIC_MARGIN
    fits = [fit_effect(forward, effect, fixed, {**held, **form}, coarse, start) for form in effect.forms]
    ok = [(f, form) for f, form in zip(fits, effect.forms) if "chi2" in f]
    if not ok:
        return fits[0]
    best, form = ok[0]
    for f, fm in ok[1:]:
        if f["chi2"] < best["chi2"] - BIC_MARGIN:
            best, form = f, fm
    best["parameters"] = {**best["parameters"], **{k: float(v) for k, v in form.items()}}
    best["forms"] = [{**{k: float(v) for k, v in fm.items()}, "chi2": round(float(f["chi2"]), 3)} for f, fm in ok]
    return best


def _polish_own(forward, effect: Effect, effects: tuple, fixed_values: dict | None, values: dict,
                coarse: bool) -> tuple[dict, np.ndarray | None]:
    names = tuple(p.name for p in effect.params)
    done, _, jacobian = polish(forward, effects, {**(fixed_values or {}), **values}, free=names, rough=coarse)
    return {k: done[k] for k in names}, jacobian


RESTART_FRACTIONS = tuple(float(t) for t in np.geomspace(0.01, 0.5, 8))   # 1 % to half the range, x 1.75


def _amounts(effect: Effect) -> list[Param]:
    """The parameters that measure how much of the effect there is: neutral at a bound (0 /mm, alpha 0)."""
    return [p for p in effect.params if p.neutral in (p.lower, p.upper)]


def at_null(effect: Effect, values: dict) -> bool:
    """Did a fit end where it started, at its null value: every amount parameter (`_amounts`) at its
    neutral value (an effect without such a parameter, a tilt or a scale, has no null bound)?"""
    amounts = _amounts(effect)
    return bool(amounts) and all(abs(values[p.name] - p.neutral) <= 1e-12 * max(1.0, p.upper - p.lower)
                                 for p in amounts)


def _restart(forward, effect: Effect, effects: tuple, fixed_values: dict | None, values: dict,
             coarse: bool) -> tuple[dict, np.ndarray | None, dict]:
    """Refit an effect that ended at its null value from starts spread over its range.

    A strongly non-linear effect may gain nothing at the grid's first points and much between them
    (back-face roughness: the lobe of a Beckmann alpha 0.03 lies between the grid's 0 and 0.125, and
    the Gauss-Newton steps from the bound alpha = 0 see a zero one-sided slope there).  Starts: every
    amount parameter at RESTART_FRACTIONS of its range from the neutral bound together (the others at
    the values found), evaluated together; from the best of them, if it beats the null, the search
    again (`_search` with that start) and Gauss-Newton steps on the effect's parameters (`polish`).  ({values}, jacobian or None,
    record {points, fractions, chi2 of each, chi2 at the null})."""
    held = dict(fixed_values or {})
    amounts = _amounts(effect)
    bounds = search_bounds(forward, effect)
    pts = []
    for t in RESTART_FRACTIONS:
        pt = dict(values)
        for p in amounts:
            lo, hi = bounds[p.name]
            end = hi if p.neutral <= lo else lo
            pt[p.name] = p.neutral + t * (end - p.neutral)
        pts.append(pt)
    if hasattr(forward, "prefetch"):
        forward.prefetch(effects, [{**held, **values}] + [{**held, **pt} for pt in pts])
    c0 = forward.evaluate_set(effects, {**held, **values})[0]
    cs = [forward.evaluate_set(effects, {**held, **pt})[0] for pt in pts]
    rec = {"fractions": list(RESTART_FRACTIONS), "chi2": [round(float(c), 3) for c in cs],
           "chi2_null": round(float(c0), 3)}
    j = int(np.argmin(cs)) if cs else 0
    if not cs or not cs[j] < c0 - 1e-9 * max(1.0, abs(c0)):
        rec["moved"] = False
        return values, None, rec
    best = _search(forward, effect, tuple(effects[:-1]), held, True, pts[j])
    if forward.evaluate_set(effects, {**held, **best})[0] > cs[j]:
        best = dict(pts[j])
    best, jac = _polish_own(forward, effect, effects, held, best, coarse)     # the search's short grids end near it
    rec["moved"] = True
    return best, jac, rec


def _polished_fit(effect: Effect) -> bool:
    """Is the effect's own fit refined by Gauss-Newton (`polish`) instead of Brent after its grid?  A
    budgeted effect with one parameter: each evaluation derives tables (seconds), and the 1-D Brent
    steps on chi^2 alone see one number per evaluation where Gauss-Newton sees every row's residual;
    on a concealed relief scale + absorption case five Brent steps (12 s) gained nothing over the
    grid's best point, and the polish that followed did the work."""
    return effect.budgeted and len(effect.params) == 1


def refit_joint(forward, effects: tuple, values: dict) -> tuple[dict, float]:
    """(values, chi2) of every parameter of `effects` refitted jointly from `values` (module docstring)."""
    values = dict(values)
    params = [(e, p) for e in effects for p in e.params]
    best = forward.evaluate_set(effects, values)[0]
    if not params:
        return values, best
    bounds = {}
    coords = {}
    for e in effects:
        bounds.update(search_bounds(forward, e))
        coords.update(e.coordinate(forward.context) if e.coordinate else {})
    for _ in range(JOINT_PASSES):
        start = best
        for e, p in params:
            lo, hi = bounds[p.name]
            x = values[p.name]
            w = 0.25 * (hi - lo)
            a, b = max(lo, x - w), min(hi, x + w)
            if p.log_scale and x > 0:
                a, b = max(lo, x / 2.0), min(hi, 2.0 * x)
            coord = coords.get(p.name)
            if coord is not None:           # the window a quarter of the coordinate's range around x
                to_u, from_u = coord
                ulo, uhi = sorted((to_u(lo), to_u(hi)))
                wu = 0.25 * (uhi - ulo)
                a, b = sorted((from_u(max(ulo, to_u(x) - wu)), from_u(min(uhi, to_u(x) + wu))))
            grid, refine = (3, 3) if e.budgeted else (5, 6)

            def cost(v, name=p.name):
                return forward.evaluate_set(effects, {**values, name: float(v)})[0]
            values[p.name] = float(_fit_param(cost, p, a, b, grid, refine, start=x, coord=coord,
                                              prefetch=_prefetch(forward, effects, dict(values), p)))
            best = forward.evaluate_set(effects, values)[0]
            edge = (values[p.name] <= a and a > lo) or (values[p.name] >= b and b < hi)
        if start - best < 1.0 or (len(params) == 1 and not edge):
            break           # one parameter inside its window: another pass would search the same curve
    return values, best


STEP_FRACTION = 0.01
STEP_FRACTION_SAMPLED = 0.03


def _step(p: Param, x: float, lo: float, hi: float, sampled: bool = False) -> float:
    """Finite-difference step: 1 % of the search range, 3 % for an effect whose evaluation re-derives
    sampled boundary tables (`sampled`: not `Effect.cheap`), at most 10 % of the value (never 0).

    Why wider for re-derived tables: the two points of a difference trace two relief geometries (or
    incidences, indices), so their tables' Monte-Carlo noise cancels only in part (common random
    numbers) and adds to the column; the column's squared norm is then too long by up to the noise's
    sum(sigma_model^2 / s^2) / (2 h^2) (two independent draws: an upper bound), which falls as 1 / h^2.
    Measured on a concealed relief scale + absorption case at its optimum (central differences of the
    diagnosis forward model at five steps): the scale column's |J|^2 was 8.4e4 / 6.9e4 /
    5.2e4 / 4.8e4 / 5.0e4 at steps of 0.5 / 1 / 2 / 3 / 4 % of the range, the bound 1.8e5 / 4.5e4 /
    1.1e4 / 5.0e3 / 2.8e3: at 3 % the bound is a tenth of the column, and the column stops shrinking (curvature bias, O(h^2), is not yet
    seen).  A column too long shortens every Gauss-Newton step and narrows the intervals."""
    h = (STEP_FRACTION_SAMPLED if sampled else STEP_FRACTION) * (hi - lo)
    if x != 0.0:
        h = min(h, max(0.1 * abs(x), 1e-3 * (hi - lo)))
    return h


def _moving(effects: tuple, free: tuple | None = None) -> list[tuple]:
    """[(param, sampled)] of the parameters of `effects` that move (`free` names, default all), in
    order; sampled: its effect re-derives boundary tables (`_step`)."""
    return [(p, not e.cheap) for e in effects for p in e.params if free is None or p.name in free]


def _bounds(forward, effects: tuple) -> dict:
    out = {}
    for e in effects:
        out.update(search_bounds(forward, e))
    return out


def _jacobian(forward, effects: tuple, values: dict, s: np.ndarray, bounds: dict,
              moving: list | None = None) -> np.ndarray:
    """J[:, j] = -(d model / d p_j) / s: the residuals' (y - m) / s derivative at fixed s, central
    differences with the steps of `_step` (one-sided at a bound), for the parameters `moving`
    (`_moving`, default every parameter of `effects`)."""
    moving = _moving(effects) if moving is None else moving
    J = np.zeros((len(forward.rows), len(moving)))
    ends = []
    for p, sampled in moving:
        x = values[p.name]
        h = _step(p, x, *bounds[p.name], sampled)
        ends.append((min(x + h, p.upper), max(x - h, p.lower)))
    if hasattr(forward, "prefetch"):       # the 2k points are independent
        forward.prefetch(effects, [{**values, p.name: x} for (p, _), e in zip(moving, ends) for x in e])
    for j, ((p, _), (xp, xm)) in enumerate(zip(moving, ends)):
        mp = forward.evaluate_set(effects, {**values, p.name: xp})[1]
        mm = forward.evaluate_set(effects, {**values, p.name: xm})[1]
        J[:, j] = -(mp - mm) / (xp - xm) / s
    return J


def polish(forward, effects: tuple, values: dict, steps: int = POLISH_STEPS,
           free: tuple | None = None, rough: bool = False) -> tuple[dict, float, np.ndarray | None]:
    """(values, chi^2, J): the named effects' least-chi^2 point near `values` by Gauss-Newton.

    The coordinate search (`refit_joint`) ends where its short grids and few Brent steps stop,
    which on a correlated pair is not the optimum: on a concealed tilt + blur case it stopped at
    tilt -2.68 deg with chi^2 227 while -2.58 gave 217.  The
    steps are fit.gauss_newton.polish's (the one definition with `relief fit`): the linearised
    least squares J d = -r (r the censored residuals of the chi^2, `fit.residual.signed_residuals`;
    J central differences, `_jacobian`), clipped to the parameters' bounds, kept only when they
    lower chi^2, with chord steps and stretches; converged within a tenth of a finite-difference
    step or within the 68 % interval.  J is the Jacobian of the intervals (at a point within that
    distance of the answer), or None when the steps ran out first.  Rank-deficient J (a ridge, a
    parameter the rows do not see): the minimum-norm step, so an undetermined parameter does not
    move.  `free`: the names of the parameters that move (default all; the others are held at
    `values`, as a conditional fit holds the effects already named, `fit_effect`).  `rough`: the
    optimum is needed roughly (a conditional fit at a later step, `fit_effect`'s `coarse`): a chord step
    that says converged is believed (fit.gauss_newton, `trust_chord`; no Jacobian then)."""
    moving = _moving(effects, free)
    values = dict(values)
    chi, _, _ = forward.evaluate_set(effects, values)
    if not moving:
        return values, chi, None
    params = [p for p, _ in moving]
    rows = forward.rows
    bounds = _bounds(forward, effects)

    def at(x: np.ndarray) -> dict:
        return {**values, **{p.name: float(xj) for p, xj in zip(params, x)}}

    def residuals(x: np.ndarray) -> tuple[float, np.ndarray]:
        c, v, s0 = forward.evaluate_set(effects, at(x))
        return c, signed_residuals(rows.bsdf_sr, v, misfit_sigma(rows, s0))

    def jacobian(x: np.ndarray, central: bool) -> np.ndarray:
        vals = at(x)
        return _jacobian(forward, effects, vals, misfit_sigma(rows, forward.evaluate_set(effects, vals)[2]), bounds,
                         moving)
    x0 = np.array([values[p.name] for p in params])
    h = np.array([_step(p, values[p.name], *bounds[p.name], sampled) for p, sampled in moving])
    ahead = None if not hasattr(forward, "prefetch") else (
        lambda xs: forward.prefetch(effects, [at(x) for x in xs]))     # a step and its stretch, together
    done = gauss_newton.polish(residuals, jacobian, x0, np.array([p.lower for p in params]),
                               np.array([p.upper for p in params]), h, steps, ahead=ahead, trust_chord=rough)
    return at(done.x), done.f, done.jacobian


def intervals(forward, effects: tuple, values: dict, jacobian: np.ndarray | None = None) -> tuple[dict, dict]:
    """({param: [lo, hi] or None}, {param: note}) at the best point (module docstring); `jacobian`:
    `polish`'s, when it handed one over (else computed here)."""
    params = [p for e in effects for p in e.params]
    if not params:
        return {}, {}
    rows = forward.rows
    _, v0, s0 = forward.evaluate_set(effects, values)
    s = misfit_sigma(rows, s0)
    bounds = _bounds(forward, effects)
    J = _jacobian(forward, effects, values, s, bounds) if jacobian is None else jacobian
    ranges = np.array([bounds[p.name][1] - bounds[p.name][0] for p in params])
    live = np.sum(J**2, axis=0) * ranges**2 >= 1.0   # moving it across its whole range changes chi^2 by >= 1
    nuisance, text = level_nuisance(rows, v0, s)
    at = getattr(forward, "model_deviations_at", None)
    shared = None if at is None else shared_columns(at(effects, values), s)
    c = parameter_covariance(J, signed_residuals(rows.bsdf_sr, v0, s), scans_of(rows), live, nuisance, text, shared,
                             np.divide(s0**2, s**2, out=np.zeros_like(s), where=s > 0))
    cov = c.cov
    out, notes = {}, {}
    for j, p in enumerate(params):
        lo, hi = bounds[p.name]
        if not live[j] or not np.isfinite(cov[j, j]) or cov[j, j] <= 0:
            why = ("the recording does not respond to it (across its whole range chi^2 changes by less than 1)"
                   if not live[j] else "its effect on the rows cannot be told apart from the other parameters'")
            out[p.name] = None
            notes[p.name] = f"not determined: {why}"
            continue
        sd = float(math.sqrt(cov[j, j]))
        if sd >= (hi - lo):
            out[p.name] = None
            notes[p.name] = f"not determined: its 1-sigma ({sd:.3g}) exceeds its whole search range [{lo:g}, {hi:g}]"
            continue
        x = values[p.name]
        out[p.name] = [round(max(x - sd, p.lower), 6), round(min(x + sd, p.upper), 6)]
        why = c.note(j)
        if why:
            notes[p.name] = why
    return out, notes

