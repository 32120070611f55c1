"""What a face of the plate is, as code: the `Face` protocol both engines use, and what it shares.

Face-local frame: every face is described as a FRONT face: the outside medium above (+z), the
glass below (-z), relief heights measured outward.  The back face of the plate is the same
object seen through the mirror z -> -z (the engines do the mirroring), which is why a relief on
the back face is its height map as measured from the outside (formats.md).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.surface.digest import relief_digest as _digest
from relief_bsdf.surface.relief import Relief


@runtime_checkable
class Face(Protocol):
    """A face of the plate, as each engine meets it (FlatFace, ReliefFace, TableFace, MicrofacetFace).

    - `tables(material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress, beam_divergence_deg)`
      -> (outside table | None, inside table): isotropic BsdfTables on `grid`, for the deterministic engine
      (`need_outside` False: the face is lit from inside only; `beam_divergence_deg`: the source's
      divergence, traced into the outside table where the face can, `beam_in_table` says);
    - `interact(d, S, from_inside, ctx, rng)` -> FaceEvent: one interaction of photons with propagation
      directions d (N, 3) and Stokes vectors S (N, 4) (frame s = z x k, the tracer's and the tables'
      frame) hitting the face from outside (d_z < 0) or inside (d_z > 0), for the photon engine;
      ctx: PhotonContext (indices, wavelength, grid for faces that sample their tables);
    - `describe()` -> dict: the physics it stands for (every output says which was used);
    - `is_flat`: a plane face (the engines use exact Fresnel for it).

    Capabilities some faces add (looked up by name, not part of the protocol): `traces_beam(...)` (the
    outside table holds a divergent beam), `resolved(...)` (a relief face's "auto" method resolved),
    `relief` (a height map: anisotropy, sector tables, the half-turned table), `half_turned` (a table
    face's half-turned outside table)."""

    is_flat: bool

    def describe(self) -> dict: ...

    def tables(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
               need_outside: bool = True, progress: Any = None, beam_divergence_deg: float = 0.0
               ) -> tuple[BsdfTable | None, BsdfTable]: ...

    def interact(self, d: np.ndarray, S: np.ndarray, from_inside: Any, ctx: "PhotonContext",
                 rng: np.random.Generator) -> "FaceEvent": ...


def relief_digest(relief: Relief) -> str:
    """Content digest of a relief (`surface.digest`, the project's one): the cache key of its tables."""
    return _digest(relief)


def beam_in_table(table: BsdfTable | None) -> float:
    """The beam divergence (deg, 1-sigma per axis) a table's incidences were traced with (0: collimated)."""
    if table is None:
        return 0.0
    return float(table.metadata.get("request", {}).get("options", {}).get("beam_divergence_deg", 0.0) or 0.0)


def material_key(material: Material) -> str:
    """The material's part of a table's key (its indices as described)."""
    return json.dumps(material.describe(), sort_keys=True, default=str)


def _grid_key(grid: TableGrid) -> tuple:
    return grid.key()


@dataclass(frozen=True)
class PhotonContext:
    """What a face needs to scatter photons at one wavelength."""

    material: Material
    wavelength_nm: float
    grid: TableGrid = field(default_factory=TableGrid)
    theta_i_outside_deg: tuple = (0.0,)

    @property
    def n_outside(self) -> float:
        return float(np.real(self.material.outside.n(self.wavelength_nm)))

    @property
    def n_glass(self) -> float:
        return float(np.real(self.material.inside.n(self.wavelength_nm)))


@dataclass
class FaceEvent:
    """Photons after one face interaction, face-local frame: `outside` True = went to z > 0."""

    d: np.ndarray
    S: np.ndarray
    outside: np.ndarray
    lost: np.ndarray


def _table_args_key(material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
                    need_outside: bool) -> tuple:
    return (material_key(material), _grid_key(grid), tuple(float(w) for w in np.unique(wavelengths_nm)),
            tuple(float(t) for t in np.unique(theta_i_outside_deg)), bool(need_outside))
