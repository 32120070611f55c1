"""How a relief meets the light inside the plate by azimuth: its slope anisotropy (the engine's warning), the
inside sector tables of a relief that scatters trapped light by azimuth, the azimuth probe that finds
one, and the face the inside table is made with (`inside_face`).  Faces are met through their
capabilities (`resolved`, `relief`): this module knows no face class."""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.plate.faces.base import _grid_key, material_key
from relief_bsdf.plate.faces.derive import _reconstruct_side
from relief_bsdf.plate.faces.photons import projected_solid_angle_cells
from relief_bsdf.plate.grid import TableGrid, critical_angles_deg
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import slope_tensor


ANISOTROPY_WARN = 1.3      # principal rms-slope ratio above which the isotropic-table assumption is flagged (the


def slope_anisotropy(relief: Relief) -> tuple[float, float]:
    """(ratio, angle_deg) of the relief's slope statistics: the ratio of the principal rms slopes
    (square root of the eigenvalue ratio of surface.stats.slope_tensor, the project's one slope
    tensor) and the azimuth of the steeper axis.  1 for a rotation-invariant relief (up to the
    sampling scatter of a finite tile, a few per cent for hundreds of correlation areas)."""
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


def _resolved_relief(face: Any, material: Material, grid: TableGrid, wavelengths_nm: Any,
                     theta_i_outside_deg: Any) -> "ReliefFace | None":
    """A relief face with "auto" resolved (its `resolved`), or None for any other face."""
    resolve = getattr(face, "resolved", None)
    if resolve is None or face.is_flat:
        return None
    return resolve(material, grid, wavelengths_nm, theta_i_outside_deg)


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
    return current_memory().get(key, lambda: _reconstruct_side(face, material, grid, wl, grid.inside_incidences_deg(critical_angles_deg(material, wl)),
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
