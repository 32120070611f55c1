"""Relief optimisation against a plate recording (paper sec. 3, steps 1-6).

Loop: parameters p = (height_scale s, filter_sigma_um g) -> surface.operations.scale_and_filter
(step 6) -> the Experiment's relief face gets the processed relief; its boundary tables of the
chosen method for light from outside and inside (step 2, plate.faces.ReliefFace, cached)
-> plate simulation on the recording's rows (step 3, `plate.simulate`, deterministic) -> the search's
log-chi residuals (step 4, `residual.LogChiMetric`) -> damped Gauss-Newton of those residuals with a
line search (`_gauss_newton`, step 5) until the metric (`residual.rms_z`, the project's one metric,
reported for every evaluation beside the search's value) falls below `threshold`, the step or the
gain become negligible, or `max_iter` distinct evaluations are spent.

Physics of the relief face: by default `auto` (plate.choice), the relief's own physics, chosen
once on the relief as read (ray tracing with inter-reflections for reliefs rough on the
wavelength scale, Kirchhoff / Rayleigh-Rice for smooth ones) and then fixed for every
evaluation; any `methods.registry` name may be given instead, e.g. the fast surrogate
"microfacet+dw".  Sampling methods (ray) use the same seed at every evaluation (common random
numbers), so the optimiser sees a smooth objective rather than Monte-Carlo jitter.

Two forward models, one answer.  The search (steps 2-3 of `fit_relief`) steers on the search model
(`Forward.search_model`: a quarter of the relief face's rays, the same seed, and for an unpolarised
source the plate's loop on intensities), which costs a demo evaluation about 3.2 CPU-s where the
model of record costs 7.6.  From the criterion's two points on, everything is evaluated on the model
of record: the polish, the response surface, the answer, its intervals and the ridge probe; what is
estimated and reported is its (docs/decisions/022).

Identifiability.  In geometric optics the height scale and the Gaussian filter both act on
slopes only, and for a Gaussian random relief the slope distribution stays Gaussian under
filtering: the two parameters then slide along a ridge of equal rms slope.  Heights become
visible in the wave regime (the coherent specular part), and slope-distribution SHAPE on
non-Gaussian reliefs.  The fit therefore reports what the recording determines:
- the filter is kept only when the recording asks for it: the scale-only fit (g = 0) and the
  two-parameter fit are compared by the project's one information criterion (criteria:
  BIC = chi^2 + k ln n with chi^2 = n search^2 of the log-chi search objective, margin 10; the chi^2
  divided by the two-parameter fit's reduced chi^2 when it exceeds 1, QBIC: a filter that only bends the model
  towards its own systematic error is not evidence), and without that evidence the answer is
  the simplest point of the ridge, g = 0;
- the estimate is the likelihood's optimum: the log metric steers the search from far away, then
  a few Gauss-Newton steps on the noise-weighted residuals (y - m) / S (S^2 = sigma_recording^2
  + sigma_model^2, the diagnosis's misfit) bring it near (`_polish`); the log metric's weights hold
  the measured values, so its optimum moves with the noise (on the demo 2.7 half-widths in the filter);
  a response surface finishes it (`_smoothed`, fit.response_surface): those residuals regressed
  linearly over a design of +-2 standard deviations, whose optimum does not sit in the bumps the
  tables' Monte-Carlo noise puts into chi^2 on the scale of the interval;
- 68 % intervals from the curvature of that chi^2 at the optimum (cov = (J^T J)^-1 with the
  regression's Jacobian, Delta chi^2 = 1; fit.covariance), inflated by the reduced chi^2 when the
  model misses the noise and raised to the Newey-West variance where the residuals run correlated
  along the scans; the correlation of (ln s, g); a ridge (moving along equal rms slope costs less
  than the criterion's bar) and non-identifiable parameters are named in plain `warnings`;
- bounds on the scale (`scale_bounds`) and the filter (`max_filter_um`) are the user's.

Checkpoints: OUT/checkpoint.json holds every evaluated parameter set and its metric; a
rerun replays them (no recomputation), and since the optimiser is deterministic it retraces
the same path and ends with the same result as an uninterrupted run.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.fit import gauss_newton
from relief_bsdf.fit.covariance import level_nuisance, parameter_covariance, scans_of, shared_columns
from relief_bsdf.fit.residual import DEFAULT_METRIC, METRIC, LogChiMetric, rms_z, signed_residuals
from relief_bsdf.fit.response_surface import Surface, smoothed_optimum
from relief_bsdf.criteria import BIC_MARGIN, bic_gain, overdispersion
from relief_bsdf.io.recording import sigma_with_fallback
from relief_bsdf.fit.forward import Forward, process_relief
from relief_bsdf.plate import TableGrid
from relief_bsdf.progress import Progress, silent
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import rms_height_and_slope

FIT_FORMAT = "relief-fit/1"
ALGORITHM = ("damped Gauss-Newton (Levenberg-Marquardt) with a line search on the log-chi search residuals "
             "(scale alone, then scale and filter along the ridge of equal rms slope), then Gauss-Newton steps "
             "on the likelihood's noise-weighted residuals and the optimum of a response surface (a linear "
             "regression of those residuals over a design of +-2 standard deviations)")
NOISE_METRIC = 1.2          # a fit "reaches the noise" at a metric (rms z, residual.rms_z) <= this
POLISH_STEPS = 6            # kept Gauss-Newton steps of `_polish` (chord steps count)


def relief_rms(relief: Relief) -> tuple[float, float]:
    """(rms height, rms slope magnitude) of the levelled relief: surface.stats' one definition."""
    h, m = rms_height_and_slope(relief)
    return float(h), float(m)


class _Stop(Exception):
    pass


