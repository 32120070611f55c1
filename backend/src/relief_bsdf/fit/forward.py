"""The one forward model of a sample's plate: what `relief simulate`, `relief fit` and `relief diagnose`
evaluate.

`PlateForward` is the sample's plate on its recording's rows, and the one place that decides for
the three jobs:

- the relief: as `fit.baseline` prepares it from the sample (`PlateForward.of`): its [relief]
  keys applied, refused when under `fit.baseline.MIN_VALID_FRACTION` of its points are valid, and
  levelled as every statistic of it is (a stage tilt is no slope of the surface);
- the rows and the physics of the relief face: the rows checked against the plate's grid and every
  `auto` face resolved once, on the relief as read (`fit.baseline.resolved`, idempotent), then
  kept for every evaluation: a scale, a filter or an effect does not switch method;
- the grid: the plate's default `TableGrid` unless one is given;
- an evaluation: `plate.simulate`'s deterministic engine on those rows and that grid, a row's
  error naming `where` (the recording's path);
- the simulation's own 1-sigma: the relative spread of `sigma_draws` draws of the boundary tables
  within their cells' sigma, carried through the plate at the relief as read
  (`plate.uncertainty.relative_deviations`), computed once and scaled with the values elsewhere
  (the relative noise of a table hardly moves with a scale, a filter or a plate effect; common
  random numbers keep it the same draw); and the draws at a point where an interval asks for them.

What differs stays in thin subclasses, each over this one: the fit's `Forward` puts a scaled and
filtered relief on the relief face (`surface.operations.scale_and_filter`), the diagnosis's
`diagnose.forward.DiagnosisForward` applies candidate effects and adds its memo, its screening
forward and its prefetch on worker processes.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.fit.baseline import Baseline, resolved
from relief_bsdf.plate import Experiment, ReliefFace, Simulated, TableGrid, simulate
from relief_bsdf.plate.faces import TRACED_METHODS
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.relief import Relief

#: table draws behind the simulation's own sigma (plate.uncertainty: the sigma known to about +-25 %)
SIGMA_DRAWS = 8
#: the share of a traced relief face's rays in the fit's search model (`Forward.search_model`)
SEARCH_SAMPLES_FRACTION = 0.25


def relief_face_name(experiment: Experiment) -> str:
    """"front" or "back": the plate's face that carries a relief (InputError when neither does)."""
    for name in ("front", "back"):
        if isinstance(getattr(experiment.plate, name), ReliefFace):
            return name
    raise InputError("forward model", "the experiment has no relief face")


class PlateForward:
    """The sample's plate on its recording's rows (module doc): `experiment` with its relief face's
    physics decided, `rows`, `grid`, `where`; evaluations by `run`, the simulation's own sigma by
    `model_rel_sigma` (at the relief as read) and `deviations` (at an evaluated point)."""

    def __init__(self, experiment: Experiment, rows: Any, grid: TableGrid | None = None, where: str = "recording",
                 sigma_draws: int = SIGMA_DRAWS) -> None:
        self.rows = rows
        self.grid = grid if grid is not None else TableGrid()
        self.where = str(where)
        self.sigma_draws = int(sigma_draws)
        # rows checked and "auto" decided once, on the relief as read, for every evaluation (fit.baseline)
        self.experiment = resolved(experiment, rows, self.grid, self.where)
        self.face_name = relief_face_name(self.experiment)
        self._rel_sigma: np.ndarray | None = None
        self._rel_dev: np.ndarray | None = None
        self._sigma_source: PlateForward | None = None      # a model of record whose sigma this one takes

    @classmethod
    def of(cls, b: Baseline, **kw: Any) -> "PlateForward":
        """The forward model of a Baseline (`fit.baseline.baseline`: the sample's relief levelled and checked)."""
        return cls(b.experiment, b.recording, grid=b.grid, where=b.where, **kw)

    @property
    def face(self) -> ReliefFace:
        """The relief face as read (its method decided)."""
        return getattr(self.experiment.plate, self.face_name)

    @property
    def method(self) -> str:
        return self.face.method

    def with_relief(self, relief: Relief) -> Experiment:
        """The experiment with `relief` on the relief face (its method, effort and seed kept)."""
        return self.experiment.with_plate(**{self.face_name: replace(self.face, relief=relief)})

    def run(self, experiment: Experiment | None = None, table_sigma_draws: int = 0) -> Simulated:
        """`experiment` (None: the plate as read) on the rows: `plate.simulate`'s deterministic engine on
        this grid; with `table_sigma_draws` >= 2 its own sigma from that many table draws at it."""
        return simulate(self.experiment if experiment is None else experiment, self.rows, grid=self.grid,
                        where=self.where, table_sigma_draws=table_sigma_draws)

    def model_rel_deviations(self) -> np.ndarray:
        """The table draws at the plate as read as relative deviations per row (sigma_draws x rows,
        plate.uncertainty.relative_deviations), computed once: their std is `model_rel_sigma`."""
        if self._sigma_source is not None:
            return self._sigma_source.model_rel_deviations()
        if self._rel_dev is None:
            from relief_bsdf.plate.uncertainty import relative_deviations
            self._rel_dev = relative_deviations(self.experiment, self.rows, self.grid, self.sigma_draws, self.where)
        return self._rel_dev

    def model_rel_sigma(self) -> np.ndarray:
        """The simulation's relative 1-sigma per row at the plate as read (module doc), computed once."""
        if self._sigma_source is not None:
            return self._sigma_source.model_rel_sigma()
        if self._rel_sigma is None:
            from relief_bsdf.plate.uncertainty import deviations_sigma
            self._rel_sigma = deviations_sigma(self.model_rel_deviations(), len(self.rows))
        return self._rel_sigma

    def deviations(self, experiment: Experiment, draws: int | None = None) -> np.ndarray:
        """The simulation's table draws at `experiment` as deviations per row (draws x rows, 1/sr;
        default plate.uncertainty.INTERVAL_DRAWS): an interval's shared model noise, made where asked."""
        from relief_bsdf.plate.uncertainty import INTERVAL_DRAWS, deviations
        return deviations(experiment, self.rows, self.grid, INTERVAL_DRAWS if draws is None else int(draws))


