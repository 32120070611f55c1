"""The angular grids of the boundary tables, which are also the deterministic plate's discretisation.

Two grids (cells narrower than the detector cone where the lobe is narrow):

- the ENGINE grid (`theta_step_deg` x `phi_step_deg`, inside incidences every
  `inside_theta_i_step_deg`): the inside tables and the plate's internal direction cells on
  which the multiple round trips are solved (uniform azimuth cells: the azimuthal Fourier
  reduction needs them).  What it carries has been scattered at least twice by the relief or
  reflected inside the plate, so it is broad; a cell error of the order of a cell is
  tolerable there, but a lobe must MOVE between two inside incidences rather than blend
  (a second pass through the relief from inside is read from the two tables around its
  incidence): every 2.5 deg, with a quarter of the rays per incidence (`inside_samples_scale`:
  the loop averages their noise over the incidences of the light inside), and read in between
  with the lobes moved to the incidence's own specular or Snell exit direction
  (`inside_interpolation`, plate.tableview._TableView._between_incidences).
- the DIRECT grid of the outside tables (light from outside, at the recording's own
  incidences): `direct_theta_step_deg` rings and azimuth cells of `direct_phi_step_deg` in a
  band of half-width `direct_band_deg` around the plane of incidence (both the specular side
  and the forward side, table azimuths 180 and 0 from the propagation azimuth, where the
  reflected and refracted lobes of an isotropic relief are centred; a 2-deg cone on an
  in-plane row at theta >= 10 deg stays inside it), `phi_step_deg` cells elsewhere; below
  the critical angle its rings are the Snell pre-images of uniform exit rings (a transmitted
  lobe is read through the flat face, where refraction stretches internal angles).  The engine reads the direct
  reflection and the first transmitted pass (outside T table -> plate -> flat face) from this
  grid, integrated over the detector cone (plate.detector.direct_reading), and gives the loop
  its cell averages on the engine grid.  `direct_theta_step_deg=None` puts the outside tables
  on the engine grid (the engine's old single-grid behaviour).

Cost (gauss_mid, 6 incidences, 400k rays): the outside tables hold 544 x 112 cells per side
(9.4x the engine grid's, the same rays; 60 MB with Mueller matrices); the inside tables 37
incidences at a quarter of the rays each; the engine's operators on 37 inside incidences
and the cone integral of the direct cells add ~1-2 s per evaluation on one quiet core (the cone
weights are kept across a fit's evaluations).  Regime: the direct grid applies with a flat second
face and no volume scattering (plate.deterministic), for the ray method's tables
(DIRECT_METHODS; a wave method pays per cell and keeps the engine grid).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from relief_bsdf.core.fresnel import critical_angle_deg

from relief_bsdf.errors import InputError
from relief_bsdf.methods.request import Request


INSIDE_EFFORT_STEP_DEG = 10.0   # the inside tables' total effort: one full-effort table every 10 deg of incidence
INSIDE_INTERPOLATIONS = ("moving", "linear")   # how the loop reads the inside tables between their incidences
DIRECT_METHODS = ("ray",)     # methods whose outside tables go on the direct grid (cost per ray, not per cell)
NO_SECTORS_DEG = 180.0        # TableGrid.sector_step_deg of a grid without inside sector tables
SECTOR_CHOICES = ("auto", "always")     # TableGrid.sectors: which ray-traced reliefs get the sector tables


CRITICAL_OFFSETS_DEG = (-3.0, -2.0, -1.25, -0.75, -0.4, -0.15, 0.1, 0.5)   # inside incidences around a critical angle


def critical_angles_deg(material: Any, wavelengths_nm: Any) -> tuple:
    """The critical angles of light inside the glass (`core.fresnel.critical_angle_deg`), one per wavelength
    (none where the glass is not the denser medium): where total internal reflection begins."""
    out = (critical_angle_deg(material.inside.n(w), material.outside.n(w))
           for w in np.unique(np.asarray(wavelengths_nm, float)))
    return tuple(t for t in out if t < 90.0)


@dataclass(frozen=True)
class TableGrid:
    """Axes of the boundary tables the plate derives from its faces (module doc).

    theta_step_deg: scatter polar cell size of the engine grid (edges 0..90).
    phi_step_deg: scatter azimuth cell size (cells centred on multiples of it; also the plate's
        azimuth grid).
    inside_theta_i_step_deg: step between the incidences of the inside tables (0..85 + 89).
    direct_theta_step_deg: polar cell size of the outside tables (None: the engine grid).
    direct_phi_step_deg: azimuth cell size of the outside tables inside the band.
    direct_band_deg: half-width of the fine azimuth band around phi 0 and 180 (rounded so that
        its edges fall on the engine grid's azimuth edges).
    inside_interpolation: how the loop reads the inside tables between their incidences: "moving"
        (each neighbour's transmitted lobe shifted to the incidence's own Snell exit direction, scaled
        to the linear blend's albedo) or "linear" (the blend of the two tables, which widens a lobe
        that moves with the incidence).  Does not change the tables (not in `key`).
    sector_step_deg: azimuth step of the inside sector tables of a relief that scatters by azimuth
        (plate.faces.inside_sectors; the same total rays whatever the step; each table the average over
        its sector's incidence azimuths, which takes dots 1.29 -> 1.09 at 15 deg: docs/decisions/004).  With
        tables at the sectors' centres, measured on
        bench_forward_accuracy (moving lobes, 400k rays, 1 M photons, 0/30/60 deg), 15 -> 7.5:
        dots 1.29 -> 1.19 (T 1.47 -> 1.18: trapped light extracted near the normal), measured map 1.35 -> 1.27,
        anisotropic 1.03 -> 1.03, exponential 1.06 -> 1.06; on relief seed 12 dots 1.36 -> 1.21, anisotropic
        0.88 -> 0.95.  Not the default: the loop keeps one kernel difference per sector (M, 4N, 4N complex64
        per wavelength), and on the measured map (200k rays, 3 incidences, one quiet core)
        23 sectors take a forward's peak memory 3.8 -> 7.1 GB, the solver's operators 7 -> 16 s and a solve
        3.2 -> 6.0 s: a diagnosis keeps several solvers in each of its processes (24 GB in all) and every
        evaluation would cost twice.  180 (NO_SECTORS_DEG): no sector tables, the inside table's own
        azimuth only, the loop azimuth-circulant as for an isotropic relief (the diagnosis's screens,
        `diagnose.forward.DiagnosisForward.screening`).
    sectors: when a ray-traced relief gets the inside sector tables: "auto" (an anisotropic relief, or
        one the azimuth probe finds scattering trapped light by azimuth: `plate.faces.inside_sectors`) or
        "always" (every ray-traced relief: the loop meets it by azimuth sector however isotropic its
        statistics).  A finite tile answers light by azimuth even where its statistics do not: on
        bench_forward_accuracy's Gaussian relief of rms slope 0.35 (relief seed 12, 651 correlation areas)
        the inside table at 2.5 deg from inside put 0.0214-0.0255 of the light into the 0-2 deg
        exit ring depending on the propagation azimuth, the one table at phi_i 0 the least of it, and the
        second pass at normal incidence read 5-8 % low near the normal.  "always" gives a relief the gate
        leaves two sectors sharing one inside table's rays (`plate.faces.TILE_SECTOR_AZIMUTHS_DEG`: the tile's
        own azimuth dependence, not its statistics'; a relief the gate picks keeps `sector_step_deg`): that
        case's rms z 1.23 -> 1.11 (seed 11: 1.16 -> 1.10) at 10 s per forward instead of 6 (the grid's 15-deg
        sectors at five tables' rays: 1.11 / 1.13 at 23-24 s).  Not the default: the diagnosis's and the
        demo fit's evaluations would cost ~1.6x, and the inside table averaged over +-45 deg of
        incidence azimuth (`inside_azimuth_spread_deg=45`, the default) does nearly as much at
        no cost (that case 1.12).  Grids with NO_SECTORS_DEG have none either way.
    inside_azimuth_spread_deg: the inside table of a ray-traced relief (the one the loop turns about the
        normal for light at every azimuth) averages the incidence azimuths within +- this of its own (ray
        option `phi_i_spread_deg`: each ray's incidence turned by its own uniform offset, its exit turned
        back; the same rays).  Default 45 (see the end of this entry).  A finite tile
        answers light by azimuth even where its statistics do not, and the loop meets the relief at every
        azimuth through this one table: at one azimuth it is the tile's answer there, which the turned
        table then lends to every other azimuth; the average stands for the azimuths the light inside
        arrives at (the second pass, most of R after the direct reflection, within a few tens of degrees
        of the plane of incidence at oblique incidence).  45 deg is the half-width of the two tile sectors
        of `sectors` "always" (chosen there on relief seed 12); measured on bench_forward_accuracy
        (400k rays, 1 M photons, 0/30/60 deg, rms z 0 -> 45 deg, the same cost; docs/decisions/003): Gaussian
        slope 0.35, relief seed 12, 1.23 -> 1.12 (ray seed 1: 1.28 -> 1.18; +-15: 1.20, +-90: 1.18, +-180:
        1.17, the two tile sectors 1.11); reported on seed 11: slope 0.12 / 0.24 / 0.35 0.81 -> 0.79, 0.94 ->
        0.92, 1.16 -> 1.12, two scales 1.00 -> 0.99; on fresh seed 13: 0.92 -> 0.92, 1.04 -> 1.05, 1.05 ->
        1.05, two scales 1.00 -> 1.00 (exponential 1.04 / 0.99 unchanged: the azimuth probe gives it sector
        tables, and a relief with sectors at 0 deg sends no light through this table).  Only where the
        loop turns this one table to every azimuth (no inside sector tables, `plate.faces.sector_plan`):
        where sector tables carry the loop, the table serves the light at its own azimuth (the in-plane
        beams, the moving lobes' reference) and is traced there (light-guide dots, relief seed 13: 1.16,
        1.29 spread).  Not in `key`: the inside table's face carries it (its ray option, in the face's cache
        key, `plate.faces.inside_face`), and no other table depends on it.  The tables' noise, which moves
        with the relief, bends the demo fit's chi^2 by ~5-8 over a hundredth of a micrometre of filter, as
        much as the interval's own curvature; the fit's response surface (fit.response_surface,
        `fit.optimise._smoothed`) averages those bumps (docs/decisions/005).  The forward at the demo's
        truth is better with 45 too (rms z 0.883 -> 0.876).  0: the table at its own azimuth alone.
    stokes_loop: the plate carries Stokes vectors through polarised (Mueller) tables (True, the
        physics of record); False: intensities only, the tables' M00 (the loop's matrices 4x smaller a
        side: its operators and solves ~16-64x cheaper), exact for unpolarised light only where no
        crossing polarises it.  The relief's transmission does, partly, and the flat back face then
        reflects s and p differently: on a concealed tilt + blur case's baseline (Gaussian, n 1.5)
        the R rows differ by 4.7 % (median; up to 6.7 % in the lobes), the T rows by 1.8 %
        (0.6 % in the lobes).  Hence not a model of record: the diagnosis's screens evaluate the CHANGE
        of the model toward a candidate on it, the probes and the current model alike
        (`diagnose.forward.DiagnosisForward.screening`).  Does not change the tables (not in `key`).
    inside_samples_scale: a sampled method's effort per inside incidence, as a fraction of the
        face's `samples` (the outside tables get `samples`): the loop integrates the inside
        tables over the incidences of the light inside, which averages their noise, so denser
        inside incidences can share the same total effort.  None: min(1, inside step / 10 deg),
        one full-effort table every 10 deg whatever the step (0.25 at the default 2.5 deg).
        Chosen by measuring (benchmarks/bench_forward_accuracy.py, 8 reliefs, 1 M
        photons, 0/30/60 deg): 0.25 instead of 0.5 moved rms z by at most 0.04 (400k rays: every
        case within 0.01 but dots 1.62 -> 1.66; 200k rays, the fit's default: gauss_mid 1.01 ->
        1.02, dots 1.72 -> 1.68, measured 2.12, exponential 1.20 unchanged) and cut the forward's
        seconds by a third (the inside tables held 3/4 of the rays).

    Defaults measured against the independent photon Monte Carlo (bench_forward_accuracy.py,
    8 reliefs, 400k rays, 1 M photons, 0/30/60 deg; nothing else chosen on them):
    direct rings 0.25 deg (against 0.5) with 5 x 5 sub-points per cell in the cone integral (against 3 x 3;
    plate.detector.SUB_POINTS: on 0.25 x 1-deg cells 3 x 3 misreads a uniform field by 0.4 % at 45 deg and
    moved the demo fit's scale by 0.3 %, 3 half-widths): the measured map's transmitted lobe has a cusp
    narrower than a 0.5-deg ring (its peak read 2.3 % low: T 1.69 -> 1.21), no case worse; with the anisotropic
    relief's 15-deg sectors every case but dots (1.65) and the measured map (1.47) at or below 1.2.
    Inside incidences every 1.25 deg (`inside_theta_i_step_deg=1.25`, the same rays in total) are
    better still (gauss_low 1.08 -> 0.87, anisotropic 1.12 -> 1.01, measured 1.47 -> 1.36, every case
    better or equal) but cost a fit evaluation ~1 s more (5.35 s instead of 4.4 s on the demo): not
    the default while the demo fit must stay under 5 minutes.
    """

    theta_step_deg: float = 1.0
    phi_step_deg: float = 5.0
    inside_theta_i_step_deg: float = 2.5
    direct_theta_step_deg: float | None = 0.25
    direct_phi_step_deg: float = 1.0
    direct_band_deg: float = 12.5
    inside_samples_scale: float | None = None
    inside_interpolation: str = "moving"
    sector_step_deg: float = 15.0
    sectors: str = "auto"
    inside_azimuth_spread_deg: float = 45.0
    stokes_loop: bool = True

    def __post_init__(self) -> None:
        k = 180.0 / self.sector_step_deg if np.isfinite(self.sector_step_deg) and self.sector_step_deg > 0 else 0.0
        if not (1 <= round(k) <= 72 and abs(k - round(k)) < 1e-9):
            raise InputError("grid.sector_step_deg", "must divide 180 deg into 1 to 72 sectors (e.g. 15 or 7.5; "
                             f"180: no sector tables), got {self.sector_step_deg}")
        if self.sectors not in SECTOR_CHOICES:
            raise InputError("grid.sectors", f"must be one of {', '.join(SECTOR_CHOICES)}, got {self.sectors!r}")
        if not (np.isfinite(self.inside_azimuth_spread_deg) and 0 <= self.inside_azimuth_spread_deg < 90):
            raise InputError("grid.inside_azimuth_spread_deg",
                             f"must be in [0, 90) degrees, got {self.inside_azimuth_spread_deg}")
        if self.inside_interpolation not in INSIDE_INTERPOLATIONS:
            raise InputError("grid.inside_interpolation", f"must be one of {', '.join(INSIDE_INTERPOLATIONS)}, "
                             f"got {self.inside_interpolation!r}")
        if self.inside_samples_scale is not None and not (0 < self.inside_samples_scale <= 1):
            raise InputError("grid.inside_samples_scale",
                             f"must be in (0, 1] or None, got {self.inside_samples_scale}")
        for k in ("theta_step_deg", "phi_step_deg", "inside_theta_i_step_deg", "direct_phi_step_deg"):
            v = getattr(self, k)
            if not (np.isfinite(v) and 0 < v <= 90):
                raise InputError(f"grid.{k}", f"must be in (0, 90] degrees, got {v}")
        if self.direct_theta_step_deg is not None and not (0 < self.direct_theta_step_deg <= 90):
            raise InputError("grid.direct_theta_step_deg",
                             f"must be in (0, 90] or None, got {self.direct_theta_step_deg}")

    @property
    def inside_samples_fraction(self) -> float:
        """Effort per inside incidence over the face's samples (`inside_samples_scale`)."""
        if self.inside_samples_scale is not None:
            return float(self.inside_samples_scale)
        return min(1.0, self.inside_theta_i_step_deg / INSIDE_EFFORT_STEP_DEG)

    @property
    def azimuth_cells(self) -> int:
        return int(round(360.0 / self.phi_step_deg))

    @property
    def has_direct_grid(self) -> bool:
        return self.direct_theta_step_deg is not None

    def theta_edges_deg(self) -> tuple:
        return tuple(np.linspace(0.0, 90.0, int(round(90 / self.theta_step_deg)) + 1))

    def phi_edges_deg(self) -> tuple:
        h = self.phi_step_deg / 2
        return tuple(np.arange(-h, 360.0 - h + 1e-9, self.phi_step_deg))

    def direct_theta_edges_deg(self, index_ratio: float | None = None) -> tuple:
        """Polar edges of the outside tables: every `direct_theta_step_deg` (the reflected side is read
        as it is), plus, for a glass of index ratio n / n0 = `index_ratio`, the Snell pre-images
        asin(sin(theta_e) / ratio) of the same uniform edges theta_e outside, which replace the uniform
        edges below the critical angle (they are finer there): the transmitted side is
        read through the flat face, where refraction stretches an internal cell by
        n cos(theta_int) / cos(theta_e) (2.5x at 60 deg, unbounded at grazing), so its cells must be
        narrow in exit angle, not in internal angle."""
        if not self.has_direct_grid:
            return self.theta_edges_deg()
        e = np.linspace(0.0, 90.0, int(round(90 / self.direct_theta_step_deg)) + 1)
        if index_ratio is not None and index_ratio > 1.0:
            # below the critical angle the pre-images are finer than the uniform edges (reflected side included)
            pre = np.degrees(np.arcsin(np.sin(np.radians(e)) / index_ratio))
            e = np.unique(np.round(np.concatenate([e[e > pre[-1]], pre]), 6))
            e = e[np.concatenate([[True], np.diff(e) > 0.05 * self.direct_theta_step_deg])]   # no sliver rings
            e[-1] = 90.0
        return tuple(e)

    def direct_phi_edges_deg(self) -> tuple:
        """Azimuth edges of the outside tables: fine cells in the bands around 0 and 180 deg, the
        engine's cells elsewhere; every engine edge is kept (the fine cells nest in the engine's)."""
        coarse = np.asarray(self.phi_edges_deg())
        if not self.has_direct_grid:
            return tuple(coarse)
        p, h = self.phi_step_deg, self.phi_step_deg / 2
        k = max(int(np.ceil((self.direct_band_deg - h) / p - 1e-9)), 0)
        band = h + k * p                                    # an engine edge
        n_fine = max(int(round(p / self.direct_phi_step_deg)), 1)
        edges = [coarse]
        for centre in (0.0, 180.0):
            e = np.linspace(centre - band, centre + band, int(round(2 * band / p)) * n_fine + 1)
            edges.append(e)
        e = np.concatenate(edges)
        e = np.mod(e - coarse[0], 360.0) + coarse[0]       # the band around 0 wraps past the first edge
        e = np.unique(np.round(np.concatenate([e, coarse]), 9))
        return tuple(e[e <= coarse[-1] + 1e-9])

    def sector_azimuths_deg(self) -> tuple:
        """Centres of the inside sector tables: every `sector_step_deg` from 0 up to a half turn (a relief's
        statistics are unchanged by a half turn); none at NO_SECTORS_DEG (one sector would be the whole
        turn: the inside table's own, the loop azimuth-circulant)."""
        n = int(round(180.0 / self.sector_step_deg))
        return tuple(float(k * self.sector_step_deg) for k in range(n)) if n > 1 else ()

    def inside_incidences_deg(self, critical_deg: Any = ()) -> np.ndarray:
        """Incidences of the inside tables: every step from 0, plus 89 deg (near-grazing light), plus
        CRITICAL_OFFSETS_DEG around each critical angle in `critical_deg` (`critical_angles_deg`).

        Near the critical angle theta_c the Fresnel transmittance from inside falls to zero like
        sqrt(theta_c - theta) (Born & Wolf 1.5.20-21 with cos theta_t -> 0), and a relief with flat
        parts (light-guide dots, a measured map's plateaus) keeps that edge in its inside table.  The
        engine reads light between two inside incidences by interpolation, which cannot follow a
        square-root edge across a 2.5-deg step: on a flat plate at 75 deg (n 1.473, light inside at
        41.0 deg, theta_c 42.8) the reflectance read 3 % low.  With incidences at theta_c - 3, -2, -1.25,
        -0.75, -0.4, -0.15, + 0.1 and + 0.5 deg (steps shrinking towards the edge as its slope grows) it
        reads 0.15 % low, the 2.5-deg step's own error away from the edge (tests/backend/plate/
        test_critical_incidences.py)."""
        th = [np.arange(0.0, 90.0 - 1e-9, self.inside_theta_i_step_deg), [89.0]]
        for tc in critical_deg:
            th.append(np.clip(float(tc) + np.asarray(CRITICAL_OFFSETS_DEG), 0.0, 89.0))
        return np.unique(np.round(np.concatenate(th), 9))

    def direct_cells(self, index_ratio: float | None = None) -> int:
        """Scatter cells of one outside table (both sides)."""
        return 2 * (len(self.direct_theta_edges_deg(index_ratio)) - 1) * (len(self.direct_phi_edges_deg()) - 1)

    def direct_within(self, max_cells: int, index_ratio: float | None = None) -> "TableGrid":
        """This grid with its direct grid coarsened until an outside table has at most `max_cells`
        cells (a sampled relief cannot fill more cells than it has facets): first the engine's
        polar step, then no direct grid at all."""
        g = self
        for step in (self.direct_theta_step_deg, self.theta_step_deg, None):
            g = replace(self, direct_theta_step_deg=step)
            if step is None or g.direct_cells(index_ratio) <= max_cells:
                return g
        return g

    def key(self) -> tuple:
        """Everything that determines the tables (cache keys)."""
        return (self.theta_step_deg, self.phi_step_deg, self.inside_theta_i_step_deg, self.direct_theta_step_deg,
                self.direct_phi_step_deg, self.direct_band_deg, self.inside_samples_fraction)

    def describe(self) -> dict:
        return {"theta_step_deg": self.theta_step_deg, "phi_step_deg": self.phi_step_deg,
                "inside_theta_i_step_deg": self.inside_theta_i_step_deg,
                "direct_theta_step_deg": self.direct_theta_step_deg,
                "direct_phi_step_deg": self.direct_phi_step_deg, "direct_band_deg": self.direct_band_deg,
                "inside_samples_fraction": self.inside_samples_fraction,
                "inside_interpolation": self.inside_interpolation, "sector_step_deg": self.sector_step_deg,
                "sectors": self.sectors, "inside_azimuth_spread_deg": self.inside_azimuth_spread_deg,
                "stokes_loop": self.stokes_loop}

    def request(self, wavelengths: Any, theta_i: Any, incident_from: str, method: str, samples: int, seed: int,
                options: dict | None = None, index_ratio: float | None = None,
                max_cells: int | None = None) -> Request:
        """The methods' Request for one side of incidence on this grid: the inside tables on the engine
        grid; the outside tables of a DIRECT_METHODS method on the direct grid (`index_ratio` n / n0 of
        the glass: its exit-side edges; `max_cells`: coarsened to at most that many cells,
        `direct_within`), of any other method (wave methods pay per cell) on the engine grid."""
        outside = incident_from == "outside"
        g = self
        if outside and method not in DIRECT_METHODS:
            g = self.direct_within(0)
        elif outside and max_cells is not None:
            g = self.direct_within(int(max_cells), index_ratio)
        if not outside:
            samples = max(int(round(samples * self.inside_samples_fraction)), 1)
        te = g.direct_theta_edges_deg(index_ratio) if outside else self.theta_edges_deg()
        pe = g.direct_phi_edges_deg() if outside else self.phi_edges_deg()
        return Request(wavelengths_nm=tuple(float(w) for w in wavelengths),
                       theta_i_deg=tuple(float(t) for t in theta_i), incident_from=(incident_from,),
                       theta_s_edges_deg=te, phi_s_edges_deg=pe,
                       samples=int(samples), seed=int(seed), options=dict(options or {}))
