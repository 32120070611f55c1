"""`MicrofacetFace`: a rough face given by a Beckmann slope distribution (Walter et al. 2007)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.core.microfacet import sample_normals, smith_G1
from relief_bsdf.errors import InputError
from relief_bsdf.plate.faces.base import FaceEvent, PhotonContext
from relief_bsdf.plate.faces.photons import fresnel_event
from relief_bsdf.plate.faces.relief import ReliefFace, _derive
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.surface.relief import Relief


@dataclass(frozen=True)
class MicrofacetFace:
    """A rough face described by a Beckmann slope distribution of roughness `alpha` (Walter et al. 2007).

    Tables: the `microfacet` method at this alpha.  Photons: a facet normal m drawn from
    D(m) (m . z) (Beckmann slopes, core.microfacet.sample_normals), one Fresnel event on it
    (fresnel_event), weight |d . m| / (|d_z| m_z) G1(d) G1(o) (Walter 2007 eq. 38-41 with the
    separable Smith G); an exit on the wrong side of the mean plane is lost (single scattering).
    Polarisation: depolarised after the event (S -> (S0, 0, 0, 0)), as the tables' diffuse cells.
    """

    alpha: float
    distribution: str = "beckmann"
    samples: int = 200_000
    is_flat = False

    def __post_init__(self) -> None:
        if not (self.alpha > 0):
            raise InputError("face.alpha", f"microfacet roughness must be > 0, got {self.alpha}")

    def describe(self) -> dict:
        return {"face": "microfacet", "alpha": self.alpha, "distribution": self.distribution,
                "photons": "sampled Beckmann facet normals"}

    def tables(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
               need_outside: bool = True, progress: Any = None, beam_divergence_deg: float = 0.0
               ) -> tuple[BsdfTable | None, BsdfTable]:
        """The `microfacet` method's tables (single incidences: the engine spreads the beam itself)."""
        flat = Relief(np.zeros((8, 8)), 1e-6, 1e-6, periodic=True, source="microfacet face (alpha given)")
        as_relief = ReliefFace(flat, method="microfacet", samples=self.samples, seed=0,
                               options={"alpha": float(self.alpha), "distribution": self.distribution})
        return _derive(as_relief, material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress)

    def interact(self, d: np.ndarray, S: np.ndarray, from_inside: Any, ctx: PhotonContext,
                 rng: np.random.Generator) -> FaceEvent:
        n = d.shape[0]
        m = sample_normals(float(self.alpha), n, rng, self.distribution)
        m = m * np.sign(m[:, 2:3])                                      # facets face +z (outside)
        dm = np.sum(d * m, axis=1)
        nd, nS = fresnel_event(d, S, ctx.n_outside, ctx.n_glass, rng, normal=m)
        ci = np.abs(d[:, 2])
        w = np.abs(dm) / np.maximum(ci * m[:, 2], 1e-12)
        w *= smith_G1(ci, self.alpha, self.distribution) * smith_G1(np.abs(nd[:, 2]), self.alpha, self.distribution)
        # the facet must face the incoming light; the exit must leave the mean plane
        came_from_above = d[:, 2] < 0
        ok = (np.where(came_from_above, dm < 0, dm > 0)) & (np.abs(nd[:, 2]) > 1e-9)
        S_out = np.zeros_like(nS)
        S_out[:, 0] = nS[:, 0] * np.where(ok, w, 0.0)
        return FaceEvent(nd, S_out, nd[:, 2] > 0, ~ok)
