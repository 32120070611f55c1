"""`ReliefFace`: a face carrying a measured or synthetic relief, its physics the boundary method (`methods`):
tables by `methods.reconstruct` of the relief (`plate.faces.derive`); photons traced through the
triangulated relief (methods.ray.ReliefTracer) when the method is geometric ray tracing ("ray"),
otherwise drawn from the face's own tables.  "auto" is resolved once per relief (`resolved`)."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.errors import RequestError
from relief_bsdf.methods.auto import choose
from relief_bsdf.methods.registry import entry
from relief_bsdf.plate.faces.base import FaceEvent, PhotonContext, _grid_key, material_key, relief_digest
from relief_bsdf.plate.faces.derive import TRACED_METHODS, _derive_outside, _reconstruct_side
from relief_bsdf.plate.faces.photons import _sample_from_tables
from relief_bsdf.plate.faces.sectors import _resolved_relief, inside_face
from relief_bsdf.plate.faces.table import TableFace
from relief_bsdf.plate.grid import TableGrid, critical_angles_deg
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.surface.relief import Relief


def _derive(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
            need_outside: bool, progress: Any = None, beam_divergence_deg: float = 0.0
            ) -> tuple[BsdfTable | None, BsdfTable]:
    """(outside | None, inside) tables of a relief face by its method (`methods.reconstruct`) on `grid`.

    Each side is cached on its own (the inside table does not depend on the outside incidences,
    so a tilt or a new incidence re-derives only the outside table).  `beam_divergence_deg`: the
    source's divergence, traced into the outside table where the method draws rays (`ray`: each ray's
    incidence spread, `beam_in_table` tells); other methods ignore it (the plate then spreads the
    incidence itself, plate.deterministic).
    """
    wl = tuple(float(w) for w in np.unique(np.asarray(wavelengths_nm, float)))
    base = (face.cache_key(), material_key(material), _grid_key(grid), wl)
    out = (_derive_outside(face, material, grid, wl, theta_i_outside_deg, progress, beam_divergence_deg)
           if need_outside else None)
    f_in = inside_face(face, material, grid, wl, progress)
    ins = current_memory().get((f_in.cache_key(),) + base[1:] + ("inside",),
                          lambda: _reconstruct_side(f_in, material, grid, wl, grid.inside_incidences_deg(critical_angles_deg(material, wl)), "inside",
                                                    progress))
    return out, ins


def half_turned_outside(face: Any, material: Material, grid: TableGrid, wavelengths_nm: Any,
                        theta_i_outside_deg: Any, progress: Any = None, beam_divergence_deg: float = 0.0
                        ) -> BsdfTable | None:
    """The outside table, at incidence azimuth 0, of a relief face turned by a half turn about its normal:
    the face's own outside table for light arriving from azimuth 180 deg, in the frame of that incidence.
    None for a face without a relief to turn (flat: turning changes nothing; a face given by slope
    statistics alone, or by its tables without a `half_turned` one: the engine's rotation stands).

    Why: the deterministic engine reads a row lit from incidence azimuth phi_i as its phi_i = 0 table
    turned by phi_i (plate.deterministic), which is exact for the ensemble of an isotropic relief but
    not for one finite tile: its lobes carry the tile's own realisation, and at phi_i = 180 they are
    those of the tile met from the other side.  A sample tilt at normal incidence is the common case
    (the sample then sees the beam from azimuth 180 in its own frame): on a 256^2 Gaussian tile the
    rotated table missed the independent photon Monte Carlo through the same tile by rms z 4.2 (R) and
    5.2 (T) on 1-deg rows, the half-turned tile by 1.07 and 0.91 (docs/decisions/002).  Turning the height map,
    heights[::-1, ::-1] (h'(x, y) = h(-x, -y), exact on the sampling grid whatever the pitch), makes it
    exact for every method."""
    if isinstance(face, TableFace):
        return face.half_turned
    face = _resolved_relief(face, material, grid, wavelengths_nm, theta_i_outside_deg)
    if face is None:
        return None
    heights = np.ascontiguousarray(np.asarray(face.relief.heights_m)[::-1, ::-1])
    turned = replace(face, relief=face.relief.with_heights(heights, "turned by a half turn about the normal"))
    return _derive_outside(turned, material, grid, wavelengths_nm, theta_i_outside_deg, progress, beam_divergence_deg)


@dataclass(frozen=True, eq=False)
class ReliefFace:
    """A face carrying a measured / synthetic relief; its physics is the boundary `method`.

    method: a `methods` name: "auto" (the default: the relief's own physics, resolved once per
        relief by `plate.choice.resolve_face`), "ray", "kirchhoff", ..., or a named fast surrogate
        ("microfacet+dw");
    samples / seed: the method's Monte-Carlo effort; options: the method's options (dict);
    coherence_length_m: the source's coherence length for wave methods (Request field; None: coherent);
    chosen_by: auto's one-line reason once resolved ("" when the method was named).
    Photons: traced through the relief (ReliefTracer) for "ray", drawn from the tables otherwise.
    """

    relief: Relief
    method: str = "auto"
    samples: int = 200_000
    seed: int = 0
    options: dict = field(default_factory=dict)
    coherence_length_m: float | None = None
    chosen_by: str = ""
    is_flat = False

    def describe(self) -> dict:
        photons = "ray-traced relief" if self.method in TRACED_METHODS else "sampled from the face's tables"
        try:
            physics = entry(self.method).physics
        except RequestError:          # an unknown name fails when its tables are asked for, naming it
            physics = ""
        return {"face": "relief", "method": self.method, "physics": physics, "chosen_by": self.chosen_by,
                "options": dict(self.options), "photons": photons,
                "relief": self.relief.source if hasattr(self.relief, "source") else ""}

    def cache_key(self) -> tuple:
        """Everything about this face that determines its tables (relief content, method, effort)."""
        return ("relief", relief_digest(self.relief), self.method, json.dumps(self.options, sort_keys=True, default=str),
                int(self.samples), int(self.seed), self.coherence_length_m)

    def tables(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
               need_outside: bool = True, progress: Any = None, beam_divergence_deg: float = 0.0
               ) -> tuple[BsdfTable | None, BsdfTable]:
        """(outside | None, inside) tables; `beam_divergence_deg` traced into the outside table where
        the method can (`_derive`, `beam_in_table`)."""
        if self.method == "auto":          # one choice for both sides (`resolved`)
            face = self.resolved(material, grid, wavelengths_nm, theta_i_outside_deg)
            return face.tables(material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress,
                               beam_divergence_deg)
        return _derive(self, material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress,
                       beam_divergence_deg)

    def traces_beam(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any) -> bool:
        """Whether this face's outside table holds a divergent beam itself (its method draws rays)."""
        return self.resolved(material, grid, wavelengths_nm, theta_i_outside_deg).method == "ray"

    def resolved(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any
                 ) -> "ReliefFace":
        """This face with method "auto" replaced by auto's choice for this relief, material, wavelengths and
        incidences (`methods.auto.choose`, light from outside AND inside: the inside index is the stricter
        case for the wave conditions); the face itself when its method is named.  The face's options that
        the chosen method knows are kept (auto's own, e.g. quiet, are dropped), auto's extras added, and
        the choice recorded (`chosen_by`)."""
        if self.method != "auto":
            return self
        req = grid.request(np.unique(np.asarray(wavelengths_nm, float)),
                           np.unique(np.asarray(theta_i_outside_deg, float)), "outside", "auto", self.samples,
                           self.seed, self.options)
        c = choose(self.relief, material, dataclasses.replace(req, incident_from=("outside", "inside")))
        known = {f.name for f in dataclasses.fields(entry(c.method).options)}
        opts = {k: v for k, v in self.options.items() if k in known}
        opts.update(c.options)
        return dataclasses.replace(self, method=c.method, options=opts, chosen_by=f"auto: {c.method}: {c.summary}")

    def tracer(self) -> Any:
        """The relief's ReliefTracer (BVH built once per relief content)."""
        from relief_bsdf.methods.ray import ReliefTracer
        return current_memory().get(("tracer", relief_digest(self.relief)), lambda: ReliefTracer(self.relief), "tracer")

    def interact(self, d: np.ndarray, S: np.ndarray, from_inside: Any, ctx: PhotonContext,
                 rng: np.random.Generator) -> FaceEvent:
        if self.method not in TRACED_METHODS:
            out_t, in_t = self.tables(ctx.material, ctx.grid, [ctx.wavelength_nm], ctx.theta_i_outside_deg, True)
            return _sample_from_tables(out_t, in_t, d, S, ctx, rng)
        r = self.tracer().scatter(d, ctx.n_outside, ctx.n_glass, rng, stokes=S)
        lost = np.asarray(r.lost, bool)
        return FaceEvent(np.asarray(r.dirs, float), np.asarray(r.stokes, float), np.asarray(r.above, bool) & ~lost,
                         lost)
