"""The job `relief simulate`: the plate of a sample as the instrument sees it, on its recording's rows.

The sample's plate through the one forward model of simulate, fit and diagnose (`fit.forward`, over
`fit.baseline`: the relief levelled and checked, the rows checked, "auto" decided once), the relief
scaled and filtered as asked (the fit's `Forward`, `surface.operations.scale_and_filter`), simulated by
the deterministic engine.  Each row's sigma is the simulation's own 1-sigma: the relative spread
of its tables' Monte-Carlo draws through the plate at the relief as read (`plate.uncertainty`,
`fit.forward.SIGMA_DRAWS` draws), times the values, as the fit and the diagnosis take it; so the
metric against the recording (`fit.residual.rms_z`) is theirs at the same parameters.  With a table file instead
of a relief, the rough face is that table and the plate's azimuth grid follows its azimuth cells.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.jobs.control import CancelToken, check
from relief_bsdf.progress import Progress


@dataclass(frozen=True)
class SimulateJob:
    """The plate of `sample` (sample.toml) with its relief face by `method` (`samples`, `seed` where the
    method samples; `sectors`: plate.grid.TableGrid.sectors), the relief's heights times
    `height_scale` and Gaussian-filtered by `filter_sigma_um`, or the boundary tables of `table`
    (HDF5, outside + inside) instead of a relief; `relief_options` (a ReliefOptions) over the
    sample's [relief] keys.  Writes `out`/simulated.csv."""

    sample: Path
    out: Path
    method: str = "auto"
    samples: int = 200_000
    seed: int = 0
    height_scale: float = 1.0
    filter_sigma_um: float = 0.0
    sectors: str = "auto"
    table: Path | None = None
    relief_options: Any = None


@dataclass(frozen=True)
class SimulateOutput:
    """`path` (simulated.csv) of `rows` rows; `metric` (rms z) against the recording; `physics`, one line
    naming the faces' methods, the bulk and the engine; `info` the simulation's own account; `relief`
    the relief as read (None with a table)."""

    path: Path
    rows: int
    metric: float
    physics: str
    info: dict
    relief: Any


def run_simulate(job: SimulateJob, progress: Progress | None = None,
                 cancel: CancelToken | None = None) -> SimulateOutput:
    from relief_bsdf.fit.residual import rms_z
    from relief_bsdf.io.recording import read_sample, write_recording
    sample = read_sample(job.sample)
    rec = sample.load_recording()
    check(cancel, "simulating")
    if job.table is None:
        relief, sim = _with_relief(job, sample)
    else:
        relief, sim = None, _with_table(job, sample, rec)
    check(cancel, "writing")
    o = Path(job.out)
    o.mkdir(parents=True, exist_ok=True)
    m = rms_z(rec.bsdf_sr, rec.sigma_sr, sim.values_per_sr, sim.sigma_per_sr)     # the metric of fit and diagnose
    physics = physics_line(sim.info)
    write_recording(o / "simulated.csv", rec.with_values(sim.values_per_sr, sim.sigma_per_sr),
                    comments=[f"relief simulate {Path(job.sample).name}", f"physics: {physics}",
                              f"metric (rms z) vs recording: {m:.6g}"])
    return SimulateOutput(o / "simulated.csv", len(rec), float(m), physics, sim.info, relief)


def _with_relief(job: SimulateJob, sample: Any) -> tuple[Any, Any]:
    """(relief as read, Simulated with the simulation's own sigma) of the sample's relief face."""
    from relief_bsdf.fit.baseline import baseline
    from relief_bsdf.fit.forward import Forward
    from relief_bsdf.plate import TableGrid
    b = baseline(sample, method=job.method, samples=job.samples, seed=job.seed, grid=TableGrid(sectors=job.sectors),
                 relief_options=job.relief_options)
    fwd = Forward.of(b)
    sim = fwd.simulated(job.height_scale, job.filter_sigma_um)
    # the simulation's own relative sigma at the relief as read, scaled with the values (module doc)
    return b.relief, replace(sim, sigma_per_sr=fwd.model_rel_sigma() * np.abs(sim.values_per_sr))


def _with_table(job: SimulateJob, sample: Any, rec: Any) -> Any:
    """Simulated plate whose rough face is the table file's tables."""
    from relief_bsdf.io.hdf5 import load_tables, table_for
    from relief_bsdf.plate import TableFace, TableGrid, experiment_from_sample, simulate
    exp = experiment_from_sample(sample, None, method=job.method, samples=job.samples, seed=job.seed)
    tabs = load_tables(job.table)
    front = sample.plate.rough_face == "front"
    ins = table_for(tabs, "inside", job.table)
    out = table_for(tabs, "outside", job.table) if front else None
    exp = exp.with_plate(**{sample.plate.rough_face: TableFace(ins, out)})
    # the plate's azimuth grid follows the table's azimuth cells (as in `relief fit`)
    grid = TableGrid(phi_step_deg=360.0 / ins.phi_s_deg.size)
    return simulate(exp, rec, grid=grid, where=str(sample.recording_path))


def physics_line(info: dict) -> str:
    """One line naming the physics a simulation used (faces' methods, bulk, engine)."""
    ph = info.get("physics", {})

    def face(d: dict) -> str:
        if d.get("face") == "relief":
            return f"relief by {d.get('method')}" + (f" ({d['chosen_by']})" if d.get("chosen_by") else "")
        return d.get("face", "?") + (f" ({d['method']})" if d.get("method") else "")
    b = ph.get("bulk", {})
    bulk = "absorption {:g}/m, scattering {:g}/m (g {:g})".format(b.get("absorption_per_m", 0.0),
                                                                 b.get("scatter_per_m", 0.0), b.get("hg_g", 0.0))
    sectors = info.get("inside_sectors")
    loop = (f"; loop by azimuth sector ({len(sectors['centres_deg'])} inside sector tables)" if sectors else "")
    return (f"front {face(ph.get('front', {}))}, back {face(ph.get('back', {}))}; bulk {bulk}; "
            f"engine {info.get('engine', '?')}{loop}")
