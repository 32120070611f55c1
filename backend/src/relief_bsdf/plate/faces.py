"""The faces of the plate: each knows its boundary tables (deterministic engine) and how it
scatters one photon (Monte Carlo).

Face-local frame: every face is described as a FRONT face: the outside medium above (+z), the
glass below (-z), relief heights measured outward.  The back face of the plate is the same
object seen through the mirror z -> -z (the engines do the mirroring), which is why a relief on
the back face is its height map as measured from the outside (formats.md).

Protocol (duck-typed, four implementations):

    face.tables(material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress=None)
        -> (outside table | None, inside table)      isotropic BsdfTables on `grid`
    face.interact(d, S, from_inside, ctx, rng) -> FaceEvent
        photons with propagation directions d (N, 3) and Stokes vectors S (N, 4) (frame s = z x k,
        the tracer's and the tables' frame) hit the face from outside (d_z < 0) or inside (d_z > 0);
        ctx: PhotonContext (indices, wavelength, grid for faces that sample their tables)
    face.is_flat, face.describe()

- FlatFace: Fresnel (Born & Wolf 1.5.20-21, Mueller matrices of core.fresnel).
- ReliefFace(relief, method, samples, seed, options): tables by `methods.reconstruct` of the
  relief; photons traced through the triangulated relief (methods.ray.ReliefTracer) when the
  method is geometric ray tracing ("ray"), otherwise drawn from the face's own tables.
- TableFace(outside, inside): given tables; photons drawn from them.
- MicrofacetFace(alpha): a Beckmann rough face (Walter et al. 2007): tables from the
  microfacet method at that alpha; photons by sampling Beckmann normals (core.microfacet) with
  one Fresnel event on the sampled facet, Smith masking G1 of both directions as the weight.

Tables are kept by the forward model's one memory owner (`plate.memory.current_memory()`) under
everything that determines them: the relief's content digest, method, options, grid, material,
wavelengths, incidences, samples, seed.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.core.index import Material
from relief_bsdf.errors import InputError
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.plate.memory import MissingTable, current_memory
from relief_bsdf.surface.digest import relief_digest as _digest
from relief_bsdf.surface.relief import Relief

TRACED_METHODS = ("ray",)          # methods whose photons trace the relief itself
THREADED_METHODS = ("microfacet",)  # analytic tables computed on this process's threads (numpy releases the GIL):
                                    # a plate's table (a back-face probe of a diagnosis: 37 incidences,
                                    # ~2 s) costs less than starting worker processes


def relief_digest(relief: Relief) -> str:
    """Content digest of a relief (`surface.digest`, the project's one): the cache key of its tables."""
    return _digest(relief)


ANISOTROPY_WARN = 1.3      # principal rms-slope ratio above which the isotropic-table assumption is flagged (the
#                            benchmark's isotropic 256^2 tiles reach 1.04-1.23 by sampling scatter alone)


def slope_anisotropy(relief: Relief) -> tuple[float, float]:
    """(ratio, angle_deg) of the relief's slope statistics: the ratio of the principal rms slopes
    (square root of the eigenvalue ratio of surface.stats.slope_tensor, the project's one slope
    tensor) and the azimuth of the steeper axis.  1 for a rotation-invariant relief (up to the
    sampling scatter of a finite tile, a few per cent for hundreds of correlation areas)."""
    from relief_bsdf.surface.stats import slope_tensor
    C = slope_tensor(relief)
    if not np.all(np.isfinite(C)):
        return 1.0, 0.0
    lam, vec = np.linalg.eigh(C)
    if lam[1] <= 0:
        return 1.0, 0.0
    ratio = float(np.sqrt(lam[1] / max(lam[0], 1e-300 * lam[1])))
    return ratio, float(np.degrees(np.arctan2(vec[1, 1], vec[0, 1])) % 180)


def anisotropic_face(face: Any) -> bool:
    """Whether a face carries a relief whose principal rms slopes differ more than ANISOTROPY_WARN (the
    one test: the engine's warning, the beam's in-plane split and the inside sector tables use it)."""
    relief = getattr(face, "relief", None)
    if relief is None or getattr(face, "method", "") == "microfacet":
        return False
    return slope_anisotropy(relief)[0] > ANISOTROPY_WARN


ISOTROPY_WARNING = r"relief .* is anisotropic \(principal rms slopes differ"   # the start of isotropy_warning's text


def isotropy_warning(face: Any) -> str:
    """A plain warning when a relief face is anisotropic (the deterministic engine assumes isotropic
    tables: one incidence azimuth, azimuth-circulant loop kernels), else ''."""
    if not anisotropic_face(face):
        return ""
    relief = face.relief
    ratio, ang = slope_anisotropy(relief)
    return (f"relief {getattr(relief, 'source', '') or 'map'} is anisotropic (principal rms slopes differ "
            f"{ratio:.2g}x, steeper axis at {ang:.0f} deg): the deterministic engine assumes isotropic boundary "
            "tables; its direct reflection and first transmitted pass are the relief's own only for rows lit at "
            "the tables' incidence azimuth (phi_i = 0), the light inside meets the relief by azimuth "
            "sector (inside_sectors), and rows at other phi_i are a rotation of phi_i = 0 (of the half-turned "
            "relief's table from the far half of azimuths); check with "
            "engine='photon'")


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


# ---------------------------------------------------------------- photon kernels shared by faces

def fresnel_event(d: np.ndarray, S: np.ndarray, n_above: float, n_below: float, rng: np.random.Generator,
                  normal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fresnel reflect / refract at a plane of normal `normal` (default +z) with Stokes vectors.

    Reflection or transmission is drawn with probability (M S)_0 / S_0 and the Stokes vector
    renormalised to the incoming S_0, so the weight is unchanged (Mueller matrices of
    core.fresnel.mueller_interface, s/p frame of the plane of incidence = s = n x k).  With a
    tilted `normal` (a microfacet) the Stokes frame is taken as the facet's plane of incidence
    (the rotation into it is neglected: the microfacet face's photons are depolarised anyway).
    Returns (new directions, new Stokes).
    """
    nrm = np.broadcast_to(np.array([0.0, 0.0, 1.0]) if normal is None else normal, d.shape)
    c = np.sum(d * nrm, axis=1)                                  # < 0: coming from above
    from_above = c < 0
    n1 = np.where(from_above, n_above, n_below)
    n2 = np.where(from_above, n_below, n_above)
    cos_i = np.abs(c)
    out_S = np.empty_like(S)
    trans = np.zeros(d.shape[0], bool)
    for fa in (True, False):
        m = from_above == fa
        if not m.any():
            continue
        a, b = (n_above, n_below) if fa else (n_below, n_above)
        ST = np.einsum("nab,nb->na", mueller_interface(cos_i[m], a, b, "T"), S[m])
        SR = np.einsum("nab,nb->na", mueller_interface(cos_i[m], a, b, "R"), S[m])
        pT = np.clip(ST[:, 0] / np.maximum(S[m, 0], 1e-300), 0.0, 1.0)
        t = rng.random(pT.size) < pT
        trans[m] = t
        new = np.where(t[:, None], ST, SR)
        out_S[m] = new * (S[m, 0] / np.maximum(new[:, 0], 1e-300))[:, None]
    eta = n1 / n2
    refl = d - 2 * c[:, None] * nrm
    sin2_t = eta**2 * (1 - cos_i**2)
    cos_t = np.sqrt(np.clip(1 - sin2_t, 0, 1))
    refr = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * nrm * np.where(from_above, 1.0, -1.0)[:, None]
    new_d = np.where(trans[:, None], refr, refl)
    return new_d / np.linalg.norm(new_d, axis=1, keepdims=True), out_S


class TableSampler:
    """Draws photon exits from an isotropic BsdfTable (diffuse cells + delta parts), one wavelength.

    Incidence: the two tabulated incidences around the photon's theta are chosen with the
    linear-interpolation weights (exact linear interpolation in expectation).  Outcome: a cell of
    R or T or a delta part, with probability proportional to its power (M00 f Omega_proj); the
    Stokes vector becomes M S P_total / P_outcome (unbiased).  Diffuse cells without Mueller
    matrices depolarise (M = f diag(1, 0, 0, 0)), delta parts without them keep S.  Direction:
    uniform in projected solid angle inside the cell, azimuth relative to the incident plane.
    """

    def __init__(self, table: BsdfTable, wavelength_nm: float):
        if not table.is_isotropic:
            raise InputError("table", "photon sampling needs an isotropic table (one phi_i)")
        t = table
        w = int(np.argmin(np.abs(t.wavelength_nm - wavelength_nm)))
        self.table, self.theta_i = t, np.asarray(t.theta_i_deg, float)
        psa = projected_solid_angle_cells(t.theta_s_edges_deg, t.phi_s_edges_deg)        # (S, P)
        v = t.values_per_sr[w, :, 0] * psa[None, None]                                      # (I, 2, S, P)
        sR = t.specular_R[w, :, 0]
        sT = t.specular_T[w, :, 0]
        self.power = np.concatenate([v.reshape(v.shape[0], -1), sR[:, None], sT[:, None]], axis=1)
        self.total = self.power.sum(axis=1)
        self.cdf = np.cumsum(self.power, axis=1) / np.maximum(self.total[:, None], 1e-300)
        self.mueller = None if t.mueller_per_sr is None else t.mueller_per_sr[w, :, 0]     # (I, 2, S, P, 4, 4)
        self.spec_m = [getattr(t, f"specular_mueller_{k}") for k in "RT"]
        self.spec_m = [None if m is None else m[w, :, 0] for m in self.spec_m]
        self.w, self.shape = w, v.shape[1:]
        self.phi0 = float(t.phi_i_deg[0])

    def sample(self, theta_in_deg: np.ndarray, phi_in_deg: np.ndarray, S: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(reflected?, delta?, theta_out deg (cells only), phi_out deg, new S) per photon."""
        ti = self.theta_i
        x = np.clip(theta_in_deg, ti[0], ti[-1])
        if ti.size > 1:
            i1 = np.clip(np.searchsorted(ti, x, side="right"), 1, ti.size - 1)
            f = (x - ti[i1 - 1]) / (ti[i1] - ti[i1 - 1])
            inc = np.where(rng.random(x.size) < f, i1, i1 - 1)
        else:
            inc = np.zeros(x.size, int)
        o = np.minimum(_rowwise_searchsorted(self.cdf, inc, rng.random(x.size)), self.power.shape[1] - 1)
        return self._outcome(inc, o, phi_in_deg, S, rng)

    def _outcome(self, inc, o, phi_in_deg, S, rng):
        ncell = self.power.shape[1] - 2
        t = self.table
        scale = self.total[inc] / np.maximum(self.power[inc, o], 1e-300)
        cell = o < ncell
        k, s_, a_ = np.unravel_index(np.where(cell, o, 0), self.shape)
        te = np.radians(np.asarray(t.theta_s_edges_deg, float))
        pe = np.asarray(t.phi_s_edges_deg, float)
        s2 = np.sin(te[s_]) ** 2 + rng.random(o.size) * (np.sin(te[s_ + 1]) ** 2 - np.sin(te[s_]) ** 2)
        th = np.degrees(np.arcsin(np.sqrt(np.clip(s2, 0, 1))))
        ph_cell = pe[a_] + rng.random(o.size) * (pe[a_ + 1] - pe[a_]) - self.phi0
        refl = np.where(cell, k == 0, o == ncell)
        ph = np.where(cell, ph_cell + phi_in_deg, phi_in_deg + 180.0)   # delta parts: specular / undeviated
        newS = np.zeros_like(S)
        if self.mueller is not None:
            psa = projected_solid_angle_cells(t.theta_s_edges_deg, t.phi_s_edges_deg)
            M = self.mueller[inc[cell], k[cell], s_[cell], a_[cell]] * psa[s_[cell], a_[cell]][:, None, None]
            newS[cell] = np.einsum("nab,nb->na", M, S[cell]) * scale[cell, None]
        else:
            newS[cell, 0] = S[cell, 0] * self.total[inc[cell]]
        for j, side in ((ncell, 0), (ncell + 1, 1)):
            m = o == j
            if m.any():
                sm = self.spec_m[side]
                newS[m] = (S[m] * self.total[inc[m], None] if sm is None
                           else np.einsum("nab,nb->na", sm[inc[m]], S[m]) * scale[m, None])
        return refl, ~cell, th, ph, newS


def _rowwise_searchsorted(cdf: np.ndarray, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """searchsorted of u[k] in cdf[rows[k]] for every k (vectorised: offset rows onto one axis)."""
    n = cdf.shape[1]
    flat = (cdf + np.arange(cdf.shape[0])[:, None] * 2.0).ravel()
    return np.searchsorted(flat, u + rows * 2.0) - rows * n


def projected_solid_angle_cells(theta_edges_deg: Any, phi_edges_deg: Any) -> np.ndarray:
    from relief_bsdf.core.frames import projected_solid_angle
    return projected_solid_angle(theta_edges_deg, phi_edges_deg)


def _sample_from_tables(out_t: BsdfTable | None, in_t: BsdfTable, d: np.ndarray, S: np.ndarray, ctx: PhotonContext,
                        rng: np.random.Generator) -> FaceEvent:
    """Face event drawn from the face's (outside, inside) tables (TableSampler) for photons `d`."""
    nd = np.empty_like(d)
    nS = np.empty_like(S)
    outside = np.zeros(d.shape[0], bool)
    from_in = d[:, 2] > 0
    for inside, table in ((False, out_t), (True, in_t)):
        m = from_in == inside
        if not m.any():
            continue
        if table is None:
            raise InputError("plate", "this face has no table for light from outside")
        memory = current_memory()
        key = ("sampler", id(table), ctx.wavelength_nm)
        held = memory.peek(key)
        if held is None or held[0] is not table:         # the table is held beside it: its id is not reused
            held = (table, TableSampler(table, ctx.wavelength_nm))
            memory.put(key, held, "sampler")
        dm = d[m]
        th_in = np.degrees(np.arccos(np.clip(np.abs(dm[:, 2]), 0, 1)))
        ph_in = np.degrees(np.arctan2(-dm[:, 1], -dm[:, 0]))          # azimuth of the incident direction
        refl, is_delta, th, ph, S2 = held[1].sample(th_in, ph_in, S[m], rng)
        n1, n2 = (ctx.n_glass, ctx.n_outside) if inside else (ctx.n_outside, ctx.n_glass)
        snell = np.degrees(np.arcsin(np.clip(np.sin(np.radians(th_in)) * n1 / n2, 0, 1)))
        th = np.where(is_delta, np.where(refl, th_in, snell), th)
        w = np.stack([np.sin(np.radians(th)) * np.cos(np.radians(ph)), np.sin(np.radians(th)) * np.sin(np.radians(ph)),
                      np.cos(np.radians(th))], 1)
        # incident side: outside = +z; R stays on the incident side, T crosses
        up = refl != inside
        w[:, 2] *= np.where(up, 1.0, -1.0)
        nd[m], nS[m], outside[m] = w, S2, up
    return FaceEvent(nd, nS, outside, np.zeros(d.shape[0], bool))


def _table_args_key(material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
                    need_outside: bool) -> tuple:
    return (material_key(material), _grid_key(grid), tuple(float(w) for w in np.unique(wavelengths_nm)),
            tuple(float(t) for t in np.unique(theta_i_outside_deg)), bool(need_outside))


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
                          lambda: _reconstruct_side(f_in, material, grid, wl, grid.inside_incidences_deg(), "inside",
                                                    progress))
    return out, ins


def inside_face(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any,
                progress: Any = None) -> "ReliefFace":
    """The face the inside table is made with.  Where the plate's loop turns that one table to every
    azimuth (a ray-traced relief without inside sector tables on `grid`, `sector_plan`), its rays spread
    over the incidence azimuths within +- `grid.inside_azimuth_spread_deg` (ray option `phi_i_spread_deg`,
    unless the face sets it; the TableGrid field says why).  Where sector tables carry the loop, the table
    serves the light at its own azimuth (the in-plane beams between the faces, the reference of the moving
    lobes) and stays there: spread, it takes the light-guide dots of bench_forward_accuracy (relief seed 13)
    from rms z 1.16 to 1.29, their lattice rows along that azimuth (docs/decisions/003).  Any other face as it is."""
    spread = float(grid.inside_azimuth_spread_deg)
    if face.method != "ray" or not spread or "phi_i_spread_deg" in face.options:
        return face
    if sector_plan(face, material, grid, wavelengths_nm, progress) is not None:
        return face
    return replace(face, options={**face.options, "phi_i_spread_deg": spread})


def _derive_outside(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any,
                    theta_i_outside_deg: Any, progress: Any = None, beam_divergence_deg: float = 0.0) -> BsdfTable:
    """The outside table of a relief face whose method is resolved (`_derive`'s outside side, cached on its own)."""
    wl = tuple(float(w) for w in np.unique(np.asarray(wavelengths_nm, float)))
    th = tuple(float(t) for t in np.unique(np.asarray(theta_i_outside_deg, float)))
    beam = float(beam_divergence_deg) if face.method == "ray" else 0.0
    key = (face.cache_key(), material_key(material), _grid_key(grid), wl, "outside", th)
    return current_memory().get(key + (("beam", beam) if beam else ()),
                           lambda: _reconstruct_side(face, material, grid, wl, th, "outside", progress, beam))


def _resolved_relief(face: Any, material: Material, grid: TableGrid, wavelengths_nm: Any,
                     theta_i_outside_deg: Any) -> "ReliefFace | None":
    """A relief face with "auto" resolved (`plate.choice.resolve_face`), or None for any other face."""
    if not isinstance(face, ReliefFace) or face.is_flat:
        return None
    if face.method == "auto":
        from relief_bsdf.plate.choice import resolve_face
        face = resolve_face(face, material, grid, wavelengths_nm, theta_i_outside_deg)
    return face


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


SECTOR_AZIMUTHS_DEG = TableGrid().sector_azimuths_deg()   # the default grid's sector centres (0 included)
SECTOR_RAY_TABLES = 5     # the sector tables share the rays of this many inside tables
TILE_SECTOR_AZIMUTHS_DEG = (0.0, 90.0)   # `inside_sectors` "always" on a relief the gate leaves: two sectors
TILE_SECTOR_RAY_TABLES = 1               # sharing the rays of one inside table
SECTORS_KEY = "inside_sectors"   # in the cache key of every sector table (`inside_sectors`)


def inside_sectors(face: Any, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any,
                   progress: Any = None) -> BsdfTable | None:
    """The inside table of an anisotropic relief traced by rays over the azimuth sectors centred on
    `grid.sector_azimuths_deg()`, or None (an isotropic relief, another method, a flat or tabulated face).
    Anisotropic: in its rms slopes (`anisotropic_face`) or in how it scatters the light trapped in the
    glass (`azimuth_dependent`: light-guide dots); every ray-traced relief with `grid.sectors` "always"
    (TableGrid: a finite tile answers by azimuth even where its statistics do not).

    The deterministic engine's loop turns the one inside table about the normal (azimuth-circulant
    kernels), exact for an isotropic relief.  On an anisotropic one the light inside the plate meets
    the relief at its own azimuths: the second pass (crossed the relief, reflected by the flat back
    face, most of R at normal incidence after the direct reflection) and every later order (the
    trapped light): the engine then lets each azimuth sector of that light scatter and leave through
    the table of its sector (0-165 deg every 15 by default, `grid.sector_step_deg`: a relief's statistics
    are unchanged by a half turn; PlateSolver `inside_sectors`).

    Each sector's table is the AVERAGE over the incidence azimuths of its sector (ray option
    `phi_i_spread_deg` = half the step: every ray's incidence turned by its own uniform offset, its exit
    turned back), seen from the sector's centre: the light of a sector arrives at every azimuth in it,
    and a lattice of dots scatters the trapped light very differently along a row of dots than a few
    degrees off it, so the table at the centre alone stands for the sector wrongly when the centre is a
    lattice direction (0, 30, 60 ... deg on a hexagonal lattice aligned with the tile).  Measured on
    bench_forward_accuracy (400k rays, 1 M photons, 0/30/60 deg; docs/decisions/004): dots 1.29 -> 1.09 (relief
    seed 11; T 1.47 -> 1.10) and 1.35 -> 1.10 (seed 12), exponential 1.05 -> 1.04 / 1.04 -> 1.04,
    anisotropic 0.99 -> 1.01 / 0.86 -> 0.87, measured map 1.18 -> 1.19, at the same rays and cost (the
    centre-sampled tables needed 7.5-deg sectors, twice the loop's memory, to take dots to 1.19).  No
    parameter was chosen: the average is the sector's definition.  The sector tables share the rays of
    SECTOR_RAY_TABLES inside tables (each light sector meets one table; bench_forward_accuracy's
    anisotropic relief: rms z 1.45 with 30-deg sectors at full rays, 1.12 with 15-deg sectors at 5/11 of
    the rays each, centre-sampled).

    `grid.sectors` "always" and a relief the gate leaves (isotropic in its statistics and in how it
    scatters trapped light): what is left to meet by azimuth is the finite tile's own answer, not a
    direction of its statistics, and two sectors (TILE_SECTOR_AZIMUTHS_DEG, each the average over +-45
    deg of incidence azimuth) sharing the rays of one inside table (TILE_SECTOR_RAY_TABLES) hold it as
    well as the grid's fifteen-degree sectors at five tables' rays: bench_forward_accuracy's Gaussian
    relief of rms slope 0.35 (400k rays, 1 M photons, 0/30/60 deg), chosen on relief seed 12
    (default 1.23; 15-deg sectors at five tables' rays 1.11; 45 / 90-deg sectors at five 1.09 / 1.09; 90 at
    one 1.11) and reported on seed 11: 1.16 -> 1.10 (15-deg sectors 1.13); slope 0.24 0.94 -> 0.91 (seed 12
    1.02 -> 1.02), slope 0.12 0.81 -> 0.80 (0.77 -> 0.75); a forward 10 s instead of 23-24 (default 6)."""
    face = _resolved_relief(face, material, grid, wavelengths_nm, theta_i_outside_deg)
    plan = None if face is None else sector_plan(face, material, grid, wavelengths_nm, progress)
    if plan is None:
        return None
    azimuths, rays, step = plan
    face = replace(face, samples=max(int(face.samples * rays / len(azimuths)), 1),
                   options={**face.options, "phi_i_spread_deg": 0.5 * step})
    wl = tuple(float(w) for w in np.unique(np.asarray(wavelengths_nm, float)))
    key = (face.cache_key(), material_key(material), _grid_key(grid), wl, SECTORS_KEY, azimuths)
    return current_memory().get(key, lambda: _reconstruct_side(face, material, grid, wl, grid.inside_incidences_deg(),
                                                          "inside", progress, phi_i_deg=azimuths))


def sector_plan(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any,
                progress: Any = None) -> tuple[tuple, int, float] | None:
    """(sector centres, inside tables' worth of rays they share, sector width deg) of a resolved relief
    face's inside sector tables on `grid` (`inside_sectors` says which reliefs get which), or None."""
    azimuths = grid.sector_azimuths_deg()
    if not azimuths or face.method != "ray":   # no sector tables on this grid (sector_step_deg 180), or not rays
        return None
    if anisotropic_face(face) or azimuth_dependent(face, material, grid, wavelengths_nm, progress):
        return azimuths, SECTOR_RAY_TABLES, float(grid.sector_step_deg)
    if grid.sectors != "always":
        return None
    return TILE_SECTOR_AZIMUTHS_DEG, TILE_SECTOR_RAY_TABLES, 180.0 / len(TILE_SECTOR_AZIMUTHS_DEG)


PROBE_THETA_DEG = 85.0        # incidence of the azimuth probe: light trapped in the glass, grazing the relief
PROBE_AZIMUTH_DEG = 45.0      # the probe's second incidence azimuth (the first is the inside table's 0 deg)
PROBE_L1 = 0.17               # relative difference above which the relief scatters trapped light by azimuth


def azimuth_dependent(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any,
                      progress: Any = None) -> bool:
    """Whether a ray-traced relief whose rms slopes are isotropic still scatters the light trapped in the
    glass differently by its azimuth (a lattice of light-guide dots: light grazing along a row of dots
    meets them otherwise than light crossing the rows; the rms-slope tensor sees only a two-fold
    anisotropy of the slopes, not their arrangement), so that the plate's loop needs the inside sector
    tables (`inside_sectors`).

    The probe: the inside table at PROBE_THETA_DEG traced at incidence azimuths 0 and PROBE_AZIMUTH_DEG,
    the second turned back by that angle; the light each sends back into the glass (R side) summed in
    coarse bins (10 deg x 30 deg); `azimuth_probe_l1` their relative L1 difference less what the
    tables' sigma (Monte-Carlo noise and the tile's realisation) alone would give.  PROBE_L1 is the
    midpoint between the Gaussian reliefs' largest value and the others' smallest on
    bench_forward_accuracy's reliefs at seed 1 (Gaussian slope 0.12 / 0.24 / 0.34: 0.05 / 0.06 / 0.11,
    two scales 0.02; light-guide dots 0.23, exponential 0.24), not on the seed the benchmark reports
    (seed 11: Gaussian <= 0.07, two scales 0.03, dots 0.27, exponential 0.24; there the sectors take
    dots 1.65 -> 1.30, exponential 1.07 -> 1.05, and Gaussian slope 0.34, below the gate, 1.15 -> 1.11:
    the sectors are the better physics everywhere, the gate decides only where they are worth their
    cost).  Same verdicts at 20k and 200k rays.  Cost: two inside incidences at the inside tables' rays."""
    wl = (float(np.median(np.asarray(wavelengths_nm, float))),)
    key = (face.cache_key(), material_key(material), _grid_key(grid), wl, "azimuth_probe", PROBE_THETA_DEG,
           PROBE_AZIMUTH_DEG)
    t = current_memory().get(key, lambda: _reconstruct_side(face, material, grid, wl, (PROBE_THETA_DEG,), "inside",
                                                       progress, phi_i_deg=(0.0, PROBE_AZIMUTH_DEG)))
    return azimuth_probe_l1(t) > PROBE_L1


def azimuth_probe_l1(table: BsdfTable) -> float:
    """The relative L1 difference sum |a - b| / sum (a + b) / 2 between a table's R sides (first incidence)
    at its two incidence azimuths, the second turned back onto the first, in 10-deg x 30-deg bins of power,
    less the difference the cells' sigma alone would make (sqrt(2 / pi) sqrt(var_a + var_b) per bin, the
    mean |difference| of two Gaussian estimates of one value); the statistic of `azimuth_dependent`."""
    pe = np.asarray(table.phi_s_edges_deg, float)
    step = float(np.median(np.diff(pe)))
    shift = int(round((float(table.phi_i_deg[1]) - float(table.phi_i_deg[0])) / step))
    te = np.asarray(table.theta_s_edges_deg, float)
    psa = projected_solid_angle_cells(te, pe)                                             # (S, P)
    tb = np.minimum((0.5 * (te[1:] + te[:-1]) // 10).astype(int), 8)                      # 10-deg rings
    pb = (np.mod(0.5 * (pe[1:] + pe[:-1]), 360.0) // 30).astype(int)                      # 30-deg sectors
    bins = (tb[:, None] * 12 + pb[None, :]).ravel()

    def binned(values: np.ndarray, sigma: np.ndarray, roll: int) -> tuple[np.ndarray, np.ndarray]:
        p = np.roll(values * psa, -roll, axis=1).ravel()
        v = np.roll((sigma * psa) ** 2, -roll, axis=1).ravel()
        return np.bincount(bins, p, minlength=108), np.bincount(bins, v, minlength=108)
    v = np.asarray(table.values_per_sr, float)
    sg = np.asarray(table.sigma_per_sr if table.sigma_per_sr is not None else np.zeros_like(v), float)
    a, va = binned(v[0, 0, 0, 0], sg[0, 0, 0, 0], 0)
    b, vb = binned(v[0, 0, 1, 0], sg[0, 0, 1, 0], shift)
    total = 0.5 * float(np.sum(a + b))
    if total <= 0:
        return 0.0
    return float(np.sum(np.abs(a - b)) - np.sqrt(2.0 / np.pi) * np.sum(np.sqrt(va + vb))) / total


def same_indices(material: Material, wavelengths_nm: Any, side: str) -> tuple[tuple, tuple]:
    """(representative wavelengths, ascending; the row of each wavelength among them): wavelengths whose
    index pair (light from `side`) is the same share one, the longest of them (a method's wavelength
    checks, such as the ray tracer's tile of at least so many wavelengths, see the longest)."""
    ws = [float(w) for w in wavelengths_nm]
    pair = [tuple(complex(x) for x in material.n_pair(w, side)) for w in ws]
    rep = {p: max(w for w, q in zip(ws, pair) if q == p) for p in pair}
    reps = tuple(sorted(set(rep.values())))
    return reps, tuple(reps.index(rep[p]) for p in pair)


def _reconstruct_side(face: "ReliefFace", material: Material, grid: TableGrid, wl: Any, theta: Any, side: str,
                      progress: Any, beam_divergence_deg: float = 0.0, phi_i_deg: tuple = (0.0,)) -> BsdfTable:
    """The face's table of light from `side`.  A geometric-optics method (`MethodEntry.wavelength_free`)
    traces once per distinct index pair: wavelengths where the indices are the same (no dispersion
    given) share the table traced at the longest of them (`same_indices`, `BsdfTable.at_wavelengths`):
    the same physics with the same random numbers, a third of the work for a recording at three
    wavelengths."""
    from dataclasses import replace as _replace
    from relief_bsdf.methods import entry, reconstruct
    reps, rows = same_indices(material, wl, side)
    if len(reps) < len(tuple(wl)) and entry(face.method).wavelength_free:
        table = _reconstruct_side(face, material, grid, reps, theta, side, progress, beam_divergence_deg, phi_i_deg)
        return table.at_wavelengths(tuple(float(w) for w in wl), rows)
    req = face_request(face, material, grid, wl, theta, side)
    if beam_divergence_deg:
        req = _replace(req, options={**req.options, "beam_divergence_deg": float(beam_divergence_deg)})
    if tuple(phi_i_deg) != (0.0,):
        req = _replace(req, phi_i_deg=tuple(float(p) for p in phi_i_deg))
    if face.coherence_length_m is not None:
        req = _replace(req, coherence_length_m=float(face.coherence_length_m))
    if face.method in TRACED_METHODS and _trace_here(face):
        from relief_bsdf.methods.ray.method import reconstruct_with
        req = _replace(req, options={**req.options, "backend": "serial"})
        (table,) = reconstruct_with(_topology_tracer(face.relief, req), face.relief, material, req, progress=progress)
        return table
    from relief_bsdf.plate.energy import closed
    if face.method in THREADED_METHODS and _trace_here(face):
        from relief_bsdf.parallel import parallel_settings
        with parallel_settings(backend="serial"):          # threads here, no worker pool to start
            (table,) = reconstruct(face.relief, material, req, face.method, progress=progress)
    else:
        (table,) = reconstruct(face.relief, material, req, face.method, progress=progress)
    return closed(table)          # a wave model's energy defect is the model's, not absorption (plate.energy)


def face_request(face: "ReliefFace", material: Material, grid: TableGrid, wavelengths_nm: Any, theta: Any,
                 side: str) -> Any:
    """The Request a relief face's tables are made with on `grid` (TableGrid.request): the outside side on
    the direct grid with the glass's exit-side edges.

    The direct grid may have more cells than the tile has facets (a 96 x 96 tile: 18 k facets, the
    direct grid ~60 k cells).  A flat facet sends a delta, so a small tile's BSDF is a sum of deltas
    whatever the cells; what the plate reads from these cells is their integral over a detector cone
    (~50 direct cells), not single cells, so the ray tables are asked for them anyway (ray option
    sparse_cells) rather than falling back to coarse cells, whose width broadens a narrow lobe
    (the reason for the direct grid).  Each cell's tile-realisation sigma says how little one cell
    is worth; the cone integral averages them."""
    options = dict(face.options)
    max_cells = 2 * face.relief.shape[0] * face.relief.shape[1]
    if side == "outside" and face.method == "ray":
        options["sparse_cells"], max_cells = True, None
    return grid.request(wavelengths_nm, theta, side, face.method, face.samples, face.seed, options,
                        index_ratio=_index_ratio(material, wavelengths_nm), max_cells=max_cells)


def _index_ratio(material: Material, wavelengths_nm: Any) -> float:
    """n_glass / n_outside at the middle wavelength (the exit-side edges of the direct grid)."""
    w = float(np.median(np.asarray(wavelengths_nm, float)))
    return float(np.real(material.inside.n(w)) / np.real(material.outside.n(w)))


def _trace_here(face: "ReliefFace") -> bool:
    """Trace a relief face's tables in this process (threads on one reused tracer; THREADED_METHODS on
    threads too) unless the run is spread over Dask or the face names its own backend: a fit re-traces
    the same grid with new heights every evaluation, and one tracer whose heights are rewritten in place (BVH refitted)
    costs ~0.03 s where worker processes rebuild a BVH each (~0.5-1 s per worker per side)."""
    from relief_bsdf.parallel import current_settings, in_worker
    if in_worker() or face.options.get("backend") is not None:
        return False
    return current_settings().backend not in ("dask",) and not current_settings().dask


def _topology_tracer(relief: Relief, request: Any) -> Any:
    """This process's ReliefTracer for the relief's grid (shape, pitch, periodicity, mesh options),
    its heights set to `relief` (`ReliefTracer.update_heights`: z rewritten, BVH refitted in place;
    `with_heights` where the Embree buffers are embreex's own), kept by the memory owner."""
    from relief_bsdf.methods.ray import ReliefTracer
    opts = request.options_for("ray")
    key = ("topology tracer", relief.shape, float(relief.dx_m), float(relief.dy_m), bool(relief.periodic),
           opts.max_bounces, json.dumps(opts.fill_holes))
    memory = current_memory()
    tr = memory.peek(key)
    if tr is None:
        tr = ReliefTracer(relief, opts.max_bounces, opts.fill_holes)
    elif tr.relief is not relief and relief_digest(tr.relief) != relief_digest(relief):
        try:
            tr.update_heights(relief)
        except RuntimeError:                 # buffers owned by embreex: a new scene on the same topology
            tr = tr.with_heights(relief)
    memory.put(key, tr, "tracer")
    return tr


def _flat_inside_incidences(material: Material, grid: TableGrid, wavelengths_nm: Any) -> np.ndarray:
    """The grid's inside incidences plus a dense band (0.05 deg) around each critical angle: Fresnel
    jumps to total reflection there, and the engine interpolates the table's delta parts linearly."""
    th = [grid.inside_incidences_deg()]
    for w in np.unique(wavelengths_nm):
        n_in = float(np.real(material.inside.n(w)))
        n_out = float(np.real(material.outside.n(w)))
        if n_in > n_out:
            tc = float(np.degrees(np.arcsin(n_out / n_in)))
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
            from relief_bsdf.methods.flat import flat_tables
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
        from relief_bsdf.errors import RequestError
        from relief_bsdf.methods.registry import entry
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
        if self.method == "auto":          # one choice for both sides (plate.choice)
            from relief_bsdf.plate.choice import resolve_face
            face = resolve_face(self, material, grid, wavelengths_nm, theta_i_outside_deg)
            return face.tables(material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress,
                               beam_divergence_deg)
        return _derive(self, material, grid, wavelengths_nm, theta_i_outside_deg, need_outside, progress,
                       beam_divergence_deg)

    def traces_beam(self, material: Material, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any) -> bool:
        """Whether this face's outside table holds a divergent beam itself (its method draws rays)."""
        face = self
        if self.method == "auto":
            from relief_bsdf.plate.choice import resolve_face
            face = resolve_face(self, material, grid, wavelengths_nm, theta_i_outside_deg)
        return face.method == "ray"

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
        from relief_bsdf.core.microfacet import sample_normals, smith_G1
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
