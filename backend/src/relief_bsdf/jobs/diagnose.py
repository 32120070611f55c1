"""The job `relief diagnose`: name the physics the simulation of a sample leaves out, and write it.

The diagnosis itself (`diagnose.run.diagnosis`: baseline by `fit.baseline`, localisation, stepwise
selection of candidate effects, intervals) writes nothing; this job writes OUT/diagnosis.json
(formats.md schema) and OUT/report.html (`diagnose.report.write_report`), each atomically.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.plate import DEFAULT_METHOD
from relief_bsdf.progress import Progress


@dataclass(frozen=True)
class DiagnoseJob:
    """Diagnose `sample` (sample.toml) into `out`: the baseline's relief face by `method` (`photons`
    Monte-Carlo samples per incidence where it samples, `seed`; `sectors`: TableGrid.sectors), the
    candidate `effects` (None: every effect module), at most `workers` worker processes (None: every
    core); `report`: also write report.html."""

    sample: Path
    out: Path
    method: str = DEFAULT_METHOD
    photons: int = 200_000
    seed: int = 0
    effects: tuple | None = None
    workers: int | None = None
    sectors: str = "auto"
    report: bool = True


@dataclass(frozen=True)
class DiagnoseOutput:
    """diagnosis.json's document (`doc`) and the folder `out` it was written to."""

    doc: dict
    out: Path


def run_diagnose(job: DiagnoseJob, progress: Progress | None = None,
                 cancel: CancelToken | None = None) -> DiagnoseOutput:
    from relief_bsdf.diagnose.report import write_report
    from relief_bsdf.diagnose.run import diagnosis
    from relief_bsdf.io.atomic import write_text_atomic
    from relief_bsdf.report.html import user_paths
    d = diagnosis(job.sample, watched(progress, cancel), method=job.method, photons=job.photons, seed=job.seed,
                  effects=list(job.effects) if job.effects is not None else None, workers=job.workers,
                  sectors=job.sectors)
    check(cancel, "writing the diagnosis")
    doc = user_paths(d.doc, job.sample, job.out)   # no absolute path of this machine beyond the user's own
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "diagnosis.json", json.dumps(doc, indent=1))
    if job.report:
        write_report(out / "report.html", d.rows, *d.baseline, *d.chosen, doc)
    return DiagnoseOutput(doc, out)