def _key(p: np.ndarray) -> str:
    return f"{float(p[0]):.10g},{float(p[1]):.10g}"


@dataclass
class FitResult:
    """The fitted relief operation and what the recording determines about it.

    intervals: 68 % interval per parameter ([lo, hi]; None where the data cannot pin it down);
    correlation: of (ln height_scale, filter_sigma_um^2) at the 2-parameter optimum (None when
        J^T J there is singular);
    filter_needed / bic_gain: whether the recording asks for the filter besides the scale
        (criteria: BIC gain of the 2-parameter fit over the scale-only fit > BIC_MARGIN);
    ridge: the two parameters slide along a valley of equal rms slope (`_ridge_probe`);
    warnings: plain sentences for the user (non-identifiable parameters, a ridge, the noise).
    """

    height_scale: float
    filter_sigma_um: float
    rms_before: float
    rms_after: float
    iterations: list
    metric: str
    stopped: str
    seconds: float
    intervals: dict = field(default_factory=dict)
    correlation: float | None = None
    filter_needed: bool = True
    bic_gain: float | None = None
    ridge: bool = False
    warnings: list = field(default_factory=list)
    computed: int = 0                 # forward evaluations computed in this run (not replayed)
    surface: dict = field(default_factory=dict)   # the response surface's design (`_smoothed`)
    search: str = ""                  # the search objective's definition (each evaluation's `search`)
    computed_by_model: dict = field(default_factory=dict)   # `computed` by model: "record", "search"
    stage_seconds: dict = field(default_factory=dict)       # wall seconds per stage of `fit_relief`

    def to_json(self, extra: dict | None = None) -> dict:
        d = {"format": FIT_FORMAT, "algorithm": ALGORITHM, "metric": self.metric, "rms_before": self.rms_before,
             "rms_after": self.rms_after,
             "parameters": {"height_scale": self.height_scale, "filter_sigma_um": self.filter_sigma_um},
             "intervals": self.intervals,
             "correlation": None if self.correlation is None else
             {"names": ["ln height_scale", "filter_sigma_um^2"], "matrix": [[1.0, self.correlation],
                                                                             [self.correlation, 1.0]]},
             "identifiability": {"filter_needed": self.filter_needed, "bic_gain_of_filter": self.bic_gain,
                                 "ridge": self.ridge,
                                 "criterion": "BIC = chi2 / c + k ln n, chi2 = n search^2 (the log-chi search "
                                 "objective), c = "
                                 "max(1, reduced chi2 of the two-parameter fit) (QBIC); the filter is kept when "
                                 f"it lowers the BIC by more than {BIC_MARGIN:g}",
                                 "estimate": "the likelihood's optimum: the search on the log-chi objective, then "
                                             "up to "
                                             f"{POLISH_STEPS} Gauss-Newton steps on the noise-weighted residuals "
                                             "(measured - simulated) / S, S^2 = sigma^2 + the simulation's own "
                                             "sigma^2, then the optimum of a linear regression of those "
                                             "residuals over a design of +-2 standard deviations around it "
                                             "(fit.response_surface: the tables' noise bends chi^2 on the "
                                             "scale of the interval)",
                                 "response_surface": self.surface,
                                 "interval_method": "cov = (J^T J)^-1 from the Jacobian of those residuals "
                                                    "(the regression's, over the design around the optimum), "
                                                    "68 % = Delta chi2 of 1, "
                                                    "inflated by the reduced chi2 when it exceeds 1 and raised per "
                                                    "parameter to the Newey-West variance when the residuals run "
                                                    "correlated along the scans, plus the forward model's "
                                                    "stated per-side level accuracy marginalised as a nuisance "
                                                    "(fit.covariance)"},
             "search_objective": self.search,
             "warnings": self.warnings, "iterations": self.iterations, "evaluations_computed": self.computed,
             "evaluations_by_model": self.computed_by_model, "stage_seconds": self.stage_seconds,
             "stopped": self.stopped,
             "seconds": self.seconds}
        d.update(extra or {})
        return d


@dataclass(frozen=True)
class FitSettings:
    """How the optimiser runs: the residual `metric`, stop at metric <= `threshold`, at most
    `max_iter` evaluations for the search (a few more for the intervals), the Gaussian filter
    bounded by `max_filter_um` (None: 20 pixel pitches), the height scale by `scale_bounds`."""

    metric: LogChiMetric = DEFAULT_METRIC
    threshold: float = 0.0
    max_iter: int = 60
    max_filter_um: float | None = None
    scale_bounds: tuple = (0.1, 10.0)

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.scale_bounds)
        if not (0 < lo < 1 < hi < float("inf")):
            raise InputError("--scale-bounds", f"need 0 < min < 1 < max, got {lo:g}, {hi:g}")
        if self.max_filter_um is not None and not (self.max_filter_um > 0):
            raise InputError("--max-filter-um", f"must be > 0, got {self.max_filter_um:g}")


