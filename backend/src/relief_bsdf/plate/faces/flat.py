"""`FlatFace`: a plane face, Fresnel reflection and refraction (Born & Wolf 1.5.20-21, Mueller matrices of
core.fresnel)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.methods.flat import flat_tables
from relief_bsdf.plate.faces.base import FaceEvent, PhotonContext, _table_args_key
from relief_bsdf.plate.faces.photons import fresnel_event
from relief_bsdf.plate.grid import TableGrid, critical_angles_deg
from relief_bsdf.plate.memory import current_memory


def _flat_inside_incidences(material: Material, grid: TableGrid, wavelengths_nm: Any) -> np.ndarray:
    """The grid's inside incidences plus a dense band (0.05 deg) around each critical angle: Fresnel
    jumps to total reflection there, and the engine interpolates the table's delta parts linearly."""
    crit = critical_angles_deg(material, wavelengths_nm)
    th = [grid.inside_incidences_deg(crit)]
    for tc in crit:
        th.append(np.clip(np.arange(tc - 2.0, tc + 2.0 + 1e-9, 0.05), 0.0, 89.0))
        th.append([tc - 1e-6, tc + 1e-6])
    return np.unique(np.round(np.concatenate(th), 9))


@dataclass(frozen=True)
class FlatFace:
    """A plane face: Fresnel reflection and refraction (Mueller matrices), nothing diffuse."""

    is_flat = True

    def describe(self) -> dict:
        return {"face": "flat", "physics": "Fresnel (plane interface)"}

    def tables(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
               need_outside: bool = True, progress: Any = None, beam_divergence_deg: float = 0.0
               ) -> tuple[BsdfTable | None, BsdfTable]:
        """Fresnel tables (a plane face maps the beam one to one: the engine reads its deltas through it)."""
        def make():
            o, i = flat_tables(material, list(np.unique(wavelengths_nm)), np.unique(theta_i_outside_deg),
                               _flat_inside_incidences(material, grid, wavelengths_nm), grid.theta_edges_deg(),
                               grid.phi_edges_deg())
            return (o if need_outside else None), i
        key = ("flat",) + _table_args_key(material, grid, wavelengths_nm, theta_i_outside_deg, need_outside)
        return current_memory().get(key, make)

    def interact(self, d: np.ndarray, S: np.ndarray, from_inside: Any, ctx: PhotonContext,
                 rng: np.random.Generator) -> FaceEvent:
        nd, nS = fresnel_event(d, S, ctx.n_outside, ctx.n_glass, rng)
        return FaceEvent(nd, nS, nd[:, 2] > 0, np.zeros(d.shape[0], bool))
