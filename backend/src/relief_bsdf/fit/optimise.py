"""Relief optimisation against a plate recording (paper sec. 3, steps 1-6).

Loop: parameters p = (height_scale s, filter_sigma_um g) -> surface.operations.scale_and_filter
(step 6) -> the Experiment's relief face gets the processed relief; its boundary tables of the
chosen method for light from outside and inside (step 2, plate.faces.ReliefFace, cached)
-> plate simulation on the recording's rows (step 3, `plate.simulate`, deterministic) -> metric
(step 4, `residual.LogChiMetric`) -> scipy.optimize Nelder-Mead (step 5) until the metric
falls below `threshold` or stops improving (xatol/fatol) or `max_iter` is reached.

Methods: any name of `methods.registry`, e.g. "microfacet+dw" (the default, fast; methods.microfacet_dw): microfacet
(Walter 2007) lobes with the relief's rms slope, and a coherent specular part from its rms
height sigma by the Kirchhoff / Debye-Waller factor (Beckmann & Spizzichino 1963; valid for
Gaussian height statistics and lateral scales >> wavelength):
    reflection    g = exp(-(2 k n1 sigma cos theta_i)^2)
    transmission  g = exp(-(k sigma (n1 cos theta_i - n2 cos theta_t))^2)
(k = 2 pi / lambda); the Fresnel delta parts are g R_F, g T_F and the diffuse cells are scaled by
(1 - g).  Height scale and smoothing then act differently on the plate (heights set the
specular peak, slopes the lobe width), so both are identifiable; a pure geometric-optics
method only sees slopes and the two parameters are degenerate.

Checkpoints: OUT/checkpoint.json holds every evaluated parameter set and its metric; a
rerun replays them (no recomputation), and since the optimiser is deterministic it retraces
the same path and ends with the same result as an uninterrupted run.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric
from relief_bsdf.io.atomic import write_text_atomic
from relief_bsdf.plate import Experiment, ReliefFace, Simulated, TableGrid, check_rows, experiment_from_sample, simulate
from relief_bsdf.plate.deterministic import model_of
from relief_bsdf.progress import Progress, silent
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import rms_height_and_slope

FIT_FORMAT = "relief-fit/1"


def relief_rms(relief: Relief) -> tuple[float, float]:
    """(rms height, rms slope magnitude) of the levelled relief: surface.stats' one definition."""
    h, m = rms_height_and_slope(relief)
    return float(h), float(m)


def process_relief(relief: Relief, height_scale: float, filter_sigma_um: float) -> Relief:
    """Step 6: the global relief modification being optimised (surface.operations.scale_and_filter)."""
    return scale_and_filter(relief, float(height_scale), max(float(filter_sigma_um), 0.0) * 1e-6)


def _relief_face_name(experiment: Experiment) -> str:
    for name in ("front", "back"):
        if isinstance(getattr(experiment.plate, name), ReliefFace):
            return name
    raise InputError("fit", "the experiment has no relief face to optimise")


@dataclass
class Forward:
    """The forward model of the fit: (height scale, filter) -> simulated recording values.

    `experiment` holds the plate with a ReliefFace on its rough face (its method, samples, seed);
    each evaluation puts the processed relief on that face and runs `plate.simulate`
    (deterministic engine on `grid`; tables cached by relief content).
    """

    relief: Relief
    experiment: Experiment
    rows: Any
    grid: TableGrid = field(default_factory=TableGrid)
    where: str = "recording"

    def __post_init__(self) -> None:
        self.face_name = _relief_face_name(self.experiment)
        check_rows(model_of(self.experiment, self.grid), self.rows, self.where)   # bad rows fail before any table

    @property
    def method(self) -> str:
        return getattr(self.experiment.plate, self.face_name).method

    def experiment_at(self, height_scale: float, filter_sigma_um: float) -> tuple[Relief, Experiment]:
        r = process_relief(self.relief, height_scale, filter_sigma_um)
        face = replace(getattr(self.experiment.plate, self.face_name), relief=r)
        return r, self.experiment.with_plate(**{self.face_name: face})

    def tables(self, height_scale: float, filter_sigma_um: float):
        """(processed relief, outside table | None, inside table) of the relief face at these parameters."""
        r, ex = self.experiment_at(height_scale, filter_sigma_um)
        face = getattr(ex.plate, self.face_name)
        return r, *face.tables(ex.plate.material, self.grid, np.unique(self.rows.wavelength_nm),
                               np.unique(self.rows.theta_i_deg), need_outside=self.face_name == "front")

    def simulate(self, height_scale: float, filter_sigma_um: float) -> np.ndarray:
        return self.simulated(height_scale, filter_sigma_um).values_per_sr

    def simulated(self, height_scale: float, filter_sigma_um: float) -> Simulated:
        _, ex = self.experiment_at(height_scale, filter_sigma_um)
        return simulate(ex, self.rows, grid=self.grid, where=self.where)