class _Objective:
    """The forward model's residuals against the recording at (s, g): cached, checkpointed, reported.

    Budget and log count distinct parameter points: the first call at a point in this run is
    logged in `iterations` (a checkpointed point replayed from disk too, so a resumed run retraces
    the same path and spends the same budget); repeated calls at a point already visited (a
    Jacobian's base point) are free.  Residuals are the metric's normalised r_k, so chi^2 = sum
    r_k^2 = n metric^2 (the log-chi metric is an rms z).  `limit`: the most distinct points before
    _Budget.
    """

    def __init__(self, forward, measured, sigma, settings: FitSettings, cache: dict, save, progress, on_eval,
                 model: str = "record", iterations: list | None = None, counter: list | None = None):
        self.forward, self.measured, self.sigma, self.settings = forward, measured, sigma, settings
        self.cache, self.save, self.progress, self.on_eval = cache, save, progress, on_eval
        # `model`: "record" (the forward model of record) or "search" (its search model, `Forward.search_model`):
        # its evaluations are logged with that name in the (shared) `iterations` and checkpointed under a prefix
        self.model = model
        self._prefix = "" if model == "record" else f"{model}:"
        self.iterations: list[dict] = [] if iterations is None else iterations
        self._seen: dict[str, np.ndarray] = {}
        self._metric: dict[str, float] = {}
        self._sim: dict[str, np.ndarray] = {}
        self.new_evals = 0
        self._counter = [0] if counter is None else counter      # new evaluations of every model (`on_eval`)
        self.n = int(np.size(measured))
        self.limit: int | None = None
        # the likelihood's recording sigma (unknown ones: io.recording's fallback), fixed for the run
        self._likelihood_sigma = sigma_with_fallback(np.asarray(measured, float), sigma)

    def _model_sigma(self, sim: np.ndarray) -> np.ndarray | None:
        """The simulation's own 1-sigma at these values (the forward model's relative sigma, computed
        once, times the values; NaN where no table carries a sigma: 0), or None without one."""
        rel = getattr(self.forward, "model_rel_sigma", None)
        return None if rel is None else np.nan_to_num(rel() * np.abs(sim))

    def chi2(self, m: float) -> float:
        return self.n * float(m) ** 2

    def residuals(self, s: float, g: float, stop_at_threshold: bool = True) -> np.ndarray:
        key = _key(np.array([s, g]))
        if key in self._seen:
            return self._seen[key]
        if self.limit is not None and len(self.iterations) >= self.limit:
            raise _Budget
        stored = self._prefix + key
        if stored not in self.cache:
            self.cache[stored] = [float(v) for v in np.asarray(self.forward.simulate(s, g), float)]
            self.new_evals += 1
            self._counter[0] += 1
            self.save(self.cache)
            if self.on_eval:
                self.on_eval(self._counter[0])
        sim = np.asarray(self.cache[stored])
        self._sim[key] = sim
        ms = self._model_sigma(sim)
        r = self.settings.metric.residuals(sim, self.measured, self.sigma, ms)
        self._seen[key] = r
        m = float(np.sqrt(np.mean(r**2))) if r.size else 0.0
        z = rms_z(self.measured, self._likelihood_sigma, sim, ms)        # the metric (fit.residual)
        self._metric[key] = z
        self.iterations.append({"parameters": {"height_scale": s, "filter_sigma_um": g}, "rms": z, "search": m,
                                "model": self.model})
        total = self.settings.max_iter
        self.progress(min(len(self.iterations), total), total, f"metric {z:.4g} at scale {s:.4g}, filter {g:.4g} um"
                      + ("" if self.model == "record" else f" ({self.model} model)"))
        if stop_at_threshold and z <= self.settings.threshold:
            raise _Stop
        return r


    def likelihood_residuals(self, s: float, g: float) -> np.ndarray:
        """z with z @ z = the noise-weighted chi^2 of the likelihood at (s, g): (measured - simulated) / S,
        S^2 = sigma_recording^2 + sigma_model^2 (sigma unknown: io.recording's documented fallback),
        readings clipped at zero censored (fit.residual.signed_residuals: the diagnosis's misfit).
        The simulation is the objective's own (cached, checkpointed)."""
        sim, S = self.simulated_and_sigma(s, g)
        return signed_residuals(np.asarray(self.measured, float), sim, S)

    def simulated_and_sigma(self, s: float, g: float) -> tuple[np.ndarray, np.ndarray]:
        """(simulated values, the likelihood's S) at (s, g) (`likelihood_residuals`)."""
        self.residuals(s, g, stop_at_threshold=False)
        sim = np.asarray(self._sim[_key(np.array([s, g]))], float)
        ms = self._model_sigma(sim)
        S = self._likelihood_sigma if ms is None else np.sqrt(self._likelihood_sigma**2 + ms**2)
        return sim, S

    def __call__(self, s: float, g: float, stop_at_threshold: bool = True) -> float:
        """The search objective (rms of the log-chi residuals) at (s, g)."""
        r = self.residuals(s, g, stop_at_threshold)
        return float(np.sqrt(np.mean(r**2))) if r.size else 0.0

    def metric(self, s: float, g: float) -> float:
        """The metric (fit.residual.rms_z) at (s, g)."""
        self.residuals(s, g, stop_at_threshold=False)
        return self._metric[_key(np.array([s, g]))]

    def best(self, only_unfiltered: bool = False) -> dict:
        """The evaluation with the lowest search objective (`search`)."""
        its = [d for d in self.iterations if d["model"] == self.model
               and (not only_unfiltered or d["parameters"]["filter_sigma_um"] == 0.0)]
        return min(its, key=lambda d: d["search"])


class _Budget(Exception):
    pass


def _ridge_scan(pitch_um: float, gmax: float) -> list[float]:
    """Filter widths (um) tried along the valley of equal rms slope before the joint search: 1, 2, 4, ...
    pixel pitches up to the bound.  At g = 0 the filter's derivative (in w = g^2) is that of its
    finest scales only, often below the table noise: a Gauss-Newton step from there is blind to
    where the filter acts, so the joint search starts from the best of a log grid instead (the
    filter's scale unknown over decades; the scale's first-order effect, the rms slope, held)."""
    out, g = [], float(pitch_um)
    while g <= gmax * (1 + 1e-9):
        out.append(g)
        g *= 2.0
    return out


def _slope_ratio_fn(relief: Relief) -> Callable[[float], float]:
    """g -> m(g) / m(0), the rms slope left after a Gaussian filter of g um (memoised)."""
    m0 = relief_rms(relief)[1] or 1.0
    memo: dict[float, float] = {}

    def ratio(g: float) -> float:
        gk = round(g, 12)
        if gk not in memo:
            memo[gk] = (relief_rms(process_relief(relief, 1.0, g))[1] / m0) if g > 0 else 1.0
        return memo[gk] or 1.0
    return ratio


