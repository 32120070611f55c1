"""The sample as every forward model takes it: one decision about the relief, the rows and the physics.

`relief simulate`, `relief fit` and `relief diagnose` simulate the same plate; this module is
the one place where a sample.toml becomes that plate's forward model, so the three agree on:

- the relief: the height map as the sample's [relief] keys (and the command line's map flags
  over them) prepare it, refused when under `MIN_VALID_FRACTION` of its points are valid, and
  levelled as every statistic of it is (`surface.stats.levelled`: the mean removed from a periodic
  tile, the least-squares plane from a measured patch).  An instrument's tilt of the stage is no slope of the surface: a plane left
  in the heights would tilt every facet by it and steer the whole lobe;
- the rows: the recording's rows checked against the plate's grid (`plate.check_rows`: a row
  the engine cannot answer fails before any table), the material's index at their wavelengths;
- the physics of the relief face: `auto` resolved once on the relief as read, for the rows'
  wavelengths and incidences (`plate.resolve_auto`), then kept for every evaluation (a scale or
  a filter of the relief does not switch method mid-fit).

The one forward model over a Baseline is `fit.forward.PlateForward` (`PlateForward.of`); what differs
between the three stays in its thin subclasses: the fit varies the relief's scale and filter
(`fit.forward.Forward`), the diagnosis adds candidate effects (`diagnose.forward.DiagnosisForward`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.plate import DEFAULT_METHOD, Experiment, TableGrid, check_rows, experiment_from_sample, resolve_auto
from relief_bsdf.surface.relief import Relief

#: the least share of valid points of a height map a forward model accepts (the rest: holes a method
#: may fill or refuse, `--fill-holes`)
MIN_VALID_FRACTION = 0.5


def sample_relief(sample: Any, relief_options: Any = None) -> Relief:
    """The sample's relief as the forward models take it (module doc): prepared by its [relief] keys
    with `relief_options` (surface.preparation.ReliefOptions) over them, checked, levelled."""
    from relief_bsdf.io.heightmaps import read_sample_relief
    from relief_bsdf.surface.stats import levelled
    relief = read_sample_relief(sample, relief_options)
    relief.require_valid(MIN_VALID_FRACTION)
    return levelled(relief)


def resolved(experiment: Experiment, rows: Any, grid: TableGrid, where: str = "recording") -> Experiment:
    """`experiment` for these rows: the rows checked against the plate's grid, every `auto` relief face
    resolved once (module doc).  Idempotent: a resolved experiment comes back unchanged."""
    check_rows(experiment, rows, where)        # bad rows fail before any table
    return resolve_auto(experiment, rows, grid)


@dataclass(frozen=True)
class Baseline:
    """A sample's plate as stated, ready to simulate: the Sample, its relief (levelled), its recording
    (the rows), the Experiment with the relief face's physics decided, the engine's grid and the name
    the rows' errors carry."""

    sample: Any
    relief: Relief
    recording: Any
    experiment: Experiment
    grid: TableGrid
    where: str


def baseline(sample: Any, *, method: str = DEFAULT_METHOD, samples: int = 200_000, seed: int = 0,
             grid: TableGrid | None = None, relief_options: Any = None, face_options: dict | None = None) -> Baseline:
    """The Baseline of a sample (io.recording.Sample): its relief by `method` (its Monte-Carlo
    `samples` and `seed` where it samples; `face_options` the method's options) on its rough face."""
    grid = grid or TableGrid()
    relief = sample_relief(sample, relief_options)
    rec = sample.load_recording()
    sample.material.check(np.unique(np.asarray(rec.wavelength_nm, float)), str(sample.path))
    exp = experiment_from_sample(sample, relief, method=method, samples=samples, seed=seed, options=face_options)
    where = str(sample.recording_path)
    return Baseline(sample, relief, rec, resolved(exp, rec, grid, where), grid, where)
