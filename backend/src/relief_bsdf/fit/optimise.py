"""Relief optimisation against a plate recording (paper sec. 3, steps 1-6).

Loop: parameters p = (height_scale s, filter_sigma_um g) -> relief.scaled(s).gaussian_filtered(g)
(step 6) -> boundary tables of the chosen method for light from outside and inside (step 2)
-> plate simulation on the recording's rows (step 3, `plate.simulate_rows`) -> metric
(step 4, `residual.LogChiMetric`) -> scipy.optimize Nelder-Mead (step 5) until the metric
falls below `threshold` or stops improving (xatol/fatol) or `max_iter` is reached.

Methods: any name of `methods.METHODS`, plus "microfacet+dw" (the default, fast): microfacet
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

from relief_bsdf.io.atomic import write_text_atomic
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.core.optics import Material, mueller_interface
from relief_bsdf.plate.solver import PlateModel, _blas_single_thread, check_rows, simulate_rows
from relief_bsdf.progress import Progress, silent
from relief_bsdf.surface.relief import Relief
from relief_bsdf.methods.request import Request
from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric

FIT_FORMAT = "relief-fit/1"


@dataclass(frozen=True)
class TableGrid:
    """Axes of the boundary tables the fit derives (plate discretisation follows them)."""

    theta_step_deg: float = 1.0
    phi_step_deg: float = 5.0
    inside_theta_i_step_deg: float = 5.0

    def request(self, wavelengths: Any, theta_i: Any, incident_from: str, method: str, samples: int, seed: int,
                options: dict | None = None) -> Request:
        te = tuple(np.linspace(0.0, 90.0, int(round(90 / self.theta_step_deg)) + 1))
        h = self.phi_step_deg / 2
        pe = tuple(np.arange(-h, 360.0 - h + 1e-9, self.phi_step_deg))
        return Request(wavelengths_nm=tuple(float(w) for w in wavelengths),
                       theta_i_deg=tuple(float(t) for t in theta_i), incident_from=(incident_from,),
                       theta_s_edges_deg=te, phi_s_edges_deg=pe, samples=int(samples), seed=int(seed),
                       options=dict(options or {}))


def relief_rms(relief: Relief) -> tuple[float, float]:
    """(rms height after plane levelling, rms slope magnitude) of the valid points."""
    h = relief.level(1).heights_m
    gy, gx = np.gradient(h, relief.dy_m, relief.dx_m)
    s2 = gx**2 + gy**2
    return float(np.sqrt(np.nanmean(h**2))), float(np.sqrt(np.nanmean(s2)))


def _debye_waller(table: BsdfTable, material: Material, sigma_m: float) -> BsdfTable:
    """Split a diffuse (microfacet) table into coherent specular + scaled diffuse (module doc)."""
    W, I = table.wavelength_nm.size, table.theta_i_deg.size
    gR = np.zeros((W, I, 1))
    gT = np.zeros((W, I, 1))
    sR = np.zeros((W, I, 1, 4, 4))
    sT = np.zeros((W, I, 1, 4, 4))
    for w, wl in enumerate(table.wavelength_nm):
        n1, n2 = (float(np.real(x)) for x in material.n_pair(wl, table.incident_from))
        k = 2 * np.pi / (wl * 1e-9)
        ci = np.cos(np.radians(table.theta_i_deg))
        st2 = (n1 / n2) ** 2 * (1 - ci**2)
        ct = np.sqrt(np.clip(1 - st2, 0, 1))
        gR[w, :, 0] = np.exp(-(2 * k * n1 * sigma_m * ci) ** 2)
        gT[w, :, 0] = np.where(st2 < 1, np.exp(-(k * sigma_m * (n1 * ci - n2 * ct)) ** 2), 0.0)
        sR[w, :, 0] = mueller_interface(ci, n1, n2, "R") * gR[w, :, 0, None, None]
        sT[w, :, 0] = mueller_interface(ci, n1, n2, "T") * gT[w, :, 0, None, None]
    v = table.values_per_sr.copy()
    v[:, :, :, 0] *= (1 - gR)[..., None, None]
    v[:, :, :, 1] *= (1 - gT)[..., None, None]
    mu = None
    if table.mueller_per_sr is not None:
        mu = table.mueller_per_sr.copy()
        mu[:, :, :, 0] *= (1 - gR)[..., None, None, None, None]
        mu[:, :, :, 1] *= (1 - gT)[..., None, None, None, None]
    return replace(table, values_per_sr=v, mueller_per_sr=mu, specular_R=sR[..., 0, 0], specular_T=sT[..., 0, 0],
                   specular_mueller_R=sR, specular_mueller_T=sT, sigma_per_sr=None,
                   method=table.method + "+dw", metadata={**table.metadata, "debye_waller_sigma_m": sigma_m})


def derive_tables(relief: Relief, material: Material, method: str, wavelengths: Any, theta_i_outside: Any,
                  grid: TableGrid = TableGrid(), samples: int = 200_000, seed: int = 0,
                  need_outside: bool = True, progress: Progress | None = None) -> tuple[BsdfTable | None, BsdfTable]:
    """(outside, inside) boundary tables of `relief` (step 2 of the loop)."""
    from relief_bsdf.methods import reconstruct
    base = method[:-3] if method.endswith("+dw") else method
    opts: dict = {}
    sigma = 0.0
    if method == "microfacet+dw":
        sigma, slope = relief_rms(relief)
        opts = {"alpha": max(slope, 1e-4)}
    theta_in = np.arange(0.0, 90.0 - 1e-9, grid.inside_theta_i_step_deg)
    theta_in = np.unique(np.concatenate([theta_in, [89.0]]))
    out = None
    if need_outside:
        req = grid.request(wavelengths, np.unique(theta_i_outside), "outside", base, samples, seed, opts)
        (out,) = reconstruct(relief, material, req, base, progress=progress)
    req = grid.request(wavelengths, theta_in, "inside", base, samples, seed, opts)
    (ins,) = reconstruct(relief, material, req, base, progress=progress)
    if method.endswith("+dw"):
        ins = _debye_waller(ins, material, sigma)
        out = _debye_waller(out, material, sigma) if out is not None else None
    return out, ins


def process_relief(relief: Relief, height_scale: float, filter_sigma_um: float) -> Relief:
    """Step 6: the global relief modification being optimised."""
    return relief.scaled(float(height_scale)).gaussian_filtered(max(float(filter_sigma_um), 0.0) * 1e-6)


@dataclass
class Forward:
    """The forward model of the fit: parameters -> simulated recording values."""

    relief: Relief
    model: PlateModel
    rows: Any
    method: str = "microfacet+dw"
    grid: TableGrid = field(default_factory=TableGrid)
    samples: int = 200_000
    seed: int = 0
    where: str = "recording"

    def __post_init__(self) -> None:
        check_rows(self.model, self.rows, self.where)   # bad rows fail before any table is derived
        # the plate's azimuth grid follows the tables' azimuth cells (finer cells would be wasted otherwise)
        self.model = replace(self.model, azimuth_cells=int(round(360.0 / self.grid.phi_step_deg)))

    def tables(self, height_scale: float, filter_sigma_um: float):
        r = process_relief(self.relief, height_scale, filter_sigma_um)
        return r, *derive_tables(r, self.model.material, self.method, np.unique(self.rows.wavelength_nm),
                                 self.rows.theta_i_deg, self.grid, self.samples, self.seed,
                                 need_outside=self.model.rough_face == "front")

    def simulate(self, height_scale: float, filter_sigma_um: float) -> np.ndarray:
        with _blas_single_thread():      # small matrices everywhere: BLAS threads only spin (plate.py)
            _, out, ins = self.tables(height_scale, filter_sigma_um)
            return simulate_rows(self.model, ins, out, self.rows, where=self.where)


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


def fit_relief(forward: Forward, measured: np.ndarray, sigma: np.ndarray | None = None, *,
               metric: LogChiMetric = DEFAULT_METRIC, threshold: float = 0.0, max_iter: int = 60,
               checkpoint: str | Path | None = None, progress: Progress | None = None,
               max_filter_um: float | None = None, on_eval: Callable[[int], None] | None = None) -> FitResult:
    """Optimise (height_scale, filter_sigma_um) so the simulated plate matches `measured`.

    Nelder-Mead on (u, g), u = ln(s m(g)/m(0)) (m = rms slope after filtering), g >= 0; the first evaluation (s = 1, g = 0) is the
    baseline "rms_before".  `checkpoint`: JSON file of {params: metric}; existing entries are
    replayed.  `on_eval(n)` is called after each *new* evaluation (tests use it to interrupt).
    """
    from scipy.optimize import minimize
    progress = progress or silent
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

def run_fit_job(sample_path: str | Path, out_dir: str | Path, method: str = "microfacet+dw", samples: int = 200_000,
                seed: int = 0, max_iter: int = 60, threshold: float = 0.0, grid: TableGrid = TableGrid(),
                progress: Progress | None = None) -> dict:
    """`relief fit`: read the sample, fit, write OUT/fit.json + relief + tables + plots + report."""
    from relief_bsdf.report import fit_report as report
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.io.heightmaps import read_relief, write_relief
    from relief_bsdf.io.recording import read_recording, read_sample, write_recording
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sample = read_sample(sample_path)
    rec = read_recording(sample.recording_path)
    relief = read_relief(sample.relief_path)
    model = PlateModel.from_sample(sample)
    fwd = Forward(relief, model, rec, method=method, grid=grid, samples=samples, seed=seed,
                  where=str(sample.recording_path))
    res = fit_relief(fwd, rec.bsdf_sr, rec.sigma_sr, threshold=threshold, max_iter=max_iter,
                     checkpoint=out / "checkpoint.json", progress=progress)
    best_relief, t_out, t_in = fwd.tables(res.height_scale, res.filter_sigma_um)
    sim_after = simulate_rows(fwd.model, t_in, t_out, rec)
    sim_before = fwd.simulate(1.0, 0.0)
    tables = [t for t in (t_out, t_in) if t is not None]
    save_tables(out / "boundary.h5", tables)
    files = {"boundary_table": "boundary.h5"}
    try:
        from relief_bsdf.io import isbsdf as bsdf_isbsdf  # type: ignore[attr-defined]
        for t in tables:
            name = f"boundary_{t.incident_from}.isbsdf"
            bsdf_isbsdf.write_isbsdf(out / name, t)  # type: ignore[attr-defined]
            files[f"isbsdf_{t.incident_from}"] = name
    except (ImportError, AttributeError):
        pass
    write_relief(out / "relief_optimised.npz", best_relief)
    files["relief"] = "relief_optimised.npz"
    write_recording(out / "simulated.csv", rec.with_values(sim_after), comments=["simulated plate after the fit"])
    files["simulated"] = "simulated.csv"
    plots = report.fit_plots(out, rec, sim_before, sim_after)
    files.update(plots)
    doc = res.to_json({"method": method, "sample": str(Path(sample_path)), "files": files,
                       "relief_history": list(best_relief.history)})
    write_text_atomic(out / "fit.json", json.dumps(doc, indent=1))
    report.write_fit_report(out / "report.html", doc, plots)
    return doc
