"""The deterministic engine of the plate: radiative transfer between the faces' boundary tables.

Entry point: `run(experiment, rows, grid)` (used by `plate.simulate`): the Experiment's faces give
their tables (`plate.faces`), `solver_of` places them on the engine's two-face system, the rows
are read by the one detector (`plate.detector`).  `PlateModel` is this engine's internal flat
configuration of an Experiment (`model_of`); `PlateSolver` / `simulate_rows` work on tables
directly (tests, benchmarks).

Geometry (formats.md frame): the plate fills -t < z < 0, the lit face is z = 0, light comes
from z > 0.  The first face (the relief, or the front face when the relief is on the back) is
described by two `BsdfTable`s (light from outside, light from inside), each at one phi_i; a row lit
from incidence azimuth phi_i reads the outside table turned by phi_i, and from the far half of
azimuths (90 < phi_i < 270 in the sample's frame: a tilt at normal incidence, a scan lit from 180)
the outside table of the relief turned by a half turn (`PlateSolver.half_turn`, exact for one tile:
`plate.faces.half_turned_outside`); the second face is flat (exact cell-averaged Fresnel) or carries its
own inside table (its delta part replaces Fresnel and its cells add a second diffuse kernel K_B).  With the
relief on the back face the system is solved with the roles swapped (same equations).

Bulk.  Without volume scattering a traversal at internal angle theta keeps exp(-a t / cos theta)
(Beer-Lambert, diagonal).  With scattering (mu_s > 0, Henyey-Greenstein g) the traversal is the
slab's reflection and transmission operators per azimuthal mode (`plate.slab`, adding-doubling),
combined with the faces by the adding equations (`_slab_system`); delta beams are attenuated by
a + mu_s,j and shed what the slab scatters out of them as diffuse sources (`_slab_sources`).
Approximation: scalar phase function on S0, Stokes vector carried unchanged by a volume event.
Source polarisation: Stokes (1, q, 0, 0), q in [-1, 1] (PlateModel.polarization: "s", "p",
"unpolarized" or q).

Method (radiative transfer between two faces, discrete ordinates):

* Internal directions are discretised into rings of the inside table's theta cells and a
  uniform azimuth grid (A cells, centres at multiples of 360/A relative to the propagation
  azimuth of the incident beam).  The state is the power per cell (fraction of the incident
  power) leaving the rough face into the plate, X.  One round trip (absorb, reflect at the
  flat face with Fresnel R_F, absorb, scatter back at the rough face with the inside table's R
  cells K) gives X = S + K A R_F A X, so X = (I - K A R_F A)^-1 S: every internal
  reflection, including light trapped by total internal reflection (R_F = 1) that escapes
  after further scattering, is summed exactly (no truncated series).
* Isotropy makes K circulant in azimuth: a real FFT over the azimuth axis block-diagonalises
  it (azimuthal reduction), so the solve is A/2+1 small (N x N) systems instead of one
  (N A) x (N A) system.  A finite tile is never quite isotropic: the one table a ray-traced relief
  gives this loop can average the incidence azimuths around its own
  (`TableGrid.inside_azimuth_spread_deg`, `plate.faces.inside_face`; +-45 deg by default).  An anisotropic
  relief traced by rays gives its inside table over twelve incidence-azimuth sectors (every 15 deg
  by default, each the average over its sector, `inside_sectors`, `TableGrid.sector_step_deg`): light
  at propagation azimuth delta then scatters by the table of its sector, K = K_0 + sum_k (K_k - K_0) P_k
  is not circulant, and the loop is solved by GMRES preconditioned by the circulant system
  (`_sector_loop`).
* The delta parts of the tables (specular reflection and transmission of the flat fraction of
  the relief, or a flat face) are kept apart as exact beams: their chain between the faces is
  a 4x4 geometric series (Mueller matrices), and what they scatter diffusely feeds S.
* Polarisation: Stokes vectors (S0, S1 = I_s - I_p, S2, S3) in the s/p basis of the plane
  (direction, z) (bsdf.py frames).  At a flat face this plane is the plane of incidence, so
  Fresnel Mueller matrices (optics.mueller_interface) apply without rotation and a flat plate
  is exact for s and p separately.  When the tables carry Mueller matrices the diffuse loop
  runs on 4-vectors; otherwise the tables are taken as polarisation independent and
  *depolarising* for their diffuse part (M = f diag(1,0,0,0)) and polarisation preserving for
  their specular part (M = p I), and the diffuse loop is scalar (exact under that assumption,
  since the flat face's polarisation is destroyed at the next rough interaction).
* Output: the plate BSDF on an outgoing grid (theta cells x azimuth grid) per side, plus
  delta beams; rows are read by `plate.detector.grid_reading` (cone (x) Gaussian blur
  quadrature for the diffuse part, response(psi) P / (Omega cos theta_s) for a delta beam).
* Two grids (plate.grid).  When the outside table is on a finer grid than the
  engine's (`TableGrid` direct grid: 0.5-deg rings with the flat face's Snell pre-images, 1-deg
  azimuth cells around the plane of incidence), the loop is solved on the engine grid with the
  outside table's cell averages there (`_TableView.cells`: projected-solid-angle overlaps, power
  kept), and the two terms that carry the narrow lobes are read from the outside table's own
  cells: the direct reflection f_R and the first transmitted pass, which leaves through the flat
  face as f_T(theta_int) T_F(theta_int) (n0/n)^2 exp(-a t / cos theta_int) at the Snell
  pre-image theta_int of each exit direction (the radiance law; the same terms the engine grid
  carries, `_flat_exit`, subtracted there).  Applies with a flat second face and no volume
  scattering (otherwise everything is read on the engine grid, as before).  In the loop the first
  transmission is then only the source of the later passes, and its cell averages enter as point
  sources at the azimuth cells' centres weighted by the centre values (`detector.centre_values`,
  unclipped: each ring's power kept): a 5-deg cell's averaging would otherwise widen a lobe that is
  narrow across the plane of incidence by the cell's variance d^2 / 12 once more at every later exit
  (Sheppard's correction).  Measured against the independent photon Monte Carlo
  (bench_forward_accuracy): the real measured map's second pass (R minus the R of an opaque
  plate) reads 7 % low at 30 and 60 deg without it, 3.9 / 3.7 % with it (in-lobe R level 0.96 -> 0.98, rms z 1.35 ->
  1.18), nearly what 2.5-deg engine cells give (3.6 / 2.8 %) without their 1.2-1.5x cost.

Regime of validity: geometric optics between the faces (plate thick compared with the
coherence length: intensities add, no thin-film fringes), laterally infinite plate
(no edge loss), translation-invariant faces (the relief's statistics do not vary over the
lit spot), discretisation error of the order of the table's cell size (the direct grid's for the
direct terms, the engine grid's for the loop).
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from relief_bsdf.bsdf.table import ROW_ARRAYS, BsdfTable, interpolation_matrix, linear_weights
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.errors import InputError
from relief_bsdf.core.frames import rot_y
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.core.index import ConstantIndex, IndexModel, Material
from relief_bsdf.plate.description import Bulk, Instrument
from relief_bsdf.plate.detector import beam_offsets, centre_values, grid_reading, offset_directions
from relief_bsdf.plate.grid import INSIDE_INTERPOLATIONS
from relief_bsdf.plate.memory import current_memory, deep_nbytes
from relief_bsdf.parallel.blas import blas_single_thread   # the plate's matrices are small (N ~ 90): one thread

_DEPOL = np.diag([1.0, 0.0, 0.0, 0.0])


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


@dataclass
class Rows:
    """The geometry of recording rows (any object with these arrays works)."""

    wavelength_nm: np.ndarray
    theta_i_deg: np.ndarray
    phi_i_deg: np.ndarray
    side: np.ndarray
    theta_s_deg: np.ndarray
    phi_s_deg: np.ndarray

    def __post_init__(self) -> None:
        for k in ("wavelength_nm", "theta_i_deg", "phi_i_deg", "theta_s_deg", "phi_s_deg"):
            setattr(self, k, np.atleast_1d(np.asarray(getattr(self, k), float)))
        self.side = np.atleast_1d(np.asarray(self.side, dtype="<U1"))

    def __len__(self) -> int:
        return self.wavelength_nm.size


def in_plane_rows(wavelength_nm: float, theta_i_deg: Sequence[float], theta_s_deg: Sequence[float],
                  sides: Sequence[str] = ("R", "T"), phi_s_deg: Sequence[float] = (0.0, 180.0)) -> Rows:
    """Rows of a typical in-plane scan (phi_i = 0, phi_s in {0, 180})."""
    g = np.array([(wavelength_nm, ti, 0.0, sd, ts, ps) for ti in theta_i_deg for sd in sides
                  for ps in phi_s_deg for ts in theta_s_deg], dtype=object)
    return Rows(g[:, 0].astype(float), g[:, 1].astype(float), g[:, 2].astype(float), g[:, 3].astype(str),
                g[:, 4].astype(float), g[:, 5].astype(float))


def check_rows(model: PlateModel, rows: Any, where: str = "recording") -> None:
    """InputError (naming `where` and the column) for rows the plate cannot produce."""
    model.index.check_range(rows.wavelength_nm, f"{where}: wavelength_nm")
    model.outside_index.check_range(rows.wavelength_nm, f"{where}: wavelength_nm")
    for key in ("theta_i_deg", "theta_s_deg"):
        v = np.asarray(getattr(rows, key), float)
        bad = ~np.isfinite(v) | (v < 0) | (v >= 90)
        if bad.any():
            raise InputError(f"{where}: {key}", f"value {v[bad][0]:g} is outside [0, 90) degrees "
                             "(a plate cannot be lit or seen at or past grazing)")
    s = np.asarray(rows.side).astype(str)
    if np.any((s != "R") & (s != "T")):
        raise InputError(f"{where}: side", "side must be R or T")


# ---------------------------------------------------------------- interpolation helpers

def _lin_weights(grid: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(i0, i1, f): x (any shape, clamped at the ends) between grid[i0] and grid[i1] at the fraction f
    (`bsdf.table.linear_weights`, the one table interpolation)."""
    return linear_weights(np.asarray(grid, float), np.asarray(x, float))


