"""The ONE detector of the plate, for both engines, and the ONE definition of instrument blur.

Goniophotometer reading (formats.md): f = P / (P_inc Omega cos theta_s), P the power the
detector collects, Omega = 2 pi (1 - cos h) the solid angle of its acceptance cone of
half-angle h.

Instrument blur (beam divergence and aperture) is a 2-D Gaussian of 1-sigma b in angle.  The
instrument's angular response to light arriving at angular distance psi from the row's
direction is the uniform cone convolved with that Gaussian:

    response(psi) = P(|psi_vec + g| <= h),  g ~ N(0, b^2 I_2)
                  = F_ncx2(h^2 / b^2; k = 2, lambda = psi^2 / b^2)

the fraction of a Gaussian centred at psi that falls inside the disc (non-central chi-square
with two degrees of freedom; b = 0: the step psi <= h).  The old copies relate to it as
follows: `plate._blurred_fraction` was a 64-point quadrature of exactly this; the old cone
points "radius widened in quadrature" matched only the second moment (an approximation, gone);
the old Monte-Carlo jitter of exit directions equals it in expectation (replaced by the weight,
which has no extra variance).  Both engines normalise by Omega (the plane integral of the
response is pi h^2, Omega differs from it by h^2 / 12 relative: 2.5e-5 at 1 deg).

- Deterministic engine: a diffuse field f cos(theta) / cos(theta_s) is averaged over a product
  quadrature of the cone
  (equal-area Vogel points) and the Gaussian (16 equal-probability rings, each at the radius of
  its ring's mean r^2, golden-angle azimuths: exact second moment), offsets added in the tangent
  plane; a delta beam adds response(psi) P / (Omega cos
  theta_s).
- Monte Carlo: each exit photon of weight w adds w response(psi) / (N Omega cos theta_s).

- Deterministic engine, direct parts on their own (finer) grid (`direct_reading`): the cone
  integral of the cells themselves, sum over equal-solid-angle sub-points of every cell of
  f_cell cos(theta_p) response(psi_p) d(omega_p) / (Omega cos theta_s); without blur the cone's
  edge takes the inside fraction of each sub-point's patch (clip((h - psi) / size + 1/2)), so
  a lobe narrower than the engine's cells, a cone on the pole and a grazing row are integrated,
  not interpolated; what is left is the cells' own averaging (1-sigma 2-deg lobe: ~1-2 % at
  the peak; 3 deg: < 1 %).

Regime: small cones and blurs (tangent-plane offsets, h + 5 b well below 45 deg).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.plate.memory import current_memory

GAUSS_POINTS = 16        # equal-probability points of the blur Gaussian in the deterministic quadrature
_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


def cone_solid_angle(half_angle_deg: float) -> float:
    """Omega = 2 pi (1 - cos h) of the detector's acceptance cone (sr)."""
    return float(2 * np.pi * (1 - np.cos(np.radians(half_angle_deg))))


def response(psi_rad: Any, half_angle_deg: float, blur_deg: float) -> np.ndarray:
    """Instrument response (0..1) to light at angular distance psi from the row: cone (x) Gaussian."""
    psi = np.asarray(psi_rad, float)
    h = np.radians(half_angle_deg)
    if blur_deg <= 0:
        return (psi <= h + 1e-12).astype(float)
    from scipy.stats import ncx2
    b = np.radians(blur_deg)
    return ncx2.cdf((h / b) ** 2, 2, (psi / b) ** 2)


def support_rad(half_angle_deg: float, blur_deg: float) -> float:
    """Angular radius outside which the response is below 1e-9 (h + 6.5 b)."""
    return float(np.radians(half_angle_deg) + 6.5 * np.radians(max(blur_deg, 0.0)))


def quadrature_offsets(half_angle_deg: float, cone_points: int = 19, blur_deg: float = 0.0) -> np.ndarray:
    """(K, 2) equal-weight tangent-plane offsets (rad) whose average is the blurred-cone average.

    Cone: equal-area Vogel spiral of `cone_points`.  Blur b > 0: each cone point is combined with
    GAUSS_POINTS equal-probability rings of the 2-D Gaussian (radius b sqrt(2 E_j), E_j the ring's
    mean of r^2 / 2 b^2; golden-angle azimuths), offsets added: a product quadrature of the
    convolution cone (x) Gaussian with its exact second moment.
    """
    k = np.arange(cone_points)
    r = np.radians(half_angle_deg) * np.sqrt((k + 0.5) / cone_points)
    psi = k * _GOLDEN
    cone = np.stack([r * np.cos(psi), r * np.sin(psi)], axis=1)
    if blur_deg <= 0:
        return cone
    gauss = gaussian_offsets(blur_deg, GAUSS_POINTS)
    return (cone[:, None, :] + gauss[None, :, :]).reshape(-1, 2)