class _Stop(Exception):
    pass


def _key(p: np.ndarray) -> str:
    return f"{float(p[0]):.10g},{float(p[1]):.10g}"


@dataclass
class FitResult:
    height_scale: float
    filter_sigma_um: float
    rms_before: float
    rms_after: float
    iterations: list
    metric: str
    stopped: str
    seconds: float

    def to_json(self, extra: dict | None = None) -> dict:
        d = {"format": FIT_FORMAT, "metric": self.metric, "rms_before": self.rms_before, "rms_after": self.rms_after,
             "parameters": {"height_scale": self.height_scale, "filter_sigma_um": self.filter_sigma_um},
             "iterations": self.iterations, "stopped": self.stopped, "seconds": self.seconds}
        d.update(extra or {})
        return d


@dataclass(frozen=True)
class FitSettings:
    """How the optimiser runs: the residual `metric`, stop at metric <= `threshold`, at most
    `max_iter` evaluations, the Gaussian filter bounded by `max_filter_um` (None: 20 pixel pitches)."""

    metric: LogChiMetric = DEFAULT_METRIC
    threshold: float = 0.0
    max_iter: int = 60
    max_filter_um: float | None = None


@dataclass(frozen=True)
class FitJob:
    """What `relief fit` runs: the boundary `method` of the relief face (its Monte-Carlo `samples` and
    `seed` where it samples), the tables' `grid`, and the optimiser's `max_iter` / `threshold`."""

    method: str = "microfacet+dw"
    samples: int = 200_000
    seed: int = 0
    max_iter: int = 60
    threshold: float = 0.0
    grid: TableGrid = TableGrid()


def fit_relief(forward: Forward, measured: np.ndarray, sigma: np.ndarray | None = None,
               settings: FitSettings = FitSettings(), *, checkpoint: str | Path | None = None,
               progress: Progress | None = None, on_eval: Callable[[int], None] | None = None) -> FitResult:
    """Optimise (height_scale, filter_sigma_um) so the simulated plate matches `measured`.

    Nelder-Mead on (u, g), u = ln(s m(g)/m(0)) (m = rms slope after filtering), g >= 0; the first evaluation (s = 1, g = 0) is the
    baseline "rms_before".  `checkpoint`: JSON file of {params: metric}; existing entries are
    replayed.  `on_eval(n)` is called after each *new* evaluation (tests use it to interrupt).
    """
    from scipy.optimize import minimize
    progress = progress or silent
    metric, threshold, max_iter, max_filter_um = (settings.metric, settings.threshold, settings.max_iter,
                                                  settings.max_filter_um)
    t0 = time.monotonic()
    cache: dict[str, float] = {}
    ck = Path(checkpoint) if checkpoint else None
    if ck and ck.exists():
        try:
            cache = {str(k): float(v) for k, v in json.loads(ck.read_text())["evaluations"].items()}
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(ck, f"unreadable checkpoint ({e}); delete it to start over") from None
    pitch_um = min(forward.relief.dx_m, forward.relief.dy_m) * 1e6
    gmax = max_filter_um if max_filter_um is not None else 20 * pitch_um
    iterations: list[dict] = []
    new_evals = [0]

    # Optimiser coordinates (u, g): u = ln(s * m(g) / m(0)) with m(g) the rms slope of the relief
    # filtered by g.  Geometric-optics lobes depend on slopes, so at fixed u the lobe width is
    # (nearly) fixed and the valley of the metric runs along g instead of curving through (s, g).
    rough = forward.relief
    m0 = relief_rms(rough)[1] or 1.0
    slope_cache: dict[float, float] = {}

    def slope_ratio(g: float) -> float:
        gk = round(g, 12)
        if gk not in slope_cache:
            slope_cache[gk] = (relief_rms(process_relief(rough, 1.0, g))[1] / m0) if g > 0 else 1.0
        return slope_cache[gk] or 1.0

    def evaluate(x: np.ndarray) -> float:
        g = float(np.clip(x[1], 0.0, gmax))
        s = float(np.exp(x[0]) / slope_ratio(g))
        key = _key(np.array([s, g]))
        if key in cache:
            m = cache[key]
        else:
            sim = forward.simulate(s, g)
            m = metric.value(sim, measured, sigma)
            cache[key] = m
            new_evals[0] += 1
            if ck:
                write_text_atomic(ck, json.dumps({"format": "relief-fit-checkpoint/1", "evaluations": cache},
                                                 indent=1))
            if on_eval:
                on_eval(new_evals[0])
        iterations.append({"parameters": {"height_scale": s, "filter_sigma_um": g}, "rms": m})
        progress(min(len(iterations), max_iter), max_iter, f"rms {m:.4g}")
        if m <= threshold:
            raise _Stop
        return m

    x0 = np.array([0.0, 0.0])
    step_g = max(2.0 * pitch_um, 0.05)
    simplex = np.array([x0, x0 + [np.log(1.25), 0.0], x0 + [0.0, step_g]])
    rms_before = evaluate(x0) if threshold < float("inf") else float("nan")
    stopped = "converged"
    try:
        minimize(evaluate, x0, method="Nelder-Mead",
                 options={"initial_simplex": simplex, "maxfev": max_iter, "xatol": 2e-3, "fatol": 1e-4})
        if len(iterations) >= max_iter:
            stopped = "max_iter"
    except _Stop:
        stopped = "threshold"
    best = min(iterations, key=lambda d: d["rms"])
    return FitResult(best["parameters"]["height_scale"], best["parameters"]["filter_sigma_um"], rms_before,
                     best["rms"], iterations, metric.describe(), stopped, time.monotonic() - t0)


