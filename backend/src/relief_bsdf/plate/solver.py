"""Fast deterministic model of a solid plate with one rough face (paper fig. 2b, "solid" model).

Geometry (formats.md frame): the plate fills -t < z < 0, the lit face is z = 0, light comes
from z > 0.  The relief sits on the front (lit) face or on the back face; the other face is
flat (Fresnel), or, with the relief in front, the back face may carry its own table (light from
inside; its delta part replaces Fresnel and its cells add a second diffuse kernel K_B, so a
round trip is K A (K_B + R_B) A).  Bulk absorption follows Beer-Lambert along each path: a traversal at internal
angle theta keeps exp(-a t / cos theta).  The boundary is described by two `BsdfTable`s of the
relief (light from outside, light from inside); each must be isotropic (one phi_i).  With the
relief on the back face, the front face may carry its own pair of tables (`front=`): the system is
then the same as a front face with tables and a second face with a table, roles swapped.

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
  (N A) x (N A) system.
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
  delta beams; rows of a recording are then averaged over the detector's acceptance cone
  (equal-area quadrature of `cone_points` directions), and a delta beam inside the cone adds
  P / (Omega cos theta_s) (formats.md goniophotometer definition).

Regime of validity: geometric optics between the faces (plate thick compared with the
coherence length: intensities add, no thin-film fringes), laterally infinite plate
(no edge loss), translation-invariant faces (the relief's statistics do not vary over the
lit spot), discretisation error of the order of the table's cell size (1 deg by default).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable, projected_solid_angle
from relief_bsdf.errors import InputError
from relief_bsdf.core.optics import ConstantIndex, IndexModel, Material, mueller_interface

_DEPOL = np.diag([1.0, 0.0, 0.0, 0.0])


def _blas_single_thread():
    """The plate's matrices are small (N ~ 90): BLAS threads only add wake-up cost, and on a loaded
    machine OpenBLAS's spinning threads make a 5 ms batched solve take seconds.  One thread."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - pinned in requirements/runtime.txt
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")
SOURCE_STOKES = {"unpolarized": np.array([1.0, 0.0, 0.0, 0.0]),
                 "s": np.array([1.0, 1.0, 0.0, 0.0]),
                 "p": np.array([1.0, -1.0, 0.0, 0.0])}


@dataclass(frozen=True)
class PlateModel:
    """Everything the forward model needs besides the boundary tables.

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
    polarization: str = "unpolarized"
    outside_index: IndexModel = ConstantIndex(1.0)
    background_per_sr: float = 0.0
    blur_deg: float = 0.0
    tilt_deg: float = 0.0
    azimuth_cells: int = 72
    cone_points: int = 19

    def __post_init__(self) -> None:
        if self.rough_face not in ("front", "back"):
            raise InputError("plate.rough_face", f"must be 'front' or 'back', got {self.rough_face!r}")
        if not (self.thickness_m > 0 and np.isfinite(self.thickness_m)):
            raise InputError("plate.thickness_mm", f"thickness must be > 0, got {self.thickness_m}")
        if not (self.absorption_per_m >= 0):
            raise InputError("plate.absorption_per_mm", f"absorption must be >= 0, got {self.absorption_per_m}")
        if not (self.detector_half_angle_deg > 0 and self.detector_half_angle_deg < 45):
            raise InputError("instrument.detector_half_angle_deg",
                             f"the detector cone half-angle must be in (0, 45) degrees, got "
                             f"{self.detector_half_angle_deg}")
        if self.polarization not in SOURCE_STOKES:
            raise InputError("instrument.polarization",
                             f"must be unpolarized, s or p, got {self.polarization!r}")

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

def _lin_matrix(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(len(x), len(grid)) linear interpolation weights, clamped at the ends."""
    grid = np.asarray(grid, float)
    x = np.atleast_1d(np.asarray(x, float))
    W = np.zeros((x.size, grid.size))
    if grid.size == 1:
        W[:, 0] = 1.0
        return W
    xc = np.clip(x, grid[0], grid[-1])
    i1 = np.clip(np.searchsorted(grid, xc, side="right"), 1, grid.size - 1)
    i0 = i1 - 1
    f = np.clip((xc - grid[i0]) / (grid[i1] - grid[i0]), 0.0, 1.0)
    r = np.arange(x.size)
    W[r, i0] += 1.0 - f
    W[r, i1] += f
    return W