@dataclass(frozen=True)
class _Coords:
    """Fit coordinates x = (ln s[, w = g^2 in um^2]) with their bounds and finite-difference steps.

    The filter enters as w = g^2: a Gaussian filter multiplies the height spectrum by
    exp(-2 pi^2 g^2 f^2), so every plate quantity is smooth in g^2 and has zero derivative in g
    at g = 0, where a gradient search in g would never leave the unfiltered relief.

    `ratio` (g -> m(g) / m(0), the rms slope a filter leaves, `_slope_ratio_fn`): the search's
    coordinates x = (ln(s m(g) / m(0)), w) instead: the first is the log of the processed relief's
    rms slope over the file's, so moving w alone keeps the slopes (the lobe width, which the scale
    alone sets in geometric optics) and changes only what the filter does besides: the valley of
    equal rms slope, along which a search in (ln s, w) must zigzag, lies along an axis.  Only for
    the search: the intervals and the polish work in (ln s, w)."""

    with_filter: bool
    lower: np.ndarray
    upper: np.ndarray
    step: np.ndarray
    ratio: Callable[[float], float] | None = None
    ln_s_bounds: tuple = (-np.inf, np.inf)

    @classmethod
    def make(cls, settings: FitSettings, with_filter: bool, gmax: float, pitch_um: float,
             ratio: Callable[[float], float] | None = None) -> "_Coords":
        lo, hi = (float(np.log(b)) for b in settings.scale_bounds)
        if with_filter:
            lo_x = lo + (float(np.log(ratio(gmax))) if ratio is not None else 0.0)
            return cls(True, np.array([lo_x, 0.0]), np.array([hi, gmax**2]),
                       np.array([0.005, max(0.25 * pitch_um, 0.01) ** 2]), ratio, (lo, hi))
        return cls(False, np.array([lo]), np.array([hi]), np.array([0.005]), None, (lo, hi))

    def sg(self, x: np.ndarray) -> tuple[float, float]:
        x = np.clip(x, self.lower, self.upper)
        if not self.with_filter:
            return float(np.exp(x[0])), 0.0
        g = float(np.sqrt(x[1]))
        ln_s = float(x[0]) - (float(np.log(self.ratio(g))) if self.ratio is not None else 0.0)
        return float(np.exp(np.clip(ln_s, *self.ln_s_bounds))), g

    def x(self, s: float, g: float) -> np.ndarray:
        if not self.with_filter:
            return np.array([np.log(s)], float)
        return np.array([np.log(s) + (np.log(self.ratio(g)) if self.ratio is not None else 0.0), g * g], float)


def _jacobian(obj: _Objective, c: _Coords, x: np.ndarray, stop_at_threshold: bool = True,
              central: bool = True, likelihood: bool = False) -> np.ndarray:
    """d r / d x by central differences (one-sided inward at a bound), or forward differences
    (`central` False: one evaluation per parameter, for the search's steps); a point already visited
    (the base point) is the objective's memo, free of budget.  `likelihood`: of the likelihood's
    residuals z (`_Objective.likelihood_residuals`) instead of the metric's."""
    def at(xx: np.ndarray) -> np.ndarray:
        if likelihood:
            return obj.likelihood_residuals(*c.sg(xx))
        return obj.residuals(*c.sg(xx), stop_at_threshold=stop_at_threshold)
    cols = []
    for j, h in enumerate(c.step):
        xp, xm = x.copy(), x.copy()
        if central:
            xp[j] = min(x[j] + h, c.upper[j])
            xm[j] = max(x[j] - h, c.lower[j])
        elif x[j] + h <= c.upper[j]:
            xp[j] = x[j] + h
        else:
            xm[j] = x[j] - h
        if xp[j] - xm[j] <= 0:
            cols.append(np.zeros(obj.n))
            continue
        cols.append((at(xp) - at(xm)) / (xp[j] - xm[j]))
    return np.stack(cols, axis=1)


def _gauss_newton(obj: _Objective, c: _Coords, x0: np.ndarray, budget: int, max_stretch: int = 3) -> None:
    """Damped Gauss-Newton (Levenberg-Marquardt) of the normalised residuals with a line search,
    within `budget` new distinct points; the best point is read from obj.iterations.

    Each iteration: the Jacobian J by forward differences (`_jacobian`, one point per parameter),
    the step d solving (J^T J + mu diag(J^T J)) d = -J^T r (Marquardt 1963), projected into the
    bounds; then a line search along d: the full step, doubled while the chi^2 keeps falling (up to
    `max_stretch` times: the residuals of a plate are far from linear in the parameters, and a GN
    step from a distant start is typically too short), or shortened (`BACKTRACK`) when it rises,
    after which mu grows tenfold.  Converged when the accepted step is below one finite-difference step in
    every coordinate (the objective is not resolved finer) or the chi^2 gain is below 1e-4
    relative.  Deterministic: the same path for the same inputs (resumable from a checkpoint)."""
    obj.limit = len(obj.iterations) + max(int(budget), 0)
    lo, hi = c.lower, c.upper
    x = np.clip(np.asarray(x0, float), lo, hi)
    mu = 1e-3
    try:
        r = obj.residuals(*c.sg(x))
        f = float(r @ r)
        while True:
            J = _jacobian(obj, c, x, central=False)
            A, b = J.T @ J, -J.T @ r
            moved = False
            for _ in range(3):                                  # raise the damping if the line search fails
                d = np.linalg.lstsq(A + mu * np.diag(np.maximum(np.diag(A), 1e-12)), b, rcond=None)[0]
                x_new, f_new, r_new = _line_search(obj, c, x, d, f, max_stretch)
                if f_new < f:
                    moved = True
                    break
                mu *= 10.0
            if not moved:
                return
            step, gain = np.abs(x_new - x), (f - f_new) / max(f, 1e-300)
            x, f, r = x_new, f_new, r_new
            mu = max(mu / 3.0, 1e-6)
            if np.all(step < c.step) or gain < 1e-4:
                return
    except _Budget:
        pass
    finally:
        obj.limit = None