# ---------------------------------------------------------------- whole job for the CLI

def run_fit_job(sample_path: str | Path, out_dir: str | Path, job: FitJob = FitJob(),
                progress: Progress | None = None) -> dict:
    """`relief fit`: read the sample, fit, write OUT/fit.json + relief + tables + plots + report."""
    method = job.method
    from relief_bsdf.report import fit_report as report
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.io.heightmaps import read_relief, write_relief
    from relief_bsdf.io.recording import read_recording, read_sample, write_recording
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sample = read_sample(sample_path)
    rec = read_recording(sample.recording_path)
    relief = read_relief(sample.relief_path)
    exp = experiment_from_sample(sample, relief, method=method, samples=job.samples, seed=job.seed)
    fwd = Forward(relief, exp, rec, grid=job.grid, where=str(sample.recording_path))
    res = fit_relief(fwd, rec.bsdf_sr, rec.sigma_sr, FitSettings(threshold=job.threshold, max_iter=job.max_iter),
                     checkpoint=out / "checkpoint.json", progress=progress)
    best_relief, t_out, t_in = fwd.tables(res.height_scale, res.filter_sigma_um)
    after = fwd.simulated(res.height_scale, res.filter_sigma_um)
    sim_after = after.values_per_sr
    sim_before = fwd.simulate(1.0, 0.0)
    tables = [t for t in (t_out, t_in) if t is not None]
    save_tables(out / "boundary.h5", tables)
    files = {"boundary_table": "boundary.h5"}
    from relief_bsdf.io.isbsdf import export_isbsdf
    for t in tables:      # OpticStudio: one scatter type per .bsdf file, BTDF centred on the refracted ray
        files[f"isbsdf_{t.incident_from}"] = [q.name for q in export_isbsdf(t, out / f"boundary_{t.incident_from}.bsdf")]
    write_relief(out / "relief_optimised.npz", best_relief)
    files["relief"] = "relief_optimised.npz"
    write_recording(out / "simulated.csv", rec.with_values(sim_after), comments=["simulated plate after the fit"])
    files["simulated"] = "simulated.csv"
    plots = report.fit_plots(out, rec, sim_before, sim_after)
    files.update(plots)
    doc = res.to_json({"method": method, "sample": str(Path(sample_path)), "files": files,
                       "relief_history": list(best_relief.history), "physics": after.info.get("physics", {})})
    write_text_atomic(out / "fit.json", json.dumps(doc, indent=1))
    report.write_fit_report(out / "report.html", doc, plots)
    return doc