def _periodic_matrix(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Like `_lin_matrix` on a 360-degree periodic axis."""
    grid = np.asarray(grid, float)
    x = np.atleast_1d(np.asarray(x, float))
    n = grid.size
    W = np.zeros((x.size, n))
    if n == 1:
        W[:, 0] = 1.0
        return W
    g0 = grid[0]
    xr = np.mod(x - g0, 360.0) + g0
    ext = np.concatenate([grid, [g0 + 360.0]])
    i1 = np.clip(np.searchsorted(ext, xr, side="right"), 1, n)
    i0 = i1 - 1
    f = np.clip((xr - ext[i0]) / (ext[i1] - ext[i0]), 0.0, 1.0)
    r = np.arange(x.size)
    np.add.at(W, (r, i0 % n), 1.0 - f)
    np.add.at(W, (r, i1 % n), f)
    return W


def _apply(W: np.ndarray, arr: np.ndarray, axis: int) -> np.ndarray:
    """Contract interpolation matrix W (new, old) with `arr` along `axis`."""
    if W.shape[0] == W.shape[1] and np.all(np.diagonal(W) == 1.0):   # rows sum to 1: identity
        return arr
    return np.moveaxis(np.tensordot(W, arr, axes=([1], [axis])), 0, axis)


class _TableView:
    """One boundary table at one wavelength, sampled on arbitrary angles (isotropic tables only)."""

    def __init__(self, table: BsdfTable, wavelength_nm: float, mueller: bool, name: str):
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
        k = 0 if side == "R" else 1
        t = self.table
        arr = self.v[:, k]                                                   # (I, S, P, ...)
        arr = _apply(_lin_matrix(t.theta_i_deg, theta_in), arr, 0)
        arr = _apply(_lin_matrix(t.theta_s_deg, theta_out), arr, 1)
        arr = _apply(_periodic_matrix(t.phi_s_deg, self.phi0 + 180.0 + np.asarray(delta_deg)), arr, 2)
        return arr

    def specular(self, side: str, theta_in: float) -> np.ndarray:
        """4x4 Mueller matrix (or scalar power fraction times I) of the delta part."""
        return self.specular_many(side, [theta_in])[0]

    def specular_many(self, side: str, theta_in: Any) -> np.ndarray:
        """(n, 4, 4) delta-part Mueller matrices at several incidence angles."""
        p, pm = self.spec[side]
        W = _lin_matrix(self.table.theta_i_deg, np.ravel(theta_in))
        return np.tensordot(W, pm, axes=(1, 0))


def _blocks(Xh: np.ndarray, c: int) -> np.ndarray:
    """(T, J, M[, 4, 4]) kernel in Fourier space -> (M, T c, J c) matrices."""
    if c == 1:
        return np.moveaxis(Xh, 2, 0)
    T, J, M = Xh.shape[:3]
    return np.transpose(Xh, (2, 0, 3, 1, 4)).reshape(M, T * 4, J * 4)


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


# ---------------------------------------------------------------- the solver

@dataclass
class PlateResult:
    """Plate BSDF of one incidence on the outgoing grid, plus the delta beams.

    grid_R / grid_T: (T, A) BSDF (1/sr) at theta_out_deg x delta_deg (delta = outgoing
    azimuth minus the incident beam's propagation azimuth phi_i + 180).
    deltas: list of (side, theta_deg, delta_deg, power fraction) for exact beams.
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
                 back: BsdfTable | None = None, front: tuple[BsdfTable, BsdfTable] | None = None):
        """`back`: optional BSDF table (light from inside) of the second, back face; None = flat.

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
        self.mueller = (inside.is_polarized or (outside is not None and outside.is_polarized)
                        or (back is not None and back.is_polarized))
        self.theta_edges = np.asarray(inside.theta_s_edges_deg, float)
        self.theta_c = 0.5 * (self.theta_edges[1:] + self.theta_edges[:-1])
        A = int(model.azimuth_cells)
        self.delta = np.arange(A) * (360.0 / A)
        self.psa = projected_solid_angle(self.theta_edges, [0.0, 360.0 / A])[:, 0]        # (N,)
        self._ops: dict = {}

    # -- per wavelength operators
    def _operators(self, wl: float) -> dict:
        if wl in self._ops:
            return self._ops[wl]
        m = self.model
        n = float(np.real(m.index.n(wl)))
        n0 = float(np.real(m.outside_index.n(wl)))
        tc = self.theta_c
        N = tc.size
        c = 4 if self.mueller else 1
        vin = _TableView(self.inside, wl, self.mueller, "inside table")
        vout = _TableView(self.outside, wl, self.mueller, "outside table") if self.outside is not None else None
        cos_c = np.maximum(np.cos(np.radians(tc)), 1e-6)
        absorb = np.exp(-m.absorption_per_m * m.thickness_m / cos_c)                       # (N,)
        # Fresnel of the flat face averaged over each internal cell (projected solid angle): the cell
        # straddling the critical angle then loses exactly what the exit remap below lets out
        e = np.radians(self.theta_edges)
        nsub = 64
        u = (np.sin(e[:-1])[:, None] ** 2 + (np.arange(nsub) + 0.5)[None] / nsub
             * (np.sin(e[1:]) ** 2 - np.sin(e[:-1]) ** 2)[:, None])
        cos_sub = np.sqrt(np.clip(1.0 - u, 0.0, 1.0))
        RF = _fresnel(cos_sub, n, n0, "R").mean(axis=1)                                     # (N, 4, 4)
        vB = _TableView(self.back, wl, self.mueller, "back-face table") if self.back is not None else None
        th_sub = np.degrees(np.arccos(cos_sub))                                             # cell average too
        if vB is not None:
            RF = vB.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1)            # its delta part
        # the rough face's own delta part acting on diffuse light from inside: specular reflection
        # keeps the cell (and the propagation azimuth), so it is diagonal in every azimuthal mode
        # (times 1 - 1e-9: between two lossless specular faces a totally reflected cell would make the
        # loop singular; it is fed nothing, and 1e-9 per round trip stands for the plate's finite size)
        SR = vin.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1) * (1 - 1e-9)  # (N, 4, 4)
        # kernel K[t, j, a] from the inside table's R cells, times the receiving cell's projected solid angle
        K = vin.diffuse("R", tc, tc, self.delta)                                           # (J, T, A[,4,4])
        K = np.moveaxis(K, 0, 1) * (self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None])
        Kh = np.fft.rfft(K, axis=2)                                                         # (T, J, M[,4,4])
        del K                                                    # big tables: keep one kernel copy at a time
        # round trip diagonal D_j = A_j R_F,j A_j (4x4 or scalar R_F,00)
        if c == 1:
            Dj = absorb**2 * RF[:, 0, 0]
            Mk = Kh.shape[2]
            Kmat = np.moveaxis(Kh, 2, 0) + np.diag(SR[:, 0, 0])[None]                      # (M, T, J)
            sysm = np.eye(N)[None] - Kmat * Dj[None, None, :]
        else:
            Dj = absorb[:, None, None] ** 2 * RF                                            # (N, 4, 4)
            Mk = Kh.shape[2]
            KD = np.einsum("tjmab,jbc->mtajc", Kh, Dj)
            idx = np.arange(N)
            KD[:, idx, :, idx, :] += np.einsum("jab,jbc->jac", SR, Dj)[:, None]
            sysm = KD.reshape(Mk, N * 4, N * 4)
            sysm *= -1.0                                                                    # I - K D in place
            sysm[:, np.arange(N * 4), np.arange(N * 4)] += 1.0
            del KD
        Kb = Rtrip = GBT = None
        if vB is not None:
            # second face with its own table: round trip K A (K_B + R_B,delta) A as full matrices per m
            KB = vB.diffuse("R", tc, tc, self.delta)
            KB = np.moveaxis(KB, 0, 1) * (self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None])
            Kb = _blocks(Kh, c) + _block_diag(SR, c)[None]
            Aa = np.repeat(absorb, c)
            Rtrip = (_blocks(np.fft.rfft(KB, axis=2), c) + _block_diag(RF, c)[None]) * Aa[None, :, None] * Aa[None, None, :]
            sysm = np.eye(N * c)[None] - Kb @ Rtrip
            GB = vB.diffuse("T", tc, tc, self.delta)
            if c == 4:
                GB = GB[..., 0, :]
            GBh = np.fft.rfft(GB, axis=2)
            GBT = (np.moveaxis(GBh, 2, 0) if c == 1 else np.moveaxis(GBh, (2, 3), (0, 2))).reshape(
                GBh.shape[2], -1, GBh.shape[1])
        # exit through the rough face from inside: inside table T cells, onto the outgoing grid (theta_c in air)
        G = vin.diffuse("T", tc, tc, self.delta)                                           # (J, O, A[,4,4])
        if c == 4:
            G = np.ascontiguousarray(G[..., 0, :])                                          # detector: S0 row
        Gh = np.fft.rfft(G, axis=2)                                                         # (J, O, M[,4])
        del G
        GhT = (np.moveaxis(Gh, 2, 0) if c == 1 else np.moveaxis(Gh, (2, 3), (0, 2))).reshape(Gh.shape[2], -1,
                                                                                            Gh.shape[1])
        # exit through the flat face: Snell map from outgoing grid theta (air) to internal theta
        # conservative remap: each outgoing cell is cut into 16 equal projected-solid-angle slices,
        # each slice's Snell pre-image falls in one internal cell (piecewise-constant radiance there)
        # and carries the exact Fresnel transmission (Mueller row 0: the detector sees S0)
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
        th_c = np.degrees(np.arcsin(min(n0 / n, 1.0)))
        below = tc < th_c
        Wi = _lin_matrix(tc[below], th_int.ravel()).reshape(N, ns, -1)                       # (O, ns, Nb)

        def exit_remap(t_slices: np.ndarray) -> np.ndarray:
            """(O, N, c): internal radiance -> outgoing cells, through transmission t per slice."""
            W = np.zeros((N, N, c))
            W[:, below, :] = np.einsum("osj,osc->ojc", Wi, t_slices)
            return W
        Wflat = exit_remap(tf)
        # exit of diffuse internal light through the rough face's delta part (its specular
        # transmission from inside): the same Snell remap, with the table's delta Mueller row 0
        Wspec = exit_remap(vin.specular_many("T", th_int).reshape(N, ns, 4, 4)[..., 0, :c] / ns)
        ops = dict(n=n, n0=n0, vin=vin, vout=vout, vB=vB, absorb=absorb, RF=RF, sys=sysm, Dj=Dj, GhT=GhT,
                   Wflat=Wflat, Wspec=Wspec, c=c, M=Mk, Kb=Kb, Rtrip=Rtrip, GBT=GBT)
        self._ops[wl] = ops
        return ops

    def solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float = 0.0) -> list[PlateResult]:
        """Plate BSDF for each incidence angle (degrees) at one wavelength."""
        with _blas_single_thread():
            return self._solve(wavelength_nm, theta_i_deg, phi_i_deg)

    def _solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float = 0.0) -> list[PlateResult]:
        m = self.model
        ops = self._operators(float(wavelength_nm))
        n, n0, c, Mk = ops["n"], ops["n0"], ops["c"], ops["M"]
        vin, vout = ops["vin"], ops["vout"]
        tc, psa, delta = self.theta_c, self.psa, self.delta
        N, A = tc.size, delta.size
        s_inc = SOURCE_STOKES[m.polarization]
        front = m.rough_face == "front"
        thetas = np.atleast_1d(np.asarray(theta_i_deg, float))
        nI = thetas.size
        S = np.zeros((nI, N, A, c))              # power per cell leaving the rough face into the plate
        direct_rough = np.zeros((nI, N, A))      # BSDF on the outgoing grid through the rough face (no loop)
        direct_R = np.zeros((nI, N, A))          # outside table R (front relief)
        direct_flat = np.zeros((nI, N, A))       # diffuse exit of the delta beam through a back-face table
        U_extra = np.zeros((nI, N, A, c))        # delta beam scattered diffusely by a back-face table
        vB = ops["vB"]
        deltas_all = []
        for q, ti in enumerate(thetas):
            ti = abs(float(ti))
            tt = float(_snell_deg(ti, n0, n))
            a_t = float(np.exp(-m.absorption_per_m * m.thickness_m / max(np.cos(np.radians(tt)), 1e-6)))
            if vB is None:
                RFt = _fresnel(np.cos(np.radians(tt)), n, n0, "R")
                TFt = _fresnel(np.cos(np.radians(tt)), n, n0, "T")
            else:
                RFt, TFt = vB.specular("R", tt), vB.specular("T", tt)
            deltas = []
            if front:
                f_r = vout.diffuse("R", [ti], tc, delta)[0]
                f_t = vout.diffuse("T", [ti], tc, delta)[0]
                if c == 1:
                    direct_R[q] = f_r
                    S[q, :, :, 0] = f_t * psa[:, None]
                else:
                    direct_R[q] = f_r[..., 0, :] @ s_inc
                    S[q] = (f_t @ s_inc) * psa[:, None, None]
                y0 = vout.specular("T", ti) @ s_inc
                deltas.append(("R", ti, 0.0, float((vout.specular("R", ti) @ s_inc)[0])))
                z0 = np.zeros(4)
            else:
                cos_i = np.cos(np.radians(ti))
                deltas.append(("R", ti, 0.0, float((_fresnel(cos_i, n0, n, "R") @ s_inc)[0])))
                z0 = a_t * (_fresnel(cos_i, n0, n, "T") @ s_inc)
                y0 = np.zeros(4)
            # delta chain: z arrives at the rough face from inside, y leaves it into the plate
            sR = vin.specular("R", tt)
            sT = vin.specular("T", tt)
            loop = a_t * a_t * RFt
            z = np.linalg.solve(np.eye(4) - loop @ sR, z0 + loop @ y0)
            y = y0 + sR @ z
            p_rough = float((sT @ z)[0])
            p_flat = float((TFt @ (a_t * y))[0])
            deltas.append(("R" if front else "T", ti, 0.0, p_rough))
            deltas.append(("T" if front else "R", ti, 0.0, p_flat))
            deltas_all.append(deltas)
            if vB is not None:   # the delta beam y, at the back face, scatters diffusely there
                yb = a_t * y
                fbr = vB.diffuse("R", [tt], tc, delta)[0]
                fbt = vB.diffuse("T", [tt], tc, delta)[0]
                if c == 1:
                    U_extra[q, :, :, 0] = fbr * (psa * ops["absorb"])[:, None] * yb[0]
                    direct_flat[q] = fbt * yb[0]
                else:
                    U_extra[q] = (fbr @ yb) * (psa * ops["absorb"])[:, None, None]
                    direct_flat[q] = fbt[..., 0, :] @ yb
            # what the delta beam z scatters diffusely at the rough face
            fr = vin.diffuse("R", [tt], tc, delta)[0]
            ft = vin.diffuse("T", [tt], tc, delta)[0]
            if c == 1:
                S[q, :, :, 0] += fr * psa[:, None] * z[0]
                direct_rough[q] += ft * z[0]
            else:
                S[q] += (fr @ z) * psa[:, None, None]
                direct_rough[q] += ft[..., 0, :] @ z
        # diffuse loop in the azimuthal Fourier domain
        Sh = np.fft.rfft(S, axis=2)                                        # (nI, N, M, c)
        rhs = np.moveaxis(np.moveaxis(Sh, 2, 1).reshape(nI, Mk, N * c), 0, 2)   # (M, N c, nI)
        if vB is not None:
            Uxh = np.moveaxis(np.moveaxis(np.fft.rfft(U_extra, axis=2), 2, 1).reshape(nI, Mk, N * c), 0, 2)
            rhs = rhs + ops["Kb"] @ Uxh
        Xh = np.linalg.solve(ops["sys"], rhs)                               # (M, N c, nI)
        XhM = Xh
        Xh = np.moveaxis(Xh, 2, 0).reshape(nI, Mk, N, c)
        X = np.fft.irfft(np.moveaxis(Xh, 1, 2), n=A, axis=2)               # (nI, N, A, c)
        absorb = ops["absorb"]
        at_flat = X * absorb[None, :, None, None]
        if c == 1:
            U = (at_flat[..., 0] * (ops["RF"][:, 0, 0] * absorb)[None, :, None])[..., None]
        else:
            U = np.einsum("jab,qjkb->qjka", ops["RF"], at_flat) * absorb[None, :, None, None]
        # rough-face exit: circular convolution over azimuth with the inside T kernel
        if vB is None:
            Uh = np.fft.rfft(U, axis=2)                                    # (nI, J, M, c)
            Um = np.moveaxis(Uh, 2, 0).reshape(Mk, nI, N * c)              # (M, q, J c)
        else:
            Um = np.moveaxis(ops["Rtrip"] @ XhM + Uxh, 2, 1)                # (M, q, J c)
        Oh = np.moveaxis(Um @ ops["GhT"], 0, 2)                             # (q, O, M)
        out_rough = np.fft.irfft(Oh, n=A, axis=2) + direct_rough
        if np.any(ops["Wspec"]):   # specular exit of the diffuse light arriving at the rough face from inside
            if vB is not None:
                U = np.fft.irfft(np.moveaxis(Um.reshape(Mk, nI, N, c), 0, 2), n=A, axis=2)   # (q, J, A, c)
            LU = np.moveaxis(U / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)
            out_rough = out_rough + (ops["Wspec"].reshape(N, N * c) @ LU) * (n0 / n) ** 2
        # flat-face exit: internal radiance (Stokes) interpolated at the Snell pre-image of each outgoing
        # direction, times the exact Fresnel transmission there, divided by (n/n0)^2 (radiance law)
        L = np.moveaxis(at_flat / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)    # (q, N c, A)
        out_flat = (ops["Wflat"].reshape(N, N * c) @ L) * (n0 / n) ** 2                   # (q, O, A)
        if vB is not None:   # diffuse exit through the back-face table, from the light arriving there
            AX = np.moveaxis(XhM * np.repeat(absorb, c)[None, :, None], 2, 1)          # (M, q, N c)
            out_flat = out_flat + np.fft.irfft(np.moveaxis(AX @ ops["GBT"], 0, 2), n=A, axis=2) + direct_flat
        results = []
        for q, ti in enumerate(thetas):
            gR = direct_R[q] + (out_rough[q] if front else out_flat[q])
            gT = out_flat[q] if front else out_rough[q]
            results.append(PlateResult(float(wavelength_nm), float(ti), float(phi_i_deg), tc, self.theta_edges,
                                       delta, gR, gT, deltas_all[q]))
        return results


# ---------------------------------------------------------------- detector and rows

def cone_offsets(half_angle_deg: float, npts: int = 19, blur_deg: float = 0.0) -> np.ndarray:
    """(npts, 2) angular offsets (radians, in the detector's tangent plane), equal weights.

    Equal-area Vogel spiral over the cone; an instrument blur of 1-sigma `blur_deg` is added
    by widening each point's radius in quadrature (a Gaussian kernel convolved with the cone).
    """
    k = np.arange(npts)
    h = np.radians(half_angle_deg)
    r = h * np.sqrt((k + 0.5) / npts)
    if blur_deg > 0:
        b = np.radians(blur_deg)
        # radius of a 2-D Gaussian with the same equal-area quantiles, added in quadrature
        rg = b * np.sqrt(-2.0 * np.log(1.0 - (k + 0.5) / npts))
        r = np.sqrt(r**2 + rg**2)
    psi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(psi), r * np.sin(psi)], axis=1)


def _cone_dirs(theta_deg: np.ndarray, phi_deg: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) in degrees of cone points around each (theta, phi): shapes (R, P)."""
    t = np.radians(theta_deg)[:, None]
    p = np.radians(phi_deg)[:, None]
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t) + 0 * p], -1)
    e1 = np.stack([np.cos(t) * np.cos(p), np.cos(t) * np.sin(p), -np.sin(t) + 0 * p], -1)
    e2 = np.stack([-np.sin(p), np.cos(p), 0 * p], -1)
    a, b = offsets[:, 0], offsets[:, 1]
    r = np.sqrt(a**2 + b**2)
    d = (np.cos(r)[None, :, None] * w + (np.sin(r) * np.where(r > 0, a / np.where(r > 0, r, 1), 0))[None, :, None] * e1
         + (np.sin(r) * np.where(r > 0, b / np.where(r > 0, r, 1), 0))[None, :, None] * e2)
    th = np.degrees(np.arccos(np.clip(np.abs(d[..., 2]), -1, 1)))
    ph = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    return th, ph


