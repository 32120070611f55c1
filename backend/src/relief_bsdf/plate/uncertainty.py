"""The simulation's own uncertainty: the boundary tables' 1-sigma carried through the plate.

A table's `sigma_per_sr` holds the 1-sigma of each cell (the Monte-Carlo noise of a sampling
method, and the realisation uncertainty of the finite tile where the method estimates it).
The plate's rows depend on the cells through the inter-reflection series between the faces,
a smooth function of the cells; rather than differentiating the solver, `rows_sigma` draws K
perturbed copies of every table that carries a sigma (cells independent and Gaussian, clipped
at zero, a cell's Mueller matrix scaled with its M00), solves the plate for each (the same
deterministic engine) and returns the sample standard deviation per row.  With K = 8 the
sigma itself is known to about +-25 % (chi distribution with 7 degrees of freedom), enough to
weight a residual.  Draws are seeded (same inputs and seed, same sigma).

Assumptions: cell errors independent (a sampled table's cells are multinomial counts, so
weakly anti-correlated; a tile realisation correlates neighbouring cells, which independent
draws understate where a detector cone averages several cells); delta (specular) parts exact.
Tables without a sigma (wave methods, Fresnel faces) contribute nothing.
"""
from __future__ import annotations

import dataclasses
import contextvars
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.parallel import default_workers, in_worker
from relief_bsdf.parallel.blas import blas_single_thread
from relief_bsdf.plate import deterministic
from relief_bsdf.plate.choice import resolve_auto
from relief_bsdf.plate.description import Experiment
from relief_bsdf.plate.deterministic import front_tables, front_traces_beam, half_turn_table, table_incidences
from relief_bsdf.plate.faces import TableFace
from relief_bsdf.plate.grid import TableGrid

DEFAULT_DRAWS = 8
# the draws made at a fitted point for its intervals' shared model noise (fit.covariance): the parameters'
# variance from them is known to about sqrt(2 / 15) = +-37 % (with 8: +-53 %, which on the seed-10 blur
# case gave x1.54 and x1.06 for two ray seeds whose spread asked for about x1.5)
INTERVAL_DRAWS = 16

# The deterministic plate's stated level accuracy per side (1-sigma, relative): what the forward
# model's in-lobe level misses an independent photon Monte Carlo through the real relief by, not
# its noise.  Measured with benchmarks/bench_forward_accuracy.py (8 reliefs: Gaussian slope
# 0.12 / 0.24 / 0.34, dots, exponential, two scales, anisotropic, a measured map; 1 M photons,
# 0/30/60 deg, 400k rays, in-lobe sum forward / recording): R 0.979-1.001, rms deviation 1.2 %, the
# largest miss 2.1 % (gauss_low), stated as 2 % (eight reliefs only, and the largest miss exceeds even that);
# T 0.992-1.002, rms deviation 0.3 % (rounded up to 0.5 %: eight cases).  Used as nuisance levels
# in the fit's and the diagnosis's intervals (fit.covariance), never in the estimate.  Measured for
# the ray method's tables on the default grid (auto's choice for reliefs rough on the wavelength
# scale); a surrogate (microfacet+dw) misses by far more and says so in its own output, a wave
# method's accuracy is checked against the direct-integration Kirchhoff instead (not a level).
FORWARD_LEVEL_SD = {"R": 0.02, "T": 0.005}


def sigma_note(draws: int) -> str:
    """What a simulation's sigma from `draws` table draws is, for its `info` (one wording everywhere)."""
    return f"boundary tables' 1-sigma carried through the plate ({int(draws)} draws)"


def perturbed(table: BsdfTable | None, rng: np.random.Generator) -> BsdfTable | None:
    """One draw of `table` within its cells' 1-sigma (None, or a table without sigma, unchanged)."""
    if table is None or table.sigma_per_sr is None:
        return table
    v = np.asarray(table.values_per_sr, float)
    s = np.nan_to_num(np.asarray(table.sigma_per_sr, float), nan=0.0)
    new = np.maximum(v + s * rng.standard_normal(v.shape), 0.0)
    kw: dict = {"values_per_sr": new.astype(table.values_per_sr.dtype, copy=False)}
    if table.mueller_per_sr is not None:
        ratio = np.divide(new, v, out=np.ones_like(v), where=v > 0)
        kw["mueller_per_sr"] = (table.mueller_per_sr * ratio[..., None, None]).astype(table.mueller_per_sr.dtype,
                                                                                    copy=False)
    return dataclasses.replace(table, **kw)


def _face_tables(experiment: Experiment, rows: Any, grid: TableGrid) -> dict:
    """{face name: (outside | None, inside, half-turned outside | None)} of the non-flat faces whose tables
    carry a sigma (the half-turned outside table: the front's, where rows are lit from the far half of
    azimuths, `plate.deterministic.half_turn_table`)."""
    p = experiment.plate
    traced = front_traces_beam(experiment, rows, grid)
    wl, ti = table_incidences(experiment, rows, traced)
    out = {}
    for name in ("front", "back"):
        face = getattr(p, name)
        if face.is_flat:
            continue
        t_out, t_in = (front_tables(experiment, grid, wl, ti, traced) if name == "front"
                       else face.tables(p.material, grid, wl, ti, need_outside=False))
        half = half_turn_table(experiment, rows, grid, traced) if name == "front" else None
        if any(t is not None and t.sigma_per_sr is not None for t in (t_out, t_in, half)):
            out[name] = (t_out, t_in, half)
    return out


