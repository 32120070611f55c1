"""The height-map jobs `relief fill` and `relief crop`: read a map as the options say, write the result.

A map is read through `io.heightmaps.read_prepared_relief` with a `surface.preparation.ReliefOptions`
(crop, downsample, periodicity, hole filling: each step recorded in the relief's history) and
written as .x3p or .npz (`io.heightmaps.write_relief`, atomic).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relief_bsdf.errors import InputError
from relief_bsdf.jobs.control import CancelToken, check
from relief_bsdf.progress import Progress

#: the height-map files a job writes
OUT_SUFFIXES = (".x3p", ".npz")


def check_out_suffix(out: str | Path) -> None:
    """InputError unless `out` names a height-map file this project writes (OUT_SUFFIXES)."""
    if Path(out).suffix.lower() not in OUT_SUFFIXES:
        raise InputError(out, "the output height map must be .x3p or .npz")


@dataclass(frozen=True)
class FillJob:
    """`relief fill`: the map `relief` (read with `options`, a ReliefOptions or None; `pitch_m` for files
    without one) with its missing points filled by harmonic (Laplace) interpolation, holes no wider
    than `max_gap_px` points (None: every hole), written to `out`."""

    relief: Path
    out: Path
    max_gap_px: int | None = None
    pitch_m: tuple | None = None
    options: Any = None


@dataclass(frozen=True)
class FillOutput:
    """The filled relief as written to `out`; `missing` points before, `left` after (in holes wider
    than the job's max_gap_px)."""

    relief: Any
    out: Path
    missing: int
    left: int


def run_fill(job: FillJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> FillOutput:
    from relief_bsdf.io.heightmaps import read_prepared_relief, write_relief
    check_out_suffix(job.out)
    if job.max_gap_px is not None and job.max_gap_px < 1:
        raise InputError("--max-gap-px", f"expected a whole number >= 1, got {job.max_gap_px}")
    relief = read_prepared_relief(job.relief, job.options, pitch_m=job.pitch_m)
    check(cancel, "filling")
    missing = int((~relief.valid).sum())
    filled = relief.fill_holes(job.max_gap_px) if missing else relief
    check(cancel, "writing")
    write_relief(job.out, filled)
    return FillOutput(filled, Path(job.out), missing, int((~filled.valid).sum()))


@dataclass(frozen=True)
class CropJob:
    """`relief crop`: the map `relief` read with `options` (its crop window and downsampling; `pitch_m`
    for files without one), written to `out`."""

    relief: Path
    out: Path
    pitch_m: tuple | None = None
    options: Any = None


@dataclass(frozen=True)
class CropOutput:
    """The cropped relief as written to `out`."""

    relief: Any
    out: Path


def run_crop(job: CropJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> CropOutput:
    from relief_bsdf.io.heightmaps import read_prepared_relief, write_relief
    check_out_suffix(job.out)
    relief = read_prepared_relief(job.relief, job.options, pitch_m=job.pitch_m)
    check(cancel, "writing")
    write_relief(job.out, relief)
    return CropOutput(relief, Path(job.out))
