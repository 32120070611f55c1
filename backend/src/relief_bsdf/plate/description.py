"""The one description of a goniophotometer experiment on a plate: faces, bulk, instrument.

This is the forward model's *data* (no engine here).  Both engines run it:

- `plate.deterministic` (radiative transfer between the two faces over the faces' boundary
  tables, discrete ordinates with azimuthal reduction; fast, used by simulate / fit / diagnose);
- `plate.photon` (photon Monte Carlo: each face scatters one photon at a time, the bulk draws
  free paths; used to check the deterministic engine and where a table would be too coarse).

One detector (`plate.detector`) turns either engine's output into recording rows, with one
definition of the instrument's angular response (detector cone convolved with a Gaussian
aperture blur).  The source's beam divergence is a spread of the INCIDENCE direction, not of
the reading: the plate is lit from a Gaussian spread of incidences (`Instrument.
beam_divergence_deg`).  The two differ off normal incidence: a lobe does not move rigidly with
the incidence (seen through the independent photon Monte Carlo on a concealed relief of
rms slope 0.11, n 1.5, theta_i 55 deg, 2.5 deg both ways: up to 9 % in the grazing reflected
flank and 8-20 % across the transmitted lobe).

Frame (formats.md): plate fills -t < z < 0, the lit face is z = 0, light comes from z > 0.

Every effect the diagnosis may switch on is a field here with a neutral default, so an
effect is "a change of this description" (`dataclasses.replace`), defined once in
`diagnose.effects.<name>`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from relief_bsdf.core.index import ConstantIndex, IndexModel, Material
from relief_bsdf.errors import InputError

SOURCE_Q = {"unpolarized": 0.0, "s": 1.0, "p": -1.0}


@dataclass(frozen=True)
class Instrument:
    """The goniophotometer.

    detector_half_angle_deg: half-angle of the detector's acceptance cone (uniform response).
    polarization_q: source Stokes vector (1, q, 0, 0) in the s/p basis of the plane of
        incidence: +1 s, -1 p, 0 unpolarised (sample.toml "s" / "p" / "unpolarized").
    blur_deg: 1-sigma of a Gaussian angular blur of the detector's aperture convolved with the
        detector cone: the instrument's angular response is cone (x) Gaussian.
    tilt_deg: sample normal rotated by this angle about the instrument's y axis (plane of
        incidence): rows are seen in the tilted sample's frame.
    background_per_sr: stray light, a constant added to every reading.
    cone_points: quadrature points of the detector cone (deterministic engine).
    beam_divergence_deg: 1-sigma per axis of the source beam's Gaussian divergence: each ray of
        the beam arrives from the nominal incidence offset by a 2-D Gaussian tangent-plane angle
        (the photon engine draws it per photon; the deterministic engine traces it into a ray-traced
        relief's outside table, each ray drawn, and otherwise solves the plate at a quadrature of
        incidences, plate.deterministic.front_traces_beam / plate.readout.simulate_rows).
    """

    detector_half_angle_deg: float = 1.0
    polarization_q: float = 0.0
    blur_deg: float = 0.0
    tilt_deg: float = 0.0
    background_per_sr: float = 0.0
    cone_points: int = 19
    beam_divergence_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (0 < self.detector_half_angle_deg < 45):
            raise InputError("instrument.detector_half_angle_deg",
                             f"the detector cone half-angle must be in (0, 45) degrees, got "
                             f"{self.detector_half_angle_deg}")
        if not (-1.0 <= self.polarization_q <= 1.0):
            raise InputError("instrument.polarization", f"source q must be in [-1, 1], got {self.polarization_q}")
        if not (self.blur_deg >= 0):
            raise InputError("instrument.blur_deg", f"must be >= 0, got {self.blur_deg}")
        if not (0 <= self.beam_divergence_deg < 15):
            raise InputError("instrument.beam_divergence_deg",
                             f"must be in [0, 15) degrees (a small Gaussian spread), got {self.beam_divergence_deg}")


@dataclass(frozen=True)
class Bulk:
    """The plate's material between the faces (per metre of path in the glass).

    absorption_per_m: Beer-Lambert coefficient a: a path of length L keeps exp(-a L).
    scatter_per_m: volume scattering coefficient mu_s (free paths ~ Exp(mu_s)).
    hg_g: Henyey-Greenstein asymmetry of the volume phase function (Henyey & Greenstein 1941);
        polarisation is carried unchanged through a volume event (scalar approximation).
    """

    absorption_per_m: float = 0.0
    scatter_per_m: float = 0.0
    hg_g: float = 0.0

    def __post_init__(self) -> None:
        if not (self.absorption_per_m >= 0):
            raise InputError("plate.absorption_per_mm", f"absorption must be >= 0, got {self.absorption_per_m}")
        if not (self.scatter_per_m >= 0):
            raise InputError("plate.scatter_per_mm", f"scattering must be >= 0, got {self.scatter_per_m}")
        if not (-1 < self.hg_g < 1):
            raise InputError("plate.hg_g", f"Henyey-Greenstein g must be in (-1, 1), got {self.hg_g}")


@dataclass(frozen=True)
class Plate:
    """A plane-parallel plate: front face (lit, z = 0), back face (z = -t), bulk, indices.

    `front` / `back` are faces (`plate.faces`: FlatFace, ReliefFace, TableFace, MicrofacetFace).
    """

    thickness_m: float
    index: IndexModel
    front: Any
    back: Any
    bulk: Bulk = field(default_factory=Bulk)
    outside_index: IndexModel = ConstantIndex(1.0)

    def __post_init__(self) -> None:
        if not (self.thickness_m > 0 and self.thickness_m < float("inf")):
            raise InputError("plate.thickness_mm", f"thickness must be > 0, got {self.thickness_m}")

    @property
    def material(self) -> Material:
        return Material(inside=self.index, outside=self.outside_index)


@dataclass(frozen=True)
class Experiment:
    """A plate in an instrument: everything a simulated recording depends on besides the rows."""

    plate: Plate
    instrument: Instrument = field(default_factory=Instrument)

    def with_instrument(self, **kw: Any) -> "Experiment":
        return replace(self, instrument=replace(self.instrument, **kw))

    def with_bulk(self, **kw: Any) -> "Experiment":
        return replace(self, plate=replace(self.plate, bulk=replace(self.plate.bulk, **kw)))

    def with_plate(self, **kw: Any) -> "Experiment":
        return replace(self, plate=replace(self.plate, **kw))
