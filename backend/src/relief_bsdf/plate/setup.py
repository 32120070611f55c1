"""How the deterministic engine is set up for one Experiment (`EngineSetup`, made by `deterministic.setup_of`).

The Experiment (`plate.description`) is the engine's only physical input: the setup adds nothing to it but
the engine's own choices for it (which face carries the relief the loop turns, the azimuth cells of the
grid, how the inside tables are read between their incidences, whether the loop carries Stokes
vectors, whether the relief is anisotropic enough for the beam's in-plane split, whether the outside
table already holds the beam divergence).  The numbers the engine reads (thickness, indices, bulk,
instrument) are read from the Experiment, never copied.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from relief_bsdf.core.index import IndexModel, Material
from relief_bsdf.errors import InputError
from relief_bsdf.plate.description import Experiment
from relief_bsdf.plate.grid import INSIDE_INTERPOLATIONS


@dataclass(frozen=True)
class EngineSetup:
    """An Experiment as the deterministic engine solves it (module doc).

    rough_face: "front" (the first face of the loop is the front face) or "back" (the relief on the back
        face: the system is solved with the roles swapped, `PlateSolver`);
    azimuth_cells: the loop's uniform azimuth cells (the grid's);
    relief_anisotropic: a beam divergence's incidences are solved in the nominal plane and shifted
        (`readout.beam_split`);
    beam_in_tables: the outside table was traced with the divergent beam (read at the nominal incidence);
    inside_interpolation: between the inside tables' incidences, "moving" lobes or "linear";
    stokes_loop: False: intensities only through polarised tables (`TableGrid.stokes_loop`).
    Tilt: the sample normal is rotated by the instrument's tilt_deg about its y axis; rows are
    transformed into the sample frame and the reading converted back with f = f' cos theta_s' / cos theta_s
    (the instrument divides by its own cos theta_s)."""

    experiment: Experiment
    rough_face: str = "front"
    azimuth_cells: int = 72
    relief_anisotropic: bool = False
    beam_in_tables: bool = False
    inside_interpolation: str = "moving"
    stokes_loop: bool = True

    def __post_init__(self) -> None:
        """The physics is checked by the description (Plate, Bulk, Instrument); here the engine's choices."""
        if self.rough_face not in ("front", "back"):
            raise InputError("plate.rough_face", f"must be 'front' or 'back', got {self.rough_face!r}")
        if self.inside_interpolation not in INSIDE_INTERPOLATIONS:
            raise InputError("grid.inside_interpolation", f"must be one of {', '.join(INSIDE_INTERPOLATIONS)}, "
                             f"got {self.inside_interpolation!r}")
        q = float(self.experiment.instrument.polarization_q)
        if not self.stokes_loop and q != 0.0:
            raise InputError("grid.stokes_loop", "an intensity-only loop cannot carry a polarised source "
                             f"(Stokes q = {q:g}): use the Stokes loop")

    def with_instrument(self, **kw: Any) -> "EngineSetup":
        return replace(self, experiment=self.experiment.with_instrument(**kw))

    # -- the Experiment's numbers, as the engine reads them
    @property
    def source_stokes(self) -> np.ndarray:
        """Source Stokes vector (1, q, 0, 0) in the s/p basis of the plane of incidence."""
        return np.array([1.0, float(self.experiment.instrument.polarization_q), 0.0, 0.0])

    @property
    def material(self) -> Material:
        return self.experiment.plate.material

    @property
    def thickness_m(self) -> float:
        return self.experiment.plate.thickness_m

    @property
    def index(self) -> IndexModel:
        return self.experiment.plate.index

    @property
    def outside_index(self) -> IndexModel:
        return self.experiment.plate.outside_index

    @property
    def absorption_per_m(self) -> float:
        return self.experiment.plate.bulk.absorption_per_m

    @property
    def scatter_per_m(self) -> float:
        return self.experiment.plate.bulk.scatter_per_m

    @property
    def hg_g(self) -> float:
        return self.experiment.plate.bulk.hg_g

    @property
    def detector_half_angle_deg(self) -> float:
        return self.experiment.instrument.detector_half_angle_deg

    @property
    def blur_deg(self) -> float:
        return self.experiment.instrument.blur_deg

    @property
    def tilt_deg(self) -> float:
        return self.experiment.instrument.tilt_deg

    @property
    def background_per_sr(self) -> float:
        return self.experiment.instrument.background_per_sr

    @property
    def cone_points(self) -> int:
        return self.experiment.instrument.cone_points

    @property
    def beam_divergence_deg(self) -> float:
        return self.experiment.instrument.beam_divergence_deg


BULK_FIELDS = ("thickness_m", "absorption_per_m", "scatter_per_m", "hg_g")   # act on a solver's bulk part alone
ENGINE_FIELDS = ("rough_face", "azimuth_cells", "relief_anisotropic", "beam_in_tables", "inside_interpolation",
                 "stokes_loop")


def plate_key(setup: EngineSetup) -> tuple:
    """What a solver's operators depend on: the plate's thickness, indices and bulk, and the engine's choices
    (not the instrument, nor the faces: their tables are the solver's own)."""
    return tuple((f, getattr(setup, f)) for f in ("index", "outside_index") + BULK_FIELDS + ENGINE_FIELDS)