BACKTRACK = (0.3, 0.1, 0.03, 0.01)


def _line_search(obj: _Objective, c: _Coords, x: np.ndarray, d: np.ndarray, f: float, max_stretch: int):
    """Best of x + t d (projected into the bounds) for t = 1, 2, 4, ... while improving, or the
    first improving t of BACKTRACK when t = 1 does not improve (a Gauss-Newton step can overshoot
    by orders of magnitude where the residuals bend, e.g. the filter's effect on a specular
    peak); returns (x, chi^2, residuals) of the best, or (x, f, None)."""
    def at(t: float):
        xt = np.clip(x + t * d, c.lower, c.upper)
        rt = obj.residuals(*c.sg(xt))
        return xt, float(rt @ rt), rt
    best = (x, f, None)
    t = 1.0
    cand = at(t)
    if cand[1] < f:
        best = cand
        for _ in range(max_stretch):
            t *= 2.0
            nxt = at(t)
            if nxt[1] >= best[1] or np.allclose(nxt[0], best[0]):
                break
            best = nxt
        return best
    for t in BACKTRACK:
        cand = at(t)
        if cand[1] < f:
            return cand
    return best


def _polish(obj: _Objective, c: _Coords, s: float, g: float,
            steps: int = POLISH_STEPS) -> tuple[float, float, np.ndarray | None]:
    """The likelihood's optimum near (s, g): Gauss-Newton steps of the noise-weighted residuals z
    (`_Objective.likelihood_residuals`) in (ln s[, g^2]) by fit.gauss_newton.polish (forward
    differences while far off, then central ones, chord steps and stretches; converged within a
    tenth of a finite-difference step or within the 68 % interval), at most `steps` kept steps.
    Returns (s, g, J): J the central Jacobian at a point within that distance of the answer (the
    intervals' Jacobian), or None when the steps ran out first.  The search minimises the log
    metric, whose weights hold the measurement itself (its noise enters them) and which is a search
    device, not the likelihood: on the demo the log metric's optimum sat 2.7 half-widths off the true
    filter, the polished one 0.8."""
    def residuals(x: np.ndarray) -> tuple[float, np.ndarray]:
        z = obj.likelihood_residuals(*c.sg(x))
        return float(z @ z), z

    def jacobian(x: np.ndarray, central: bool) -> np.ndarray:
        return _jacobian(obj, c, x, central=central, likelihood=True)
    done = gauss_newton.polish(residuals, jacobian, c.x(s, g), c.lower, c.upper, c.step, steps, central=False)
    s, g = c.sg(done.x)
    return s, g, done.jacobian


SURFACE_SIGMAS = 2.0         # the response surface's half-width, in standard deviations of the estimate


def _smoothed(obj: _Objective, c: _Coords, s: float, g: float,
              J: np.ndarray | None) -> tuple[float, float, np.ndarray, Surface]:
    """The likelihood's optimum near the polished (s, g) from a response surface (fit.response_surface):
    the noise-weighted residuals z regressed linearly over a design of +-SURFACE_SIGMAS standard
    deviations of the estimate (from `J`, the polish's central Jacobian, or one made here; inflated
    by the reduced chi^2 when it exceeds 1), at least a tenth of a finite-difference step (what the
    polish resolves); one step for a coordinate the rows do not see.
    The polish's steps follow the local slopes of chi^2, which the tables' Monte-Carlo noise bends
    on the scale of the interval itself; the regression averages them over the design.  Returns
    (s, g, J, surface): J the regression's Jacobian, which serves the intervals."""
    x0 = c.x(s, g)
    if J is None:
        J = _jacobian(obj, c, x0, likelihood=True)
    z = obj.likelihood_residuals(s, g)
    c_hat = max(1.0, float(z @ z) / max(z.size - x0.size, 1))
    JtJ = J.T @ J
    sd = np.full(x0.size, np.inf)
    seen = np.isfinite(np.diag(JtJ)) & (np.diag(JtJ) > 0)
    if np.all(np.isfinite(JtJ)) and seen.all() and np.linalg.matrix_rank(JtJ) == x0.size:
        sd = np.sqrt(np.maximum(np.diag(np.linalg.inv(JtJ)), 0.0) * c_hat)
    elif np.all(np.isfinite(JtJ)) and seen.any():
        sd[seen] = np.sqrt(np.maximum(np.diag(np.linalg.pinv(JtJ[np.ix_(seen, seen)])), 0.0) * c_hat)
    # a coordinate the rows do not see (J^T J singular) gets one finite-difference step, not a design
    # across its bounds: the regression's minimum-norm step then leaves it where it is
    width = np.where(np.isfinite(sd), np.minimum(SURFACE_SIGMAS * sd, 0.25 * (c.upper - c.lower)), c.step)
    h = np.maximum(width, 0.1 * c.step)
    surf = smoothed_optimum(lambda x: obj.likelihood_residuals(*c.sg(x)), x0, c.lower, c.upper, h)
    s, g = c.sg(surf.x)
    return s, g, surf.jacobian, surf