def gaussian_offsets(sigma_deg: float, n: int) -> np.ndarray:
    """(n, 2) equal-weight tangent-plane offsets (rad) of a 2-D Gaussian of 1-sigma `sigma_deg` per
    axis: n equal-probability rings, each at the radius of its ring's mean r^2 (sigma sqrt(2 E_j)),
    golden-angle azimuths; the exact second moment.  The one construction of the aperture blur's
    points (`quadrature_offsets`) and the beam divergence's incidences (`beam_offsets`)."""
    j = np.arange(n)
    rg = np.radians(sigma_deg) * np.sqrt(2.0 * _exp_bin_means(n))
    pg = j * _GOLDEN + 0.5
    return np.stack([rg * np.cos(pg), rg * np.sin(pg)], axis=1)


BEAM_RINGS = 3          # radial Gauss-Laguerre nodes of the beam divergence's quadrature
BEAM_AZIMUTHS = 8       # incidences per ring (deterministic engine, tables of single incidences: BEAM_RINGS x BEAM_AZIMUTHS solves)


def beam_offsets(sigma_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """((Q, 2) tangent-plane offsets in rad, (Q,) weights summing to 1): the quadrature of incidence
    directions for a source beam of Gaussian divergence `sigma_deg` per axis.  The deterministic engine
    solves the plate at each and sums what the detector reads with these weights
    (plate.readout.simulate_rows).

    Polar product rule: x = r^2 / 2 sigma^2 is Exp(1) for the 2-D Gaussian, so the radii are
    sigma sqrt(2 x_k) at the Gauss-Laguerre nodes x_k with their weights w_k (exact for polynomials in
    r^2 up to degree 2 BEAM_RINGS - 1), each ring split into BEAM_AZIMUTHS equal azimuths (alternate
    rings turned by half a step; exact for azimuthal harmonics below BEAM_AZIMUTHS).  A narrow lobe
    is moved to every node, so the outer nodes must be faint: the Laguerre weights are (3 rings:
    0.71, 0.28, 0.010 at 0.91, 2.14, 3.55 sigma); equal-probability rings with one point each (the
    aperture blur's construction, `gaussian_offsets`) put 1/Q of the beam at 2.8-3.1 sigma and missed the
    independent Monte Carlo's transmitted tail at 3.4 sigma by 2-3x either way."""
    x, w = np.polynomial.laguerre.laggauss(BEAM_RINGS)
    r = np.radians(sigma_deg) * np.sqrt(2.0 * x)
    k = np.arange(BEAM_AZIMUTHS)
    phi = 2 * np.pi * (k[None, :] + 0.5 * (np.arange(BEAM_RINGS)[:, None] % 2)) / BEAM_AZIMUTHS
    off = np.stack([(r[:, None] * np.cos(phi)).ravel(), (r[:, None] * np.sin(phi)).ravel()], axis=1)
    return off, np.repeat(w / BEAM_AZIMUTHS, BEAM_AZIMUTHS)


def _exp_bin_means(n: int) -> np.ndarray:
    """Conditional means of X ~ Exp(1) (X = r^2 / 2 b^2 of the 2-D Gaussian) in n equal-probability bins:
    radii b sqrt(2 E_j) give the quadrature the Gaussian's exact second moment (mean E_j = 1)."""
    a = -np.log(1.0 - np.arange(n) / n)                  # bin edges a_j, a_n = inf
    ea = np.exp(-a)
    b = a[1:]
    eb = np.append(np.exp(-b), 0.0)
    beb = np.append(b * np.exp(-b), 0.0)
    return (a * ea - beb + ea - eb) / (ea - eb)


def offset_directions(theta_deg: np.ndarray, phi_deg: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) in degrees of the quadrature points around each row direction: shapes (R, K)."""
    t = np.radians(theta_deg)[:, None]
    p = np.radians(phi_deg)[:, None]
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t) + 0 * p], -1)
    e1 = np.stack([np.cos(t) * np.cos(p), np.cos(t) * np.sin(p), -np.sin(t) + 0 * p], -1)
    e2 = np.stack([-np.sin(p), np.cos(p), 0 * p], -1)
    a, b = offsets[:, 0], offsets[:, 1]
    r = np.hypot(a, b)
    safe = np.where(r > 0, r, 1.0)
    ca = np.where(r > 0, np.sin(r) * a / safe, 0.0)
    cb = np.where(r > 0, np.sin(r) * b / safe, 0.0)
    d = np.cos(r)[None, :, None] * w + ca[None, :, None] * e1 + cb[None, :, None] * e2
    th = np.degrees(np.arccos(np.clip(np.abs(d[..., 2]), -1, 1)))
    ph = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    return th, ph


def projection_weights(theta_deg: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """cos(theta) of each quadrature point over cos(theta_s) of its row, (R, K); 0 below the horizon.

    The reading f = P / (P_inc Omega cos theta_s) collects the power f cos(theta) d(omega) of every
    direction in the cone, so a point's BSDF counts with its own projection cos(theta), not the
    row's: at 85 deg a 2-deg cone spans cos(theta) from 0.05 to 0.12 around cos(theta_s) = 0.087.
    """
    t = np.radians(np.asarray(theta_deg, float))[:, None]
    a, b = offsets[:, 0], offsets[:, 1]
    r = np.hypot(a, b)
    along = np.where(r > 0, np.sin(r) * a / np.where(r > 0, r, 1.0), 0.0)     # offset toward +theta
    cz = np.cos(r)[None, :] * np.cos(t) - along[None, :] * np.sin(t)
    return np.maximum(cz, 0.0) / np.maximum(np.cos(t), 1e-12)


def unit(theta_deg: Any, phi_deg: Any) -> np.ndarray:
    """Unit vectors (..., 3) of polar / azimuth angles in degrees (upper hemisphere)."""
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    return np.stack(np.broadcast_arrays(np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)), -1)


def delta_reading(beam_theta_deg: float, beam_phi_deg: float, power: float, theta_s_deg: np.ndarray,
                  phi_s_deg: np.ndarray, half_angle_deg: float, blur_deg: float) -> np.ndarray:
    """BSDF reading (1/sr) of rows seeing a delta beam of `power` (fraction of the incident power)."""
    wb = unit(beam_theta_deg, beam_phi_deg)
    wr = unit(theta_s_deg, phi_s_deg)
    ang = np.arccos(np.clip(wr @ wb, -1, 1))
    frac = response(ang, half_angle_deg, blur_deg)
    return frac * power / (cone_solid_angle(half_angle_deg) * np.cos(np.radians(theta_s_deg)))


def photon_reading(exit_dirs: np.ndarray, weights: np.ndarray, n_photons: int, theta_s_deg: np.ndarray,
                   phi_s_deg: np.ndarray, half_angle_deg: float, blur_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(BSDF, 1-sigma) of rows from exit photons: sum w response(psi) / (N Omega cos theta_s).

    `exit_dirs` (P, 3) unit vectors already folded into the rows' hemisphere (theta from the
    side's outward normal, +z).  The 1-sigma is sqrt(sum (w response)^2) / (N Omega cos theta_s).
    """
    from scipy.spatial import cKDTree
    val = np.zeros(theta_s_deg.size)
    err = np.zeros(theta_s_deg.size)
    if exit_dirs.shape[0] == 0 or theta_s_deg.size == 0:
        return val, err
    tree = cKDTree(exit_dirs)
    q = unit(theta_s_deg, phi_s_deg)
    reach = min(support_rad(half_angle_deg, blur_deg), np.pi)
    hits = tree.query_ball_point(q, 2 * np.sin(reach / 2))
    norm = n_photons * cone_solid_angle(half_angle_deg) * np.cos(np.radians(theta_s_deg))
    for j, idx in enumerate(hits):
        if idx:
            ang = np.arccos(np.clip(exit_dirs[idx] @ q[j], -1, 1))
            ww = weights[idx] * response(ang, half_angle_deg, blur_deg)
            val[j] = ww.sum() / norm[j]
            err[j] = np.sqrt(np.sum(ww**2)) / norm[j]
    return val, err


def _bilinear_periodic(grid: np.ndarray, theta_out_deg: np.ndarray, delta_deg: np.ndarray, t_: np.ndarray,
                       d_: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a (T, A) grid, theta clamped, azimuth periodic."""
    g = np.concatenate([grid, grid[:, :1]], axis=1)
    ext = np.concatenate([delta_deg, [360.0]])
    tc_ = np.clip(t_, theta_out_deg[0], theta_out_deg[-1])
    i1 = np.clip(np.searchsorted(theta_out_deg, tc_, side="right"), 1, theta_out_deg.size - 1)
    ft = (tc_ - theta_out_deg[i1 - 1]) / (theta_out_deg[i1] - theta_out_deg[i1 - 1])
    ia = np.clip(np.searchsorted(ext, d_, side="right"), 1, ext.size - 1)
    fa = (d_ - ext[ia - 1]) / (ext[ia] - ext[ia - 1])
    return ((g[i1 - 1, ia - 1] * (1 - fa) + g[i1 - 1, ia] * fa) * (1 - ft)
            + (g[i1, ia - 1] * (1 - fa) + g[i1, ia] * fa) * ft)


def centre_values(grid: np.ndarray, clip: bool = True) -> np.ndarray:
    """Point values at the cell centres from azimuth-cell AVERAGES (periodic axis 1; further axes, such
    as a Mueller matrix's, ride along).

    A cell of width d holding the average of a smooth f holds f(centre) + d^2 f'' / 24 + O(d^4)
    (Taylor expansion of the cell integral), so f(centre) = a_i - (a_{i-1} - 2 a_i + a_{i+1}) / 24
    to fourth order (the finite-volume average-to-point conversion).  Interpolating cell averages
    as point values instead biases a lobe's azimuthal maximum low by d^2 |f''| / 24: at 45 deg a
    5-deg azimuth cell is 3.5 deg of arc, and in-plane rows of oblique transmitted lobes read
    ~5 % low against an independent photon Monte Carlo (benchmarks/bench_forward_accuracy.py).
    The correction sums to zero around a ring, so a ring's total is kept; read as the weights of a
    comb of point sources at the centres, the corrected values carry the field's own azimuthal
    variance where the averages carry d^2 / 12 more (Sheppard's correction of binned moments): the
    plate's loop takes its first transmission this way (plate.deterministic, `_incidence`).
    `clip` (a reading): negative results (a correction larger than a faint cell next to a bright
    one) are clipped at 0; False (a source, a Mueller matrix): kept, linear and power-conserving.
    """
    lap = np.roll(grid, 1, axis=1) - 2.0 * grid + np.roll(grid, -1, axis=1)
    out = grid - lap / 24.0
    return np.maximum(out, 0.0) if clip else out


SUB_POINTS = 5          # per axis of a direct-grid cell: equal-solid-angle sub-points of the cone integral


@dataclass(frozen=True)
class DirectField:
    """The direct parts of a plate on the outside table's own cells, for `direct_reading`.

    theta_edges_deg / delta_edges_deg: the cells (azimuth relative to the incident beam's
    propagation azimuth); R: (S, P) BSDF of the direct reflection (S0); T: (S, P, c) Stokes
    vector of the first transmission inside the glass (per unit internal projected solid angle);
    eta = n0 / n; t_exit(theta_int_deg) -> (n, c): the row of the exit's Mueller matrix times
    what the traversal and the radiance law apply (Fresnel T row 0 x (n0/n)^2 x absorption).
    """

    theta_edges_deg: np.ndarray
    delta_edges_deg: np.ndarray
    R: np.ndarray
    T: np.ndarray
    eta: float
    t_exit: Any

    def __post_init__(self) -> None:
        tc = 0.5 * (self.theta_edges_deg[1:] + self.theta_edges_deg[:-1])
        pc = 0.5 * (self.delta_edges_deg[1:] + self.delta_edges_deg[:-1])
        object.__setattr__(self, "_centres", (tc, pc))
        object.__setattr__(self, "_slopes", {"R": _limited_slopes(self.R, tc, pc),
                                             "T": _limited_slopes(self.T, tc, pc)})

    def gather(self, side: str, pts: "_SubPoints", idx: np.ndarray) -> "_Gather":
        """Where the sub-points `idx` read this field's cells (the same for every field on these cells
        and index ratio, so `direct_reading` keeps it): each sub-point's cell and its offsets from the
        cell centre; T: each exit direction's Snell pre-image in the internal cells, and its sub-ring
        (the exit factor depends on the polar angle only)."""
        tc, pc = self._centres
        az = pts.az(idx)
        sr = th_int = None
        if side == "R":
            ring, th = pts.ring(idx), pts.sub_theta_deg[pts.sub_ring(idx)]
        else:
            th_int = np.degrees(np.arcsin(np.clip(np.sin(np.radians(pts.sub_theta_deg)) * self.eta, 0.0, 1.0)))
            ring_int = np.clip(np.searchsorted(self.theta_edges_deg, th_int, side="right") - 1, 0,
                               self.R.shape[0] - 1)
            sr = pts.sub_ring(idx)
            ring, th = ring_int[sr], th_int[sr]
        dt = th - tc[ring]
        dp = np.mod(pts.delta_deg(idx) - pc[az] + 180.0, 360.0) - 180.0
        return _Gather(ring * pc.size + az, dt, dp, sr, th_int)

    def values(self, side: str, g: "_Gather") -> np.ndarray:
        """The field at the gathered sub-points: cell average + limited slopes x offset from the cell
        centre (second order, conservative: the slope terms integrate to ~0 over a cell; minmod: no
        new extrema at a lobe's hard edge).  T: the internal Stokes vector times the exit's row."""
        F = self.R if side == "R" else self.T
        gt, gp = self._slopes[side]
        flat = lambda a: a.reshape((-1,) + a.shape[2:])            # noqa: E731  (cells first)
        Fc, gtc, gpc = flat(F)[g.cell], flat(gt)[g.cell], flat(gp)[g.cell]
        if side == "R":
            return np.maximum(Fc + gtc * g.dt + gpc * g.dp, 0.0)
        T = Fc + gtc * g.dt[:, None] + gpc * g.dp[:, None]
        return np.maximum(np.einsum("nc,nc->n", T, self.t_exit(g.th_int)[g.sub_ring]), 0.0)


@dataclass(frozen=True)
class _Gather:
    """Sub-points' cells (flat index ring x azimuths + azimuth), offsets from the cell centres (deg),
    and for T each sub-point's sub-ring and the internal polar angle of every sub-ring."""

    cell: np.ndarray
    dt: np.ndarray
    dp: np.ndarray
    sub_ring: np.ndarray | None
    th_int: np.ndarray | None


def _minmod(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.where(a * b > 0, np.sign(a) * np.minimum(np.abs(a), np.abs(b)), 0.0)


def _limited_slopes(F: np.ndarray, tc: np.ndarray, pc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d/dtheta, d/ddelta) per cell (per degree) of cell averages F (S, P[, c]): minmod of the one-sided
    differences to the neighbouring centres (azimuth periodic; zero at the polar ends)."""
    ext = (slice(None),) + (None,) * (F.ndim - 1)
    d = np.diff(F, axis=0) / np.diff(tc)[ext]
    gt = np.zeros_like(F)
    gt[1:-1] = _minmod(d[:-1], d[1:])
    step = np.mod(np.roll(pc, -1) - pc, 360.0)                              # centre to the next centre
    ext_p = (None, slice(None)) + (None,) * (F.ndim - 2)
    fwd = (np.roll(F, -1, axis=1) - F) / step[ext_p]
    gp = _minmod(np.roll(fwd, 1, axis=1), fwd)
    return gt, gp


@dataclass(frozen=True)
class _SubPoints:
    """Equal-solid-angle sub-points of every cell of a grid (k^2 per cell), laid out sub-ring by sub-ring,
    each sub-ring with the same increasing azimuths `ring_az_rad` (a sub-point's index is sub-ring x
    azimuths + azimuth).  Held per sub-ring and per azimuth only; a sub-point's own quantities (cell,
    weight, unit vector) are made for the indices asked: the default direct grid has ~3 M sub-points
    (1800 sub-rings x 1800 azimuths, ~200 MB as per-point arrays, 2.9 s to build in every process that
    reads a plate), of which the rows' cones meet a small part."""

    cos_sub: np.ndarray           # cos theta of each sub-ring
    sub_theta_rad: np.ndarray     # polar angle of each sub-ring
    ring_of_sub: np.ndarray       # the cell ring of each sub-ring
    ring_az_rad: np.ndarray       # the azimuths of every sub-ring, increasing, within one turn
    az_of_sub: np.ndarray         # the cell azimuth of each of those azimuths
    per_sr: np.ndarray            # (S, P) the solid angle of one sub-point of each cell (the cell's, shared equally)

    @property
    def size(self) -> int:
        return self.cos_sub.size * self.ring_az_rad.size

    @property
    def sub_theta_deg(self) -> np.ndarray:
        return np.degrees(self.sub_theta_rad)

    @property
    def max_weight_sr(self) -> float:
        return float(self.per_sr.max())

    def sub_ring(self, idx: np.ndarray) -> np.ndarray:
        return idx // self.ring_az_rad.size

    def ring(self, idx: np.ndarray) -> np.ndarray:
        return self.ring_of_sub[idx // self.ring_az_rad.size]

    def az(self, idx: np.ndarray) -> np.ndarray:
        return self.az_of_sub[idx % self.ring_az_rad.size]

    def cos_theta(self, idx: np.ndarray) -> np.ndarray:
        return self.cos_sub[idx // self.ring_az_rad.size]

    def delta_deg(self, idx: np.ndarray) -> np.ndarray:
        return np.degrees(self.ring_az_rad[idx % self.ring_az_rad.size])

    def weight_sr(self, idx: np.ndarray) -> np.ndarray:
        return self.per_sr[self.ring(idx), self.az(idx)]

    def vec(self, idx: np.ndarray) -> np.ndarray:
        """(n, 3) unit vectors of the sub-points `idx` (azimuth = delta)."""
        cz = self.cos_theta(idx)
        ph = self.ring_az_rad[idx % self.ring_az_rad.size]
        sz = np.sqrt(np.clip(1 - cz**2, 0, 1))
        return np.stack([sz * np.cos(ph), sz * np.sin(ph), cz], 1)


def _sub_points(theta_edges_deg: np.ndarray, delta_edges_deg: np.ndarray, k: int | None = None) -> _SubPoints:
    """k equal-solid-angle sub-rings per cell, and k x (cell width / narrowest width) azimuth sub-points
    (a wide cell is cut as finely as a narrow one); weights: the cell's solid angle shared equally."""
    k = int(k or SUB_POINTS)
    key = ("detector sub-points", theta_edges_deg.tobytes(), delta_edges_deg.tobytes(), k)
    return current_memory().get(key, lambda: _make_sub_points(theta_edges_deg, delta_edges_deg, k), "detector")


def _make_sub_points(theta_edges_deg: np.ndarray, delta_edges_deg: np.ndarray, k: int) -> _SubPoints:
    ct = np.cos(np.radians(theta_edges_deg))
    u = (np.arange(k) + 0.5) / k
    cos_sub = (ct[:-1, None] + u[None] * (ct[1:] - ct[:-1])[:, None]).ravel()          # (S k,) equal solid angle
    ring_sub = np.repeat(np.arange(ct.size - 1), k)
    dw = np.diff(delta_edges_deg)
    per = k * np.maximum(np.round(dw / dw.min()), 1).astype(int)                        # azimuth sub-points per cell
    az_sub = np.repeat(np.arange(dw.size), per)
    frac = (np.arange(az_sub.size) - np.repeat(np.cumsum(per) - per, per) + 0.5) / per[az_sub]
    ph_sub = np.radians(delta_edges_deg[:-1][az_sub] + frac * dw[az_sub])
    cell_sr = (ct[:-1] - ct[1:])[:, None] * np.radians(dw)[None, :]
    if np.any(np.diff(ph_sub) <= 0) or ph_sub[-1] - ph_sub[0] >= 2 * np.pi:
        raise ValueError("cone sub-points: the azimuth edges must increase within one turn")
    t_sub = np.arccos(np.clip(cos_sub, -1, 1))
    return _SubPoints(cos_sub, t_sub, ring_sub, ph_sub, az_sub, cell_sr / (k * per)[None, :])


def direct_reading(field: DirectField, side: np.ndarray, theta_s: np.ndarray, delta_s: np.ndarray,
                   det: Any) -> np.ndarray:
    """Readings (1/sr) of the rows from a DirectField: the cone integral of the cells themselves.

    f = sum_p w_p f(p) cos(theta_p) response(psi_p) / (Omega cos theta_s) over equal-solid-angle
    sub-points p of every cell (SUB_POINTS^2 per cell, weight = the cell's solid angle / their
    number): each cell counts with (an estimate of) its overlap with the cone, so a lobe narrower
    than the engine grid, a cone on the pole (cells of vanishing solid angle) and a grazing row
    (cos theta varying across the cone) are integrated, not interpolated.  Inside a cell the field
    is its average plus limited slopes (DirectField._reconstruct), and the cone's edge takes the
    inside fraction of each sub-point's patch, so a cell cut by the cone counts its inside part to
    second order (a 1-sigma 2-deg Gaussian lobe: 0.1 % at 45-70 deg; without the slopes 1-1.6 %).
    The cells must be smaller than the cone for this to be accurate.
    """
    out = np.zeros(theta_s.size)
    pts = _sub_points(field.theta_edges_deg, field.delta_edges_deg)
    for sd in ("R", "T"):
        sel = np.nonzero(side == sd)[0]
        if sel.size == 0:
            continue
        row, idx, inv, wt, gather, w_sr, cos_t = _reading_weights(pts, field, theta_s[sel], delta_s[sel], det, sd)
        if idx.size:
            val = field.values(sd, gather) * w_sr * cos_t
            out[sel] = np.bincount(row, weights=val[inv] * wt, minlength=sel.size)
    return out / (cone_solid_angle(det.detector_half_angle_deg) * np.cos(np.radians(theta_s)))


def _reading_weights(pts: _SubPoints, field: DirectField, theta_s: np.ndarray, delta_s: np.ndarray,
                     det: Any, side: str) -> tuple:
    """(row, idx, inv, response, gather, weight_sr, cos_theta) of the rows' cones on one side: the (row,
    sub-point idx[inv], response) triplets, idx the sub-points seen (sorted, each once), where they read
    the cells (`DirectField.gather`), and their solid angles and cos theta.  The same for every
    evaluation of a fit (rows, cells, index ratio and instrument fixed), so the memory owner keeps them."""
    key = ("detector weights", field.theta_edges_deg.tobytes(), field.delta_edges_deg.tobytes(), theta_s.tobytes(), delta_s.tobytes(),
           float(det.detector_half_angle_deg), float(det.blur_deg), pts.size, side,
           float(field.eta) if side == "T" else None)
    return current_memory().get(key, lambda: _make_reading_weights(pts, field, theta_s, delta_s, det, side), "detector")


def _make_reading_weights(pts: _SubPoints, field: DirectField, theta_s: np.ndarray, delta_s: np.ndarray,
                          det: Any, side: str) -> tuple:
    h = np.radians(det.detector_half_angle_deg)
    reach = min(support_rad(det.detector_half_angle_deg, det.blur_deg) + float(np.sqrt(pts.max_weight_sr)), np.pi)
    q = unit(theta_s, delta_s)
    row, col = _cone_members(pts, np.radians(theta_s), np.radians(delta_s), reach)
    met, at = _each_once(col, pts.size)             # the sub-points met (their vectors made once each)
    psi = np.arccos(np.clip(np.einsum("ij,ij->i", pts.vec(met)[at[col]], q[row]), -1, 1))
    if det.blur_deg > 0:
        wt = response(psi, det.detector_half_angle_deg, det.blur_deg)
    else:        # the cone's edge cuts a sub-point's patch: its inside fraction, to first order
        wt = np.clip((h - psi) / np.sqrt(pts.weight_sr(met))[at[col]] + 0.5, 0.0, 1.0)
    keep = wt > 0
    col = col[keep]
    idx, where = _each_once(col, pts.size)          # the sub-points read
    return row[keep], idx, where[col], wt[keep], field.gather(side, pts, idx), pts.weight_sr(idx), pts.cos_theta(idx)


def _each_once(col: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(idx, where): the distinct values of `col` (indices below `size`) in increasing order, and each
    one's place in idx (read at `col` only): np.unique(col, return_inverse=True) without its sort."""
    seen = np.zeros(size, bool)
    seen[col] = True
    idx = np.flatnonzero(seen)
    where = np.empty(size, np.intp)
    where[idx] = np.arange(idx.size)
    return idx, where


def _cone_members(pts: _SubPoints, theta_rad: np.ndarray, delta_rad: np.ndarray,
                  reach_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(row, col): the sub-points within the angular distance `reach_rad` of each row's direction, rows
    in order and each row's sub-points in increasing index (a sorted ball query), found sub-ring by
    sub-ring: a sub-ring at polar angle t meets the cap around (ts, ds) where |d - ds| <= w,
    cos w = (cos reach - cos t cos ts) / (sin t sin ts) (spherical law of cosines; the whole ring when
    that is <= -1, none when > 1), one run of the ring's increasing azimuths, or two across the
    turn's end.  Only the sub-rings with |t - ts| <= reach can meet it."""
    t, az = pts.sub_theta_rad, pts.ring_az_rad
    A = az.size
    r_idx, k_idx = np.nonzero(np.abs(t[None, :] - theta_rad[:, None]) <= reach_rad)   # row-major: rows, rings
    num = np.cos(reach_rad) - np.cos(t[k_idx]) * np.cos(theta_rad[r_idx])
    den = np.sin(t[k_idx]) * np.sin(theta_rad[r_idx])
    C = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.where(num <= 0, -np.inf, np.inf))
    w = np.arccos(np.clip(C, -1.0, 1.0))
    start = az[0] + np.mod(delta_rad[r_idx] - w - az[0], 2 * np.pi)        # the run's start within the turn
    stop = start + 2 * w
    end = az[0] + 2 * np.pi
    lo1 = np.searchsorted(az, start, "left")
    hi1 = np.searchsorted(az, np.minimum(stop, end), "right")
    hi2 = np.where(stop > end, np.searchsorted(az, stop - 2 * np.pi, "right"), 0)     # wrapped part: [0, hi2)
    whole, none = C <= -1.0, C > 1.0                 # every azimuth of the ring, or none
    lo1 = np.where(whole, 0, lo1)
    hi1 = np.where(whole, A, np.where(none, lo1, hi1))
    hi2 = np.where(whole | none, 0, np.minimum(hi2, lo1))
    starts = np.stack([np.zeros_like(lo1), lo1], 1).ravel() + np.repeat(k_idx * A, 2)
    lens = np.stack([hi2, np.maximum(hi1 - lo1, 0)], 1).ravel()
    total = int(lens.sum())
    first = np.cumsum(lens) - lens
    col = np.repeat(starts, lens) + (np.arange(total) - np.repeat(first, lens))
    row = np.repeat(np.repeat(r_idx, 2), lens)
    return row, col


def grid_reading(res: Any, side: np.ndarray, theta_s: np.ndarray, phi_s: np.ndarray, det: Any,
                 parts: tuple = ("diffuse", "deltas", "background")) -> np.ndarray:
    """Detector readings (1/sr) of the rows of one incidence from a deterministic result.

    `res`: a PlateResult (grid_R / grid_T on theta_out_deg x delta_deg, delta beams); `det`:
    anything with detector_half_angle_deg, cone_points, blur_deg, background_per_sr.  `parts`:
    what is read, the diffuse field (direct and loop parts), the delta beams, the stray light
    (the beam divergence reads the diffuse field at each incidence of its quadrature and the
    delta beams once, plate.readout.simulate_rows).
    """
    off = quadrature_offsets(det.detector_half_angle_deg, det.cone_points, det.blur_deg)
    th, ph = offset_directions(theta_s, phi_s, off)
    proj = projection_weights(theta_s, off)
    dl = np.mod(ph - (res.phi_i_deg + 180.0), 360.0)
    out = np.zeros(theta_s.size)
    direct = getattr(res, "direct", None)
    grids = (("R", res.grid_R), ("T", res.grid_T)) if direct is None else (("R", res.loop_R), ("T", res.loop_T))
    if "diffuse" not in parts:
        grids, direct = (), None
    if direct is not None:
        out += direct_reading(direct, side, theta_s, np.mod(phi_s - (res.phi_i_deg + 180.0), 360.0), det)
    for sd, grid in grids:
        sel = side == sd
        if sel.any():
            v = _bilinear_periodic(centre_values(grid), res.theta_out_deg, res.delta_deg, th[sel].ravel(),
                                   dl[sel].ravel())
            out[sel] += (v.reshape(-1, off.shape[0]) * proj[sel]).mean(axis=1)
    for sd, tdeg, ddeg, p in (res.deltas if "deltas" in parts else ()):
        sel = np.nonzero(side == sd)[0]
        if p != 0.0 and sel.size:
            out[sel] += delta_reading(tdeg, res.phi_i_deg + 180.0 + ddeg, p, theta_s[sel], phi_s[sel],
                                      det.detector_half_angle_deg, det.blur_deg)
    # FFT round-off can leave -1e-20 where the field is zero: a BSDF is never negative
    return np.maximum(out, 0.0) + (det.background_per_sr if "background" in parts else 0.0)