def rows_from_result(res: PlateResult, side: np.ndarray, theta_s: np.ndarray, phi_s: np.ndarray,
                     model: PlateModel) -> np.ndarray:
    """Detector readings (BSDF, 1/sr) of the rows of one incidence."""
    off = cone_offsets(model.detector_half_angle_deg, model.cone_points, model.blur_deg)
    th, ph = _cone_dirs(theta_s, phi_s, off)
    dl = ph - (res.phi_i_deg + 180.0)
    out = np.zeros(theta_s.size)
    ext = np.concatenate([res.delta_deg, [360.0]])
    for sd, grid in (("R", res.grid_R), ("T", res.grid_T)):
        sel = side == sd
        if not sel.any():
            continue
        g = np.concatenate([grid, grid[:, :1]], axis=1)                  # periodic closure
        t_ = th[sel].ravel()
        d_ = np.mod(dl[sel].ravel(), 360.0)
        tg = res.theta_out_deg
        tc_ = np.clip(t_, tg[0], tg[-1])
        i1 = np.clip(np.searchsorted(tg, tc_, side="right"), 1, tg.size - 1)
        ft = (tc_ - tg[i1 - 1]) / (tg[i1] - tg[i1 - 1])
        ia = np.clip(np.searchsorted(ext, d_, side="right"), 1, ext.size - 1)
        fa = (d_ - ext[ia - 1]) / (ext[ia] - ext[ia - 1])
        v = ((g[i1 - 1, ia - 1] * (1 - fa) + g[i1 - 1, ia] * fa) * (1 - ft)
             + (g[i1, ia - 1] * (1 - fa) + g[i1, ia] * fa) * ft)
        out[sel] = v.reshape(-1, off.shape[0]).mean(axis=1)
    # delta beams: the fraction of the (blurred) cone quadrature that contains the beam direction
    h = np.radians(model.detector_half_angle_deg)
    omega = 2 * np.pi * (1 - np.cos(h))
    for sd, tdeg, ddeg, p in res.deltas:
        if p == 0.0:
            continue
        sel = np.nonzero(side == sd)[0]
        if sel.size == 0:
            continue
        wb = _unit(tdeg, res.phi_i_deg + 180.0 + ddeg)
        wr = _unit(theta_s[sel], phi_s[sel])
        ang = np.arccos(np.clip(wr @ wb, -1, 1))
        if model.blur_deg > 0:
            b = np.radians(model.blur_deg)
            # fraction of a Gaussian-blurred beam inside the cone (Rayleigh radial law, offset ignored
            # when the beam is at the centre; otherwise the beam is blurred before the cone test)
            frac = _blurred_fraction(ang, h, b)
        else:
            frac = (ang <= h + 1e-12).astype(float)
        out[sel] += frac * p / (omega * np.cos(np.radians(theta_s[sel])))
    # FFT round-off can leave -1e-20 where the field is zero: a BSDF is never negative
    return np.maximum(out, 0.0) + model.background_per_sr