def _intervals(obj: _Objective, c: _Coords, s: float, g: float, gmax: float,
               J: np.ndarray | None = None) -> tuple[dict, float | None, list]:
    """68 % intervals from the likelihood's Jacobian at (s, g) (fit.covariance): cov(x) = (J^T J)^-1 (Delta chi^2 = 1),
    inflated by the reduced chi^2 when it exceeds 1 (Birge ratio: the model misses the noise) and,
    per parameter, to the Newey-West (HAC) variance when the residuals run correlated along the scans;
    a parameter is 'not determined' (None) when J^T J is singular or its interval reaches past the
    bounds.  `J`: a Jacobian already made at (s, g): the response surface's regression (`_smoothed`), or a
    central one within a tenth of a step (`_polish`)."""
    x0 = c.x(s, g)
    if J is None:
        J = _jacobian(obj, c, x0, likelihood=True)
    sim, S = obj.simulated_and_sigma(*c.sg(x0))
    r = signed_residuals(np.asarray(obj.measured, float), sim, S)       # = obj.likelihood_residuals there
    rows = getattr(obj.forward, "rows", None)
    scans = nuisance = None
    text = ""
    if rows is not None and len(rows) == r.size:
        scans = scans_of(rows)
        nuisance, text = level_nuisance(rows, sim, S)
    at = getattr(obj.forward, "model_deviations_at", None)
    shared = frac = None
    if at is not None and scans is not None:
        shared = shared_columns(at(*c.sg(x0)), S)
        ms = obj._model_sigma(sim)
        frac = None if ms is None else np.divide(ms**2, S**2, out=np.zeros_like(S), where=S > 0)
    cv = parameter_covariance(J, r, scans, nuisance=nuisance, nuisance_text=text, shared=shared, model_fraction=frac)
    cov = cv.cov
    warnings: list[str] = []
    iv: dict = {"height_scale": None, "filter_sigma_um": [0.0, 0.0] if not c.with_filter else None}
    corr = None
    if not np.all(np.isfinite(cov)):
        warnings.append("the recording does not pin down the relief parameters (their effects on the rows are "
                        "not independent here): no intervals are given")
        return iv, (1.0 if c.with_filter else None), warnings
    if np.any(cv.hac_widening > 1.0 + 1e-9):
        warnings.append(f"the intervals are widened for {cv.hac_reason()}")
    if cv.shared_widening is not None and np.any(cv.shared_widening > np.maximum(cv.hac_widening, 1.0 + 1e-9)):
        warnings.append(f"the intervals are widened x{float(np.max(cv.shared_widening)):.2f} at most for "
                        f"{cv.shared_reason()}")
    if cv.nuisance_widening is not None and np.any(cv.nuisance_widening > 1.005):
        warnings.append(f"the intervals are widened x{float(np.max(cv.nuisance_widening)):.2f} at most for "
                        f"{cv.nuisance_text}")
    lo, hi = obj.settings.scale_bounds
    sv = float(np.sqrt(cov[0, 0]))
    if s * np.exp(-sv) <= lo or s * np.exp(sv) >= hi:
        warnings.append(f"height_scale is not identifiable: its 68 % interval reaches the bounds [{lo:g}, {hi:g}]")
    else:
        iv["height_scale"] = [float(s * np.exp(-sv)), float(s * np.exp(sv))]
    if c.with_filter:
        sw = float(np.sqrt(cov[1, 1]))                       # of w = g^2
        corr = float(cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]))
        if g * g + sw >= gmax**2:
            warnings.append(f"filter_sigma_um is not identifiable: its 68 % interval reaches the bound {gmax:g} um")
        else:
            iv["filter_sigma_um"] = [float(np.sqrt(max(g * g - sw, 0.0))), float(np.sqrt(g * g + sw))]
    return iv, corr, warnings


def _ridge_probe(obj: _Objective, ratio: Callable[[float], float], both: dict, gmax: float,
                 pitch_um: float) -> tuple[bool, dict]:
    """Is there a ridge?  One evaluation along the slope-preserving direction: the best point's
    rms slope kept with the filter moved to g1 = max(2 g, 4 pitches, 0.05 um) (within the bound).
    A ridge when that costs less chi^2 (in units of the reduced chi^2 when > 1) than the
    information criterion needs to tell two models apart (ln n + BIC_MARGIN).  `ratio`: the fit's
    memoised `_slope_ratio_fn` (the filters it already applied are not applied again)."""
    b = both["parameters"]
    s_u = b["height_scale"] * ratio(b["filter_sigma_um"])
    g1 = float(min(max(2.0 * b["filter_sigma_um"], 4.0 * pitch_um, 0.05), gmax))
    lo, hi = obj.settings.scale_bounds
    s1 = float(np.clip(s_u / ratio(g1), lo, hi))
    m1 = obj(s1, g1, stop_at_threshold=False)
    cost = (obj.chi2(m1) - obj.chi2(both["search"])) / max(1.0, both["search"] ** 2)
    return bool(cost <= np.log(obj.n) + BIC_MARGIN), {"height_scale": s1, "filter_sigma_um": g1}


class _Stages:
    """Wall seconds per stage of a fit (fit.json's stage_seconds: where the time goes)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._t = time.monotonic()

    def lap(self, name: str) -> None:
        now = time.monotonic()
        self.seconds[name] = round(self.seconds.get(name, 0.0) + now - self._t, 3)
        self._t = now


def _past_the_valley(obj: _Objective) -> bool:
    """The ridge scan has passed its valley: its last two points each rose above the one before (the
    search objective along equal rms slope, `_ridge_scan`), so wider filters only bend the slope
    distribution further from the recording's."""
    scan = [d["search"] for d in obj.iterations if d["model"] == obj.model and d["parameters"]["filter_sigma_um"] > 0]
    return len(scan) >= 3 and scan[-1] > scan[-2] > scan[-3]