class Forward(PlateForward):
    """The fit's forward model: (height scale, filter) -> the plate with the relief scaled and filtered
    (step 6 of the fit, `process_relief`) on its relief face -> simulated recording values.

    `relief`: the relief as read (the one on the experiment's relief face); the rest as PlateForward.
    """

    def __init__(self, relief: Relief, experiment: Experiment, rows: Any, grid: TableGrid | None = None,
                 where: str = "recording", sigma_draws: int = SIGMA_DRAWS) -> None:
        super().__init__(experiment, rows, grid, where, sigma_draws)
        self.relief = relief
        self._dev_at: dict = {}

    @classmethod
    def of(cls, b: Baseline, **kw: Any) -> "Forward":
        return cls(b.relief, b.experiment, b.recording, grid=b.grid, where=b.where, **kw)

    def search_model(self, samples_fraction: float = SEARCH_SAMPLES_FRACTION) -> "Forward":
        """The fit's search model: this forward model with `samples_fraction` of the rays of a traced relief
        face (the same seed: common random numbers, a smooth objective) and, for an unpolarised source,
        the plate's loop on intensities (`TableGrid.stokes_loop` False); the model sigma of this one.

        What it costs and misses, on the demo plate (ray, 200k rays, one process): an evaluation 7.6 CPU-s
        of which the tables 5.1-5.9 (3.7 M segments outside, 5.8 M inside) and the Stokes loop 1.7-2.3; at a
        quarter of the rays on the intensity loop the same evaluation is about 3.2 CPU-s, its rows 5 %
        (median) off the model of record and its rms z 1.07 where the model of record's is 0.92.  It
        steers the search from far away (`fit.optimise`); what is estimated, tested and reported is
        always evaluated on the model of record (docs/decisions/022)."""
        face = self.face
        if face.method in TRACED_METHODS:
            face = replace(face, samples=max(int(round(face.samples * float(samples_fraction))), 1))
        grid = self.grid
        if float(self.experiment.instrument.polarization_q) == 0.0:
            grid = replace(grid, stokes_loop=False)
        if face is self.face and grid == self.grid:
            return self
        other = Forward(self.relief, self.experiment.with_plate(**{self.face_name: face}), self.rows, grid, self.where,
                        self.sigma_draws)
        other._sigma_source = self
        return other

    def experiment_at(self, height_scale: float, filter_sigma_um: float) -> tuple[Relief, Experiment]:
        """(processed relief, the experiment with it on the relief face)."""
        r = process_relief(self.relief, height_scale, filter_sigma_um)
        return r, self.with_relief(r)

    def tables(self, height_scale: float, filter_sigma_um: float):
        """(processed relief, outside table | None, inside table) of the relief face at these parameters."""
        r, ex = self.experiment_at(height_scale, filter_sigma_um)
        face = getattr(ex.plate, self.face_name)
        return r, *face.tables(ex.plate.material, self.grid, np.unique(self.rows.wavelength_nm),
                               np.unique(self.rows.theta_i_deg), need_outside=self.face_name == "front")

    def simulate(self, height_scale: float, filter_sigma_um: float) -> np.ndarray:
        return self.simulated(height_scale, filter_sigma_um).values_per_sr

    def simulated(self, height_scale: float, filter_sigma_um: float, table_sigma_draws: int = 0) -> Simulated:
        return self.run(self.experiment_at(height_scale, filter_sigma_um)[1], table_sigma_draws)

    def model_deviations_at(self, height_scale: float, filter_sigma_um: float) -> np.ndarray:
        """The simulation's table draws at (scale, filter) as deviations per row (`deviations`, at least
        INTERVAL_DRAWS and `sigma_draws`), kept: the fitted point's draws also give its simulated sigma."""
        from relief_bsdf.plate.uncertainty import INTERVAL_DRAWS
        key = f"{float(height_scale):.10g},{float(filter_sigma_um):.10g}"
        if key not in self._dev_at:
            self._dev_at[key] = self.deviations(self.experiment_at(height_scale, filter_sigma_um)[1],
                                                max(INTERVAL_DRAWS, self.sigma_draws))
        return self._dev_at[key]

    def simulated_with_sigma(self, height_scale: float, filter_sigma_um: float) -> Simulated:
        """`simulated` with its 1-sigma per row: the spread of the table draws at this point
        (`model_deviations_at`, the same draws as the intervals there: made once, not again)."""
        from relief_bsdf.plate.uncertainty import sigma_note
        sim = self.simulated(height_scale, filter_sigma_um)
        dev = self.model_deviations_at(height_scale, filter_sigma_um)
        if dev.shape[0] < 2:
            return sim
        return Simulated(sim.values_per_sr, dev.std(axis=0, ddof=1), {**sim.info, "sigma": sigma_note(dev.shape[0])})


def process_relief(relief: Relief, height_scale: float, filter_sigma_um: float) -> Relief:
    """Step 6 of the fit: the global relief modification being optimised (surface.operations.scale_and_filter)."""
    return scale_and_filter(relief, float(height_scale), max(float(filter_sigma_um), 0.0) * 1e-6)