def rows_sigma(experiment: Experiment, rows: Any, grid: TableGrid | None = None, draws: int = DEFAULT_DRAWS,
               seed: int = 0) -> np.ndarray:
    """1-sigma per row of the deterministic simulation from its tables' own uncertainty (module doc);
    NaN (unknown) when no face's table carries a sigma."""
    runs = rows_draws(experiment, rows, grid, draws, seed)
    if runs is None:
        return np.full(int(np.size(rows.theta_i_deg)), np.nan)
    return runs.std(axis=0, ddof=1)


def rows_draws(experiment: Experiment, rows: Any, grid: TableGrid | None = None, draws: int = DEFAULT_DRAWS,
               seed: int = 0) -> np.ndarray | None:
    """(draws, rows): the deterministic simulation on `draws` perturbed copies of its tables (module doc),
    or None when no face's table carries a sigma (or draws < 2).  Each draw is one realisation of the
    tables' noise seen by every row at once: rows that read the same cells move together."""
    grid = grid or TableGrid()
    faces = _face_tables(experiment, rows, grid)
    n = int(np.size(rows.theta_i_deg))
    if not faces or draws < 2:
        return None
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5161]))
    runs = np.empty((draws, n))

    def solve(swaps: dict) -> np.ndarray:
        # a draw's solver serves once: not kept for reuse, where it would push the baseline's out
        return deterministic.run(experiment.with_plate(**swaps), rows, grid, keep_solver=False)[0]
    # the draws' plate solves run on this process's threads, a batch of `threads` at a time (numpy and
    # LAPACK release the GIL); the perturbations are drawn in order in this thread: the same numbers.
    # (Not map_tasks(threads=): its tasks would all be made first, every draw's tables held at once.)
    threads = 1 if in_worker() else max(1, min(default_workers(), draws))
    # one BLAS thread for the whole block (each solve asks for it too; set once here, no thread
    # restores the process's setting while another still solves)
    with blas_single_thread(), ThreadPoolExecutor(max_workers=threads) as pool:
        for lo in range(0, draws, threads):
            batch = [{name: TableFace(perturbed(t_in, rng), perturbed(t_out, rng), perturbed(half, rng))
                      for name, (t_out, t_in, half) in faces.items()} for _ in range(lo, min(draws, lo + threads))]
            # each solve in a copy of this thread's context: the job's memory owner (plate.memory) and the
            # parallel settings in force reach the pool's threads
            runs[lo:lo + len(batch)] = list(pool.map(lambda b: contextvars.copy_context().run(solve, b), batch))
    return runs


def relative_sigma(experiment: Experiment, rows: Any, grid: TableGrid | None = None, draws: int = DEFAULT_DRAWS,
                   where: str = "recording") -> np.ndarray:
    """The simulation's relative 1-sigma per row, sigma / |value| (`rows_sigma` over the deterministic
    engine's values), 0 where the value is 0 or no table carries a sigma, at most 1.  The fit and the
    diagnosis compute it once on their baseline and scale it with the values at other parameters: the
    relative noise of a table hardly moves with the relief's scale and filter or a plate effect, and
    common random numbers keep it the same draw."""
    return deviations_sigma(relative_deviations(experiment, rows, grid, draws, where), int(np.size(rows.theta_i_deg)))


def relative_deviations(experiment: Experiment, rows: Any, grid: TableGrid | None = None,
                        draws: int = DEFAULT_DRAWS, where: str = "recording") -> np.ndarray:
    """(draws, rows): each table draw's deviation from the draws' mean (`rows_draws`), relative to the
    deterministic engine's value (0 where the value is 0), a row whose relative sigma exceeds 1 scaled
    down to 1 (as `relative_sigma`); (0, rows) when no table carries a sigma.  Their standard deviation
    is `relative_sigma`; their products are the rows' covariance through the shared tables, which an
    interval needs where the effects leave the noise where it was (`deviations` at the point otherwise)."""
    grid = grid or TableGrid()
    v = np.abs(deterministic.run(resolve_auto(experiment, rows, grid), rows, grid, where=where)[0])   # as `simulate`
    dev = deviations(experiment, rows, grid, draws)
    if dev.shape[0] == 0:
        return dev
    dev = np.divide(dev, v, out=np.zeros_like(dev), where=v > 0)
    rel = dev.std(axis=0, ddof=1)
    return dev * np.divide(1.0, rel, out=np.ones_like(rel), where=rel > 1.0)


def deviations(experiment: Experiment, rows: Any, grid: TableGrid | None = None, draws: int = DEFAULT_DRAWS,
               seed: int = 0) -> np.ndarray:
    """(draws, rows): each table draw's deviation (1/sr) from the draws' mean (`rows_draws`, "auto" faces
    resolved as the simulation resolves them); (0, rows) when no table carries a sigma.  Made where an
    interval is asked (the fitted point): the noise's reach moves with the effects (a beam divergence
    traced into the outside table spreads it over the lobe; the baseline's draws, scaled, moved a fitted
    divergence 3x less than the draws at it and the ray seeds do)."""
    grid = grid or TableGrid()
    runs = rows_draws(resolve_auto(experiment, rows, grid), rows, grid, draws, seed)
    if runs is None:
        return np.zeros((0, int(np.size(rows.theta_i_deg))))
    return runs - runs.mean(axis=0)


def deviations_sigma(dev: np.ndarray, n: int) -> np.ndarray:
    """The relative 1-sigma per row of `relative_deviations` (0 without draws)."""
    if dev.shape[0] < 2:
        return np.zeros(n)
    return np.clip(np.nan_to_num(dev.std(axis=0, ddof=1), nan=0.0), 0.0, 1.0)