def _on_record(obj: _Objective, search: _Objective, only_unfiltered: bool) -> dict:
    """The search's best point (`_Objective.best`; scale alone with `only_unfiltered`) evaluated on the
    model of record `obj`: its entry there (parameters, search objective, metric).  The search model's own
    values carry its extra noise; what the criterion compares and the polish starts from is the model of
    record's.  A search that never evaluated (a threshold met at the start) hands over the record's best."""
    if not any(d["model"] == search.model for d in search.iterations):
        return obj.best(only_unfiltered)
    p = search.best(only_unfiltered)["parameters"]
    s, g = p["height_scale"], p["filter_sigma_um"]
    return {"parameters": dict(p), "search": obj(s, g, stop_at_threshold=False), "rms": obj.metric(s, g)}


def _store(checkpoint: Any, measured: np.ndarray, sigma: np.ndarray | None) -> Any:
    """The fit's checkpoint store (io.checkpoint: JSON data bound to a key): a given CheckpointStore,
    or one for a bare path keyed by the recording's values and sigma (what the fit job, `jobs.run_fit`, keys by
    the inputs' content, method, effort and grid)."""
    from relief_bsdf.io.checkpoint import CheckpointStore
    if checkpoint is None or isinstance(checkpoint, CheckpointStore):
        return checkpoint
    import hashlib
    h = hashlib.sha256(np.ascontiguousarray(measured, float).tobytes())
    h.update(b"-" if sigma is None else np.ascontiguousarray(sigma, float).tobytes())
    return CheckpointStore(checkpoint, {"kind": "relief-fit", "recording_values": h.hexdigest()})


def _load_cache(store: Any, n_rows: int) -> dict[str, list]:
    """The checkpoint's evaluations {"s,g": simulated values}, validated before use: each a list of
    `n_rows` finite numbers.  Anything else (a NaN, a wrong length, not numbers) is damage: the whole
    checkpoint is ignored with one note and the fit starts afresh (never a NaN metric, never a crash)."""
    if store is None:
        return {}
    ev = store.load().get("evaluations", {})
    try:
        cache = {str(k): [float(x) for x in v] for k, v in ev.items()}
    except (TypeError, ValueError, AttributeError):
        return store.ignore("its evaluations are not lists of numbers")
    for k, v in cache.items():
        if len(v) != n_rows:
            return store.ignore(f"evaluation at {k} holds {len(v)} values for {n_rows} recording rows")
        if not np.all(np.isfinite(v)):
            return store.ignore(f"evaluation at {k} holds a non-finite value (NaN or infinity)")
    return cache


def _saver(store: Any) -> Callable[[dict], None]:
    if store is None:
        return lambda cache: None
    return lambda cache: store.save({"evaluations": cache})