def _unit(theta_deg: Any, phi_deg: Any) -> np.ndarray:
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    return np.stack(np.broadcast_arrays(np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)), -1)


def _blurred_fraction(ang: np.ndarray, h: float, b: float, n: int = 64) -> np.ndarray:
    """Fraction of a 2-D Gaussian (1-sigma b) centred at angular distance `ang` inside a disc of radius h."""
    k = np.arange(n)
    r = b * np.sqrt(-2.0 * np.log(1.0 - (k + 0.5) / n))
    psi = k * np.pi * (3.0 - np.sqrt(5.0))
    x = ang[:, None] + r[None] * np.cos(psi)[None]
    y = r[None] * np.sin(psi)[None]
    return np.mean(x**2 + y**2 <= h**2, axis=1)


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
    factor = 1.0
    if model.tilt_deg:
        ti, pi = to_sample_frame(ti, pi, np.full(ti.shape, "R"), model.tilt_deg)
        ts0 = ts
        ts, ps = to_sample_frame(ts, ps, side, model.tilt_deg)
        factor = np.cos(np.radians(ts)) / np.cos(np.radians(ts0))
        ti, pi, ts, ps = (np.round(a, 9) for a in (ti, pi, ts, ps))
    out = np.zeros(wl.size)
    for w in np.unique(wl):
        mw = wl == w
        keys = np.unique(np.stack([ti[mw], pi[mw]], 1), axis=0)
        thetas = np.unique(keys[:, 0])
        res = {float(t): r for t, r in zip(thetas, solver.solve(w, thetas))}
        for t, p in keys:
            sel = mw & (ti == t) & (pi == p)
            r = res[float(t)]
            r = replace(r, phi_i_deg=float(p))
            out[sel] = rows_from_result(r, side[sel], ts[sel], ps[sel], model)
    return (out - model.background_per_sr) * factor + model.background_per_sr


