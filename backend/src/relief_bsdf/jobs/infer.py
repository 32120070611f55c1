"""The job `relief infer`: a relief for a sample that has none, from its measured plate.

A thin job over `infer.job.infer` (the inversion of the transmitted lobe into a facet-slope
density, a periodic relief with it, the plate simulated on every recording row), which writes
OUT/relief.npz, sample.toml, simulated.csv and infer.json.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.progress import Progress


@dataclass(frozen=True)
class InferJob:
    """Infer a relief for `sample` (sample.toml: its [recording], measured plate files or recording.csv)
    into `out`, seeded by `seed` (relief and rays), `samples` Monte-Carlo samples per incidence of the
    ray-traced relief; `tile_px` the relief's side in points (None: infer's own, `infer.job.TILE_PX`)."""

    sample: Path
    out: Path
    seed: int = 0
    samples: int = 100_000
    tile_px: int | None = None


@dataclass(frozen=True)
class InferOutput:
    """infer.json's document (`doc`) and the folder `out` with relief.npz, sample.toml, simulated.csv."""

    doc: dict
    out: Path

    @property
    def relief(self) -> Path:
        return self.out / "relief.npz"


def run_infer(job: InferJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> InferOutput:
    from relief_bsdf.errors import InputError
    from relief_bsdf.infer.job import infer
    if job.samples < 1000:
        raise InputError("--samples", f"need at least 1000 samples, got {job.samples}")
    check(cancel, "inferring")
    size = {} if job.tile_px is None else {"tile_px": int(job.tile_px)}
    doc = infer(job.sample, job.out, seed=job.seed, progress=watched(progress, cancel), samples=job.samples, **size)
    return InferOutput(doc, Path(job.out))