def fit_relief(forward: Forward, measured: np.ndarray, sigma: np.ndarray | None = None,
               settings: FitSettings = FitSettings(), *, checkpoint: Any = None,
               progress: Progress | None = None, on_eval: Callable[[int], None] | None = None) -> FitResult:
    """Optimise (height_scale, filter_sigma_um) so the simulated plate matches `measured`, and say
    what the recording determines (module doc, "Identifiability").

    1. baseline (s = 1, g = 0) on the forward model of record: "rms_before";
    2. scale alone from there (g = 0), on the search model (`Forward.search_model`: a quarter of the
       rays, the intensity loop; the model of record itself for a forward model without one): damped
       Gauss-Newton with a line search of the normalised residuals (`_gauss_newton`, forward-difference
       Jacobians) within a reserve of max(6, max_iter // 5) evaluations: the one-parameter model of step 4;
    3. both parameters, on the search model: the filter at 1, 2, 4, ... pixel pitches along the valley
       of equal rms slope through step 2's optimum (`_ridge_scan`, until two points in a row rise:
       `_past_the_valley`), then the same Gauss-Newton from the best point seen, in the search's
       coordinates (ln of the rms-slope scale, g^2; `_Coords`), the budget less the reserve; then the
       slope-equivalent scale of its best point (g = 0, the same rms slope: the other end of a ridge),
       and scale alone from there with what is left when it beats step 2's optimum;
    4. the search's best point with and without the filter evaluated on the model of record
       (`_on_record`); the filter is kept only when the recording asks for it (criteria: BIC with
       chi^2 = sum r^2 there); otherwise the scale-only optimum is the answer (the simplest point of a
       ridge);
    5. from the answer, a few Gauss-Newton steps on the likelihood's noise-weighted residuals
       (`_polish`: the log metric steers the search, the likelihood gives the estimate), the optimum
       of a response surface of those residuals over a design of +-2 standard deviations around it
       (`_smoothed`: 8 evaluations a round, one or two rounds), then 68 % intervals and the
       correlation from the regression's Jacobian there (`_intervals`), and one probe along equal rms
       slope for a ridge (`_ridge_probe`): a few evaluations more, all on the model of record.
    The budget counts distinct parameter points of either model (a Jacobian's base point is not paid
    twice); fit.json's iterations name each one's model.
    `checkpoint`: an io.checkpoint.CheckpointStore (or a .json path, keyed by the recording) of
    {params: simulated values}; its entries are replayed (deterministic path, same result as an
    uninterrupted run); a checkpoint of another run is ignored with a note.  `on_eval(n)` is called after each
    *new* evaluation (tests use it to interrupt).
    """
    progress = progress or silent
    t0 = time.monotonic()
    store = _store(checkpoint, measured, sigma)
    cache, save, iterations, counter = _load_cache(store, int(np.size(measured))), _saver(store), [], [0]
    obj = _Objective(forward, measured, sigma, settings, cache, save, progress, on_eval, "record", iterations, counter)
    # the search and the polish steer on the search model (`Forward.search_model`); a forward model without
    # one (a test's stand-in) steers on itself
    make_search = getattr(forward, "search_model", None)
    search_fwd = make_search() if make_search is not None else forward
    sobj = obj if search_fwd is forward else _Objective(search_fwd, measured, sigma, settings, cache, save,
                                                        progress, on_eval, "search", iterations, counter)
    pitch_um = min(forward.relief.dx_m, forward.relief.dy_m) * 1e6
    gmax = settings.max_filter_um if settings.max_filter_um is not None else 20 * pitch_um
    c2 = _Coords.make(settings, True, gmax, pitch_um)
    c1 = _Coords.make(settings, False, gmax, pitch_um)
    slope_ratio = _slope_ratio_fn(forward.relief)
    cs = _Coords.make(settings, True, gmax, pitch_um, ratio=slope_ratio)     # the search's (module doc)
    stopped = "converged"
    clock = _Stages()
    try:
        obj(1.0, 0.0)
        rms_before = obj.metric(1.0, 0.0)
        clock.lap("baseline and the model sigma")
        # scale alone first (cheap, robust from far away: it sets the slopes, the lobe width; its optimum
        # is the criterion's one-parameter model), then both from there; then scale alone again only where
        # the slope-equivalent scale of the joint optimum (g = 0, the same rms slope: the other end of a
        # ridge) beats the scale-only optimum found first
        reserve = max(6, settings.max_iter // 5)           # for the scale-only search after the joint one
        _gauss_newton(sobj, c1, c1.x(1.0, 0.0), reserve)
        a0 = sobj.best(only_unfiltered=True)["parameters"]["height_scale"]
        for g in _ridge_scan(pitch_um, gmax):
            if len(obj.iterations) >= settings.max_iter - reserve or _past_the_valley(sobj):
                break                                   # within the budget (the reserve kept)
            sobj(*cs.sg(np.array([np.log(a0), g * g])))
        b = sobj.best()["parameters"]
        _gauss_newton(sobj, cs, cs.x(b["height_scale"], b["filter_sigma_um"]),
                      settings.max_iter - len(obj.iterations) - reserve)
        b = sobj.best()["parameters"]
        s_u = b["height_scale"] * slope_ratio(b["filter_sigma_um"])
        if len(obj.iterations) < settings.max_iter:
            sobj(s_u, 0.0)
            if sobj.best(only_unfiltered=True)["parameters"]["height_scale"] == s_u:
                _gauss_newton(sobj, c1, c1.x(s_u, 0.0), settings.max_iter - len(obj.iterations))
        if len(obj.iterations) >= settings.max_iter:
            stopped = "max_iter"
    except _Stop:
        stopped = "threshold"
        rms_before = obj.iterations[0]["rms"]
    clock.lap("search")
    # the criterion's two models, each at the search's best point, on the model of record
    both, alone = (_on_record(obj, sobj, only_unfiltered) for only_unfiltered in (False, True))
    clock.lap("criterion")
    c_hat = overdispersion(obj.chi2(both["search"]), 2, obj.n)       # QBIC when the model misses the noise
    gain = bic_gain(obj.chi2(alone["search"]), 1, obj.chi2(both["search"]), 2, obj.n, c_hat)
    needed = both["parameters"]["filter_sigma_um"] > 0 and gain > BIC_MARGIN
    chosen = both if needed else alone
    s, g = chosen["parameters"]["height_scale"], chosen["parameters"]["filter_sigma_um"]
    s, g, J = _polish(obj, c2 if needed else c1, s, g)         # the likelihood's optimum (step 5)
    clock.lap("polish")
    s, g, J, surface = _smoothed(obj, c2 if needed else c1, s, g, J)
    clock.lap("response surface")
    surface_doc = {"design_points": surface.points, "rounds": surface.rounds,
                   "coordinates": ["ln height_scale", "filter_sigma_um^2"][:surface.x.size],
                   "scatter_about_linear_model": surface.scatter}
    chosen = {"parameters": {"height_scale": s, "filter_sigma_um": g}, "rms": obj.metric(s, g)}
    iv, corr, warnings = _intervals(obj, c2 if needed else c1, s, g, gmax, J)
    if not needed:
        bp = both["parameters"]
        _, corr, _ = _intervals(obj, c2, bp["height_scale"], bp["filter_sigma_um"], gmax)
        warnings.append(f"the recording does not ask for filtering the relief (BIC gain of the filter "
                        f"{gain:.3g} <= {BIC_MARGIN:g}): reported without filter")
    clock.lap("intervals")
    ridge, probe = _ridge_probe(obj, slope_ratio, both, gmax, pitch_um)
    clock.lap("ridge probe")
    if ridge:
        warnings.append(f"height scale and filter trade off along a ridge: ({s:.4g}, {g:.4g} um) and "
                        f"({probe['height_scale']:.4g}, {probe['filter_sigma_um']:.4g} um) have the same rms "
                        "slope and fit alike; the recording fixes that combination, not both parameters")
    if chosen["rms"] > NOISE_METRIC:
        warnings.append(f"the best fit misses the recording's noise (metric {chosen['rms']:.3g} > {NOISE_METRIC:g}): "
                        "the intervals are inflated by it but cover the noise only, not a systematic error of the "
                        "forward model (e.g. its table grid); physics beyond scale and filter may be missing "
                        "(relief diagnose)")
    by_model = {"record": obj.new_evals, **({"search": sobj.new_evals} if sobj is not obj else {})}
    return FitResult(s, g, rms_before, chosen["rms"], obj.iterations, METRIC, stopped,
                     time.monotonic() - t0, iv, corr, bool(needed), float(gain), bool(ridge), warnings,
                     sum(by_model.values()), surface_doc, "log-chi search objective: " + settings.metric.describe(),
                     by_model, clock.seconds)
