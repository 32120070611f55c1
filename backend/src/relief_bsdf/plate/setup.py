"""The deterministic engine's configuration of an Experiment."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from relief_bsdf.core.index import ConstantIndex, IndexModel, Material
from relief_bsdf.errors import InputError
from relief_bsdf.plate.description import Bulk, Instrument
from relief_bsdf.plate.grid import INSIDE_INTERPOLATIONS


SOURCE_STOKES = {"unpolarized": np.array([1.0, 0.0, 0.0, 0.0]),
                 "s": np.array([1.0, 1.0, 0.0, 0.0]),
                 "p": np.array([1.0, -1.0, 0.0, 0.0])}


@dataclass(frozen=True)
class PlateModel:
    """The engine's internal configuration: everything besides the boundary tables (see `model_of`).

    The "effects" a diagnosis may switch on are plain fields with neutral defaults:
    absorption_per_m (bulk absorption), polarization (source state "unpolarized", "s",
    "p"), background_per_sr (stray light added to every row), blur_deg (Gaussian
    instrument blur, 1-sigma, added to the detector cone), tilt_deg (sample tilt about the
    y axis: incidence seen by the sample is theta_i + tilt in the plane of incidence),
    The second face is flat unless a table is given to PlateSolver / simulate_rows (`back`,
    relief on the front only).  Tilt: the sample
    normal is rotated by tilt_deg about the y axis of the instrument; rows are transformed into
    the sample frame and the reading converted back with f = f' cos theta_s' / cos theta_s (the
    instrument divides by its own cos theta_s).
    """

    thickness_m: float
    index: IndexModel
    rough_face: str = "front"
    absorption_per_m: float = 0.0
    detector_half_angle_deg: float = 1.0
    polarization: str | float = "unpolarized"
    outside_index: IndexModel = ConstantIndex(1.0)
    background_per_sr: float = 0.0
    blur_deg: float = 0.0
    tilt_deg: float = 0.0
    azimuth_cells: int = 72
    cone_points: int = 19
    scatter_per_m: float = 0.0
    hg_g: float = 0.0
    beam_divergence_deg: float = 0.0
    relief_anisotropic: bool = False     # the beam divergence's incidences solved in-plane and shifted (beam_split)
    beam_in_tables: bool = False         # the outside table was traced with the divergent beam (read once)
    inside_interpolation: str = "moving"  # between the inside tables' incidences: "moving" lobes or "linear"
    stokes_loop: bool = True              # False: intensities only through polarised tables (TableGrid.stokes_loop)

    def __post_init__(self) -> None:
        """The checks are the description's (plate.description: Instrument, Bulk): one owner each."""
        if self.rough_face not in ("front", "back"):
            raise InputError("plate.rough_face", f"must be 'front' or 'back', got {self.rough_face!r}")
        if not (self.thickness_m > 0 and np.isfinite(self.thickness_m)):
            raise InputError("plate.thickness_mm", f"thickness must be > 0, got {self.thickness_m}")
        if isinstance(self.polarization, str) and self.polarization not in SOURCE_STOKES:
            raise InputError("instrument.polarization",
                             f"must be unpolarized, s or p, got {self.polarization!r}")
        Instrument(self.detector_half_angle_deg, float(self.source_stokes[1]), self.blur_deg, self.tilt_deg,
                   self.background_per_sr, self.cone_points, self.beam_divergence_deg)
        Bulk(self.absorption_per_m, self.scatter_per_m, self.hg_g)
        if self.inside_interpolation not in INSIDE_INTERPOLATIONS:
            raise InputError("grid.inside_interpolation", f"must be one of {', '.join(INSIDE_INTERPOLATIONS)}, "
                             f"got {self.inside_interpolation!r}")
        if not self.stokes_loop and float(self.source_stokes[1]) != 0.0:
            raise InputError("grid.stokes_loop", "an intensity-only loop cannot carry a polarised source "
                             f"(Stokes q = {float(self.source_stokes[1]):g}): use the Stokes loop")

    @property
    def source_stokes(self) -> np.ndarray:
        """Source Stokes vector (1, q, 0, 0) in the s/p basis of the plane of incidence."""
        if isinstance(self.polarization, str):
            return SOURCE_STOKES[self.polarization]
        return np.array([1.0, float(self.polarization), 0.0, 0.0])

    @property
    def material(self) -> Material:
        return Material(inside=self.index, outside=self.outside_index)

    def with_effects(self, **kw: Any) -> "PlateModel":
        return replace(self, **kw)

    @staticmethod
    def from_sample(sample: Any) -> "PlateModel":
        """Build from a `relief_bsdf.io.recording.Sample` (sample.toml)."""
        p, ins = sample.plate, sample.instrument
        a = getattr(p, "absorption_per_mm", None)
        try:
            return PlateModel._from_specs(p, ins, a)
        except InputError as e:
            raise InputError(f"{sample.path}: {e.where}", e.message) from None

    @staticmethod
    def _from_specs(p: Any, ins: Any, a: Any) -> "PlateModel":
        return PlateModel(thickness_m=float(p.thickness_mm) * 1e-3, index=p.index, rough_face=p.rough_face,
                          absorption_per_m=0.0 if a is None else float(a) * 1e3,
                          detector_half_angle_deg=float(ins.detector_half_angle_deg),
                          polarization=str(ins.polarization))
