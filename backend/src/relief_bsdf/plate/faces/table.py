"""`TableFace`: a face given by its boundary tables; photons drawn from them."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.errors import InputError
from relief_bsdf.plate.faces.base import FaceEvent, PhotonContext, beam_in_table
from relief_bsdf.plate.faces.photons import _sample_from_tables
from relief_bsdf.plate.grid import TableGrid


@dataclass(frozen=True, eq=False)
class TableFace:
    """A face given by its tables: `inside` (light from the glass) and optionally `outside`; optionally
    `half_turned`, the outside table of its relief turned by a half turn (`half_turned_outside`: rows lit
    from the far half of azimuths read it; without it they read `outside` turned)."""

    inside: BsdfTable
    outside: BsdfTable | None = None
    half_turned: BsdfTable | None = None
    is_flat = False

    def describe(self) -> dict:
        return {"face": "table", "method": self.inside.method, "photons": "sampled from the tables"}

    def tables(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
               need_outside: bool = True, progress: Any = None, beam_divergence_deg: float = 0.0
               ) -> tuple[BsdfTable | None, BsdfTable]:
        """The given tables (whatever beam they were traced with, `traces_beam`)."""
        if need_outside and self.outside is None:
            raise InputError("plate", "this table face is lit from outside but has no outside table")
        return (self.outside if need_outside else None), self.inside

    def traces_beam(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any) -> bool:
        """Whether the outside table was traced with a divergent beam (`beam_in_table`)."""
        return beam_in_table(self.outside) > 0

    def interact(self, d: np.ndarray, S: np.ndarray, from_inside: Any, ctx: PhotonContext,
                 rng: np.random.Generator) -> FaceEvent:
        return _sample_from_tables(self.outside, self.inside, d, S, ctx, rng)
