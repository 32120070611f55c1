"""The job `relief reconstruct`: a relief's boundary BSDF tables by one method, written to HDF5.

Read the height map (its options: crop, downsample, periodicity, hole filling), reconstruct the
tables of both requested sides of incidence with the method (`methods.reconstruct`, "auto"
resolved there from the relief's statistics), write them atomically (`io.hdf5.save_tables`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relief_bsdf.errors import InputError
from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.progress import Progress

#: the table files this job writes
TABLE_SUFFIXES = (".h5", ".hdf5")
#: principal rms slopes more than 20 % apart: one incidence azimuth misdescribes the relief
AZIMUTH_WARN_RATIO = 1.2


def check_table_out(out: str | Path) -> None:
    """InputError unless `out` names an HDF5 table file."""
    if Path(out).suffix.lower() not in TABLE_SUFFIXES:
        raise InputError(Path(out), "the output table must be an HDF5 file (.h5)")


def check_method(method: str) -> None:
    """InputError (RequestError) naming an unknown method, before anything is read."""
    from relief_bsdf.methods import get_method
    get_method(method)


@dataclass(frozen=True)
class ReconstructJob:
    """Tables of the boundary `relief` (a height-map file, read with `options`, a ReliefOptions or
    None; `pitch_m` (dx, dy) for files without one) over `material` (core.index.Material), by
    `method` for `request` (methods.request.Request, validated), written to `out` (.h5)."""

    relief: Path
    out: Path
    material: Any
    request: Any
    method: str = "auto"
    options: Any = None
    pitch_m: tuple | None = None


@dataclass(frozen=True)
class ReconstructOutput:
    """The `tables` written to `out`, the `relief` as read (after its options), the method asked for and
    the one that ran (`chosen`: "auto"'s choice, None when the method was named)."""

    tables: list
    out: Path
    relief: Any
    method: str
    chosen: str | None


def run_reconstruct(job: ReconstructJob, progress: Progress | None = None,
                    cancel: CancelToken | None = None) -> ReconstructOutput:
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.io.heightmaps import read_prepared_relief
    from relief_bsdf.methods import reconstruct
    check_table_out(job.out)
    check_method(job.method)
    relief = read_prepared_relief(job.relief, job.options, pitch_m=job.pitch_m)
    warn_one_azimuth(relief, job.request)
    check(cancel, "reconstructing")
    tables = reconstruct(relief, job.material, job.request, job.method, progress=watched(progress, cancel))
    check(cancel, "writing")
    save_tables(job.out, tables)
    chosen = tables[0].method if tables and tables[0].method != job.method else None
    return ReconstructOutput(tables, Path(job.out), relief, job.method, chosen)


def warn_one_azimuth(relief: Any, request: Any) -> None:
    """One warning when the relief's principal rms slopes differ by more than 20 % and the request has
    a single incidence azimuth: its table then holds the relief seen from that azimuth only (an
    export of it stands for every orientation), so it says which option gives the azimuths."""
    from relief_bsdf.plate.faces import slope_anisotropy
    if len(set(float(p) % 360.0 for p in request.phi_i_deg)) > 1:
        return
    ratio, axis = slope_anisotropy(relief)
    if ratio > AZIMUTH_WARN_RATIO:
        warnings.warn(f"{relief.source or 'the map'} is anisotropic (principal rms slopes {ratio:.2g}x apart, steeper "
                      f"axis at {axis:.0f} deg): one incidence azimuth does not describe it; give the azimuths with "
                      "--phi-i-deg (e.g. 0,45,90,135)", RuntimeWarning, stacklevel=3)