def _lin_matrix(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(len(x), len(grid)) linear interpolation weights, clamped at the ends."""
    return interpolation_matrix(grid, x)


def _periodic_matrix(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Like `_lin_matrix` on a 360-degree periodic axis."""
    return interpolation_matrix(grid, x, periodic=True)


def _apply(W: np.ndarray, arr: np.ndarray, axis: int) -> np.ndarray:
    """Contract interpolation matrix W (new, old) with `arr` along `axis`.

    Linear interpolation has at most two weights per row: the contraction is then, along the leading
    axis (whose entries are contiguous blocks: a table's incidences), each new block written in place
    as w0 X[i0] + w1 X[i1], one block of scratch; along an inner axis, two gathers.  (A dense product
    would pass over every old index for each new one and copy the big Mueller arrays through
    transposes; the gathers along the leading axis made two fresh copies of the whole result, 3x the
    time of the blocks on the inside table's (37, 90, 37, 4, 4) modes, the same numbers.)"""
    if W.shape[0] == W.shape[1] and np.all(np.diagonal(W) == 1.0):   # rows sum to 1: identity
        return arr
    nz = W != 0
    if nz.sum(axis=1).max(initial=0) > 2:
        return np.moveaxis(np.tensordot(W, arr, axes=([1], [axis])), 0, axis)
    order = np.argsort(~nz, axis=1, kind="stable")[:, :2]              # the (up to) two weights of each row
    w = np.take_along_axis(W, order, axis=1)
    dtype = np.result_type(arr.dtype, W.dtype)
    if axis == 0 and W.shape[1] > 1 and np.any(w[:, 0] != 1.0):
        return _blend_blocks(arr, order, w, dtype)
    out = np.take(arr, order[:, 0], axis=axis).astype(dtype, copy=False)
    second = W.shape[1] > 1 and np.any(w[:, 1])
    if not second and np.all(w[:, 0] == 1.0):
        return out                                                      # a selection (a rotation of the azimuths)
    shape = [1] * arr.ndim
    shape[axis] = -1
    out *= w[:, 0].reshape(shape)
    if second:
        second = np.take(arr, order[:, 1], axis=axis).astype(dtype, copy=False)
        second *= w[:, 1].reshape(shape)
        out += second
    return out


def _blend_blocks(arr: np.ndarray, order: np.ndarray, w: np.ndarray, dtype) -> np.ndarray:
    """out[j] = w[j, 0] arr[order[j, 0]] + w[j, 1] arr[order[j, 1]] along the leading axis, block by
    block in place (`_apply`; products in `dtype`, the gathers' numbers)."""
    out = np.empty((order.shape[0],) + arr.shape[1:], dtype)
    scratch = np.empty(arr.shape[1:], dtype)
    for j in range(order.shape[0]):
        np.multiply(arr[order[j, 0]], w[j, 0], out=out[j], dtype=dtype)
        if w[j, 1] != 0.0:
            np.multiply(arr[order[j, 1]], w[j, 1], out=scratch, dtype=dtype)
            out[j] += scratch
    return out


def _overlap_theta(edges_deg: np.ndarray, coarse_edges_deg: np.ndarray) -> np.ndarray:
    """(C, S) weights turning cell averages on polar edges `edges_deg` into averages on `coarse_edges_deg`:
    the overlap of the cells in projected solid angle (u = sin^2 theta: d(sin^2) = 2 sin cos d theta),
    each cell's value taken as uniform over it (its average)."""
    u = np.sin(np.radians(np.asarray(edges_deg, float))) ** 2
    uc = np.sin(np.radians(np.asarray(coarse_edges_deg, float))) ** 2
    ov = np.clip(np.minimum(uc[1:, None], u[None, 1:]) - np.maximum(uc[:-1, None], u[None, :-1]), 0.0, None)
    return ov / np.maximum(uc[1:] - uc[:-1], 1e-300)[:, None]


def _overlap_phi(edges_deg: np.ndarray, centres_deg: np.ndarray, width_deg: float) -> np.ndarray:
    """(A, P) weights turning azimuth-cell averages on `edges_deg` into averages over the cells
    [c - w/2, c + w/2] (periodic: the table's cells are also taken 360 deg to either side)."""
    e = np.asarray(edges_deg, float)
    lo = np.asarray(centres_deg, float)[:, None] - width_deg / 2
    hi = lo + width_deg
    W = np.zeros((lo.size, e.size - 1))
    for k in (-720.0, -360.0, 0.0, 360.0, 720.0):
        W += np.clip(np.minimum(hi, e[None, 1:] + k) - np.maximum(lo, e[None, :-1] + k), 0.0, None)
    return W / width_deg


MOVE_EXIT_LIMIT_DEG = 80.0    # a transmitted lobe moves with its Snell exit angle below this; beyond, it blends


def _exit_angle_deg(theta_in_deg: np.ndarray, n_in: float, n_out: float) -> np.ndarray:
    """Where the transmitted lobe of light arriving at theta_in is centred: the Snell exit angle (NaN
    beyond the critical angle or past MOVE_EXIT_LIMIT_DEG, where the lobe blends)."""
    th = np.asarray(theta_in_deg, float)
    out = _snell_deg(th, n_in, n_out)
    return np.where((np.sin(np.radians(th)) * n_in < n_out) & (out <= MOVE_EXIT_LIMIT_DEG), out, np.nan)


def _psa_weights(theta_out_deg: np.ndarray) -> np.ndarray:
    """Projected solid angle per degree of azimuth of the cells centred on theta_out (edges halfway, 0, 90)."""
    t = np.asarray(theta_out_deg, float)
    return projected_solid_angle(np.concatenate([[0.0], 0.5 * (t[1:] + t[:-1]), [90.0]]), [0.0, 1.0])[:, 0]


class _TableView:
    """One boundary table at one wavelength, sampled on arbitrary angles (isotropic tables only).

    `moving` (n_inside, n_outside), for a table of light from inside: between two of its incidences
    the lobes MOVE rather than blend (`_between_incidences`)."""

    def __init__(self, table: BsdfTable, wavelength_nm: float, mueller: bool, name: str,
                 moving: tuple[float, float] | None = None):
        self.moving = moving
        if not table.is_isotropic:
            raise InputError(name, "the plate model needs an isotropic boundary table (one phi_i)")
        self.table = table
        ww = _lin_matrix(table.wavelength_nm, [wavelength_nm])[0]
        self.mueller = mueller

        def at_wavelength(arr):          # a view when the wavelength is on the grid (no copy of a big table)
            hit = np.nonzero(ww == 1.0)[0]
            return arr[hit[0], :, 0] if hit.size else np.tensordot(ww, arr[:, :, 0], axes=(0, 0))
        if mueller:
            if table.mueller_per_sr is not None:
                v = at_wavelength(table.mueller_per_sr)                                         # (I, 2, S, P, 4, 4)
            else:
                v = at_wavelength(table.values_per_sr)[..., None, None] * _DEPOL
        else:
            v = at_wavelength(table.values_per_sr)                                              # (I, 2, S, P)
        self.v = v
        self.spec = {}
        for k, name_ in ((0, "R"), (1, "T")):
            p = ww @ getattr(table, f"specular_{name_}")[:, :, 0]                              # (I,)
            m = getattr(table, f"specular_mueller_{name_}")
            pm = (np.tensordot(ww, m[:, :, 0], axes=(0, 0)) if m is not None
                  else p[:, None, None] * np.eye(4))
            self.spec[name_] = (p, pm)
        self.phi0 = float(table.phi_i_deg[0])

    def diffuse(self, side: str, theta_in: np.ndarray, theta_out: np.ndarray, delta_deg: np.ndarray) -> np.ndarray:
        """f(theta_in -> theta_out, relative propagation azimuth delta): (J, T, A[, 4, 4])."""
        arr = self._on_exit_grid(side, theta_out, delta_deg)
        return self._between_incidences(side, arr, theta_in, theta_out, delta_deg)  # last: it makes the array grow

    def _moves(self, side: str, theta_out: np.ndarray, delta_deg: np.ndarray) -> bool:
        """The transmitted lobes of an inside table move (`_between_incidences`) on these exit axes: polar
        angles from the pole up (uniform steps), an even number of uniform azimuths from 0 (each has its
        opposite, across the pole), two incidences at least."""
        t, d = np.asarray(theta_out, float), np.asarray(delta_deg, float)
        if (self.moving is None or side != "T" or self.table.theta_i_deg.size < 2 or t.size < 2 or d.size < 2
                or d.size % 2):
            return False
        step = t[1] - t[0]
        return bool(np.allclose(np.diff(t), step) and abs(t[0] - step / 2) < 1e-9
                    and np.allclose(d, np.arange(d.size) * 360.0 / d.size))

    def _between_incidences(self, side: str, arr: np.ndarray, theta_in: np.ndarray, theta_out: np.ndarray,
                            delta_deg: np.ndarray) -> np.ndarray:
        """The table's cells `arr` (I, T, A, ...) on the exit axes, at the incidences theta_in (J, T, A, ...).

        Linear in theta_i, except for the transmitted side of a table of light from inside (`moving`):
        there a lobe MOVES with its incidence rather than blends (a narrow transmitted
        lobe blended between two incidences 2.5 deg apart is two half lobes ~4 deg apart outside, the
        second pass of a smooth relief's reflection).  Each of the two incidences theta_a around theta_in
        lends its cells shifted by s = e(theta_in) - e(theta_a), e the Snell exit angle where the lobe
        is centred (`_exit_angle_deg`): the direction at polar angle x and relative azimuth delta takes
        the table's value at x - s cos(delta) on the line through the pole (the other side of the pole
        is the opposite azimuth), a translation of the lobe along delta = 0 to first order.  The result
        is scaled to the albedo of the linear blend at each theta_in (energy as before: R + T of the loop
        unchanged; the translation moves light across the cells' projected solid angles).  Regime: the
        lobe's shape changes little over one step of incidence; near the critical angle (exit beyond
        MOVE_EXIT_LIMIT_DEG) it blends.  The reflected side blends: inside the glass it is twice the
        slope wide and first read at the third pass; moving it too changed no case of
        benchmarks/bench_forward_accuracy.py (gauss_low, gauss_mid, anisotropic, measured map, to 0.01
        in rms z) and cost 0.7 s per solver."""
        W = _lin_matrix(self.table.theta_i_deg, theta_in)
        if not self._moves(side, theta_out, delta_deg):
            return _apply(W, arr, 0)
        t_in = np.asarray(self.table.theta_i_deg, float)
        x_in = np.atleast_1d(np.asarray(theta_in, float))
        to, d = np.asarray(theta_out, float), np.asarray(delta_deg, float)
        T, A = to.size, d.size
        axis = np.concatenate([-to[::-1], to])                               # signed polar angle, through the pole
        cosd = np.cos(np.radians(d))
        e_q = _exit_angle_deg(np.clip(x_in, t_in[0], t_in[-1]), *self.moving)
        e_t = _exit_angle_deg(t_in, *self.moving)
        i0, i1, f = _lin_weights(t_in, x_in)                                 # the two incidences around theta_in
        flat = arr.reshape(t_in.size * T * A, -1)                         # rows: (incidence, polar, azimuth)
        a = np.arange(A)[None, None, :]
        sources, weights = [], []                                          # four per new cell
        for ii, w in ((i0, 1.0 - f), (i1, f)):
            s = e_q - e_t[ii]
            s = np.where(np.isfinite(s), s, 0.0)
            k0, k1, g = _lin_weights(axis, to[None, :, None] - s[:, None, None] * cosd[None, None, :])  # (J, T, A)
            for k, wk in ((k0, 1.0 - g), (k1, g)):
                row = np.where(k >= T, k - T, T - 1 - k)                  # across the pole: the opposite azimuth
                col = np.where(k >= T, a, (a + A // 2) % A)
                sources.append((ii[:, None, None] * T + row) * A + col)
                weights.append(wk * w[:, None, None])
        # the four weighted cells summed per new cell as one sparse product (rows: the new cells), in the
        # order above: the numbers of four gathers added in turn, without their four copies of the result
        from scipy import sparse
        n_new = x_in.size * T * A
        blend = sparse.csr_matrix((np.stack(weights, axis=-1).ravel(), np.stack(sources, axis=-1).ravel(),
                                   np.arange(0, 4 * n_new + 1, 4)), shape=(n_new, flat.shape[0]))
        out = np.asarray(blend @ flat.astype(np.result_type(arr, float), copy=False)).reshape(
            (x_in.size, T, A, flat.shape[1]))
        # albedo of each incidence, unpolarised (the first component: Mueller element 00 or the detector row's)
        psa = _psa_weights(to)
        alb_lin = W @ np.einsum("itA,t->i", flat[:, 0].reshape(t_in.size, T, A), psa)
        alb_mov = np.einsum("jtA,t->j", out[..., 0], psa)
        scale = np.where(alb_mov > 0, alb_lin / np.where(alb_mov > 0, alb_mov, 1.0), 1.0)
        out = out.reshape((x_in.size,) + arr.shape[1:])
        out *= scale.reshape((-1,) + (1,) * (out.ndim - 1))
        return out

    def _on_exit_grid(self, side: str, theta_out: np.ndarray, delta_deg: np.ndarray) -> np.ndarray:
        """The table's cells of one side at its own incidences, sampled on the exit angles and the
        relative propagation azimuths delta: (I, T, A[, 4, 4])."""
        t = self.table
        arr = self.v[:, 0 if side == "R" else 1]                              # (I, S, P, ...)
        arr = _apply(_periodic_matrix(t.phi_s_deg, self.phi0 + 180.0 + np.asarray(delta_deg)), arr, 2)
        return _apply(_lin_matrix(t.theta_s_deg, theta_out), arr, 1)

    def diffuse_modes(self, side: str, theta_in: np.ndarray, theta_out: np.ndarray, delta_deg: np.ndarray,
                      detector_row: bool = False) -> np.ndarray:
        """rfft over the azimuth cells of `diffuse` (J, T, M[, 4, 4]; with `detector_row` the Mueller
        row S0 alone, (J, T, M[, 4])): the Fourier modes the circulant loop works with.  The FFT is taken
        on the table's own incidences and then interpolated in theta_i (linear maps on different axes
        commute), so the (J, T, A, 4, 4) kernel on the engine grid is never built."""
        arr = self._on_exit_grid(side, theta_out, delta_deg)
        if detector_row and self.mueller:
            arr = arr[..., 0, :]
        if self._moves(side, theta_out, delta_deg):      # the lobes move: in theta_i first, then the modes
            return np.ascontiguousarray(np.fft.rfft(self._between_incidences(side, arr, theta_in, theta_out,
                                                                             delta_deg), axis=2))
        modes = np.ascontiguousarray(np.fft.rfft(arr, axis=2))        # rfft leaves the modes strided
        return _apply(_lin_matrix(self.table.theta_i_deg, theta_in), modes, 0)

    def on_grid(self, theta_edges_deg: np.ndarray, azimuth_cells: int) -> bool:
        """The table's cells are the engine's (same polar edges, azimuth cells centred on the engine's)."""
        t = self.table
        pe = np.asarray(t.phi_s_edges_deg, float)
        d = 360.0 / azimuth_cells
        want = self.phi0 + 180.0 - d / 2 + np.arange(azimuth_cells + 1) * d
        same_phi = pe.size == want.size and np.allclose(np.sort(np.mod(pe[:-1] - want[0] + 1e-9, 360.0)),
                                                          np.mod(want[:-1] - want[0] + 1e-9, 360.0), atol=1e-6)
        return bool(np.array_equal(np.asarray(t.theta_s_edges_deg, float), np.asarray(theta_edges_deg, float))
                    and same_phi)

    def at_incidence(self, side: str, theta_in: float) -> np.ndarray:
        """The table's own cells at one incidence (linear in theta_i): (S, P[, 4, 4])."""
        k = 0 if side == "R" else 1
        return _apply(_lin_matrix(self.table.theta_i_deg, [theta_in]), self.v[:, k], 0)[0]

    def cells(self, side: str, theta_in: float, theta_edges_deg: np.ndarray, delta_deg: np.ndarray) -> np.ndarray:
        """Cell averages on the engine grid (polar edges x azimuth cells centred on delta, relative
        propagation azimuth) from the table's own cells (projected-solid-angle overlaps): (T, A[, 4, 4])."""
        arr = self.at_incidence(side, theta_in)
        t = self.table
        Wt = _overlap_theta(t.theta_s_edges_deg, theta_edges_deg)
        Wp = _overlap_phi(t.phi_s_edges_deg, self.phi0 + 180.0 + np.asarray(delta_deg, float),
                          360.0 / np.asarray(delta_deg).size)
        arr = np.tensordot(Wt, arr, axes=(1, 0))
        return np.moveaxis(np.tensordot(Wp, arr, axes=(1, 1)), 0, 1)

    def specular(self, side: str, theta_in: float) -> np.ndarray:
        """4x4 Mueller matrix (or scalar power fraction times I) of the delta part."""
        return self.specular_many(side, [theta_in])[0]

    def specular_many(self, side: str, theta_in: Any) -> np.ndarray:
        """(n, 4, 4) delta-part Mueller matrices at several incidence angles."""
        p, pm = self.spec[side]
        W = _lin_matrix(self.table.theta_i_deg, np.ravel(theta_in))
        return np.tensordot(W, pm, axes=(1, 0))


def _reflect_up(ops: dict, at: np.ndarray) -> np.ndarray:
    """(q, N, A, c) power per cell arriving back at the rough face from inside: `at` (power per cell at the
    flat face) times the flat face's cell-averaged Fresnel R (Mueller for c = 4) and one traversal."""
    absorb = ops["absorb"]
    if ops["c"] == 1:
        return (at[..., 0] * (ops["RF"][:, 0, 0] * absorb)[None, :, None])[..., None]
    return np.einsum("jab,qjkb->qjka", ops["RF"], at) * absorb[None, :, None, None]


def _exit_modes(U: np.ndarray) -> np.ndarray:
    """(q, N, A, c) cells -> (M, q, N c) azimuthal Fourier modes."""
    nI, N, _, c = U.shape
    Uh = np.fft.rfft(U, axis=2)
    return np.moveaxis(Uh, 2, 0).reshape(Uh.shape[2], nI, N * c)


def _rough_exit(Um: np.ndarray, GhT: np.ndarray, A: int) -> np.ndarray:
    """(q, O, A) BSDF leaving through the rough face of the light arriving from inside in modes Um (M, q, J c),
    by the exit kernel GhT (M, J c, O): a circular convolution over azimuth."""
    return np.fft.irfft(np.moveaxis(Um @ GhT, 0, 2), n=A, axis=2)


def _phi_slice(table: BsdfTable, ip: int) -> BsdfTable:
    """The table at its ip-th incidence azimuth only (every array's phi_i axis, axis 2, cut to one)."""
    kw = {"phi_i_deg": np.asarray(table.phi_i_deg)[ip:ip + 1]}
    for name in ROW_ARRAYS:
        a = getattr(table, name)
        if a is not None:
            kw[name] = a[:, :, ip:ip + 1]
    return replace(table, **kw)


def _blocks(Xh: np.ndarray, c: int, out: np.ndarray | None = None) -> np.ndarray:
    """(T, J, M[, 4, 4]) kernel in Fourier space -> (M, T c, J c) matrices; written into `out` (a view of
    that shape, e.g. a slice of a bigger array) when given, without an intermediate copy."""
    view = np.moveaxis(Xh, 2, 0) if c == 1 else np.transpose(Xh, (2, 0, 3, 1, 4))      # (M, T[, 4], J[, 4])
    if out is None:
        return view if c == 1 else view.reshape(view.shape[0], view.shape[1] * 4, view.shape[3] * 4)
    target = out.view()
    target.shape = view.shape                # raises rather than copy: the numbers must land in `out`
    target[...] = view
    return out


def _block_diag(D: np.ndarray, c: int) -> np.ndarray:
    """(N, 4, 4) per-cell Mueller matrices -> (N c, N c) block-diagonal (c = 1: the M00 diagonal)."""
    N = D.shape[0]
    if c == 1:
        return np.diag(D[:, 0, 0])
    out = np.zeros((N, 4, N, 4))
    idx = np.arange(N)
    out[idx, :, idx, :] = D
    return out.reshape(N * 4, N * 4)


def _fresnel(cos_i: np.ndarray, n1: float, n2: float, kind: str) -> np.ndarray:
    return mueller_interface(np.asarray(cos_i, float), n1, n2, kind)


def _snell_deg(theta_deg: Any, n1: float, n2: float) -> np.ndarray:
    s = np.sin(np.radians(theta_deg)) * n1 / n2
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))


# ---------------------------------------------------------------- volume scattering (plate.slab)

def _kron4(X: np.ndarray) -> np.ndarray:
    """(M, N, N) scalar operators -> (M, 4N, 4N) acting on Stokes vectors unchanged (scalar phase function)."""
    M, N, _ = X.shape
    return np.einsum("mij,ab->miajb", X, np.eye(4)).reshape(M, 4 * N, 4 * N)


def _slab_system(m: "PlateModel", theta_edges: np.ndarray, A: int, Kb: np.ndarray, R2: np.ndarray, c: int) -> dict:
    """Adding of the scattering slab to the faces, per azimuthal mode (adding equations, van de Hulst 1980).

    X (down-going at the top of the slab, leaving the first face) reaches the second face as
    B X, B = (I - Rv R2)^-1 Tv, and returns to the first face as Rc X, Rc = Rv + Tv R2 B
    (R2: the second face's reflection; Rv, Tv: the slab's).  Round trip: X = S + Kb Rc X.
    Without scattering Rv = 0, Tv = diag(exp(-a t / mu)) and this is the diagonal loop.
    """
    from relief_bsdf.plate.slab import slab_operators
    key = ("slab", tuple(np.round(theta_edges, 9)), int(A), m.thickness_m, m.absorption_per_m, m.scatter_per_m, m.hg_g)
    sl = current_memory().get(key, lambda: slab_operators(theta_edges, A, m.thickness_m, m.absorption_per_m,
                                                          m.scatter_per_m, m.hg_g), "slab")
    Rv, Tv, Td = (sl.R, sl.T, sl.T_diffuse) if c == 1 else (_kron4(sl.R), _kron4(sl.T), _kron4(sl.T_diffuse))
    eye = np.eye(Rv.shape[1])[None]
    B = np.linalg.solve(eye - Rv @ R2, Tv)
    Rc = Rv + Tv @ R2 @ B
    Q = np.linalg.inv(eye - R2 @ Rv)
    return dict(slab=sl, Rv=Rv, Tv=Tv, Td=Td, R2=R2, B=B, Q=Q, Rtrip=Rc, sys=eye - Kb @ Rc)


def _cell_of(theta_edges: np.ndarray, theta_deg: float) -> int:
    return int(np.clip(np.searchsorted(theta_edges, theta_deg, side="right") - 1, 0, theta_edges.size - 2))


def _beam_extinction(m: "PlateModel", slab: dict | None, theta_edges: np.ndarray, theta_deg: float) -> float:
    """Attenuation coefficient of a delta beam: a, plus the cell-visible scattering mu_s,j with a slab."""
    if slab is None:
        return m.absorption_per_m
    return float(slab["slab"].ext_per_m[_cell_of(theta_edges, theta_deg)])


def _slab_sources(slab: dict, Wh: np.ndarray, beams: np.ndarray, theta_edges: np.ndarray, thetas: np.ndarray,
                  n0: float, n: float, c: int) -> tuple[np.ndarray, np.ndarray]:
    """(U_x, D_x): extra diffuse light arriving at the first face (up) and at the second face (down).

    Sources: Wh (M, N c, q) leaving the second face upward (a back-face table's diffuse reflection
    of the beam); the delta beams shed into the slab what it scatters out of them: the down beam
    y (leaving the first face) gives Td y down at the second face and Rv y up at the first; the up
    beam b (leaving the second face) gives Td b up and Rv b down.  A beam at internal angle t is
    given its cell's columns, scaled so that it sheds exactly the power its exact attenuation
    removes.  Then W = Q (Wh + R2 s_down), U_x = u_up + Tv W, D_x = s_down + Rv W.
    """
    sl = slab["slab"]
    Rv, Td = slab["Rv"], slab["Td"]
    M, Nc, nI = Wh.shape
    s_down = np.zeros_like(Wh)
    u_up = np.zeros_like(Wh)
    for q, ti in enumerate(thetas):
        tt = float(np.degrees(np.arcsin(min(np.sin(np.radians(abs(ti))) * n0 / n, 1.0))))
        j = _cell_of(theta_edges, tt)
        mu_t = max(np.cos(np.radians(tt)), 1e-6)
        cols = slice(j * c, (j + 1) * c)
        y, b = beams[q, 0][:c], beams[q, 1][:c]
        scale = _shed_scale(sl, j, mu_t)
        s_down[:, :, q] = (Td[:, :, cols] @ y + Rv[:, :, cols] @ b) * scale
        u_up[:, :, q] = (Rv[:, :, cols] @ y + Td[:, :, cols] @ b) * scale
    W = slab["Q"] @ (Wh + slab["R2"] @ s_down)
    return u_up + slab["Tv"] @ W, s_down + Rv @ W


def _shed_scale(sl: Any, j: int, mu_beam: float) -> float:
    """Power a beam at mu_beam loses in the slab over what its cell's operators remove (1 at the centre)."""
    lost_cell = 1 - sl.direct[j]
    if lost_cell <= 0:
        return 0.0
    return float((1 - np.exp(-sl.ext_per_m[j] * sl.thickness_m / mu_beam)) / lost_cell)


# ---------------------------------------------------------------- the solver

@dataclass
class PlateResult:
    """Plate BSDF of one incidence on the outgoing grid, plus the delta beams.

    grid_R / grid_T: (T, A) BSDF (1/sr) at theta_out_deg x delta_deg (delta = outgoing
    azimuth minus the incident beam's propagation azimuth phi_i + 180).
    deltas: list of (side, theta_deg, delta_deg, power fraction) for exact beams.
    direct / loop_R / loop_T: when the outside table is finer than the engine grid, the direct
    reflection and the first transmitted pass on the table's own cells (read by integrating them
    over the detector cone) and the rest on the engine grid; grid_R / grid_T hold the sum.
    """

    wavelength_nm: float
    theta_i_deg: float
    phi_i_deg: float
    theta_out_deg: np.ndarray
    theta_edges_deg: np.ndarray
    delta_deg: np.ndarray
    grid_R: np.ndarray
    grid_T: np.ndarray
    deltas: list = field(default_factory=list)
    direct: Any = None            # DirectField of the outside table's direct parts (or None)
    loop_R: Any = None            # with `direct`: grid_R / grid_T without the direct parts (engine grid)
    loop_T: Any = None

    def hemispherical(self) -> dict:
        """Directional-hemispherical R and T of the plate (diffuse + delta)."""
        da = 360.0 / self.delta_deg.size
        psa = projected_solid_angle(self.theta_edges_deg, [0.0, da])[:, 0]
        out = {}
        for side, g in (("R", self.grid_R), ("T", self.grid_T)):
            d = float(np.sum(g * psa[:, None]))
            s = float(sum(p for sd, _, _, p in self.deltas if sd == side))
            out[side] = d + s
            out[f"diffuse_{side}"] = d
            out[f"specular_{side}"] = s
        return out


class PlateSolver:
    """Plate operator for one pair of boundary tables; call `solve` per wavelength and incidences.

    Per wavelength the round-trip system is factorised once and reused for every incidence.
    """

    def __init__(self, model: PlateModel, inside: BsdfTable, outside: BsdfTable | None = None,
                 back: BsdfTable | None = None, front: tuple[BsdfTable, BsdfTable] | None = None,
                 inside_sectors: BsdfTable | None = None):
        """`back`: optional BSDF table (light from inside) of the second, back face; None = flat.

        `inside_sectors`: the relief's inside table by incidence-azimuth sector (an anisotropic relief,
        `plate.faces.inside_sectors`; with a sector at 0 deg the inside table serves no light of the
        loop); the light inside the plate (every order of the loop: the second pass and the trapped
        light) then scatters and leaves through the sector nearest its azimuth
        (`_sector_loop`, `_sector_exits`).

        `front`: optional (outside, inside) tables of the FRONT face when the relief is on the back
        (None = flat).  The plate is then solved with the roles swapped: the front face is the first
        face (both tables) and the relief the second face, which light reaches only from inside
        (`inside` is the relief's inside table), i.e. exactly the front-relief-plus-back-table system.
        """
        if front is not None:
            if model.rough_face != "back":
                raise InputError("plate", "a BSDF table for the front face needs the relief on the back face "
                                 "(with the relief in front, give the second face as `back`)")
            if back is not None:
                raise InputError("plate", "with the relief on the back face, the second face is the relief: "
                                 "give the front face as `front`, not `back`")
            f_out, f_in = front
            model, back = replace(model, rough_face="front"), inside
            outside, inside = f_out, f_in
        if back is not None:
            if model.rough_face != "front":
                raise InputError("plate", "a BSDF table for the second face is supported when the relief is on "
                                 "the front face (the back face is then the second face)")
            if back.incident_from != "inside":
                raise InputError("plate", "the back-face table must have incident_from = 'inside'")
        self.back = back
        self.inside_sectors = inside_sectors
        if inside_sectors is not None and (model.rough_face != "front" or inside_sectors.incident_from != "inside"):
            raise InputError("plate", "inside sector tables need the relief on the front face and incident_from "
                             "= 'inside'")
        if inside.incident_from != "inside":
            raise InputError("plate", "the inside table must have incident_from = 'inside'")
        if model.rough_face == "front":
            if outside is None:
                raise InputError("plate", "a relief on the front face needs the outside table too")
            if outside.incident_from != "outside":
                raise InputError("plate", "the outside table must have incident_from = 'outside'")
        self.model = model
        self.inside = inside
        self.outside = outside
        self.mueller = model.stokes_loop and (inside.is_polarized or (outside is not None and outside.is_polarized)
                                              or (back is not None and back.is_polarized))
        self.theta_edges = np.asarray(inside.theta_s_edges_deg, float)
        self.theta_c = 0.5 * (self.theta_edges[1:] + self.theta_edges[:-1])
        A = int(model.azimuth_cells)
        self.delta = np.arange(A) * (360.0 / A)
        self.psa = projected_solid_angle(self.theta_edges, [0.0, 360.0 / A])[:, 0]        # (N,)
        self._ops: dict = {}
        self._tops: dict = {}          # the tables' part of the operators (`_table_ops`), shared across bulks
        self._twins: dict = {}         # wavelength -> the one solved in its place (`_twin_wavelength`)
        # the solver on the outside table of the relief turned by a half turn, for the rows lit from the
        # far half of azimuths (`far_side`, `plate.faces.half_turned_outside`; set by `solver_of`), or None:
        # those rows are then read from this solver's phi_i = 0 table turned by their azimuth
        self.half_turn: "PlateSolver | None" = None

    def memory_bytes(self) -> int:
        """Bytes this solver holds of its own (its operators, their factors, the fields kept per wavelength;
        `plate.memory`): its tables count here only where the memory owner does not hold them itself, and
        the half-turned solver is an entry of its own."""
        memory = current_memory()
        seen: set = set()
        tables = [t for t in (self.inside, self.outside, self.back, self.inside_sectors) if t is not None]
        for t in tables:                 # the owner's tables (and the views of them the operators keep) count there
            if memory.key_of(t) is not None:
                deep_nbytes(t, seen)
        own = deep_nbytes((self._ops, self._tops, self._twins), seen)
        return own + deep_nbytes([t for t in tables if memory.key_of(t) is None], seen)

    # -- per wavelength operators
    def _table_ops(self, wl: float) -> dict:
        """The part of a wavelength's operators that the boundary tables and the indices fix (the
        kernels in azimuthal modes, the faces' delta parts and exit maps); the bulk (thickness,
        absorption, volume scattering) acts through `_operators` alone.  Shared by the solvers of
        one plate's tables whose bulk differs (`_reused_solver`: a fit of the absorption)."""
        if wl in self._tops:
            return self._tops[wl]
        m = self.model
        n = float(np.real(m.index.n(wl)))
        n0 = float(np.real(m.outside_index.n(wl)))
        tc = self.theta_c
        N = tc.size
        c = 4 if self.mueller else 1
        mv = (n, n0) if m.inside_interpolation == "moving" else None
        vin = _TableView(self.inside, wl, self.mueller, "inside table", mv)
        # Fresnel of the flat face averaged over each internal cell (projected solid angle): the cell
        # straddling the critical angle then loses exactly what the exit remap below lets out
        e = np.radians(self.theta_edges)
        nsub = 64
        u = (np.sin(e[:-1])[:, None] ** 2 + (np.arange(nsub) + 0.5)[None] / nsub
             * (np.sin(e[1:]) ** 2 - np.sin(e[:-1]) ** 2)[:, None])
        cos_sub = np.sqrt(np.clip(1.0 - u, 0.0, 1.0))
        RF = _fresnel(cos_sub, n, n0, "R").mean(axis=1)                                     # (N, 4, 4)
        vB = _TableView(self.back, wl, self.mueller, "back-face table", mv) if self.back is not None else None
        th_sub = np.degrees(np.arccos(cos_sub))                                             # cell average too
        if vB is not None:
            RF = vB.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1)            # its delta part
        # the rough face's own delta part acting on diffuse light from inside: specular reflection
        # keeps the cell (and the propagation azimuth), so it is diagonal in every azimuthal mode
        # (times 1 - 1e-9: between two lossless specular faces a totally reflected cell would make the
        # loop singular; it is fed nothing, and 1e-9 per round trip stands for the plate's finite size)
        SR = vin.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1) * (1 - 1e-9)  # (N, 4, 4)
        # kernel K[t, j, a] from the inside table's R cells, times the receiving cell's projected solid angle
        Kh = np.moveaxis(vin.diffuse_modes("R", tc, tc, self.delta), 0, 1)                 # (T, J, M[,4,4])
        Kh *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
        KBh = GBT = None
        if vB is not None:
            KBh = np.moveaxis(vB.diffuse_modes("R", tc, tc, self.delta), 0, 1)
            KBh *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
            GBh = vB.diffuse_modes("T", tc, tc, self.delta, detector_row=True)
            GBT = (np.moveaxis(GBh, 2, 0) if c == 1 else np.moveaxis(GBh, (2, 3), (0, 2))).reshape(
                GBh.shape[2], -1, GBh.shape[1])
        GhT, Wflat, Wspec = self._exit_maps(vin, vB, n, n0, c)
        sector_kernels = None
        if self.inside_sectors is not None and vB is None and m.rough_face == "front":
            sector_kernels = self._sector_kernels(wl, c, mv, Kh, GhT)
        t = dict(n=n, n0=n0, c=c, vin=vin, vB=vB, RF=RF, SR=SR, Kh=Kh, KBh=KBh, GBT=GBT, GhT=GhT,
                 Wflat=Wflat, Wspec=Wspec, sector_kernels=sector_kernels)
        self._tops[wl] = t
        return t

    def _operators(self, wl: float) -> dict:
        if wl in self._ops:
            return self._ops[wl]
        m = self.model
        t = self._table_ops(wl)
        c, RF, SR, Kh, KBh = t["c"], t["RF"], t["SR"], t["Kh"], t["KBh"]
        tc = self.theta_c
        N = tc.size
        cos_c = np.maximum(np.cos(np.radians(tc)), 1e-6)
        absorb = np.exp(-m.absorption_per_m * m.thickness_m / cos_c)                       # (N,)
        Mk = Kh.shape[2]
        # round trip diagonal D_j = A_j R_F,j A_j (4x4 or scalar R_F,00)
        if c == 1:
            Dj = absorb**2 * RF[:, 0, 0]
            Kmat = np.moveaxis(Kh, 2, 0) + np.diag(SR[:, 0, 0])[None]                      # (M, T, J)
            sysm = np.eye(N)[None] - Kmat * Dj[None, None, :]
        else:
            Dj = absorb[:, None, None] ** 2 * RF                                            # (N, 4, 4)
            KD = np.empty((Mk, N, 4, N, 4), np.result_type(Kh, Dj))                       # C order: the reshape
            # KD[m, t, a, j, c] = sum_b Kh[t, j, m, a, b] Dj[j, b, c]: a batched 4x4 product written in the
            # system's layout (np.matmul over (1 x 4) @ (4 x 4): 7x faster than the einsum on 90 x 90 x 37)
            np.matmul(np.transpose(Kh, (2, 0, 3, 1, 4))[..., None, :], Dj, out=KD[..., None, :])  # reshape: a view
            idx = np.arange(N)
            KD[:, idx, :, idx, :] += np.einsum("jab,jbc->jac", SR, Dj)[:, None]
            sysm = KD.reshape(Mk, N * 4, N * 4)
            sysm *= -1.0                                                                    # I - K D in place
            sysm[:, np.arange(N * 4), np.arange(N * 4)] += 1.0
            del KD
        Kb = Rtrip = KBm = None
        if t["vB"] is not None:
            # second face with its own table: round trip K A (K_B + R_B,delta) A as full matrices per m
            Kb = _blocks(Kh, c) + _block_diag(SR, c)[None]
            Aa = np.repeat(absorb, c)
            KBm = _blocks(KBh, c)
            Rtrip = (KBm + _block_diag(RF, c)[None]) * Aa[None, :, None] * Aa[None, None, :]
            sysm = np.eye(N * c)[None] - Kb @ Rtrip
        slab_ops = None
        if m.scatter_per_m > 0:   # volume scattering: the slab's operators replace the diagonal traversal
            Kb = _blocks(Kh, c) + _block_diag(SR, c)[None]
            R2 = (0.0 if KBm is None else KBm) + _block_diag(RF, c)[None]
            slab_ops = _slab_system(m, self.theta_edges, self.delta.size, Kb, R2, c)
            Rtrip, sysm = slab_ops["Rtrip"], slab_ops["sys"]
        ops = dict(wl=wl, n=t["n"], n0=t["n0"], vin=t["vin"], vB=t["vB"], absorb=absorb, RF=RF, sys=sysm, Dj=Dj,
                   GhT=t["GhT"], sectors=t["sector_kernels"] if slab_ops is None else None,
                   Wflat=t["Wflat"], Wspec=t["Wspec"], c=c, M=Mk, Kb=Kb, Rtrip=Rtrip, GBT=t["GBT"], slab=slab_ops)
        ops.update(self._outside_ops(wl, ops))
        self._ops[wl] = ops
        return ops

    def _outside_ops(self, wl: float, ops: dict) -> dict:
        """The outside table's part of a wavelength's operators: its view, and whether the direct
        reflection and the first transmitted pass are read from its own finer grid
        (plate.detector.direct_reading) while the loop works on the engine grid."""
        vout = _TableView(self.outside, wl, self.mueller, "outside table") if self.outside is not None else None
        out_on_grid = vout is None or vout.on_grid(self.theta_edges, self.delta.size)
        direct = (not out_on_grid and self.model.rough_face == "front" and ops["vB"] is None and ops["slab"] is None)
        return dict(vout=vout, out_on_grid=out_on_grid, direct=direct, solved={})   # `solve`'s results: anew

    def with_outside(self, model: PlateModel, outside: BsdfTable) -> "PlateSolver":
        """This solver for another outside table (and instrument) on the same inside, back and sector
        tables and plate: the loop's operators (kernels, round trip, exit maps) depend on those alone,
        so only the outside table's part is re-derived (a tilt or a beam traced into the outside
        table changes that table alone).  The numbers are those of a fresh solver."""
        new = copy.copy(self)
        new.model, new.outside, new._twins = model, outside, {}
        new._ops = {wl: {**ops, **new._outside_ops(wl, ops)} for wl, ops in self._ops.items()}
        return new

    def _exit_maps(self, vin: "_TableView", vB: "_TableView | None", n: float, n0: float,
                   c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(GhT, Wflat, Wspec): how diffuse internal light leaves through each face onto the outgoing grid.

        GhT: the rough face's inside T cells per azimuthal mode.  Wflat / Wspec: exit through the
        second face's Fresnel (or its table's delta part) and through the rough face's delta part: a
        conservative Snell remap (each outgoing cell cut into 64 equal projected-solid-angle slices,
        each slice's pre-image in one internal cell, exact transmission per slice, Mueller row 0).
        """
        tc, N, e = self.theta_c, self.theta_c.size, np.radians(self.theta_edges)
        GhT = self._exit_kernel(vin, c)
        ns = 64
        u = (np.sin(e[:-1])[:, None] ** 2 + (np.arange(ns) + 0.5)[None] / ns
             * (np.sin(e[1:]) ** 2 - np.sin(e[:-1]) ** 2)[:, None])                           # (O, ns)
        th_int = _snell_deg(np.degrees(np.arcsin(np.sqrt(u))), n0, n)
        if vB is None:
            tf = _fresnel(np.cos(np.radians(th_int)), n, n0, "T")[..., 0, :c] / ns           # (O, ns, c)
        else:
            tf = vB.specular_many("T", th_int).reshape(N, ns, 4, 4)[..., 0, :c] / ns
        # internal radiance linearly interpolated between cell centres, held constant across the
        # critical angle (trapped cells never feed the exit) and at the grid ends
        below = tc < np.degrees(np.arcsin(min(n0 / n, 1.0)))
        Wi = _lin_matrix(tc[below], th_int.ravel()).reshape(N, ns, -1)                       # (O, ns, Nb)

        def exit_remap(t_slices: np.ndarray) -> np.ndarray:
            """(O, N, c): internal radiance -> outgoing cells, through transmission t per slice."""
            W = np.zeros((N, N, c))
            W[:, below, :] = np.einsum("osj,osc->ojc", Wi, t_slices)
            return W
        Wspec = exit_remap(vin.specular_many("T", th_int).reshape(N, ns, 4, 4)[..., 0, :c] / ns)
        return GhT, exit_remap(tf), Wspec

    def _exit_kernel(self, vin: "_TableView", c: int) -> np.ndarray:
        """(M, J c, O): a table's inside T cells (diffuse light leaving through the rough face from inside)
        per azimuthal mode, detector row S0 of the Mueller matrix."""
        tc = self.theta_c
        Gh = vin.diffuse_modes("T", tc, tc, self.delta, detector_row=True)                 # (J, O, M[,4])
        return (np.moveaxis(Gh, 2, 0) if c == 1 else np.moveaxis(Gh, (2, 3), (0, 2))).reshape(Gh.shape[2], -1,
                                                                                              Gh.shape[1])

    def _sector_kernels(self, wl: float, c: int, moving: tuple[float, float] | None, Kh: np.ndarray,
                        GhT: np.ndarray) -> "_SectorKernels":
        """The inside sector tables' (`inside_sectors`) loop and exit kernels minus the 0-deg table's (Kh,
        GhT), in the engine's modes like the 0-deg table's (`moving`: as the 0-deg table's view,
        `_table_ops`).  Each loop difference is written straight into its slice of the stacked single
        precision array (`_SectorKernels.loop`): no (M, N c, N c) complex copy per sector is kept."""
        t = self.inside_sectors
        if isinstance(t, SectorsHeader):
            raise RuntimeError(f"the inside sector table was dropped before the kernels at {wl:g} nm were made")
        ps = np.asarray(t.phi_i_deg, float)
        M, nc = Kh.shape[2], Kh.shape[0] * c
        loop = np.empty((M, 2 * nc, ps.size * nc), SECTOR_LOOP_DTYPE)
        exits = []
        for ip, p in enumerate(ps):
            v = _TableView(_phi_slice(t, ip), wl, self.mueller, "inside sector table", moving)
            K = np.moveaxis(v.diffuse_modes("R", self.theta_c, self.theta_c, self.delta), 0, 1)
            K *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
            K -= Kh
            _blocks(K.real, c, out=loop[:, :nc, ip * nc:(ip + 1) * nc])
            _blocks(K.imag, c, out=loop[:, nc:, ip * nc:(ip + 1) * nc])
            exits.append((self._exit_kernel(v, c) - GhT).astype(SECTOR_EXIT_DTYPE))
        return _SectorKernels(ps, loop, tuple(exits))

    def _sector_cells(self, sk: "_SectorKernels") -> np.ndarray:
        """(K, A) 0/1: the propagation azimuths delta that meet the relief through sector k.  The inside
        table traced at incidence azimuth p stands for light arriving at propagation azimuth p + 180
        (methods.ray's frame), i.e. at delta = p for rows lit at phi_i = 0 (the engine's frame for an
        anisotropic relief); each cell takes the nearest p mod 180 (a half turn leaves a relief's
        statistics unchanged; without a sector at 0 deg the 0-deg inside table's cells are those of no
        sector), whose table averages the sector's incidence azimuths (`plate.faces.inside_sectors`;
        measured on the anisotropic relief of bench_forward_accuracy with tables at the sectors' centres:
        rms z 1.45 with 30-deg sectors, 1.12 with 15; blending the two nearest tables instead of taking
        the nearest: 1.37 / 1.15, but the measured map 1.70 -> 1.75 / 1.77)."""
        own = np.asarray(sk.azimuths_deg, float)
        first = 0 if own.size and own[0] == 0.0 else 1          # the 0-deg table among the sectors, or the base
        ps = own if first == 0 else np.concatenate([[0.0], own])
        d = np.abs(np.mod(self.delta[:, None] - ps[None, :] + 90.0, 180.0) - 90.0)       # (A, 1 + K)
        near = np.argmin(d, axis=1)
        return (near[None, :] == np.arange(first, ps.size)[:, None]).astype(float)

    def _sector_average(self, ops: dict) -> tuple[np.ndarray, np.ndarray]:
        """((K, A) sector cells, sum_k w_k dK_k): the sectors' cells (`_sector_cells`, the loop's and the
        exits') and the azimuth-weighted kernel difference of the sector loop's preconditioner
        (`_sector_loop`); the tables and the grid fix them, so they are computed once per wavelength and
        shared by the solvers whose bulk differs (`_table_ops`)."""
        t = self._tops[ops["wl"]]
        if "sector_average" not in t:
            P = self._sector_cells(ops["sectors"])
            t["sector_average"] = (P, ops["sectors"].weighted(P.mean(axis=1)))
        return t["sector_average"]

    def _sector_loop(self, ops: dict, S: np.ndarray, to_modes: Any, to_cells: Any) -> np.ndarray:
        """X (M, N c, q) in modes solving X = S + K D X with the rough face's loop kernel K taken by azimuth
        sector (an anisotropic relief, `inside_sectors`): light arriving at the relief from inside at
        propagation azimuth delta scatters by the table traced nearest delta (`_sector_cells`), so K is
        K_0 + sum_k dK_k P_k (P_k: the cells of sector k) and no longer circulant.  Every order of the
        loop meets the relief by its own azimuth: the second pass (the light transmitted by the relief and
        reflected by the flat face) and the trapped light.

        Solved by GMRES, preconditioned by the circulant loop of the sectors' azimuth-weighted kernel
        Kw = K_0 + sum_k w_k dK_k (w_k: sector k's share of the azimuth cells; exact when the light is
        uniform in azimuth): (I - (I - Kw D)^-1 sum_k dK_k (P_k - w_k) D) X = (I - Kw D)^-1 S, all
        incidences in one Krylov space (the operator is the same for each); the sum over the sectors is
        one single-precision product (`_SectorKernels.apply`)."""
        from scipy.sparse.linalg import LinearOperator, gmres
        c, Dj, sk = ops["c"], ops["Dj"], ops["sectors"]
        if "sector_loop" not in ops:
            P, avg = self._sector_average(ops)
            if c == 1:                                                                 # avg D, D diagonal
                avgD = avg * Dj[None, None, :]
            else:                                                                      # D block-diagonal
                M, nc = avg.shape[:2]
                avgD = (avg.reshape(M, nc, nc // 4, 1, 4) @ Dj[None, None]).reshape(avg.shape)
            ops["sector_loop"] = (_lu_factors(ops.pop("sys") - avgD),     # the factors replace the system
                                  P - P.mean(axis=1)[:, None])
        pre, Pw = ops["sector_loop"]
        shape = to_cells(S).shape                                                          # (q, N, A, c)

        def round_trip(X: np.ndarray) -> np.ndarray:       # D X: absorb, flat face's Fresnel R, absorb
            if c == 1:
                return X * Dj[None, :, None, None]
            return np.einsum("jab,qjkb->qjka", Dj, X)

        def extra(X: np.ndarray) -> np.ndarray:            # (I - Kw D)^-1 sum_k dK_k (P_k - w_k) D X, cells
            Y = round_trip(X)
            Z = sk.apply(np.stack([to_modes(Y * m[None, None, :, None]) for m in Pw]))
            return to_cells(_lu_apply(pre, Z))

        b = to_cells(_lu_apply(pre, S)).ravel()
        op = LinearOperator((b.size, b.size), matvec=lambda x: x - extra(x.reshape(shape)).ravel(), dtype=float)
        x, info = gmres(op, b, x0=b.copy(), rtol=1e-7, atol=0.0, restart=40, maxiter=20)
        if info != 0:
            raise RuntimeError(f"plate loop by azimuth sector: GMRES did not converge ({info} iterations)")
        return to_modes(x.reshape(shape))

    def _sector_exits(self, ops: dict, U: np.ndarray, A: int) -> np.ndarray:
        """(q, O, A): what the exit through the rough face changes when the light arriving there from inside
        (U, cells, every order) leaves by azimuth sector, each through its own inside table instead of the
        0-deg one turned (added to the rough face's diffuse exit; the exit is linear in the kernel)."""
        out = 0.0
        for dG, mask in zip(ops["sectors"].exits, self._sector_average(ops)[0]):
            if mask.any():
                out = out + _rough_exit(_exit_modes(U * mask[None, None, :, None]), dG, A)
        return out

    def solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float = 0.0) -> list[PlateResult]:
        """Plate BSDF for each incidence angle (degrees) at one wavelength.

        Of the instrument only the source's polarisation enters the solve (the incidences are given),
        and every part of the field is linear in the source's Stokes vector s (Mueller tables, Fresnel
        matrices, the loop's linear systems): the field of s is sum_k s_k F(e_k), F(e_k) the field of
        the k-th unit Stokes vector, solved once each.  (With depolarising tables the diffuse parts take
        the source's intensity alone while the flat faces' delta beams see its polarisation: not linear
        in s, so that field is solved, and kept, for s itself.)  The fields are kept with the
        wavelength's operators (`_SOLVED_KEPT` requests, `_SOLVED_BYTES` at most), which the solvers
        that differ only in the instrument share (`_reused_solver`): an evaluation that changes only
        the source's polarisation or how the rows are read (stray light; a cone or blur too where the
        tables' direct grid does not adapt to it) solves nothing.  An unpolarised source's field is
        F(e_0) itself, bit for bit; the sector loop's GMRES (relative tolerance 1e-7) solves each unit
        source to its tolerance.  Results are never changed by their readers (`dataclasses.replace`)."""
        twin = self._twin_wavelength(float(wavelength_nm))
        if twin != float(wavelength_nm):
            return [replace(r, wavelength_nm=float(wavelength_nm)) for r in self.solve(twin, theta_i_deg, phi_i_deg)]
        ops = self._operators(float(wavelength_nm))
        s = np.asarray(self.model.source_stokes, float)
        if not self.mueller or (s[0] == 1.0 and not s[1:].any()):
            return list(self._field(ops, wavelength_nm, theta_i_deg, phi_i_deg, s))
        parts = [(np.eye(4)[k], float(s[k])) for k in range(4) if s[k] != 0.0]
        fields = [self._field(ops, wavelength_nm, theta_i_deg, phi_i_deg, e) for e, _ in parts]
        return [_stokes_sum([f[q] for f in fields], [w for _, w in parts]) for q in range(len(fields[0]))]

    def _twin_wavelength(self, wl: float) -> float:
        """The wavelength solved in place of `wl`: the shortest of the tables' wavelengths whose every input
        is that of `wl` (the indices inside and outside, every table's row: a geometric-optics relief at a
        recording's wavelengths without dispersion, `plate.faces.same_indices`), else `wl` itself.  Its
        results are those of `wl` (the plate's bulk and instrument do not depend on the wavelength), so a
        recording at three wavelengths without dispersion is solved once."""
        tables = [t for t in (self.inside, self.outside, self.back, self.inside_sectors) if t is not None]
        m = self.model
        n = (complex(m.index.n(wl)), complex(m.outside_index.n(wl)))
        key = (wl, n) + tuple(id(t) for t in tables)          # the tables are the solver's (held while it lives)
        if key not in self._twins:
            same = (float(w) for w in np.sort(np.asarray(self.inside.wavelength_nm, float)) if w < wl
                    and (complex(m.index.n(w)), complex(m.outside_index.n(w))) == n
                    and all(t.same_at(float(w), wl) for t in tables))
            self._twins[key] = next(same, wl)                   # the shortest twin (compared lazily), else wl
        return self._twins[key]

    def _field(self, ops: dict, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float,
               stokes: np.ndarray) -> list[PlateResult]:
        """The plate's results for the source Stokes vector `stokes` (kept with the operators: `solve`)."""
        key = (np.asarray(theta_i_deg, float).tobytes(), float(phi_i_deg), np.asarray(stokes, float).tobytes())
        kept = ops["solved"]
        if key not in kept:
            with blas_single_thread():
                res = self._solve(wavelength_nm, theta_i_deg, phi_i_deg, stokes)
            size = sum(_result_bytes(r) for r in res)
            if size > _SOLVED_BYTES:
                return res
            kept[key] = (res, size)
            while len(kept) > _SOLVED_KEPT or sum(z for _, z in kept.values()) > _SOLVED_BYTES:
                kept.pop(next(iter(kept)))
        return kept[key][0]

    def _solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float,
               stokes: np.ndarray) -> list[PlateResult]:
        ops = self._operators(float(wavelength_nm))
        thetas = np.atleast_1d(np.asarray(theta_i_deg, float))
        src = _Sources.empty(thetas.size, self.theta_c.size, self.delta.size, ops["c"])
        for q, ti in enumerate(thetas):
            self._incidence(ops, src, q, abs(float(ti)), stokes)
        out_rough, out_flat = self._diffuse_exits(ops, src, thetas)
        front = self.model.rough_face == "front"
        first_T = self._flat_exit(ops, src.S_first) if ops["direct"] else None
        results = []
        for q, ti in enumerate(thetas):
            gR = src.direct_R[q] + (out_rough[q] if front else out_flat[q])
            gT = out_flat[q] if front else out_rough[q]
            r = PlateResult(float(wavelength_nm), float(ti), float(phi_i_deg), self.theta_c,
                            self.theta_edges, self.delta, gR, gT, src.deltas[q])
            if src.direct[q] is not None:   # the loop on the engine grid, the direct parts on their own grid
                r = replace(r, direct=src.direct[q], loop_R=out_rough[q], loop_T=out_flat[q] - first_T[q])
            results.append(r)
        return results

    def _flat_exit(self, ops: dict, S: np.ndarray) -> np.ndarray:
        """(q, O, A) BSDF through the flat second face of power per cell S (q, N, A, c) arriving there
        after one traversal (absorption), by the same Snell remap as the loop's exit (`_exit_maps`)."""
        c, n, n0, psa = ops["c"], ops["n"], ops["n0"], self.psa
        nI, N, A = S.shape[0], self.theta_c.size, self.delta.size
        L = np.moveaxis(S * ops["absorb"][None, :, None, None] / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)
        return (ops["Wflat"].reshape(N, N * c) @ L) * (n0 / n) ** 2

    def _direct_field(self, ops: dict, ti: float, s_inc: np.ndarray) -> "DirectField":
        """The outside table's cells at incidence ti as the detector reads them (plate.detector.DirectField):
        R, the direct reflection's S0; T, the Stokes vector of the first transmission inside the glass,
        leaving through the flat face with Fresnel T, (n0/n)^2 (radiance law) and Beer-Lambert absorption."""
        from relief_bsdf.plate.detector import DirectField
        vout, c, m = ops["vout"], ops["c"], self.model
        f_r, f_t = vout.at_incidence("R", ti), vout.at_incidence("T", ti)
        R = f_r if c == 1 else f_r[..., 0, :] @ s_inc
        T = f_t[..., None] if c == 1 else f_t @ s_inc
        n, n0 = ops["n"], ops["n0"]

        def t_exit(theta_int_deg: np.ndarray) -> np.ndarray:
            cos_t = np.cos(np.radians(theta_int_deg))
            tf = _fresnel(cos_t, n, n0, "T")[..., 0, :c]
            return tf * ((n0 / n) ** 2 * np.exp(-m.absorption_per_m * m.thickness_m / np.maximum(cos_t, 1e-6)))[:, None]
        t = vout.table
        return DirectField(np.asarray(t.theta_s_edges_deg, float),
                           np.asarray(t.phi_s_edges_deg, float) - (vout.phi0 + 180.0),
                           np.asarray(R, float), np.asarray(T, float), n0 / n, t_exit)

    def _incidence(self, ops: dict, src: "_Sources", q: int, ti: float, s_inc: np.ndarray) -> None:
        """Incidence q: first-face scattering of the source (Stokes vector s_inc), the delta-beam chain,
        and what the beams scatter."""
        m, c, vin, vout, vB = self.model, ops["c"], ops["vin"], ops["vout"], ops["vB"]
        n, n0, tc, psa, delta = ops["n"], ops["n0"], self.theta_c, self.psa, self.delta
        tt = float(_snell_deg(ti, n0, n))
        a_t = float(np.exp(-_beam_extinction(m, ops["slab"], self.theta_edges, tt) * m.thickness_m
                           / max(np.cos(np.radians(tt)), 1e-6)))
        if vB is None:
            RFt, TFt = _fresnel(np.cos(np.radians(tt)), n, n0, "R"), _fresnel(np.cos(np.radians(tt)), n, n0, "T")
        else:
            RFt, TFt = vB.specular("R", tt), vB.specular("T", tt)
        deltas = []
        if m.rough_face == "front":
            if not ops["out_on_grid"]:
                f_r = vout.cells("R", ti, self.theta_edges, delta)
                f_t = vout.cells("T", ti, self.theta_edges, delta)
                if ops["direct"]:
                    src.direct[q] = self._direct_field(ops, ti, s_inc)
                    # the first pass is read on the direct grid; in the loop the first transmission is
                    # only the source of the later passes: its azimuth cells enter as point sources at
                    # their centres, weighted by the centre values (no binning variance, module doc)
                    f_t = centre_values(f_t, clip=False)
            else:
                f_r = vout.diffuse("R", [ti], tc, delta)[0]
                f_t = vout.diffuse("T", [ti], tc, delta)[0]
            src.direct_R[q] = f_r if c == 1 else f_r[..., 0, :] @ s_inc
            src.S[q] = (f_t * psa[:, None])[..., None] if c == 1 else (f_t @ s_inc) * psa[:, None, None]
            src.S_first[q] = src.S[q]
            y0, z0 = vout.specular("T", ti) @ s_inc, np.zeros(4)
            deltas.append(("R", ti, 0.0, float((vout.specular("R", ti) @ s_inc)[0])))
        else:
            cos_i = np.cos(np.radians(ti))
            deltas.append(("R", ti, 0.0, float((_fresnel(cos_i, n0, n, "R") @ s_inc)[0])))
            y0, z0 = np.zeros(4), a_t * (_fresnel(cos_i, n0, n, "T") @ s_inc)
        # delta chain: z arrives at the rough face from inside, y leaves it into the plate
        sR, sT = vin.specular("R", tt), vin.specular("T", tt)
        loop = a_t * a_t * RFt
        z = np.linalg.solve(np.eye(4) - loop @ sR, z0 + loop @ y0)
        y = y0 + sR @ z
        front = m.rough_face == "front"
        deltas.append(("R" if front else "T", ti, 0.0, float((sT @ z)[0])))
        deltas.append(("T" if front else "R", ti, 0.0, float((TFt @ (a_t * y))[0])))
        src.deltas.append(deltas)
        src.beams[q] = y, (z / a_t if a_t > 1e-300 else 0.0 * z)
        self._beam_scattering(ops, src, q, tt, a_t * y, z)

    def _beam_scattering(self, ops: dict, src: "_Sources", q: int, tt: float, yb: np.ndarray, z: np.ndarray) -> None:
        """Diffuse light the delta beams make at the faces: yb at a back-face table, z at the rough face."""
        c, vin, vB, tc, psa, delta = ops["c"], ops["vin"], ops["vB"], self.theta_c, self.psa, self.delta
        if vB is not None:
            up_absorb = ops["absorb"] if ops["slab"] is None else 1.0     # a slab's operators carry the traversal
            fbr = vB.diffuse("R", [tt], tc, delta)[0]
            fbt = vB.diffuse("T", [tt], tc, delta)[0]
            if c == 1:
                src.U_extra[q, :, :, 0] = fbr * (psa * up_absorb)[:, None] * yb[0]
                src.direct_flat[q] = fbt * yb[0]
            else:
                src.U_extra[q] = (fbr @ yb) * (psa * up_absorb)[:, None, None]
                src.direct_flat[q] = fbt[..., 0, :] @ yb
        fr = vin.diffuse("R", [tt], tc, delta)[0]
        ft = vin.diffuse("T", [tt], tc, delta)[0]
        if c == 1:
            src.S[q, :, :, 0] += fr * psa[:, None] * z[0]
            src.direct_rough[q] += ft * z[0]
        else:
            src.S[q] += (fr @ z) * psa[:, None, None]
            src.direct_rough[q] += ft[..., 0, :] @ z

    def _diffuse_loop(self, ops: dict, src: "_Sources", thetas: np.ndarray) -> dict:
        """Solve X = S + Kb Rc X per azimuthal mode; return the light at both faces (modes and cells)."""
        c, Mk, vB, slab = ops["c"], ops["M"], ops["vB"], ops["slab"]
        nI, N, A = thetas.size, self.theta_c.size, self.delta.size
        to_modes = lambda arr: np.moveaxis(np.moveaxis(np.fft.rfft(arr, axis=2), 2, 1).reshape(nI, Mk, N * c), 0, 2)  # noqa: E731
        to_cells = lambda YM: np.fft.irfft(np.moveaxis(np.moveaxis(YM, 2, 0).reshape(nI, Mk, N, c), 1, 2), n=A, axis=2)  # noqa: E731
        rhs = to_modes(src.S)                                                # (M, N c, nI)
        Uxh = Dxh = None
        if vB is not None or slab is not None:
            Uxh = to_modes(src.U_extra)
            if slab is not None:   # with the slab: U_extra leaves the back face upward; beams shed light
                Uxh, Dxh = _slab_sources(slab, Uxh, src.beams, self.theta_edges, thetas, ops["n0"], ops["n"], c)
            rhs = rhs + ops["Kb"] @ Uxh
        if ops["sectors"] is not None:   # an anisotropic relief: the loop meets the relief by azimuth sector
            XhM = self._sector_loop(ops, rhs, to_modes, to_cells)
        else:
            XhM = _loop_solve(ops, rhs)                                      # (M, N c, nI)
        absorb = ops["absorb"]
        out = {"XhM": XhM, "Uxh": Uxh}
        if slab is not None:       # light arriving at the second face: B X + what the beams shed there
            out["DbM"] = slab["B"] @ XhM + Dxh
            out["at_flat"] = to_cells(out["DbM"])
        else:
            out["at_flat"] = to_cells(XhM) * absorb[None, :, None, None]
        if vB is None and slab is None:    # back up to the rough face through the flat face's Fresnel R
            U = _reflect_up(ops, out["at_flat"])
            out["Um"] = _exit_modes(U)                                                          # (M, q, J c)
            out["U"] = U
        else:
            out["Um"] = np.moveaxis(ops["Rtrip"] @ XhM + Uxh, 2, 1)                         # (M, q, J c)
            out["U"] = None
        return out

    def _diffuse_exits(self, ops: dict, src: "_Sources", thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(out_rough, out_flat): the plate's diffuse BSDF leaving through each face, (q, O, A)."""
        c, Mk, n, n0 = ops["c"], ops["M"], ops["n"], ops["n0"]
        nI, N, A, psa = thetas.size, self.theta_c.size, self.delta.size, self.psa
        d = self._diffuse_loop(ops, src, thetas)
        Um = d["Um"]
        # rough-face exit: circular convolution over azimuth with the inside T kernel
        out_rough = _rough_exit(Um, ops["GhT"], A) + src.direct_rough
        if ops["sectors"] is not None:   # an anisotropic relief: every order leaves by azimuth sector
            out_rough = out_rough + self._sector_exits(ops, d["U"], A)
        if np.any(ops["Wspec"]):   # specular exit of the diffuse light arriving at the rough face from inside
            U = d["U"] if d["U"] is not None else np.fft.irfft(np.moveaxis(Um.reshape(Mk, nI, N, c), 0, 2), n=A, axis=2)
            LU = np.moveaxis(U / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)
            out_rough = out_rough + (ops["Wspec"].reshape(N, N * c) @ LU) * (n0 / n) ** 2
        # flat-face exit: internal radiance (Stokes) interpolated at the Snell pre-image of each outgoing
        # direction, times the exact Fresnel transmission there, divided by (n/n0)^2 (radiance law)
        L = np.moveaxis(d["at_flat"] / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)  # (q, N c, A)
        out_flat = (ops["Wflat"].reshape(N, N * c) @ L) * (n0 / n) ** 2                     # (q, O, A)
        if ops["vB"] is not None:   # diffuse exit through the back-face table, from the light arriving there
            AX = d["DbM"] if ops["slab"] is not None else d["XhM"] * np.repeat(ops["absorb"], c)[None, :, None]
            out_flat = (out_flat + np.fft.irfft(np.moveaxis(np.moveaxis(AX, 2, 1) @ ops["GBT"], 0, 2), n=A, axis=2)
                        + src.direct_flat)
        return out_rough, out_flat


SECTOR_LOOP_DTYPE = np.float32      # the sector loop's kernel differences (`_SectorKernels`: precision argument)
SECTOR_EXIT_DTYPE = np.complex64    # the sector exits' kernel differences


@dataclass(frozen=True)
class _SectorKernels:
    """The inside sector tables' kernels minus the 0-deg table's (`PlateSolver._sector_kernels`).

    `loop` (M, 2 N c, K N c) SECTOR_LOOP_DTYPE: per azimuthal mode the K loop-kernel differences dK_k side by
    side, their real parts over their imaginary parts, so that sum_k dK_k Y_k is ONE real product per mode
    (`apply`): the loop's GMRES applies it at every iteration, and at a few right-hand sides a complex
    product per sector is bound by reading the kernels (twelve sectors of (M, N c, N c) are 0.4 GB
    per wavelength).  `exits` (M, N c, O) SECTOR_EXIT_DTYPE: each sector's exit kernel minus the 0-deg one.

    Precision (why single precision is enough).  The differences are made in double precision and then
    rounded once to single (relative rounding 2^-24 = 6e-8 of each element); every product with them is
    taken in double precision (`apply`'s sums in single, then promoted; `_rough_exit` promotes the exits).
    They carry only the part of the field that differs from sector to sector, a fraction of the light
    inside the plate, so the rows change by at most ~1e-7 of their value (GMRES solves to 1e-7 relative
    anyway), while the tables they come from carry the Monte-Carlo noise of their rays, 1e-3 to 1e-1 per
    cell, and a recording's noise is ~1e-2: the rounding is five orders of magnitude below what the rows
    can tell.  Measured on an anisotropic relief traced by rays (tests/backend/plate/test_sector_precision.py):
    the simulated rows move by under 1e-6 of their largest value against double-precision kernels, asserted
    < 1e-4.  The sums that are not differences (the circulant loop's system and its LU factors, the 0-deg
    kernels) stay double: they carry the whole field."""

    azimuths_deg: np.ndarray
    loop: np.ndarray
    exits: tuple

    def weighted(self, w: np.ndarray) -> np.ndarray:
        """sum_k w_k dK_k, (M, N c, N c) complex in the kernels' precision (summed in it; promoted where used)."""
        M, two_nc, knc = self.loop.shape
        nc = two_nc // 2
        r = (self.loop.reshape(M * two_nc, knc // nc, nc).transpose(0, 2, 1) @ np.asarray(w, self.loop.dtype))
        r = r.reshape(M, two_nc, nc)
        out = np.empty((M, nc, nc), np.result_type(self.loop.dtype, np.complex64))
        out.real, out.imag = r[:, :nc], r[:, nc:]
        return out

    def apply(self, Y: np.ndarray) -> np.ndarray:
        """sum_k dK_k Y_k for Y (K, M, N c, q) complex: (M, N c, q) complex.  With dK = R + i I and
        Y = a + i b: [R; I] [a b] = [[R a, R b], [I a, I b]], so Re = R a - I b and Im = R b + I a."""
        K, M, nc, q = Y.shape
        ab = np.empty((M, K * nc, 2 * q), self.loop.dtype)
        Yt = np.moveaxis(Y, 0, 1).reshape(M, K * nc, q)
        ab[..., :q] = Yt.real
        ab[..., q:] = Yt.imag
        P = self.loop @ ab                                                                  # (M, 2 N c, 2 q)
        return (P[:, :nc, :q] - P[:, nc:, q:]).astype(float) + 1j * (P[:, :nc, q:] + P[:, nc:, :q])


@dataclass(frozen=True)
class SectorsHeader:
    """What a solver keeps of its inside sector table once the table's kernels exist for every wavelength it
    solves (`drop_sector_table`): the sector centres, the table's metadata and which of its wavelengths
    carry the same numbers (`same_at`, for `PlateSolver._twin_wavelength`); no cells."""

    phi_i_deg: np.ndarray
    wavelength_nm: np.ndarray
    metadata: dict
    same: frozenset            # (a_nm, b_nm) pairs whose rows are equal

    @staticmethod
    def of(table: BsdfTable) -> "SectorsHeader":
        w = [float(x) for x in np.asarray(table.wavelength_nm, float)]
        return SectorsHeader(np.asarray(table.phi_i_deg, float).copy(), np.asarray(w), dict(table.metadata),
                             frozenset((a, b) for a in w for b in w if table.same_at(a, b)))

    def same_at(self, a_nm: float, b_nm: float) -> bool:
        return (float(a_nm), float(b_nm)) in self.same


@dataclass
class _Sources:
    """Per-incidence source terms of the round-trip problem (power per cell / BSDF on the grid)."""

    S: np.ndarray               # (q, N, A, c) leaving the rough face into the plate
    direct_rough: np.ndarray    # (q, N, A) BSDF through the rough face without the loop
    direct_R: np.ndarray        # (q, N, A) outside table R (front relief)
    direct_flat: np.ndarray     # (q, N, A) diffuse exit of the delta beam through a back-face table
    U_extra: np.ndarray         # (q, N, A, c) delta beam scattered diffusely by a back-face table
    beams: np.ndarray           # (q, 2, 4) down beam y at the first face, up beam at the second face
    S_first: np.ndarray         # (q, N, A, c) the part of S that is the outside table's first transmission
    deltas: list = field(default_factory=list)
    direct: list = field(default_factory=list)   # per incidence: DirectField or None

    @staticmethod
    def empty(nI: int, N: int, A: int, c: int) -> "_Sources":
        z = np.zeros
        return _Sources(z((nI, N, A, c)), z((nI, N, A)), z((nI, N, A)), z((nI, N, A)), z((nI, N, A, c)),
                        z((nI, 2, 4)), z((nI, N, A, c)), direct=[None] * nI)


# ---------------------------------------------------------------- rows

def row_arrays(rows):
    """(wavelength_nm, theta_i_deg, phi_i_deg, side, theta_s_deg, phi_s_deg) of any row set as arrays."""
    return (np.asarray(rows.wavelength_nm, float), np.asarray(rows.theta_i_deg, float),
            np.asarray(rows.phi_i_deg, float), np.asarray(rows.side).astype(str),
            np.asarray(rows.theta_s_deg, float), np.asarray(rows.phi_s_deg, float))


def simulate_rows(model: PlateModel, inside: BsdfTable, outside: BsdfTable | None, rows: Any,
                  solver: PlateSolver | None = None, where: str = "recording",
                  back: BsdfTable | None = None, front: tuple[BsdfTable, BsdfTable] | None = None) -> np.ndarray:
    """Plate BSDF (1/sr) on every row of a recording (same order), detector cone included.

    `back`: optional table (light from inside) of the second face when the relief is on the front;
    `front`: optional (outside, inside) tables of the front face when the relief is on the back.
    """
    check_rows(model, rows, where)
    solver = solver or PlateSolver(model, inside, outside, back, front)
    wl, ti, pi, side, ts, ps = row_arrays(rows)
    beam = model.beam_divergence_deg
    if beam <= 0:
        out = _readings(solver, model, wl, ti, pi, side, ts, ps, model, ("diffuse", "deltas"))
        return out + model.background_per_sr
    wide = replace(model, blur_deg=float(np.hypot(model.blur_deg, beam)))
    if model.beam_in_tables:          # the outside table holds the beam: read at the nominal incidence
        diffuse = _readings(solver, model, wl, ti, pi, side, ts, ps, model, ("diffuse",))
        return diffuse + _readings(solver, model, wl, ti, pi, side, ts, ps, wide, ("deltas",)) + model.background_per_sr
    _, weights = beam_offsets(beam)
    q = weights.size
    tq, pq = beam_incidences(ti, pi, beam)
    rep = lambda a: np.repeat(a, q)       # noqa: E731  (row k's q incidences are entries k q .. k q + q - 1)
    diffuse = _readings(solver, model, rep(wl), tq.ravel(), pq.ravel(), rep(side), rep(ts), rep(ps), model,
                        ("diffuse",), nominal=(rep(ti), rep(pi))).reshape(-1, q) @ weights
    deltas = _readings(solver, model, wl, ti, pi, side, ts, ps, wide, ("deltas",))
    return diffuse + deltas + model.background_per_sr


def beam_incidences(theta_i_deg: Any, phi_i_deg: Any, beam_divergence_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) in degrees, shape (rows, Q): the incidences of the beam divergence's quadrature
    (`plate.detector.beam_offsets`) around each row's nominal incidence, instrument frame."""
    th, ph = offset_directions(np.asarray(theta_i_deg, float), np.asarray(phi_i_deg, float),
                               beam_offsets(beam_divergence_deg)[0])
    return np.round(th, 9), np.round(np.mod(ph, 360.0), 9)


def beam_split(theta_deg: Any, phi_deg: Any, nominal_theta_deg: Any, nominal_phi_deg: Any
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How the engine solves a beam-divergence incidence: (theta, phi) of the incidence it solves and
    the shift (2, ...) of the scattered field's tangential directions, all in the sample's frame.

    A divergent ray's source direction has tangential part s = sin(theta) (cos phi, sin phi).  Split
    along the nominal plane of incidence (unit u) and across it (v): s = a u + b v.  The engine solves
    the in-plane part exactly, at the incidence theta'' = asin|a| in that plane (phi'' = the nominal
    azimuth, + 180 deg when a < 0: a relief's statistics are unchanged by a half turn), and moves the
    cross-plane part b as a translation of the scattered field in direction cosines: for a surface
    whose statistics do not vary along it, scattering depends to first order on the change of
    tangential wave vector only (Kirchhoff's phase term is exp(i k (s_out - s_in) . r); Beckmann &
    Spizzichino 1963, ch. 3), and the BSDF, power per projected solid angle d(s_x) d(s_y), is carried
    along: f_b(s_out) = f''(s_out + b v).  The specular direction lands exactly where it belongs; the
    lobe's shape is that of theta'' instead of theta (second order in b).

    Why not rotate: an isotropic table turned about the normal by phi' - phi would be exact for an
    isotropic relief, but it turns the lobe's shape with it; at normal incidence the divergent rays
    come from every azimuth, and an anisotropic relief's lobe (wide along its steep axis) was smeared
    round the normal: on a concealed case (measured map, slopes 2.3x apart, 3.25-deg divergence) the
    rotation missed the independent photon Monte Carlo through the relief by chi^2 3590 on the 70 rows
    at theta_i = 0.  The shift keeps the lobe oriented with the relief.
    """
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    pn = np.radians(np.asarray(nominal_phi_deg, float) + 0 * t)
    s = np.sin(t)
    a = s * np.cos(p - pn)
    b = s * np.sin(p - pn)
    theta2 = np.round(np.degrees(np.arcsin(np.clip(np.abs(a), 0.0, 1.0))), 9)
    phi2 = np.round(np.mod(np.degrees(pn) + np.where(a < 0, 180.0, 0.0), 360.0), 9)
    shift = np.stack([-b * np.sin(pn), b * np.cos(pn)])
    return theta2, phi2, shift


def _shifted(theta_deg: np.ndarray, phi_deg: np.ndarray, shift: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directions whose tangential part is that of (theta, phi) plus `shift` (2, N), and whether each
    exists (|s| < 1; beyond, the shifted field is evanescent and reads 0)."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    sx = np.sin(t) * np.cos(p) + shift[0]
    sy = np.sin(t) * np.sin(p) + shift[1]
    r = np.hypot(sx, sy)
    ok = r < 1.0
    th = np.degrees(np.arcsin(np.clip(r, 0.0, 1.0)))
    ph = np.mod(np.degrees(np.arctan2(sy, sx)), 360.0)
    return np.round(th, 9), np.round(ph, 9), ok


def _readings(solver: PlateSolver, model: PlateModel, wl, ti, pi, side, ts, ps, det: Any,
              parts: tuple, nominal: tuple | None = None) -> np.ndarray:
    """Detector readings (1/sr, stray light not added) of rows given in the instrument frame: the
    sample tilt applied (rows seen in the tilted sample's frame, f = f' cos theta_s' / cos theta_s),
    the plate solved once per incidence; `det` the detector (cone, aperture blur), `parts` which
    parts of the field are read (`plate.detector.grid_reading`).  `nominal`: (theta, phi) of each
    row's nominal incidence when (ti, pi) are the beam divergence's incidences around it: they are
    then solved in the nominal plane with the field shifted across it (`beam_split`)."""
    factor = 1.0
    ok = np.ones(wl.size, bool)
    split = nominal is not None and model.relief_anisotropic
    if model.tilt_deg:
        ti, pi = to_sample_frame(ti, pi, np.full(ti.shape, "R"), model.tilt_deg)
        if split:
            nominal = to_sample_frame(nominal[0], nominal[1], np.full(ti.shape, "R"), model.tilt_deg)
        ts0 = ts
        ts, ps = to_sample_frame(ts, ps, side, model.tilt_deg)
        factor = np.cos(np.radians(ts)) / np.cos(np.radians(ts0))
        ti, pi, ts, ps = (np.round(a, 9) for a in (ti, pi, ts, ps))
    if split:
        ti, pi, shift = beam_split(ti, pi, nominal[0], nominal[1])
        ts, ps, ok = _shifted(ts, ps, shift)
    out = np.zeros(wl.size)
    half = getattr(solver, "half_turn", None)
    far = far_side(ti, pi) if half is not None else np.zeros(wl.size, bool)
    for w in np.unique(wl):
        for on_far, s in ((False, solver), (True, half)):
            mw = (wl == w) & (far == on_far)
            if not mw.any():
                continue
            keys = np.unique(np.stack([ti[mw], pi[mw]], 1), axis=0)
            thetas = np.unique(keys[:, 0])
            res = {float(t): r for t, r in zip(thetas, s.solve(w, thetas))}
            for t, p in keys:
                sel = mw & (ti == t) & (pi == p)
                r = replace(res[float(t)], phi_i_deg=float(p))
                out[sel] = grid_reading(r, side[sel], ts[sel], ps[sel], det, parts)
    return np.where(ok, out, 0.0) * factor


def _stokes_sum(results: list, weights: list) -> PlateResult:
    """sum_k w_k results_k of one incidence's PlateResults for unit sources (`PlateSolver.solve`): every
    field linear in the source, the delta beams' powers too (same directions in each)."""
    first = results[0]

    def add(get):
        parts = [get(r) for r in results]
        return None if parts[0] is None else sum(w * p for w, p in zip(weights, parts))
    deltas = [(sd, t, d, float(sum(w * r.deltas[i][3] for w, r in zip(weights, results))))
              for i, (sd, t, d, _) in enumerate(first.deltas)]
    direct = first.direct
    if direct is not None:
        direct = replace(direct, R=add(lambda r: r.direct.R), T=add(lambda r: r.direct.T))
    return replace(first, grid_R=add(lambda r: r.grid_R), grid_T=add(lambda r: r.grid_T), deltas=deltas,
                   direct=direct, loop_R=add(lambda r: r.loop_R), loop_T=add(lambda r: r.loop_T))


def _result_bytes(r: PlateResult) -> int:
    """Bytes of a PlateResult's fields (the kept fields' budget, `_SOLVED_BYTES`)."""
    arrays = [r.grid_R, r.grid_T, r.loop_R, r.loop_T]
    if r.direct is not None:
        arrays += [r.direct.R, r.direct.T, *r.direct._slopes["R"], *r.direct._slopes["T"]]
    return int(sum(a.nbytes for a in arrays if isinstance(a, np.ndarray)))


def _loop_solve(ops: dict, rhs: np.ndarray) -> np.ndarray:
    """X = (I - K D)^-1 rhs per azimuthal mode, (M, N c, nI).  The LU factors of the round-trip
    system are kept in `ops`: the operators are shared by every solve on the same tables and plate
    (`_reused_solver`: a source polarisation, stray light, cone, blur or tilt changes only the
    sources), so an evaluation that changes only those solves with the factors instead of
    factoring the (M, N c, N c) system again."""
    if "sys_lu" not in ops:
        ops["sys_lu"] = _lu_factors(ops.pop("sys"))          # the factors replace the system (memory)
    return _lu_apply(ops["sys_lu"], rhs)


def _lu_factors(mats: np.ndarray) -> list:
    """LU factors (LAPACK getrf) of each matrix of a stack (M, n, n)."""
    from scipy.linalg import lu_factor
    return [lu_factor(a, check_finite=False) for a in mats]


def _lu_apply(factors: list, rhs: np.ndarray) -> np.ndarray:
    """A_m^-1 rhs_m for each matrix m of the stack whose `_lu_factors` are given (getrs), (M, n, k)."""
    from scipy.linalg import lu_solve
    return np.stack([lu_solve(f, b, check_finite=False) for f, b in zip(factors, rhs)])


def to_sample_frame(theta_deg: Any, phi_deg: Any, side: Any, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of instrument-frame directions (R: above, T: below) seen in the tilted sample's frame."""
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    sgn = np.where(np.asarray(side) == "T", -1.0, 1.0)
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), sgn * np.cos(t)], -1)
    w2 = w @ rot_y(tilt_deg)            # R^T w for each row
    th = np.degrees(np.arccos(np.clip(np.abs(w2[..., 2]), 0.0, 1.0)))
    ph = np.mod(np.degrees(np.arctan2(w2[..., 1], w2[..., 0])), 360.0)
    return th, ph


# ---------------------------------------------------------------- the Experiment on this engine

def model_of(experiment: Any, grid: Any, rough_face: str = "front", beam_in_tables: bool = False) -> PlateModel:
    """The engine's flat configuration of an Experiment (plate, bulk, instrument) on `grid`;
    `beam_in_tables`: the front's outside table holds the beam divergence (`front_traces_beam`)."""
    p, ins, b = experiment.plate, experiment.instrument, experiment.plate.bulk
    return PlateModel(thickness_m=p.thickness_m, index=p.index, rough_face=rough_face,
                      absorption_per_m=b.absorption_per_m, detector_half_angle_deg=ins.detector_half_angle_deg,
                      polarization=float(ins.polarization_q), outside_index=p.outside_index,
                      background_per_sr=ins.background_per_sr, blur_deg=ins.blur_deg, tilt_deg=ins.tilt_deg,
                      azimuth_cells=grid.azimuth_cells, cone_points=ins.cone_points,
                      scatter_per_m=b.scatter_per_m, hg_g=b.hg_g, beam_divergence_deg=ins.beam_divergence_deg,
                      relief_anisotropic=relief_anisotropic(experiment), beam_in_tables=bool(beam_in_tables),
                      inside_interpolation=grid.inside_interpolation, stokes_loop=grid.stokes_loop)


def relief_anisotropic(experiment: Any) -> bool:
    """Whether a face's relief is anisotropic beyond what isotropic tables stand for
    (`plate.faces.anisotropic_face`, the one test of it)."""
    from relief_bsdf.plate.faces import anisotropic_face
    return any(anisotropic_face(f) for f in (experiment.plate.front, experiment.plate.back))


def sample_incidences(experiment: Any, rows: Any, beam_traced: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wavelengths, theta, phi) of every outside incidence the engine solves for these rows, in the
    sample's frame: the rows' own, or under a sample tilt those the tilted sample sees; with a beam
    divergence the quadrature's incidences too, unless the outside table traces the beam itself
    (`beam_traced`, `front_traces_beam`); theta and phi one entry per incidence (not unique)."""
    wl = np.unique(np.asarray(rows.wavelength_nm, float))
    ti = np.abs(np.asarray(rows.theta_i_deg, float))
    pi = np.asarray(rows.phi_i_deg, float) + 0 * ti
    beam = 0.0 if beam_traced else experiment.instrument.beam_divergence_deg
    tilt = experiment.instrument.tilt_deg
    tq = pq = None
    if beam > 0:                      # the nominal incidences (delta parts) and the quadrature's
        tq, pq = (a.ravel() for a in beam_incidences(ti, pi, beam))
    q = 0 if tq is None else tq.size // max(ti.size, 1)
    if tilt:
        if tq is not None:
            tq, pq = to_sample_frame(tq, pq, np.full(tq.shape, "R"), tilt)
        ti, pi = to_sample_frame(ti, pi, np.full(ti.shape, "R"), tilt)
        ti, pi = np.round(ti, 9), np.round(pi, 9)
    if tq is not None:
        if relief_anisotropic(experiment):          # solved in the nominal plane (beam_split)
            tq, pq = beam_split(tq, pq, np.repeat(ti, q), np.repeat(pi, q))[:2]
        ti = np.concatenate([ti, np.round(tq, 9)])
        pi = np.concatenate([pi, np.round(pq, 9)])
    return wl, ti, pi


def table_incidences(experiment: Any, rows: Any, beam_traced: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(wavelengths, outside incidences) the faces' tables need for these rows (`sample_incidences`,
    every azimuth: the phi_i = 0 table serves any row where no half-turned table is made)."""
    wl, ti, _ = sample_incidences(experiment, rows, beam_traced)
    return wl, np.unique(ti)


def far_side(theta_deg: Any, phi_deg: Any) -> np.ndarray:
    """Whether each incidence (sample frame) is lit from the far half of azimuths, 90 < phi < 270 deg,
    where the engine reads the half-turned relief's outside table (`PlateSolver.half_turn`); normal
    incidence has no azimuth and is read from the table at 0."""
    t = np.asarray(theta_deg, float)
    return (t > 1e-9) & (np.cos(np.radians(np.asarray(phi_deg, float) + 0 * t)) < -1e-9)


def solver_of(experiment: Any, rows: Any, grid: Any, progress: Any = None, keep: bool = True) -> PlateSolver:
    """PlateSolver of an Experiment: the faces' tables placed on the engine's two-face system.

    Front non-flat: its (outside, inside) tables, the back face's inside table if it is not flat.
    Front flat, back non-flat: relief-on-back system (the back face's inside table).  Both flat:
    the flat face's Fresnel tables on the front.  A flat back face uses the engine's exact
    cell-averaged Fresnel (no table).  `keep` False: a new solver is not kept for reuse
    (`_reused_solver`; one-off tables such as the model sigma's perturbed draws).

    Before any table is derived, a held solver made for the same tables is looked up by what determines
    those tables (`request_key`: the faces' content, material, grid, wavelengths, incidences): a hit
    derives, resamples and even holds no table (`held_for_request`; its sector table may be gone,
    `drop_sector_table`)."""
    p = experiment.plate
    mat = p.material
    traced = front_traces_beam(experiment, rows, grid)
    memory = current_memory()
    request = request_key(experiment, rows, grid, traced) if keep else None
    front, back = p.front, p.back
    relief_on_back = front.is_flat and not back.is_flat
    model = model_of(experiment, grid, "back" if relief_on_back else "front", traced)
    if request is not None:
        held = held_for_request(memory, request, model)
        if held is not None:
            return held
    wl, ti = table_incidences(experiment, rows, traced)
    if relief_on_back:
        _, b_in = back.tables(mat, grid, wl, ti, need_outside=False, progress=progress)
        solver = _reused_solver(model, b_in, None, None, keep=keep)
        _note_request(memory, request, solver, None)
        return solver
    f_out, f_in = front_tables(experiment, grid, wl, ti, traced, progress)
    b_in = None if back.is_flat else back.tables(mat, grid, wl, ti, need_outside=False, progress=progress)[1]
    from relief_bsdf.plate.faces import inside_sectors
    sectors = inside_sectors(front, mat, grid, wl, ti, progress) if b_in is None else None
    solver = _reused_solver(model, f_in, f_out, b_in, sectors, keep)
    solver.half_turn = None
    t_out = half_turn_table(experiment, rows, grid, traced, progress)
    if t_out is not None:           # the same loop tables: only the outside part is new (`with_outside`)
        half = _reused_solver(model, f_in, t_out, b_in, sectors, keep)
        half.half_turn = None
        solver.half_turn = half
    _note_request(memory, request, solver, solver.half_turn)
    return solver


def _face_token(face: Any) -> tuple | None:
    """What determines a face's tables, without deriving them (None: a face this does not know)."""
    from relief_bsdf.plate.faces import FlatFace, MicrofacetFace, ReliefFace, TableFace
    if isinstance(face, FlatFace):
        return ("flat",)
    if isinstance(face, ReliefFace):
        return face.cache_key()
    if isinstance(face, MicrofacetFace):
        return ("microfacet", float(face.alpha), face.distribution, int(face.samples))
    if isinstance(face, TableFace):     # the tables themselves: a held solver holds them, so their ids stay theirs
        return ("table faces", id(face.inside), id(face.outside), id(face.half_turned))
    return None


def request_key(experiment: Any, rows: Any, grid: Any, traced: bool) -> tuple | None:
    """Everything that determines the tables `solver_of` places for these rows (faces' content, material,
    grid, wavelengths, the outside incidences of both half-turns, the beam traced into the outside table),
    computed without deriving a table; None where a face is of a kind this does not know."""
    from relief_bsdf.plate.faces import material_key
    p = experiment.plate
    faces = (_face_token(p.front), _face_token(p.back))
    if None in faces:
        return None
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    far = tuple(float(t) for t in np.unique(t_all[far_side(t_all, p_all)]))
    beam = float(experiment.instrument.beam_divergence_deg) if traced else 0.0
    return ("request",) + faces + (material_key(p.material), repr(grid), tuple(float(w) for w in wl),
                                   tuple(float(t) for t in np.unique(t_all)), far, beam)


def _note_request(memory: Any, request: tuple | None, solver: PlateSolver, half: PlateSolver | None) -> None:
    """Mark the held solver (and its half-turned one) as the answer to `request` (`held_for_request`)."""
    key = getattr(solver, "memory_key", None)
    held = memory.peek(key) if request is not None and key is not None else None
    if held is None:
        return
    half_key = getattr(half, "memory_key", None) if half is not None else None
    if half is not None and half_key is None:
        return
    held.requests = {**getattr(held, "requests", {}), request: half_key}


def held_for_request(memory: Any, request: tuple, model: PlateModel) -> PlateSolver | None:
    """A solver for `model` on the tables of `request`, from a held solver made for that request (the same
    plate: a copy carrying the new instrument; another bulk: the tables' part shared, `_reused_solver`),
    or None.  The tables' keys count as used (`ForwardMemory.note_used`), as if they had been asked for."""
    plate = _plate_key(model)
    found = [(key, held, getattr(held, "requests", {})[request]) for key, held in memory.entries("solver")
             if request in getattr(held, "requests", {})]
    for exact in (True, False):              # the same plate first, then another bulk (as `_reused_solver`)
        for key, held, half_key in reversed(found):
            main = _answer(memory, key, held, half_key, model, plate, exact)
            if main is not None:
                _note_request(memory, request, main, main.half_turn)
                return main
    return None


def _answer(memory: Any, key: tuple, held: PlateSolver, half_key: tuple | None, model: PlateModel, plate: tuple,
            exact: bool) -> PlateSolver | None:
    """`held_for_request`'s solver from one held solver and its half-turned one, or None."""
    if (key[2] == plate) != exact:
        return None
    half = None
    if half_key is not None:
        half = memory.peek(half_key)
        if half is None or (half_key[2] == plate) != exact:
            return None
    main = _variant(memory, key, held, model, plate)
    if main is None:
        return None
    main.half_turn = None
    if half is not None:
        half = _variant(memory, half_key, half, model, plate)
        if half is None:
            return None
        half.half_turn = None
        main.half_turn = half
        memory.note_used([t for t in half_key[1] if t is not None and t[0] != "object"])
    memory.note_used([t for t in key[1] if t is not None and t[0] != "object"])
    return main


def _variant(memory: Any, key: tuple, held: PlateSolver, model: PlateModel, plate: tuple) -> PlateSolver | None:
    """The held solver `held` (under `key` = ("solver", tokens, plate)) for `model`: a copy when the plate is
    the same, a kept copy sharing the tables' part when only the bulk differs, else None."""
    if key[2] == plate:
        memory.touch(key)
        new = copy.copy(held)
        new.model = model
        return new
    if tuple(kv for kv in key[2] if kv[0] not in _BULK_FIELDS) == tuple(kv for kv in plate if kv[0] not in _BULK_FIELDS):
        new = copy.copy(held)
        new.model, new._ops = model, {}
        return _kept(memory, key[1], plate, new)
    return None


def drop_sector_table(solver: PlateSolver) -> None:
    """Once a solver's sector kernels exist for the wavelengths it solved, its inside sector table (the
    largest table of an evaluation, as large as the kernels) is let go: the solver and the held solver it
    was copied from keep a `SectorsHeader`, the memory owner discards the table and adds what it cost
    to the held solver's cost (evicting that solver now costs the table too).  Later solvers on the same
    tables come from `held_for_request` without it; one that needs it again derives it again."""
    t = solver.inside_sectors
    if t is None or isinstance(t, SectorsHeader):
        return
    memory = current_memory()
    header = SectorsHeader.of(t)
    table_key = memory.key_of(t)
    cost = memory.cost_of(table_key) if table_key is not None else 0.0
    for s in (solver, solver.half_turn):
        if s is None:
            continue
        key = getattr(s, "memory_key", None)
        for obj in (s, memory.peek(key) if key is not None else None):
            if obj is not None and obj.inside_sectors is t:
                obj.inside_sectors = header
        if key is not None and cost:
            memory.refresh(key, cost)
            cost = 0.0
    if table_key is not None:
        memory.discard(table_key)


def half_turn_table(experiment: Any, rows: Any, grid: Any, traced: bool, progress: Any = None) -> BsdfTable | None:
    """The front face's half-turned outside table (`plate.faces.half_turned_outside`) at the incidences of
    these rows that the sample sees from the far half of azimuths (`far_side`), or None (none there, or a
    face without a relief to turn)."""
    from relief_bsdf.plate.faces import half_turned_outside
    wl, t_all, p_all = sample_incidences(experiment, rows, traced)
    far = np.unique(t_all[far_side(t_all, p_all)])
    if not far.size:
        return None
    beam = experiment.instrument.beam_divergence_deg if traced else 0.0
    return half_turned_outside(experiment.plate.front, experiment.plate.material, grid, wl, far, progress, beam)


def front_traces_beam(experiment: Any, rows: Any, grid: Any) -> bool:
    """Whether the front face's outside table holds the source's beam divergence itself: a relief
    traced by rays draws each ray's incidence from the beam (methods.ray, option beam_divergence_deg),
    exact for any relief, isotropic or not, and one table per nominal incidence instead of the
    quadrature's BEAM_RINGS x BEAM_AZIMUTHS; other methods (wave optics, surrogates) give tables of
    single incidences, which `simulate_rows` sums over the quadrature."""
    from relief_bsdf.plate.faces import beam_in_table
    beam = experiment.instrument.beam_divergence_deg
    front = experiment.plate.front
    if beam <= 0 or front.is_flat or not hasattr(front, "traces_beam"):
        return False
    wl, ti = table_incidences(experiment, rows, True)
    if not front.traces_beam(experiment.plate.material, grid, wl, ti):
        return False
    held = beam_in_table(getattr(front, "outside", None))
    if held and abs(held - beam) > 1e-9:
        raise InputError("instrument.beam_divergence_deg",
                         f"the front face's outside table was traced with a beam divergence of {held:g} deg, "
                         f"the instrument states {beam:g} deg")
    return True


def front_tables(experiment: Any, grid: Any, wl: Any, ti: Any, traced: bool, progress: Any = None) -> tuple:
    """(outside, inside) tables of the front face, the beam traced into the outside one when `traced`."""
    p = experiment.plate
    beam = experiment.instrument.beam_divergence_deg if traced else 0.0
    return p.front.tables(p.material, grid, wl, ti, need_outside=True, progress=progress, beam_divergence_deg=beam)


_SOLVED_KEPT = 8             # unit-source fields kept per wavelength's operators (`PlateSolver.solve`) ...
_SOLVED_BYTES = 150e6        # ... and their bytes at most (a beam divergence's many incidences: not kept)
_BULK_FIELDS = ("thickness_m", "absorption_per_m", "scatter_per_m", "hg_g")    # act on `_operators` alone
_INSTRUMENT_FIELDS = ("detector_half_angle_deg", "polarization", "background_per_sr", "blur_deg", "tilt_deg",
                      "cone_points", "beam_divergence_deg")


def _table_token(memory: Any, table: BsdfTable | None) -> tuple | None:
    """What names a table in a solver's key: the memory owner's key of it (its content), else the object
    itself (a table the caller made: the solver holds it, so its id is not reused while the solver is held)."""
    if table is None:
        return None
    return memory.key_of(table) or ("object", id(table))


def _reused_solver(model: PlateModel, inside: BsdfTable, outside: BsdfTable | None,
                   back: BsdfTable | None, sectors: BsdfTable | None = None, keep: bool = True) -> PlateSolver:
    """A PlateSolver whose per-wavelength operators (round-trip system, exit maps) are those of an
    earlier solver on the same tables (by content: the memory owner's keys) and the same plate
    (thickness, indices, bulk, grid): they do not depend on the instrument (source polarisation,
    cone, blur, tilt, stray light), which acts only on the incident Stokes vector and the detector
    reading.  A fit or diagnosis that changes only the instrument then reuses them.  Short of that:
    the same tables with another bulk (absorption, thickness, volume scattering) share the tables'
    part (`PlateSolver._table_ops`); another outside table on the same loop tables and plate (a tilt)
    shares the loop's operators (`PlateSolver.with_outside`).  The numbers are always those of a fresh
    solver.  A new solver is held by the memory owner (`plate.memory`, kind "solver") unless `keep` is
    False; `run` measures it again once it has solved."""
    memory = current_memory()
    plate = _plate_key(model)
    tokens = tuple(_table_token(memory, t) for t in (inside, outside, back, sectors))
    held = [(k[1], k[2], v) for k, v in memory.entries("solver")]          # (tokens, plate, solver), oldest first
    for t, key, solver in reversed(held):
        if t == tokens and key == plate:
            memory.touch(("solver", t, key))
            new = copy.copy(solver)          # shares the operators (solver._ops), carries the new instrument
            new.model = model
            return _with_sectors(new, sectors)
    tabs = tuple((f, getattr(model, f)) for f, _ in plate if f not in _BULK_FIELDS)
    for t, key, solver in reversed(held):     # the same tables, another bulk (an absorption)
        if t == tokens and tuple(kv for kv in key if kv[0] not in _BULK_FIELDS) == tabs:
            new = copy.copy(solver)
            new.model, new._ops = model, {}        # the bulk's part anew, the tables' part (solver._tops) shared
            return _kept(memory, tokens, plate, _with_sectors(new, sectors), keep)
    for t, key, solver in reversed(held):     # same loop tables, another outside table (a tilt)
        if (key == plate and t[0] == tokens[0] and t[2] == tokens[2] and t[3] == tokens[3] and outside is not None
                and t[1] is not None and outside.is_polarized == solver.outside.is_polarized):
            return _kept(memory, tokens, plate, _with_sectors(solver.with_outside(model, outside), sectors), keep)
    return _kept(memory, tokens, plate, PlateSolver(model, inside, outside, back=back, inside_sectors=sectors), keep)


def _plate_key(model: PlateModel) -> tuple:
    """The fields of a model that a solver's operators depend on (all but the instrument's)."""
    return tuple((f, getattr(model, f)) for f in PlateModel.__dataclass_fields__ if f not in _INSTRUMENT_FIELDS)


def _with_sectors(solver: PlateSolver, sectors: BsdfTable | None) -> PlateSolver:
    """`solver` with the sector table it was asked for (a held solver may keep only its `SectorsHeader`)."""
    if sectors is not None and isinstance(solver.inside_sectors, SectorsHeader):
        solver.inside_sectors = sectors
    return solver


def _kept(memory: Any, tokens: tuple, plate: tuple, solver: PlateSolver, keep: bool = True) -> PlateSolver:
    """Hold `solver` in the memory owner under its tables' tokens and plate (not when `keep` is False)."""
    if keep:
        memory.put(("solver", tokens, plate), solver, "solver")
        solver.memory_key = ("solver", tokens, plate)
    return solver


def refresh_solver(solver: PlateSolver, cost_s: float = 0.0) -> None:
    """Measure a held solver again after it solved (its operators are made lazily), add what the solve
    cost, and evict to the budget."""
    key = getattr(solver, "memory_key", None)
    if key is not None:
        current_memory().refresh(key, cost_s)


def run(experiment: Any, rows: Any, grid: Any, progress: Any = None, where: str = "recording",
        keep_solver: bool = True) -> tuple[np.ndarray, dict]:
    """Deterministic plate BSDF of an Experiment on every row (detector included) and what was used;
    `keep_solver` False: its solver is not kept for reuse (`solver_of`)."""
    import warnings
    from relief_bsdf.plate.faces import isotropy_warning
    solver = solver_of(experiment, rows, grid, progress, keep_solver)
    t0 = time.perf_counter()
    vals = simulate_rows(solver.model, solver.inside, solver.outside, rows, solver=solver, where=where)
    if keep_solver:                          # the kernels exist: the sector table goes before the solver is measured
        drop_sector_table(solver)
    for s in (solver, solver.half_turn):
        if s is not None:
            refresh_solver(s, time.perf_counter() - t0)
    info = {"engine": "deterministic", "grid": grid.describe()}
    sectors = solver.inside_sectors
    if sectors is not None:                  # the loop meets the relief by azimuth sector (plate.faces.inside_sectors)
        spread = sectors.metadata.get("request", {}).get("options", {}).get("phi_i_spread_deg", 0.0)
        info["inside_sectors"] = {"centres_deg": [float(p) for p in sectors.phi_i_deg],
                                  "each": (f"the inside table averaged over its sector's incidence azimuths, +-{spread:g} deg"
                                           if spread else "the inside table at the sector's centre")}
    notes = [w for w in (isotropy_warning(f) for f in (experiment.plate.front, experiment.plate.back)) if w]
    for w in notes:
        warnings.warn(w, RuntimeWarning, stacklevel=2)
    if notes:
        info["warnings"] = notes
    return vals, info
