"""The job `relief fit`: optimise the relief's height scale and smoothing against a sample's recording,
and write what was found.

The sample's plate as every forward model takes it (`fit.baseline`), the optimiser
(`fit.optimise.fit_relief`, checkpointed in OUT/checkpoint.json), then the outputs, each written
atomically: fit.json (`fit.optimise.FitResult.to_json` with the method, the files and the physics),
the fitted relief's boundary tables (boundary.h5 and OpticStudio IS-BSDF files), the fitted relief
(relief_optimised.npz), the simulated plate after the fit with its own sigma (simulated.csv), the
plots and report.html (`report.fit_report`).
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.plate import DEFAULT_METHOD, TableGrid
from relief_bsdf.progress import Progress


@dataclass(frozen=True)
class FitJob:
    """Fit `sample` (sample.toml) into `out`: the relief face by `method` (its Monte-Carlo `samples` and
    `seed` where it samples) on the tables' `grid`; the optimiser's budget `max_iter`, its stop
    `threshold` (metric, rms z), the bounds of the height scale (`scale_bounds`) and of the filter
    (`max_filter_um`, None: 20 pixel pitches); `relief_options` (a ReliefOptions) over the sample's
    [relief] keys."""

    sample: Path
    out: Path
    method: str = DEFAULT_METHOD
    samples: int = 200_000
    seed: int = 0
    max_iter: int = 60
    threshold: float = 0.0
    grid: TableGrid = field(default_factory=TableGrid)
    scale_bounds: tuple = (0.1, 10.0)
    max_filter_um: float | None = None
    relief_options: Any = None


@dataclass(frozen=True)
class FitOutput:
    """fit.json's document (`doc`) and the folder `out` it was written to with the other files
    (`doc["files"]`, relative to `out`)."""

    doc: dict
    out: Path


def _job_store(out: Path, sample: Any, job: FitJob) -> Any:
    """OUT/checkpoint.json keyed by everything that determines an evaluation: the inputs' content
    (sample, relief, recording), method, effort, seed and grid (io.checkpoint adds the code
    version); the optimiser's budget is not in it, so a longer rerun resumes."""
    from relief_bsdf.io.checkpoint import CheckpointStore, input_digests
    key = {"kind": "relief-fit", "inputs": input_digests(sample=sample.path, relief=sample.relief_path,
                                                         recording=sample.recording_path,
                                                         **{f"recording_{k}": q for k, q in
                                                            enumerate(sample.recording_paths[1:], 1)}),
           "method": job.method, "samples": job.samples, "seed": job.seed, "grid": dataclasses.asdict(job.grid)}
    if job.relief_options is not None:
        key["relief_options"] = dataclasses.asdict(job.relief_options)
    return CheckpointStore(out / "checkpoint.json", key)


def run_fit(job: FitJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> FitOutput:
    """Run the fit job (module doc).

    The forward model keeps what it derives in one memory owner (`plate.memory`) held to a third of
    the job's memory (`--memory-gb`): the fit evaluates in this process (its tables traced on its
    threads), every evaluation at a new relief, so what it keeps is the tracer, the detector's
    weights and the last evaluations' tables and solver; the rest of the memory is for the evaluation
    being built."""
    from relief_bsdf.plate.memory import ForwardMemory, job_memory_bytes
    with ForwardMemory(job_memory_bytes() / 3).active():
        return _run(job, watched(progress, cancel), cancel)


def _run(job: FitJob, progress: Progress, cancel: CancelToken | None) -> FitOutput:
    from relief_bsdf.fit.baseline import baseline
    from relief_bsdf.fit.forward import Forward
    from relief_bsdf.fit.optimise import FitSettings, fit_relief
    from relief_bsdf.io.recording import read_sample
    from relief_bsdf.parallel.memory import small_pages
    small_pages()           # here and in its workers (parallel.memory)
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    sample = read_sample(job.sample)
    b = baseline(sample, method=job.method, samples=job.samples, seed=job.seed, grid=job.grid,
                 relief_options=job.relief_options)
    rec = b.recording
    fwd = Forward.of(b)
    settings = FitSettings(threshold=job.threshold, max_iter=job.max_iter, scale_bounds=job.scale_bounds,
                           max_filter_um=job.max_filter_um)
    check(cancel, "fitting")
    res = fit_relief(fwd, rec.bsdf_sr, rec.sigma_sr, settings, checkpoint=_job_store(out, sample, job),
                     progress=progress)
    check(cancel, "writing the fit's outputs")
    return FitOutput(_write(job, out, fwd, rec, res), out)


def _write(job: FitJob, out: Path, fwd: Any, rec: Any, res: Any) -> dict:
    """Every output of the fit (module doc); returns fit.json's document."""
    from relief_bsdf.io.atomic import write_text_atomic
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.io.isbsdf import export_isbsdf
    from relief_bsdf.io.recording import write_recording
    from relief_bsdf.report import fit_report as report
    from relief_bsdf.report.html import user_paths
    t0 = time.monotonic()
    best_relief, t_out, t_in = fwd.tables(res.height_scale, res.filter_sigma_um)
    after = fwd.simulated_with_sigma(res.height_scale, res.filter_sigma_um)
    sim_after = after.values_per_sr
    sim_before = fwd.simulate(1.0, 0.0)
    tables = [t for t in (t_out, t_in) if t is not None]
    save_tables(out / "boundary.h5", tables)
    files: dict = {"boundary_table": "boundary.h5"}
    for t in tables:      # OpticStudio: one scatter type per .bsdf file, BTDF centred on the refracted ray
        written = export_isbsdf(t, out / f"boundary_{t.incident_from}.bsdf")
        files[f"isbsdf_{t.incident_from}"] = [q.name for q in written]
    write_relief(out / "relief_optimised.npz", best_relief)
    files["relief"] = "relief_optimised.npz"
    write_recording(out / "simulated.csv", rec.with_values(sim_after, after.sigma_per_sr),
                    comments=["simulated plate after the fit; sigma_sr: the simulation's own 1-sigma (its tables' "
                              "uncertainty through the plate)"])
    files["simulated"] = "simulated.csv"
    rel = fwd.model_rel_sigma()         # the metric's model sigma (the optimiser's)
    plots = report.fit_plots(out, rec, sim_before, sim_after, rel * np.abs(sim_before), rel * np.abs(sim_after))
    files.update(plots)
    face = fwd.face
    doc = res.to_json({"method": face.method, "method_requested": job.method, "method_reason": face.chosen_by,
                       "sample": str(Path(job.sample)), "files": files,
                       "relief_history": list(best_relief.history), "physics": after.info.get("physics", {}),
                       "grid": fwd.grid.describe(),     # the plate's table grid; the sector tables when it used them
                       "stage_seconds": {**res.stage_seconds, "outputs": round(time.monotonic() - t0, 3)},
                       **({"inside_sectors": after.info["inside_sectors"]} if "inside_sectors" in after.info else {})})
    doc = user_paths(doc, job.sample, job.out)     # no absolute path of this machine beyond the user's own
    write_text_atomic(out / "fit.json", json.dumps(doc, indent=1))
    report.write_fit_report(out / "report.html", doc, plots)
    return doc