def rot_y(tilt_deg: float) -> np.ndarray:
    """Rotation taking sample-frame vectors to the instrument frame (normal tilted about y)."""
    a = np.radians(tilt_deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


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


# ---------------------------------------------------------------- analytic boundary tables for tests / checks

def flat_tables(material: Material, wavelengths_nm: Sequence[float], theta_i_outside_deg: Sequence[float],
                theta_i_inside_deg: Sequence[float], theta_s_edges_deg: Sequence[float] | None = None,
                phi_s_edges_deg: Sequence[float] | None = None) -> tuple[BsdfTable, BsdfTable]:
    """(outside, inside) tables of a perfectly flat boundary: all power in the delta parts, with Mueller.

    Fresnel (Born & Wolf 1.5.20-21) through `optics.mueller_interface`; the diffuse cells are zero.
    """
    from relief_bsdf.methods.request import DEFAULT_PHI_S_EDGES_DEG, DEFAULT_THETA_S_EDGES_DEG
    te = np.asarray(theta_s_edges_deg if theta_s_edges_deg is not None else DEFAULT_THETA_S_EDGES_DEG, float)
    pe = np.asarray(phi_s_edges_deg if phi_s_edges_deg is not None else DEFAULT_PHI_S_EDGES_DEG, float)
    out = []
    for side, th in (("outside", theta_i_outside_deg), ("inside", theta_i_inside_deg)):
        th = np.asarray(th, float)
        W = len(wavelengths_nm)
        sR = np.zeros((W, th.size, 1, 4, 4))
        sT = np.zeros((W, th.size, 1, 4, 4))
        for k, wl in enumerate(wavelengths_nm):
            n1, n2 = material.n_pair(wl, side)
            cos_i = np.cos(np.radians(th))
            sR[k, :, 0] = mueller_interface(cos_i, n1, n2, "R")
            sT[k, :, 0] = mueller_interface(cos_i, n1, n2, "T")
        vals = np.zeros((W, th.size, 1, 2, te.size - 1, pe.size - 1))
        out.append(BsdfTable(np.asarray(wavelengths_nm, float), th, [0.0], te, pe, vals, incident_from=side,
                             specular_R=sR[..., 0, 0], specular_T=sT[..., 0, 0],
                             specular_mueller_R=sR,
                             specular_mueller_T=sT, method="flat", material=material.describe()))
    return out[0], out[1]
