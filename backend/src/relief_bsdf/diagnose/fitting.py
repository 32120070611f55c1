"""Fit one candidate effect's parameters by least censored chi^2 on the plate model.

Search (per parameter, within its bounds or the effect's data-driven bracket): a coarse
grid that always contains the neutral value (the baseline, so a fit never ends worse than
no effect), then a bounded Brent refinement between the best grid point's neighbours
(scipy.optimize.minimize_scalar).  A log-scale parameter (a width ~ 1 / value) is searched
on log10 and compared with its neutral value.  Several parameters: one coordinate pass
per parameter, then the first again in a narrowed interval.  Cheap effects (tables
re-used) get a finer grid than effects that re-derive the boundary tables.

An effect the plate model cannot express for this sample (an InputError of the plate or a
method's RequestError, such as Kirchhoff's sampling limits on this relief) comes back as
skipped, with the reason, never as a number.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize

from relief_bsdf.diagnose.effects import Effect, Param
from relief_bsdf.errors import InputError

GRID_CHEAP, REFINE_CHEAP = 9, 10
GRID_TABLES, REFINE_TABLES = 5, 5


def _fit_1d(f, lo: float, hi: float, grid: int, refine: int, extra: tuple = ()) -> tuple[float, float]:
    """Grid (plus `extra` points) then bounded Brent between the best grid point's neighbours."""
    xs = np.unique(np.concatenate([np.linspace(lo, hi, grid), np.asarray(extra, float)]))
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


def _fit_param(cost, p: Param, lo: float, hi: float, grid: int, refine: int) -> float:
    """Best value of one parameter (the others held) for cost(value); the neutral value unless beaten.

    A parameter the data do not constrain (a flat cost, e.g. the source polarisation seen through
    depolarising tables) stays neutral instead of taking whichever grid end comes first.
    """
    c0 = cost(p.neutral)
    if p.log_scale:
        u, cu = _fit_1d(lambda u: cost(10.0**u), np.log10(lo), np.log10(hi), grid, refine)
        x, cx = 10.0**u, cu
    else:
        x, cx = _fit_1d(cost, lo, hi, grid, refine, (p.neutral,) if lo <= p.neutral <= hi else ())
    return x if cx < c0 - 1e-9 * max(1.0, abs(c0)) else p.neutral


def _search(forward, effect: Effect) -> dict:
    grid, refine = (GRID_CHEAP, REFINE_CHEAP) if effect.cheap else (GRID_TABLES, REFINE_TABLES)
    bounds = {p.name: (p.lower, p.upper) for p in effect.params}
    if effect.bracket is not None:
        bounds.update(effect.bracket(forward.context, forward))
    values = effect.neutral
    if len(effect.params) > 1:        # coupled parameters: coarser passes, one more for the first
        grid, refine = max(3, grid - 1), max(2, refine - 2)
    order = list(effect.params) + ([effect.params[0]] if len(effect.params) > 1 else [])
    for j, p in enumerate(order):
        lo, hi = bounds[p.name]
        if j == len(effect.params) and values[p.name] != p.neutral:   # second pass: narrowed interval
            lo, hi = max(lo, 0.5 * values[p.name]), min(hi, 1.5 * values[p.name])
        held = dict(values)

        def cost(x, name=p.name, held=held):
            return forward.evaluate(effect, {**held, name: float(x)})[0]
        values[p.name] = float(_fit_param(cost, p, min(lo, hi), max(lo, hi), grid, refine))
    return values


def fit_effect(forward, effect: Effect) -> dict:
    """{effect, parameters, chi2, k, values, model_sigma} or {effect, skipped: reason}."""
    reason = effect.skip_reason(forward.context)
    if reason:
        return {"effect": effect.name, "skipped": reason}
    try:
        values = _search(forward, effect) if effect.params else {}
        c, v, s = forward.evaluate(effect, values)
    except InputError as e:
        return {"effect": effect.name, "skipped": str(e)}
    return {"effect": effect.name, "parameters": {k: float(x) for k, x in values.items()}, "chi2": c,
            "k": effect.k, "values": v, "model_sigma": s}
