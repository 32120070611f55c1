"""Method `ray`: geometric-optics ray tracing of the real relief with Embree (paper sec. 2.3).

Model and regime of validity
----------------------------
Geometric optics on the measured surface: valid when the relief's lateral features
(correlation length) and heights are much larger than the wavelength, so that each
facet reflects and refracts like a flat interface and diffraction is negligible
(Beckmann & Spizzichino 1963, ch. 2; Ogilvy 1991 sec. 4).  Polarisation is tracked
exactly within that model; interference between rays is ignored.

- Surface: the height map as a piecewise-linear periodic mesh (`relief_bsdf.surface.mesh`): a
  ray leaving the tile sideways re-enters from the opposite side (the tile is one
  period of an infinite surface), which removes the paper's boundary losses at
  grazing incidence.  Non-periodic maps are mirror-extended (see mesh.py).
- Interaction: at each hit the local facet is a flat interface between n1 (medium of
  the ray) and n2 (the other one).  Fresnel amplitudes (Born & Wolf 1.5.20-21, as in
  `optics.fresnel_amplitudes`), Snell refraction, total internal reflection (complex
  r_s, r_p with unit modulus: the phase retardance is kept in the Mueller matrix).
  Light transmitted into an absorbing medium (complex index, metals) is absorbed and
  counted as `lost`.
- Reflect or refract is chosen by Russian roulette with probability equal to the
  reflectance of the ray's *current* polarisation state, P_R = (M_R S)_0 / S_0, and the
  state is renormalised, S <- M S / P.  This is unbiased and keeps every ray weight at 1
  (Veach 1997 sec. 4.2 roulette; energy conserved ray by ray for lossless media).  For
  tables (`reconstruct`) the first interaction is split deterministically into both
  branches with weights P_R and 1 - P_R (option `first_hit_split`, default True): a flat
  surface is then exact, and the BRDF of a dielectric gets all N rays instead of ~4% of
  them.  Without polarisation (`polarized=False`) the unpolarised Fresnel reflectance is
  used at every bounce (the usual scalar approximation, which ignores that the first
  bounce polarises the light for the second).
- Polarisation: each ray carries a 4 x K real matrix (K = 1: one Stokes vector; K = 4: a
  Mueller matrix whose columns are the responses to the incident basis states) in the
  basis (s, p) with s a unit vector normal to the propagation direction k and p = s x k.
  At a hit the basis is rotated about k onto the facet's s = n x k / |n x k| (Stokes
  rotation by twice the angle between the old and new s), the facet's Mueller matrix
  (`optics.mueller_interface` form) is applied, and s is kept for the outgoing wave.
  With p = s x k for every wave this is Born & Wolf's sign convention, so a flat
  interface gives exactly `optics.mueller_interface`.
  Reference frames at the layer's entry and exit: s = z x k / |z x k| (k the physical
  propagation direction; along z, s = (-sin phi, cos phi, 0)), p = s x k.  The sign of s
  does not change a Stokes vector when p = s x k, so this is the frame of bsdf.py
  (s = z x w with w pointing away from the surface) for both incident and scattered light.
  For light from inside the table's frame is mirrored (z -> -z, bsdf.py) and its Stokes bases
  are the same formulas applied in that mirrored frame, as `microfacet` does: a mirror maps
  the physical basis (s, s x k) to (s', -p'), so the traced (physical) Mueller matrices are
  converted by M -> D M D, D = diag(1, 1, -1, -1).  `ReliefTracer.scatter` works in the
  physical frame throughout (s = z x k, p = s x k).
- Detector: every ray leaves the relief layer (above its highest or below its lowest
  point, moving away); exit directions are binned into the request's (theta_s, phi_s)
  cells, f = sum(weights) / (N * projected solid angle), which makes
  `BsdfTable.hemispherical()` equal to the power fractions of the incident beam (the beam
  irradiates the tile uniformly on the mean plane).  Rays that leave within
  `specular_tol_rad` of the mean plane's mirror / refraction direction (exactly flat
  facets) go to the delta parts `specular_R/T`.  Max bounces, absorption and numerical
  leaks (a ray found on the wrong side of the surface) are counted in `lost` with the
  detail in metadata; nothing is dropped silently.

Engine (speed, see benchmarks/bench_ray.py)
-------------------------------------------
One Embree BVH per relief (`ReliefTracer`, ~1.5 s at 1024^2 here), reused for every
wavelength, incidence and side (`reconstruct_with` reuses it across requests too).  Each
(side, wavelength, incidence) is one `parallel.map_tasks` task (`_incidence_task`), so local
processes and `--dask` spread them; a worker builds the BVH once (`parallel.worker_cached`,
keyed by a digest of the heights and mesh options) and traces with one thread, while in this
process (serial backend, or a single incidence) the task's chunks use every core.  Rays are
traced in fixed chunks of 65536 (own seed each: `parallel.task_rng(seed, side, wavelength,
theta, phi, chunk)`) whose sums are added in chunk order, so the numbers do not depend on the
backend, worker or thread count.  A task returns its finished float32 table rows, written
straight into the tables (`map_tasks(on_result=...)`): memory is the tables plus one
incidence's accumulators per worker.  Beam entry points are stratified over the tile and sorted by 32 x 32 px
blocks (BVH coherence).  Each bounce is a handful of float32 numpy passes over a structure
of arrays; finished rays are binned per chunk with np.bincount (cells by `_CellIndex`: float32
arithmetic and lookup tables, no float modulo or search for uniform grids).
Without polarisation and with real indices (`polarized=False`) a leaner loop runs
(`_trace_chunk_scalar`): the first interaction of the one-sided beam writes both branches
straight into one batch, finished rays go once into preallocated exit buffers, one gather per
bounce; on the issue-3 benchmark its numpy work is ~0.35x Embree's CPU time on the same
segments.  No BLAS call in the loop: a matrix product wakes OpenBLAS's thread pool, whose
spinning threads doubled the process CPU time.  Polarised tables (Mueller matrices, the
default) take the general loop and cost about 1.2-1.7x the scalar ones.

Options (request.options): polarized (True), max_bounces (100), first_hit_split (True),
specular_tol_rad (1e-5), fill_holes (None: NaN refused; True or a max gap in px), threads
(in this process; a pool worker uses one), backend (map_tasks backend, default as configured).
`request.samples` rays per (wavelength, incidence, side).  Tables store the unpolarised
BSDF (M00) whatever `request.polarization` says; the Mueller matrices carry the rest.
"""
from __future__ import annotations

import hashlib
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable, direction, projected_solid_angle
from relief_bsdf.errors import RequestError
from relief_bsdf.surface.mesh import TileMesh, build_tile_mesh
from relief_bsdf.core.optics import fresnel_amplitudes
from relief_bsdf.parallel.tasks import (default_workers, forget_worker_cached, in_worker, last_run, map_tasks, task_rng,
                        worker_cached)
from relief_bsdf.progress import silent
from relief_bsdf.surface.relief import Relief

F32 = np.float32
CHUNK = 1 << 16                # rays per independent chunk (its own seed, one thread at a time)

# exit states
ABOVE, BELOW, LOST_BOUNCES, LOST_LEAK, LOST_ABSORBED = 0, 1, 2, 3, 4
STATE_NAMES = {LOST_BOUNCES: "max_bounces", LOST_LEAK: "numerical_leak", LOST_ABSORBED: "absorbed"}


@dataclass
class ScatterResult:
    """What left the relief layer, one entry per input ray (see `ReliefTracer.scatter`).

    dirs: (N, 3) propagation directions on leaving (undefined where lost).
    weight: (N,) power weight (1 for lossless roulette; the input S0 when Stokes were given).
    above: (N,) True when the ray left upward (z > relief), False downward or lost.
    stokes: (N, 4) exit Stokes vectors (S0 = weight) in the frame s = z x k, p = s x k; None
        when traced without polarisation.
    lost: (N,) True when the ray did not leave (absorbed, max bounces, numerical leak).
    bounces: (N,) number of surface interactions.
    state: (N,) int8: 0 above, 1 below, 2 max bounces, 3 numerical leak, 4 absorbed.
    segments: total ray segments traced (Embree queries), for speed figures.
    """

    dirs: np.ndarray
    weight: np.ndarray
    above: np.ndarray
    stokes: np.ndarray | None
    lost: np.ndarray
    bounces: np.ndarray
    state: np.ndarray
    segments: int = 0


# ----------------------------------------------------------------------------- small vector helpers


def _normalize_rows(v: np.ndarray) -> np.ndarray:
    n = np.sqrt(np.einsum("ij,ij->i", v, v))
    return v / n[:, None]


def _frame_s(k: np.ndarray, phi_ref_rad: float | np.ndarray = 0.0) -> np.ndarray:
    """s = z x k / |z x k| for each row of k; (-sin phi, cos phi, 0) where k is along z."""
    s = np.empty(k.shape, dtype=k.dtype)
    s[:, 0] = -k[:, 1]
    s[:, 1] = k[:, 0]
    s[:, 2] = 0
    nrm = np.hypot(s[:, 0], s[:, 1])
    small = nrm < 1e-7
    nrm = np.where(small, 1, nrm)
    s[:, 0] /= nrm
    s[:, 1] /= nrm
    if small.any():
        phi = np.broadcast_to(np.asarray(phi_ref_rad, dtype=np.float64), (k.shape[0],))[small]
        s[small, 0] = -np.sin(phi)
        s[small, 1] = np.cos(phi)
    return s


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (n, 3) arrays by column multiply-adds (about 2x faster than einsum)."""
    out = a[:, 0] * b[:, 0]
    out += a[:, 1] * b[:, 1]
    out += a[:, 2] * b[:, 2]
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross is generic and slower)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    np.subtract(ay * bz, az * by, out=out[..., 0])
    np.subtract(az * bx, ax * bz, out=out[..., 1])
    np.subtract(ax * by, ay * bx, out=out[..., 2])
    return out


def _rotate_stokes(A: np.ndarray, s_old: np.ndarray, k: np.ndarray, s_new: np.ndarray) -> None:
    """Re-express the Stokes columns of A (4, K, n) from basis (s_old, s_old x k) to (s_new, s_new x k).

    With c = s_old . s_new, d = p_old . s_new (p_old = s_old x k) the field components
    transform as E_s' = c E_s + d E_p, E_p' = -d E_s + c E_p, hence
    S1' = (c^2 - d^2) S1 + 2cd S2, S2' = -2cd S1 + (c^2 - d^2) S2 (S0, S3 unchanged).
    """
    c = _rowdot(s_old, s_new)
    d = _rowdot(_cross(s_old, k), s_new)          # p_old . s_new, p_old = s_old x k
    c2, d2 = c * c, d * d
    r = c2 + d2
    r[r == 0] = 1
    cos2 = c2 - d2
    cos2 /= r
    sin2 = 2 * c * d
    sin2 /= r
    # in place, same float32 roundings as cos2 a1 + sin2 a2 and -sin2 a1 + cos2 a2
    a1 = A[1]
    a2 = A[2]
    new1 = cos2 * a1
    new1 += sin2 * a2
    a2 *= cos2
    a1 *= sin2
    a2 -= a1
    A[1] = new1


def interface_coefficients(cos_i: np.ndarray, n1: np.ndarray, n2: np.ndarray):
    """Mueller coefficients (a, b, c, d) of reflection and transmission at a flat facet.

    The Mueller matrix is [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]]
    (the form of `optics.mueller_interface`, Born & Wolf 1.5.20-21 and 1.5.27).  Real
    arithmetic in float32 for real indices (TIR handled: |r_s| = |r_p| = 1 with the phase
    difference in c, d); complex (float64) path through `optics.fresnel_amplitudes` when an
    index is complex.  Returns (R: (aR, bR, cR, dR), T: (aT, bT, cT, dT)); T is zero past the
    critical angle, and for an absorbing n2 it is the power entering (and absorbed in) n2.
    """
    if np.iscomplexobj(n1) or np.iscomplexobj(n2):
        ci = cos_i.astype(np.float64)
        rs, rp, ts, tp = fresnel_amplitudes(ci, n1, n2)
        A_, B_ = np.abs(rs) ** 2, np.abs(rp) ** 2
        C_ = rs * np.conj(rp)
        R = (0.5 * (A_ + B_), 0.5 * (A_ - B_), np.real(C_), np.imag(C_))
        # transmitted power, whatever happens to it later (absorbed for a metal)
        aT = 1.0 - R[0]
        bT = -R[1]
        R = tuple(np.asarray(x, dtype=F32) for x in R)
        z = np.zeros_like(R[0])
        return R, (aT.astype(F32), bT.astype(F32), z, z)
    ci = cos_i
    eta2 = (n1 / n2) ** 2
    sin2_t = eta2 * np.maximum(0, 1 - ci * ci)
    tir = sin2_t >= 1
    ct = np.sqrt(np.maximum(0, 1 - sin2_t))
    a = n1 * ci
    b = n2 * ct
    c = n2 * ci
    d = n1 * ct
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (a - b) / (a + b)
        rp = (c - d) / (c + d)
        rs2, rp2 = rs * rs, rp * rp
        aR = 0.5 * (rs2 + rp2)
        bR = 0.5 * (rs2 - rp2)
        cR = rs * rp
        dR = np.zeros_like(aR)
        # transmission: power factor (n2 ct)/(n1 ci) times t_s t_p
        ts = 2 * a / (a + b)
        tp = 2 * a / (c + d)
        scale = b / a
        cT = scale * ts * tp
    aT = 1 - aR
    bT = -bR
    if tir.any():
        # r = (X - iY)/(X + iY) = (X - iY)^2 / (X^2 + Y^2): unit modulus, phase only
        g = np.sqrt(np.maximum(0, sin2_t - 1))
        A1 = (n1 * ci)[tir] if np.ndim(n1) else n1 * ci[tir]
        B1 = (n2 * g)[tir] if np.ndim(n2) else n2 * g[tir]
        P1 = (n2 * ci)[tir] if np.ndim(n2) else n2 * ci[tir]
        Q1 = (n1 * g)[tir] if np.ndim(n1) else n1 * g[tir]
        den = (A1 * A1 + B1 * B1) * (P1 * P1 + Q1 * Q1)
        ab, pq = A1 * A1 - B1 * B1, P1 * P1 - Q1 * Q1
        reC = (ab * pq + 4 * A1 * B1 * P1 * Q1) / den
        imC = (2 * P1 * Q1 * ab - 2 * A1 * B1 * pq) / den
        aR[tir], bR[tir], cR[tir], dR[tir] = 1, 0, reC, imC
        aT[tir], bT[tir], cT[tir] = 0, 0, 0
    cT = np.where(tir | ~np.isfinite(cT), 0, cT).astype(F32)
    for arr in (aR, bR, cR):
        np.nan_to_num(arr, copy=False)
    return (aR, bR, cR, dR), (aT, bT, cT, np.zeros_like(aT))


def _apply_mueller(A: np.ndarray, a, b, c, d, inv_p) -> None:
    """A <- M A / p in place, M = [[a,b,0,0],[b,a,0,0],[0,0,c,d],[0,0,-d,c]] per ray."""
    a = a * inv_p
    b = b * inv_p
    c = c * inv_p
    d = d * inv_p
    r0, r1, r2, r3 = A[0], A[1], A[2], A[3]
    n0 = a * r0
    n0 += b * r1                   # a r0 + b r1
    r0 *= b
    r1 *= a
    r1 += r0                       # b r0 + a r1 (same roundings as the expression)
    r0[...] = n0
    n2 = c * r2
    n2 += d * r3                   # c r2 + d r3
    r3 *= c
    r2 *= d
    r3 -= r2                       # c r3 - d r2
    r2[...] = n2


# ----------------------------------------------------------------------------- the tracer


class ReliefTracer:
    """Periodic relief mesh in an Embree BVH, built once; traces ray batches through the layer.

    Thread-safe: `scatter` and `trace` may be called from several threads at once (Embree
    queries release the GIL; each call works on its own arrays).
    """

    def __init__(self, relief: Relief, max_bounces: int = 100, fill_holes: bool | int | None = None,
                 threads: int | None = None):
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        if int(max_bounces) < 1:
            raise RequestError(f"max_bounces must be >= 1, got {max_bounces}", "max_bounces")
        self.relief = relief
        self.max_bounces = int(max_bounces)
        self.threads = int(threads or default_workers())
        t0 = time.perf_counter()
        self.mesh: TileMesh = build_tile_mesh(relief, fill_holes)
        self.scene = rtcs.EmbreeScene()
        self._embree_mesh = TriangleMesh(self.scene, self.mesh.vertices, self.mesh.triangles)
        m = self.mesh
        self.Lx, self.Ly = (F32(m.period[0]), F32(m.period[1]))
        self.hx, self.hy = F32(m.period[0] / 2), F32(m.period[1] / 2)
        big = max(m.period[0] / 2, m.period[1] / 2, abs(m.z_min), abs(m.z_max), 1.0)
        # offset of a new ray origin from its hit point: 64 float32 ulps of the largest coordinate
        self.eps = F32(64 * big * 2.0**-24)
        self.z_top = F32(m.z_max + 8 * self.eps)
        self.z_bot = F32(m.z_min - 8 * self.eps)
        # commit the BVH now (first query) so timings of later calls are clean
        self.scene.run(np.array([[0, 0, self.z_top + 1]], F32), np.array([[0, 0, -1]], F32))
        self.build_s = time.perf_counter() - t0
        self.record_segments: list | None = None

    # ------------------------------------------------------------------ public API
    def scatter(self, dirs, n_above, n_below, rng, stokes=None, origins_xy=None,
                polarized: bool = True) -> ScatterResult:
        """Send rays with propagation directions `dirs` (N, 3) into the relief layer.

        dz < 0: from above (the medium of index n_above, the lit side); dz > 0: from below
        (n_below, the dielectric).  origins_xy (N, 2) in metres, relative to the tile (taken
        modulo the period); default uniform over the tile.  stokes (N, 4) in the frame
        s = z x k / |z x k|, p = s x k (along z: s = (0, 1, 0)); default unpolarised.  With
        polarized=False (and no stokes) the scalar approximation is used and stokes is None.
        Each ray has exactly one outcome (Russian roulette, weights stay at S0).
        """
        k = np.asarray(dirs, dtype=np.float64)
        if k.ndim != 2 or k.shape[1] != 3:
            raise RequestError(f"dirs must have shape (N, 3), got {k.shape}", "dirs")
        n = k.shape[0]
        k = _normalize_rows(k)
        if np.any(np.abs(k[:, 2]) < 1e-9) or not np.all(np.isfinite(k)):
            raise RequestError("ray directions must be finite and cross the mean plane (dz != 0)", "dirs")
        n_above, n_below = _check_index_pair(n_above, n_below)
        if n == 0:
            return ScatterResult(dirs=np.zeros((0, 3)), weight=np.zeros(0), above=np.zeros(0, bool),
                                 stokes=np.zeros((0, 4)) if (stokes is not None or polarized) else None,
                                 lost=np.zeros(0, bool), bounces=np.zeros(0, np.int64), state=np.zeros(0, np.int8))
        from_below = k[:, 2] > 0
        if from_below.any() and np.iscomplexobj(n_below) and np.imag(n_below) > 0:
            raise RequestError("rays cannot arrive from inside an absorbing medium", "dirs")
        if origins_xy is None:
            xy = rng.random((n, 2))
            xy[:, 0] = (xy[:, 0] - 0.5) * self.Lx
            xy[:, 1] = (xy[:, 1] - 0.5) * self.Ly
        else:
            xy = np.asarray(origins_xy, dtype=np.float64) / self.mesh.unit_m
            if xy.shape != (n, 2):
                raise RequestError(f"origins_xy must have shape ({n}, 2), got {xy.shape}", "origins_xy")
            xy = np.mod(xy + [self.hx, self.hy], [self.Lx, self.Ly]) - [self.hx, self.hy]
        K = 0
        weight = np.ones(n)
        if stokes is not None:
            st = np.asarray(stokes, dtype=np.float64)
            if st.shape != (n, 4):
                raise RequestError(f"stokes must have shape ({n}, 4), got {st.shape}", "stokes")
            if np.any(~np.isfinite(st)) or np.any(st[:, 0] < 0):
                raise RequestError("Stokes vectors must be finite with S0 >= 0", "stokes")
            weight = st[:, 0].copy()
            zero = weight == 0                       # e.g. absorbed to nothing: traced, weight 0
            if zero.any():
                st = st.copy()
                st[zero] = (1.0, 0.0, 0.0, 0.0)
            K = 1
        elif polarized:
            st = np.zeros((n, 4))
            st[:, 0] = 1
            K = 1
        # coherence: sort by 32 x 32 px blocks of the entry point
        order = _block_order(xy, self.hx, self.hy)
        o = np.empty((n, 3), F32)
        o[:, :2] = xy[order]
        o[:, 2] = np.where(from_below[order], self.z_bot, self.z_top)
        kk = k[order].astype(F32)
        A = None
        if K:
            A = (st[order] / st[order, :1]).T.astype(F32)[:, None, :]  # (4, 1, n)
        seeds = rng.integers(0, 2**63 - 1, size=max(1, -(-n // CHUNK)))
        res = self._run_chunks(o, kk, from_below[order], A, seeds, n_above, n_below, split_first=False)
        out_k, out_A, out_w, out_state, out_b, segs = res
        inv = np.empty(n, np.int64)
        inv[order] = np.arange(n)
        state = out_state[inv]
        lost = state >= 2
        stokes_out = None
        if K:
            stokes_out = out_A[:, 0, :].T[inv].astype(np.float64) * weight[:, None]
        return ScatterResult(dirs=out_k[inv].astype(np.float64), weight=weight * out_w[inv],
                             above=state == ABOVE, stokes=stokes_out, lost=lost,
                             bounces=out_b[inv].astype(np.int64), state=state, segments=segs)

    # ------------------------------------------------------------------ chunk driver
    def _run_chunks(self, o, k, below, A, seeds, n_above, n_below, split_first, reduce=None):
        """Trace all rays in fixed-size chunks over a thread pool; deterministic for given seeds.

        Without `reduce`, returns concatenated raw outputs; with it, returns the list of
        reduce(chunk_index, raw_output) results in chunk order.
        """
        n = o.shape[0]
        bounds = [(i, min(n, i + CHUNK)) for i in range(0, n, CHUNK)]

        def job(ci):
            lo, hi = bounds[ci]
            rng = np.random.Generator(np.random.PCG64(int(seeds[ci])))
            sub_A = None if A is None else np.ascontiguousarray(A[:, :, lo:hi])
            out = self._trace_chunk(o[lo:hi].copy(), k[lo:hi].copy(), below[lo:hi].copy(), sub_A, rng,
                                    n_above, n_below, split_first)
            return reduce(ci, out) if reduce else out

        if self.threads > 1 and len(bounds) > 1:
            with ThreadPoolExecutor(max_workers=self.threads) as ex:
                outs = list(ex.map(job, range(len(bounds))))
        else:
            outs = [job(ci) for ci in range(len(bounds))]
        if reduce:
            return outs
        lo_of = [b[0] for b in bounds]
        ks, As, ws, sts, nbs = [], [], [], [], []
        for ci, ex in enumerate(outs):
            k_, A_, w_, st_, nb_ = ex.ordered()
            ks.append(k_)
            As.append(A_)
            ws.append(w_)
            sts.append(st_)
            nbs.append(nb_)
        del lo_of
        segs = sum(ex.segments for ex in outs)
        A_all = None if A is None else np.concatenate(As, axis=2)
        return (np.concatenate(ks), A_all, np.concatenate(ws), np.concatenate(sts), np.concatenate(nbs), segs)

    def _trace_chunk(self, o, k, below, A, rng, n_above, n_below, split_first, s_init=None, phi_exit_rad=0.0):
        """Trace one batch until every ray has left the layer or is lost.

        o, k: (n, 3) float32 origins and unit propagation directions; below: (n,) bool, True
        for rays in the lower medium; A: (4, K, n) float32 polarisation state (column 0 has
        S0 = 1) or None.  With split_first each ray's first interaction yields two rays
        (reflected: output index i, transmitted: i + n) with weights P_R and 1 - P_R.
        Returns (k_out (m, 3), A_out (4, K, m) or None, weight (m,), state (m,) int8,
        bounces (m,) int16, segments) with m = n or 2 n; rays' Stokes columns are returned in
        their exit frames (s = z x k).
        """
        complex_idx = np.iscomplexobj(n_above) or np.iscomplexobj(n_below)
        if A is None and not complex_idx:
            return self._trace_chunk_scalar(o, k, below, rng, float(n_above), float(n_below), split_first)
        n0 = o.shape[0]
        K = 0 if A is None else A.shape[1]
        exits: list = []
        st = _RayState(o=o, k=k, below=below, ids=np.arange(n0, dtype=np.int64), w=np.ones(n0, F32),
                       nb=np.zeros(n0, np.int16), pending=np.full(n0, bool(split_first)), A=A, s=None)
        if K:
            st.s = _frame_s(k) if s_init is None else np.ascontiguousarray(
                np.broadcast_to(np.asarray(s_init, F32), k.shape))
        complex_idx = np.iscomplexobj(n_above) or np.iscomplexobj(n_below)
        absorbing_below = complex_idx and np.imag(n_below) > 0
        hx, hy = self.hx, self.hy
        z_top, z_bot = self.z_top, self.z_bot
        segments = 0
        scene = self.scene

        def finish(rows: _RayState, state):
            if rows.ids.size:
                if K and state <= BELOW:
                    # exit frame s = z x k; exactly along z (flat relief at normal incidence) the
                    # frame of the specular azimuth phi_exit_rad (bsdf.py: s from the azimuth)
                    _rotate_stokes(rows.A, rows.s, rows.k, _frame_s(rows.k, phi_exit_rad))
                exits.append((rows, np.full(rows.ids.size, state, np.int8)))

        while st.ids.size:
            n = st.ids.size
            segments += n
            o, k = st.o, st.k
            kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                tx = (np.copysign(hx, kx) - o[:, 0]) / kx
                ty = (np.copysign(hy, ky) - o[:, 1]) / ky
                tz = (np.where(kz > 0, z_top, z_bot) - o[:, 2]) / kz
            t_lat = np.fmin(tx, ty)
            tfar = np.fmin(t_lat, tz)
            np.maximum(tfar, 0, out=tfar)
            if self.record_segments is not None:      # benchmark hook: replay the same batches
                self.record_segments.append((o.copy(), k.copy(), tfar.copy()))
            res = scene.run(o, k, dists=tfar, output=1)
            hit = res["primID"] >= 0
            n_hit = int(np.count_nonzero(hit))
            parts = []
            if n_hit < n:
                miss = ~hit
                out_slab = miss & ~(t_lat < tz)
                if out_slab.any():
                    up = kz > 0
                    ok_up = out_slab & up & ~st.below
                    ok_dn = out_slab & ~up & st.below
                    finish(st.take(np.flatnonzero(ok_up), exit_only=True), ABOVE)
                    finish(st.take(np.flatnonzero(ok_dn), exit_only=True), BELOW)
                    bad = out_slab & ~(ok_up | ok_dn)
                    if bad.any():
                        finish(st.take(np.flatnonzero(bad), exit_only=True), LOST_LEAK)
                wrap = np.flatnonzero(miss & ~out_slab)
                if wrap.size:
                    wr = st.take(wrap)
                    t = t_lat[wrap]
                    ow = wr.o + t[:, None] * wr.k
                    bx = tx[wrap] <= t
                    by = ty[wrap] <= t
                    ow[bx, 0] = -np.copysign(hx, wr.k[bx, 0])
                    ow[by, 1] = -np.copysign(hy, wr.k[by, 1])
                    wr.o = ow
                    parts.append(wr)
            if n_hit:
                if n_hit == n:
                    h = st
                    ng, t_hit = res["Ng"], res["tfar"]
                else:
                    hi = np.flatnonzero(hit)
                    h = st.take(hi)
                    ng, t_hit = np.take(res["Ng"], hi, axis=0), res["tfar"][hi]
                parts = self._interact(h, ng, t_hit, rng, n_above, n_below, complex_idx, absorbing_below,
                                       n0, finish) + parts
            if not parts:
                break
            st = parts[0] if len(parts) == 1 else _RayState.concat(parts)
        if not exits:
            z = np.zeros(0, np.int64)
            return _Exits(ids=z, k=np.zeros((0, 3), F32), A=np.zeros((4, K, 0), F32) if K else None,
                          w=np.zeros(0, F32), state=np.zeros(0, np.int8), nb=np.zeros(0, np.int16),
                          segments=segments, n_paths=n0, m=2 * n0 if split_first else n0)
        rows = _RayState.concat([e[0] for e in exits]) if len(exits) > 1 else exits[0][0]
        state = np.concatenate([e[1] for e in exits])
        return _Exits(ids=rows.ids, k=rows.k, A=rows.A, w=rows.w, state=state, nb=rows.nb, segments=segments,
                      n_paths=n0, m=2 * n0 if split_first else n0)

    def _interact(self, h, ng, t_hit, rng, n_above, n_below, complex_idx, absorbing_below, n0, finish):
        """One surface interaction for every ray of `h` (all hit); returns the continuing rays."""
        K = 0 if h.A is None else h.A.shape[1]
        eps = self.eps
        k = h.k
        bh = h.below
        # unit facet normal oriented up (+z), then toward the incident side
        nrm = np.sqrt(_rowdot(ng, ng))
        np.copysign(nrm, ng[:, 2], out=nrm)
        dot = _rowdot(k, ng) / nrm
        # a ray above the surface must hit it from above (dot < 0), a ray below from below
        leak = (dot > 0) != bh
        if leak.any():
            finish(h.take(np.flatnonzero(leak), exit_only=True), LOST_LEAK)
            good = np.flatnonzero(~leak)
            h = h.take(good)
            ng, t_hit, nrm, dot, k, bh = ng[good], t_hit[good], nrm[good], dot[good], h.k, h.below
        sgn = np.where(bh, F32(-1), F32(1)) / nrm               # nf = sgn * ng: unit, incident side
        nf = ng * sgn[:, None]
        ci = np.abs(dot)
        h.nb = h.nb + np.int16(1)
        if complex_idx:
            n1 = np.where(bh, n_below, n_above).astype(np.complex128)
            n2 = np.where(bh, n_above, n_below).astype(np.complex128)
            eta = np.real(n1 / n2).astype(F32)
        else:
            n1 = np.where(bh, F32(n_below), F32(n_above))
            n2 = np.where(bh, F32(n_above), F32(n_below))
            eta = n1 / n2
        sin2t = eta * eta * (1 - ci * ci)
        tir = sin2t >= 1
        ct = np.sqrt(np.maximum(0, 1 - sin2t))
        if K:
            (aR, bR, cR, dR), (aT, bT, cT, dT) = interface_coefficients(ci, n1, n2)
            s_new = _cross(nf, k)
            sn = np.sqrt(_rowdot(s_new, s_new))
            degenerate = sn < 1e-6
            s_new /= np.where(degenerate, 1, sn)[:, None]
            if degenerate.any():
                s_new[degenerate] = h.s[degenerate]
            _rotate_stokes(h.A, h.s, k, s_new)
            pR = np.clip(aR + bR * h.A[1, 0], 0, 1).astype(F32)
        else:
            pR = _reflectance_unpolarized(ci, n1, n2, ct) if not complex_idx else \
                interface_coefficients(ci, n1, n2)[0][0].astype(F32)
            pR[tir] = 1
        absorbed_T = (~bh) if absorbing_below else None
        split = h.pending
        n_split = int(np.count_nonzero(split))
        all_split = n_split == ci.size
        if all_split:
            refl = None                                   # every ray keeps the reflected branch
        else:
            refl = rng.random(ci.size, dtype=F32) < pR
            if n_split:
                refl |= split
        p_hit = k * t_hit[:, None]
        p_hit += h.o
        parts = []
        # transmitted copies of split rays (the reflected branch keeps the ray)
        if n_split:
            j_ok = ~tir & (pR < 1)
            if not all_split:
                j_ok &= split
            j = np.flatnonzero(j_ok)
            if j.size:
                full = j.size == ci.size
                tr = _RayState(o=None, k=None, below=~bh if full else ~bh[j], ids=(h.ids if full else h.ids[j]) + n0,
                               w=(h.w if full else h.w[j]) * (1 - (pR if full else pR[j])),
                               nb=h.nb if full else h.nb[j],
                               pending=np.zeros(j.size, bool), A=None, s=None)
                etaj, cij, ctj = (eta, ci, ct) if full else (eta[j], ci[j], ct[j])
                kj, nfj = (k, nf) if full else (np.take(k, j, axis=0), np.take(nf, j, axis=0))
                kt = kj * etaj[:, None]
                kt += (etaj * cij - ctj)[:, None] * nfj
                kt /= np.sqrt(_rowdot(kt, kt))[:, None]
                tr.o = (p_hit if full else np.take(p_hit, j, axis=0)) - eps * nfj
                tr.k = kt
                if K:
                    tr.A = np.take(h.A, j, axis=2)
                    pj = pR if full else pR[j]
                    sel = (lambda x: x) if full else (lambda x: x[j])
                    _apply_mueller(tr.A, sel(aT), sel(bT), sel(cT), sel(dT), 1 / np.maximum(1 - pj, F32(1e-30)))
                    tr.s = s_new if full else s_new[j]
                if absorbed_T is not None and absorbed_T[j].any():
                    a_ = absorbed_T[j]
                    finish(tr.take(np.flatnonzero(a_), exit_only=True), LOST_ABSORBED)
                    tr = tr.take(np.flatnonzero(~a_))
                parts.append(tr)
            h.w = h.w * pR if all_split else np.where(split, h.w * pR, h.w)
        # the ray itself: reflect (norm preserved) or refract (renormalised)
        if all_split:
            knew = nf * (2 * ci)[:, None]
            knew += k
            h.o = p_hit + eps * nf
            h.pending = np.zeros(ci.size, bool)
        else:
            a = np.where(refl, F32(1), eta)
            b = np.where(refl, 2 * ci, eta * ci - ct)
            knew = a[:, None] * k + b[:, None] * nf
            knew /= np.sqrt(_rowdot(knew, knew))[:, None]
            h.o = p_hit + (np.where(refl, eps, -eps))[:, None] * nf
            h.below = bh ^ ~refl
            if n_split:
                h.pending = np.zeros(ci.size, bool)
        h.k = knew
        if K:
            if all_split:
                _apply_mueller(h.A, aR, bR, cR, dR, 1 / np.maximum(pR, F32(1e-30)))
            else:
                pc = np.where(refl, pR, 1 - pR)
                _apply_mueller(h.A, np.where(refl, aR, aT), np.where(refl, bR, bT), np.where(refl, cR, cT),
                               np.where(refl, dR, dT), 1 / np.maximum(pc, F32(1e-30)))
            h.s = s_new
        end = None
        if absorbed_T is not None and refl is not None:
            end = ~refl & absorbed_T
            if end.any():
                finish(h.take(np.flatnonzero(end), exit_only=True), LOST_ABSORBED)
        over = h.nb >= self.max_bounces
        if over.any():
            sel = over if end is None else over & ~end
            finish(h.take(np.flatnonzero(sel), exit_only=True), LOST_BOUNCES)
            end = over if end is None else end | over
        if end is not None and end.any():
            h = h.take(np.flatnonzero(~end))
        return [h] + parts

    # ------------------------------------------------------------------ scalar fast path
    def _trace_chunk_scalar(self, o, k, below, rng, n_above: float, n_below: float, split_first: bool) -> "_Exits":
        with np.errstate(divide="ignore", invalid="ignore"):     # once per chunk (errstate is not free)
            return self._trace_chunk_scalar_(o, k, below, rng, n_above, n_below, split_first)

    def _trace_chunk_scalar_(self, o, k, below, rng, n_above: float, n_below: float, split_first: bool) -> "_Exits":
        """`_trace_chunk` without polarisation and with real indices: the same physics, leaner.

        Same model as the general path (unpolarised Fresnel reflectance, Snell, TIR, periodic
        wrap, deterministic first-hit split, roulette afterwards), organised for speed: finished
        rays are written once into preallocated exit buffers (no per-bounce lists), the rays in
        flight are gathered once per bounce (the ones that hit), and the interaction works on
        contiguous float32 component arrays (no (n, 3) einsum or temporaries of the general path).
        The first interaction of every ray (split) is done in its own pass before the roulette
        bounces, so the random draws are one `rng.random` per roulette bounce, in a fixed order.
        """
        n0 = o.shape[0]
        m = 2 * n0 if split_first else n0
        ex = _ExitBuffer(m)
        hx, hy, eps = self.hx, self.hy, self.eps
        na, nbl = F32(n_above), F32(n_below)
        eta_dn, eta_up = na / nbl, nbl / na          # n1 / n2 for a ray above / below the surface
        scene = self.scene
        max_b = self.max_bounces
        rec = self.record_segments
        bnd_hi, bnd_c = self._slab_bounds(m)
        segments = 0
        # (o, k, below, w, nb, ids) of the rays in flight
        cur = (o, k, below, np.ones(n0, F32), np.zeros(n0, np.int16), np.arange(n0, dtype=np.int64))
        nxt = []                                      # rays made by the first interaction (split)
        pending = split_first
        while True:
            o, k, below, w, nb, ids = cur
            n = ids.size
            if n == 0:
                if pending:
                    pending = False
                    if not nxt:
                        break
                    cur = nxt[0] if len(nxt) == 1 else tuple(np.concatenate(a) for a in zip(*nxt))
                    nxt = []
                    continue
                break
            segments += n
            # distances to the tile's sides and the slab's faces along k, on the flat (3 n) views:
            # ((+-hx, +-hy, +-zh) by the sign of k - (o - (0, 0, zc))) / k, zc, zh: slab centre, half height
            m3 = 3 * n
            T = np.copysign(bnd_hi[:m3], k.reshape(-1))
            T -= o.reshape(-1)
            T += bnd_c[:m3]
            T /= k.reshape(-1)
            T = T.reshape(n, 3)
            tx, ty, tz = T[:, 0], T[:, 1], T[:, 2]
            t_lat = np.fmin(tx, ty)
            tfar = np.fmin(t_lat, tz)
            np.maximum(tfar, 0, out=tfar)
            if rec is not None:                       # benchmark hook: replay the same batches
                rec.append((o.copy(), k.copy(), tfar.copy()))
            res = scene.run(o, k, dists=tfar, output=1)
            hit = res["primID"] >= 0
            nh = int(np.count_nonzero(hit))
            hi = np.flatnonzero(hit) if 0 < nh < n else None
            wrapped = None
            if nh < n:
                side_exit = ~(t_lat < tz)                 # a miss that reached the slab face, not a tile side
                if nh == 0 and side_exit.all():
                    # every ray left the slab (the usual end of a roulette phase): no gathers
                    upm = k[:, 2] > 0
                    st = np.where(upm, np.int8(ABOVE), np.int8(BELOW))
                    bad = upm == below
                    if bad.any():
                        st[bad] = LOST_LEAK
                    ex.put_all(k, w, nb, ids, st)
                else:
                    mi = np.flatnonzero(~hit)
                    lat = ~side_exit[mi]
                    if lat.any():
                        wi = mi[lat]
                        mi = mi[~lat]
                        t = t_lat[wi]
                        ow = np.take(o, wi, axis=0)
                        kw_ = np.take(k, wi, axis=0)
                        ow += t[:, None] * kw_
                        bx = tx[wi] <= t
                        by = ty[wi] <= t
                        ow[bx, 0] = -np.copysign(hx, kw_[bx, 0])
                        ow[by, 1] = -np.copysign(hy, kw_[by, 1])
                        wrapped = (ow, kw_, below[wi], w[wi], nb[wi], ids[wi])
                    if mi.size:
                        # left the slab: upward from above or downward from below; else a leak
                        upm = np.take(k[:, 2], mi) > 0
                        st = np.where(upm, np.int8(ABOVE), np.int8(BELOW))
                        bad = upm == below[mi]
                        if bad.any():
                            st[bad] = LOST_LEAK
                        ex.put(k, mi, w, nb, ids, st)
            parts = []
            if nh:
                if nh == n:
                    ng, th = res["Ng"], res["tfar"]
                else:
                    o, k, below, w, nb, ids = (np.take(o, hi, axis=0), np.take(k, hi, axis=0), below[hi], w[hi],
                                               nb[hi], ids[hi])
                    ng, th = np.take(res["Ng"], hi, axis=0), res["tfar"][hi]
                kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
                gx, gy, gz = ng[:, 0], ng[:, 1], ng[:, 2]
                # unit facet normal oriented up (+z): g / |g| with the sign of g_z
                inv = gx * gx
                inv += gy * gy
                inv += gz * gz
                np.sqrt(inv, out=inv)
                np.divide(F32(1), inv, out=inv)
                np.copysign(inv, gz, out=inv)
                dot = kx * gx
                dot += ky * gy
                dot += kz * gz
                dot *= inv                                # k . n_up
                leak = (dot > 0) != below                 # above must hit from above, below from below
                if leak.any():
                    li = np.flatnonzero(leak)
                    ex.put(k, li, w, nb, ids, np.full(li.size, LOST_LEAK, np.int8))
                    g = np.flatnonzero(~leak)
                    o, k, below, w, nb, ids = (np.take(o, g, axis=0), np.take(k, g, axis=0), below[g], w[g],
                                               nb[g], ids[g])
                    ng, th, inv, dot = np.take(ng, g, axis=0), th[g], inv[g], dot[g]
                    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
                    gx, gy, gz = ng[:, 0], ng[:, 1], ng[:, 2]
                nh = ids.size
                if nh:
                    one_side = pending and max_b > 1 and (below.all() if below[0] else not below.any())
                    if one_side:
                        parts = [self._scalar_split(o, k, bool(below[0]), w, nb, ids, ng, th, inv, dot,
                                                    eta_up if below[0] else eta_dn, eps, n0)]
                    else:
                        parts = self._scalar_interact(o, k, below, w, nb, ids, gx, gy, gz, th, inv, dot, eta_dn,
                                                      eta_up, eps, pending, rng, n0, ex, max_b)
            if pending:
                # the first interaction's outputs wait for the roulette phase; the wrapped stay pending
                nxt.extend(parts)
                cur = wrapped if wrapped is not None else _EMPTY_SCALAR
            else:
                if wrapped is not None:
                    parts.append(wrapped)
                cur = parts[0] if len(parts) == 1 else (tuple(np.concatenate(a) for a in zip(*parts)) if parts
                                                         else _EMPTY_SCALAR)
        return ex.exits(segments, n0, m)

    def _slab_bounds(self, m: int):
        """Flat float32 arrays (hx, hy, zh) and (0, 0, zc) repeated m times (cached per size)."""
        cache = self.__dict__.setdefault("_bounds_cache", {})
        if m not in cache:
            zh = (self.z_top - self.z_bot) / F32(2)
            zc = (self.z_top + self.z_bot) / F32(2)
            cache[m] = (np.tile(np.array([self.hx, self.hy, zh], F32), m), np.tile(np.array([0, 0, zc], F32), m))
        return cache[m]

    @staticmethod
    def _scalar_split(o, k, from_below: bool, w, nb, ids, ng, th, inv, dot, eta, eps, n0):
        """First interaction of rays that all arrive from one side: both branches, one output batch.

        The same physics as `_scalar_interact(pending=True)` (unpolarised Fresnel reflectance, Snell,
        TIR) with the medium pair fixed (eta = n1 / n2 a scalar), written straight into one
        (reflected rows, then transmitted rows) batch: reflected ray i keeps id i and weight w pR,
        its transmitted copy gets id i + n0 and weight w (1 - pR); copies with pR = 1 (TIR) are dropped.
        Needs max_bounces > 1 (the caller checks).
        """
        nh = ids.size
        eta = F32(eta)
        # unit normal on the incident side: nf = sigma g / |g| (inv carries 1/|g| with the sign of g_z)
        s = inv if not from_below else np.negative(inv, out=inv)
        ci = np.abs(dot)
        ct = ci * ci
        np.subtract(F32(1), ct, out=ct)
        ct *= eta * eta                                  # sin^2 t
        tir = ct >= 1
        np.subtract(F32(1), ct, out=ct)
        np.maximum(ct, 0, out=ct)
        np.sqrt(ct, out=ct)                              # cos t
        eci = eta * ci
        ect = eta * ct
        rs = eci - ct
        rs /= eci + ct
        rp = ci - ect
        rp /= ci + ect
        rs *= rs
        rp *= rp
        rs += rp
        rs *= F32(0.5)
        pR = np.fmin(rs, F32(1), out=rs)                 # 0/0 (grazing) -> NaN -> 1
        pR[tir] = 1
        bt = np.subtract(eci, ct, out=eci)               # k_t = eta k + (eta ci - ct) nf
        two_ci = np.add(ci, ci, out=ci)                  # k_r = k + 2 ci nf
        O2 = np.empty((2 * nh, 3), F32)
        K2 = np.empty((2 * nh, 3), F32)
        tmp = np.empty(nh, F32)
        for c in range(3):
            nfc = ng[:, c] * s
            kc = k[:, c]
            pc = kc * th
            pc += o[:, c]
            np.multiply(nfc, eps, out=tmp)
            np.add(pc, tmp, out=O2[:nh, c])
            np.subtract(pc, tmp, out=O2[nh:, c])
            np.multiply(two_ci, nfc, out=tmp)
            np.add(kc, tmp, out=K2[:nh, c])
            np.multiply(bt, nfc, out=nfc)
            np.multiply(kc, eta, out=tmp)
            np.add(tmp, nfc, out=K2[nh:, c])
        kt = K2[nh:]
        nr = kt[:, 0] * kt[:, 0]
        nr += kt[:, 1] * kt[:, 1]
        nr += kt[:, 2] * kt[:, 2]
        np.sqrt(nr, out=nr)
        for c in range(3):
            kt[:, c] /= nr
        W2 = np.empty(2 * nh, F32)
        np.multiply(w, pR, out=W2[:nh])
        np.subtract(F32(1), pR, out=pR)
        np.multiply(w, pR, out=W2[nh:])
        NB2 = np.empty(2 * nh, np.int16)
        np.add(nb, np.int16(1), out=NB2[:nh])
        NB2[nh:] = NB2[:nh]
        I2 = np.empty(2 * nh, np.int64)
        I2[:nh] = ids
        np.add(ids, n0, out=I2[nh:])
        B2 = np.empty(2 * nh, bool)
        B2[:nh] = from_below
        B2[nh:] = not from_below
        if tir.any():                                    # no transmitted copy past the critical angle
            keep = np.concatenate([np.ones(nh, bool), ~tir])
            g = np.flatnonzero(keep)
            return np.take(O2, g, axis=0), np.take(K2, g, axis=0), B2[g], W2[g], NB2[g], I2[g]
        return O2, K2, B2, W2, NB2, I2

    @staticmethod
    def _scalar_interact(o, k, below, w, nb, ids, gx, gy, gz, th, inv, dot, eta_dn, eta_up, eps, pending, rng, n0,
                         ex, max_b):
        """One unpolarised interaction for rays that all hit (see `_trace_chunk_scalar`)."""
        nh = ids.size
        kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
        # nf = unit normal on the incident side: n_up for a ray above, -n_up below
        s = np.where(below, -inv, inv)
        nfx, nfy, nfz = gx * s, gy * s, gz * s
        ci = np.abs(dot)
        eta = np.where(below, eta_up, eta_dn)
        # Snell: sin^2 t = eta^2 (1 - cos^2 i); TIR when >= 1
        sin2t = ci * ci
        np.subtract(F32(1), sin2t, out=sin2t)
        sin2t *= eta * eta
        tir = sin2t >= 1
        ct = np.subtract(F32(1), sin2t, out=sin2t)
        np.maximum(ct, 0, out=ct)
        np.sqrt(ct, out=ct)
        # unpolarised Fresnel reflectance (Born & Wolf 1.5.20-21 divided through by n1):
        # r_s = (eta ci - ct) / (eta ci + ct), r_p = (ci - eta ct) / (ci + eta ct)
        eci = eta * ci
        ect = eta * ct
        rs = (eci - ct) / (eci + ct)                  # 0/0 (grazing) -> NaN -> reflectance 1 below
        rp = (ci - ect) / (ci + ect)
        rs *= rs
        rp *= rp
        rs += rp
        pR = np.multiply(rs, F32(0.5), out=rs)
        np.nan_to_num(pR, copy=False, nan=1.0)
        pR[tir] = 1
        nb = nb + np.int16(1)
        # hit point
        p = k * th[:, None]
        p += o
        # refraction coefficient b_t = eta ci - ct (k_t = eta k + b_t nf), reflection b_r = 2 ci
        bt = eci
        bt -= ct
        parts = []
        if pending:
            # deterministic split: the reflected branch keeps the ray (weight w pR), the transmitted
            # copy gets id + n0 and weight w (1 - pR) where transmission exists
            j = np.flatnonzero(pR < 1)
            if j.size:
                full = j.size == nh
                sel = (lambda a: a) if full else (lambda a: a[j])
                etj, btj = sel(eta), sel(bt)
                fx, fy, fz = sel(nfx), sel(nfy), sel(nfz)
                kt = np.empty((j.size, 3), F32)
                kt[:, 0] = etj * sel(kx) + btj * fx
                kt[:, 1] = etj * sel(ky) + btj * fy
                kt[:, 2] = etj * sel(kz) + btj * fz
                nr = np.sqrt(_rowdot(kt, kt))
                kt /= nr[:, None]
                ot = np.take(p, j, axis=0) if not full else p.copy()
                ot[:, 0] -= eps * fx
                ot[:, 1] -= eps * fy
                ot[:, 2] -= eps * fz
                wt = sel(w) * (1 - sel(pR))
                parts.append((ot, kt, ~sel(below), wt, sel(nb), sel(ids) + n0))
            w = w * pR
            a = None
            b = 2 * ci
            off = eps
        else:
            refl = rng.random(nh, dtype=F32) < pR
            a = np.where(refl, F32(1), eta)
            b = np.where(refl, 2 * ci, bt)
            off = np.where(refl, eps, -eps)
            below = below ^ ~refl
        knew = np.empty((nh, 3), F32)
        if a is None:
            np.multiply(b, nfx, out=knew[:, 0])
            knew[:, 0] += kx
            np.multiply(b, nfy, out=knew[:, 1])
            knew[:, 1] += ky
            np.multiply(b, nfz, out=knew[:, 2])
            knew[:, 2] += kz
        else:
            knew[:, 0] = a * kx + b * nfx
            knew[:, 1] = a * ky + b * nfy
            knew[:, 2] = a * kz + b * nfz
            nr = knew[:, 0] * knew[:, 0]
            nr += knew[:, 1] * knew[:, 1]
            nr += knew[:, 2] * knew[:, 2]
            np.sqrt(nr, out=nr)
            knew /= nr[:, None]
        p[:, 0] += off * nfx
        p[:, 1] += off * nfy
        p[:, 2] += off * nfz
        over = nb >= max_b
        if over.any():
            oi = np.flatnonzero(over)
            ex.put(knew, oi, w, nb, ids, np.full(oi.size, LOST_BOUNCES, np.int8))
            g = np.flatnonzero(~over)
            if g.size == 0:
                return parts
            p, knew, below, w, nb, ids = np.take(p, g, axis=0), np.take(knew, g, axis=0), below[g], w[g], nb[g], ids[g]
        return [(p, knew, below, w, nb, ids)] + parts


@dataclass
class _Exits:
    """Every ray that ended (in no particular order): `ids` says which input ray (+ n for split copies)."""

    ids: np.ndarray
    k: np.ndarray
    A: np.ndarray | None
    w: np.ndarray
    state: np.ndarray
    nb: np.ndarray
    segments: int
    n_paths: int
    m: int

    def ordered(self):
        """(k, A, w, state, nb) arrays of length m in id order (never-ended ids: lost as leaks)."""
        m = self.m
        k = np.zeros((m, 3), F32)
        w = np.zeros(m, F32)
        state = np.full(m, LOST_LEAK, np.int8)
        nb = np.zeros(m, np.int16)
        k[self.ids] = self.k
        w[self.ids] = self.w
        state[self.ids] = self.state
        nb[self.ids] = self.nb
        A = None
        if self.A is not None:
            A = np.zeros((4, self.A.shape[1], m), F32)
            A[:, :, self.ids] = self.A
        return k, A, w, state, nb


class _ExitBuffer:
    """Preallocated exit records of one chunk (each output ray ends once)."""

    def __init__(self, m: int):
        self.k = np.empty((m, 3), F32)
        self.w = np.empty(m, F32)
        self.state = np.empty(m, np.int8)
        self.nb = np.empty(m, np.int16)
        self.ids = np.empty(m, np.int64)
        self.n = 0

    def put(self, k, idx, w, nb, ids, state) -> None:
        a, b = self.n, self.n + idx.size
        # mode="clip": no bounds-check buffer (idx comes from flatnonzero, always in range)
        np.take(k, idx, axis=0, out=self.k[a:b], mode="clip")
        np.take(w, idx, out=self.w[a:b], mode="clip")
        np.take(nb, idx, out=self.nb[a:b], mode="clip")
        np.take(ids, idx, out=self.ids[a:b], mode="clip")
        self.state[a:b] = state
        self.n = b

    def put_all(self, k, w, nb, ids, state) -> None:
        a, b = self.n, self.n + ids.size
        self.k[a:b] = k
        self.w[a:b] = w
        self.nb[a:b] = nb
        self.ids[a:b] = ids
        self.state[a:b] = state
        self.n = b

    def exits(self, segments: int, n_paths: int, m: int) -> "_Exits":
        e = self.n
        return _Exits(ids=self.ids[:e], k=self.k[:e], A=None, w=self.w[:e], state=self.state[:e], nb=self.nb[:e],
                      segments=segments, n_paths=n_paths, m=m)


_EMPTY_SCALAR = (np.zeros((0, 3), F32), np.zeros((0, 3), F32), np.zeros(0, bool), np.zeros(0, F32),
                 np.zeros(0, np.int16), np.zeros(0, np.int64))


@dataclass
class _RayState:
    """Structure of arrays of the rays in flight (float32 geometry, (4, K, n) Stokes columns)."""

    o: np.ndarray
    k: np.ndarray
    below: np.ndarray
    ids: np.ndarray
    w: np.ndarray
    nb: np.ndarray
    pending: np.ndarray
    A: np.ndarray | None
    s: np.ndarray | None

    def take(self, idx: np.ndarray, exit_only: bool = False) -> "_RayState":
        """Rows `idx`; exit_only keeps what the detector needs (ids, k, w, nb, A, s)."""
        if exit_only:
            return _RayState(o=None, k=np.take(self.k, idx, axis=0), below=None, ids=self.ids[idx], w=self.w[idx],
                             nb=self.nb[idx], pending=None,
                             A=None if self.A is None else np.take(self.A, idx, axis=2),
                             s=None if self.s is None else np.take(self.s, idx, axis=0))
        return _RayState(o=np.take(self.o, idx, axis=0), k=np.take(self.k, idx, axis=0), below=self.below[idx],
                         ids=self.ids[idx], w=self.w[idx], nb=self.nb[idx], pending=self.pending[idx],
                         A=None if self.A is None else np.take(self.A, idx, axis=2),
                         s=None if self.s is None else np.take(self.s, idx, axis=0))

    @staticmethod
    def concat(parts: list) -> "_RayState":
        def cat(name, axis=0):
            vals = [getattr(p, name) for p in parts]
            return None if any(v is None for v in vals) else np.concatenate(vals, axis=axis)
        return _RayState(o=cat("o"), k=cat("k"), below=cat("below"), ids=cat("ids"), w=cat("w"), nb=cat("nb"),
                         pending=cat("pending"), A=cat("A", axis=2), s=cat("s"))


def _reflectance_unpolarized(ci, n1, n2, ct):
    """Unpolarised Fresnel reflectance (|r_s|^2 + |r_p|^2)/2 in float32, real indices, below TIR."""
    a = n1 * ci
    b = n2 * ct
    c = n2 * ci
    d = n1 * ct
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (a - b) / (a + b)
        rp = (c - d) / (c + d)
    out = F32(0.5) * (rs * rs + rp * rp)
    return np.nan_to_num(out, copy=False, nan=1.0)


def _check_index_pair(n_above, n_below):
    vals = []
    for name, v in (("n_above", n_above), ("n_below", n_below)):
        v = np.asarray(v)[()]
        if not np.isfinite(v) or np.real(v) <= 0 or np.imag(v) < 0:
            raise RequestError(f"unphysical refractive index {name} = {v!r} (need Re n > 0, Im n >= 0)", name)
        vals.append(complex(v) if np.imag(v) > 0 else float(np.real(v)))
    if isinstance(vals[0], complex):
        raise RequestError("the medium above the relief must be transparent (real index)", "n_above")
    return vals[0], vals[1]


def _block_order(xy: np.ndarray, hx: float, hy: float, block: float = 32.0) -> np.ndarray:
    """Permutation sorting entry points by 32 x 32 px tiles (ray coherence in the BVH)."""
    bx = np.floor((xy[:, 0] + hx) / block).astype(np.int64)
    by = np.floor((xy[:, 1] + hy) / block).astype(np.int64)
    key = by * (int(2 * hx / block) + 2) + bx
    return np.argsort(key, kind="stable")


# ----------------------------------------------------------------------------- reconstruction

def _options(request) -> dict:
    o = dict(request.options or {})
    known = {"polarized", "max_bounces", "first_hit_split", "specular_tol_rad", "fill_holes", "threads",
             "block_px", "backend"}
    out = {"polarized": bool(o.get("polarized", True)), "max_bounces": int(o.get("max_bounces", 100)),
           "first_hit_split": bool(o.get("first_hit_split", True)),
           "specular_tol_rad": float(o.get("specular_tol_rad", 1e-5)), "fill_holes": o.get("fill_holes"),
           "threads": o.get("threads"), "backend": o.get("backend")}
    out["unknown"] = sorted(set(o) - known)
    if out["max_bounces"] < 1:
        raise RequestError(f"max_bounces must be >= 1, got {out['max_bounces']}", "max_bounces")
    if not (0 <= out["specular_tol_rad"] < 0.01):
        raise RequestError("specular_tol_rad must lie in [0, 0.01) rad", "specular_tol_rad")
    return out


MIN_SAMPLES_PER_SIDE = 16
MIN_WAVELENGTHS_PER_TILE = 10.0


def check_request(relief: Relief, material, request) -> dict:
    """Every reason to refuse, raised as RequestError/InputError before any tracing starts."""
    request.validate()
    opts = _options(request)
    where = relief.source or "relief"
    relief.require_valid()
    if not relief.valid.all() and opts["fill_holes"] in (None, False):
        raise RequestError(f"{(~relief.valid).sum()} height samples of {where} are invalid (NaN): the ray tracer "
                           "needs a closed surface; fill them explicitly (relief fill / Relief.fill_holes) or set "
                           "the request option fill_holes=True (or a max gap in px)", where)
    ny, nx = relief.shape
    if min(nx, ny) < MIN_SAMPLES_PER_SIDE:
        raise RequestError(f"relief {where} of {ny} x {nx} samples is too small for ray tracing "
                           f"(need at least {MIN_SAMPLES_PER_SIDE} per side)", where)
    lam_max_m = max(request.wavelengths_nm) * 1e-9
    ext = min(nx * relief.dx_m, ny * relief.dy_m)
    if ext < MIN_WAVELENGTHS_PER_TILE * lam_max_m:
        raise RequestError(f"relief {where} spans {ext * 1e6:.3g} um, less than {MIN_WAVELENGTHS_PER_TILE:g} "
                           f"wavelengths ({lam_max_m * 1e9:g} nm): geometric optics does not apply; "
                           "use a wave method (kirchhoff, rayleigh-rice)", where)
    n_cells = 2 * (len(request.theta_s_edges_deg) - 1) * (len(request.phi_s_edges_deg) - 1)
    facets = 2 * nx * ny
    if facets < n_cells:
        raise RequestError(f"relief {where} is too coarse for the request: its {facets} facets cannot fill "
                           f"{n_cells} scatter cells; use a larger map or coarser theta_s/phi_s cells", where)
    material.check_incidence(request.wavelengths_nm, request.incident_from)
    return opts


def _beam_strata(n: int, Lx: float, Ly: float, block_px: float = 32.0):
    """Stratified beam: (nxs, nys) strata covering the tile and their order by 32 x 32 px blocks."""
    nxs = max(1, int(round(math.sqrt(n * Lx / Ly))))
    nys = max(1, -(-n // nxs))
    iy, ix = np.divmod(np.arange(nxs * nys, dtype=np.int64), nxs)
    bx = (ix * (Lx / nxs) // block_px).astype(np.int64)
    by = (iy * (Ly / nys) // block_px).astype(np.int64)
    order = np.argsort(by * (int(Lx // block_px) + 2) + bx, kind="stable")
    return nxs, nys, order


class _Accumulator:
    """Per-task sums of weights (and Mueller elements) per scatter cell."""

    def __init__(self, S: int, A: int, polarized: bool):
        self.S, self.A = S, A
        nc = 2 * S * A
        self.sum_w = np.zeros(nc)
        self.sum_w2 = np.zeros(nc)
        self.sum_M = np.zeros((16, nc)) if polarized else None
        self.spec = np.zeros(2)
        self.spec_w2 = np.zeros(2)
        self.spec_M = np.zeros((2, 16)) if polarized else None
        self.lost = {name: 0.0 for name in STATE_NAMES.values()}
        self.outside_table = 0.0
        self.segments = 0
        self.bounce_sum = 0.0
        self.paths = 0
        self.exits = 0

    def add(self, other: "_Accumulator") -> None:
        self.sum_w += other.sum_w
        self.sum_w2 += other.sum_w2
        if self.sum_M is not None:
            self.sum_M += other.sum_M
            self.spec_M += other.spec_M
        self.spec += other.spec
        self.spec_w2 += other.spec_w2
        for k_ in self.lost:
            self.lost[k_] += other.lost[k_]
        self.outside_table += other.outside_table
        self.segments += other.segments
        self.bounce_sum += other.bounce_sum
        self.paths += other.paths
        self.exits += other.exits


class _CellIndex:
    """Scatter cell of exit directions for the request's (theta_s, phi_s) edges, built once per task.

    Uniform edges (the default 1-degree rings x 5-degree azimuths, and any uniform grid): float32
    arithmetic on arccos |k_z| and atan2(k_y, k_x) in units of the cell width, truncation, and
    small lookup tables that fold the azimuth modulo 360 degrees and mark cells beyond the edges
    (no float modulo, no search).  Other edges: `_theta_bins` / `_phi_bins` (search).
    `__call__(k)` returns int32 cell = ring * A + azimuth, or -1 outside the table.
    """

    def __init__(self, te: np.ndarray, pe: np.ndarray):
        self.S, self.A = te.size - 1, pe.size - 1
        self.te, self.pe = te, pe
        self.te_sin2 = np.sin(np.radians(te)) ** 2
        dt, dp = np.diff(te), np.diff(pe)
        n_full = 360.0 / dp[0]
        self.fast = bool(np.allclose(dt, dt[0], rtol=1e-9, atol=1e-9) and np.allclose(dp, dp[0])
                         and abs(n_full - round(n_full)) < 1e-9)
        if not self.fast:
            return
        S, A = self.S, self.A
        # ring: x = (theta - te0) / dt, shifted by one ring so that truncation == floor for x > -1
        self.t_scale = F32(180.0 / np.pi / dt[0])
        self.t_off = F32(1.0 - te[0] / dt[0])
        nt = int(math.ceil(90.0 / dt[0] + 1.0 - te[0] / dt[0])) + 2
        ring = np.arange(nt) - 1                       # truncated value j -> ring j - 1
        if te[-1] >= 90.0 - 1e-9:
            ring[ring == S] = S - 1                    # theta = 90 exactly belongs to the last ring
        ring[(ring < 0) | (ring >= S)] = -1
        self.ring_lut = ring.astype(np.int32)
        # azimuth: x = (phi - pe0) / dp + shift with shift a multiple of the full turn making x >= 0
        nf = int(round(n_full))
        lo = -180.0 / dp[0] - pe[0] / dp[0]
        shift = nf * int(math.ceil(max(0.0, -lo) / nf + 1e-9))
        self.p_scale = F32(180.0 / np.pi / dp[0])
        self.p_off = F32(shift - pe[0] / dp[0])
        npl = int(math.ceil(180.0 / dp[0] - pe[0] / dp[0] + shift)) + 2
        az = np.arange(npl) % nf
        az[az >= A] = -1                               # beyond the last edge (span < 360)
        self.az_lut = az.astype(np.int32)

    def __call__(self, k: np.ndarray) -> np.ndarray:
        S, A = self.S, self.A
        if not self.fast:
            ib = _theta_bins(k[:, 2], self.te_sin2)
            ia = _phi_bins(k, self.pe)
            cell = (ib * A + ia).astype(np.int32)
            cell[(ib < 0) | (ib >= S) | (ia < 0) | (ia >= A)] = -1
            return cell
        x = np.abs(k[:, 2])
        np.minimum(x, F32(1), out=x)
        np.arccos(x, out=x)
        x *= self.t_scale
        x += self.t_off
        np.maximum(x, F32(0), out=x)
        ib = np.take(self.ring_lut, x.astype(np.int32), mode="clip")
        y = np.arctan2(k[:, 1], k[:, 0])
        y *= self.p_scale
        y += self.p_off
        ia = np.take(self.az_lut, y.astype(np.int32), mode="clip")
        cell = ib * np.int32(A)
        cell += ia
        cell[(ib < 0) | (ia < 0)] = -1
        return cell


def _bin_chunk(acc: _Accumulator, ex: "_Exits", side_of_state: tuple, cells: _CellIndex, spec_dirs, cos_tol):
    """Bin one chunk's exits into the accumulator (vectorised, np.bincount)."""
    acc.segments += ex.segments
    acc.paths += ex.n_paths
    w = ex.w
    state = ex.state
    if state.size and state.max() > BELOW:
        for code, name in STATE_NAMES.items():
            sel = state == code
            if sel.any():
                acc.lost[name] += float(w[sel].sum(dtype=np.float64))
        done = np.flatnonzero(state <= BELOW)
        all_done = done.size == state.size
    else:
        done, all_done = None, True
    n_done = state.size if all_done else done.size
    acc.exits += n_done
    acc.bounce_sum += float(ex.nb.sum(dtype=np.float64) if all_done else ex.nb[done].sum(dtype=np.float64))
    if n_done == 0:
        return
    k = ex.k if all_done else ex.k[done]
    wd = w if all_done else w[done]
    st = state if all_done else state[done]
    # table side per exit: 0 (incidence side) or 1; state ABOVE = 0, BELOW = 1
    side = st if side_of_state[0] == 0 else (1 - st)
    # delta parts: exits along the mean plane's mirror / refraction direction.  A float32 prefilter,
    # then float64 with renormalisation (a float32 unit vector's norm is off by ~1e-8 >> 1 - cos(tol))
    spec = None
    for sd in (0, 1):
        if spec_dirs[sd] is not None:
            d = np.asarray(spec_dirs[sd], np.float64)
            # explicit multiply-adds, not `k @ d`: a BLAS matrix-vector product wakes OpenBLAS's
            # thread pool, whose spinning threads cost as much CPU as the whole binning
            d32 = d.astype(F32)
            c = k[:, 0] * d32[0]
            c += k[:, 1] * d32[1]
            c += k[:, 2] * d32[2]
            near = c > F32(0.9999)
            cand = np.flatnonzero(near) if near.any() else ()
            if len(cand):
                kc = k[cand].astype(np.float64)
                ok = np.einsum("ij,j->i", kc, d) > cos_tol * np.sqrt(np.einsum("ij,ij->i", kc, kc))
                ok &= side[cand] == sd
                if ok.any():
                    if spec is None:
                        spec = np.zeros(k.shape[0], bool)
                    spec[cand[ok]] = True
    S, A_ = acc.S, acc.A
    cell = cells(k)
    inside = cell >= 0
    cell += side.astype(np.int32) * np.int32(S * A_)
    if spec is not None:
        inside &= ~spec
        for sd in (0, 1):
            msk = spec & (side == sd)
            if msk.any():
                acc.spec[sd] += float(wd[msk].sum(dtype=np.float64))
                acc.spec_w2[sd] += float((wd[msk].astype(np.float64) ** 2).sum())
                if acc.sum_M is not None:
                    Ms = np.take(ex.A.reshape(16, -1)[:, done] if not all_done else ex.A.reshape(16, -1),
                                 np.flatnonzero(msk), axis=1)
                    acc.spec_M[sd] += (Ms * wd[msk]).sum(axis=1, dtype=np.float64)
    n_in = int(np.count_nonzero(inside))
    outside = wd.size - n_in - (0 if spec is None else int(np.count_nonzero(spec)))
    if outside:
        acc.outside_table += float(wd[~inside & (True if spec is None else ~spec)].sum(dtype=np.float64))
    full = n_in == wd.size
    c_in = cell if full else cell[inside]
    w_in = (wd if full else wd[inside]).astype(np.float64)
    nc = acc.sum_w.size
    acc.sum_w += np.bincount(c_in, weights=w_in, minlength=nc)
    acc.sum_w2 += np.bincount(c_in, weights=w_in * w_in, minlength=nc)
    if acc.sum_M is not None:
        M16 = ex.A.reshape(16, -1)
        wf = w_in.astype(F32)
        if not (all_done and full):                  # one gather of the binned rays' columns
            M16 = np.take(M16, np.flatnonzero(inside) if all_done else (done if full else done[inside]), axis=1)
            M16 *= wf
        else:
            M16 = M16 * wf
        for e in range(16):
            acc.sum_M[e] += np.bincount(c_in, weights=M16[e], minlength=nc)


def _theta_bins(kz: np.ndarray, te_sin2: np.ndarray) -> np.ndarray:
    """Ring index of each direction (edges given as sin^2 theta); -1 or S when outside the edges.

    Uniform edges in theta: arithmetic on arccos (float32); otherwise a search on sin^2.
    """
    te = np.degrees(np.arcsin(np.sqrt(np.clip(te_sin2, 0.0, 1.0))))
    d = np.diff(te)
    S = d.size
    if np.allclose(d, d[0], rtol=1e-9, atol=1e-9):
        x = np.abs(kz)
        np.minimum(x, F32(1), out=x)
        np.arccos(x, out=x)
        x *= F32(180.0 / np.pi / d[0])               # theta in units of the ring width from te[0]
        x -= F32(te[0] / d[0])
        np.floor(x, out=x)
        ib = x.astype(np.int32)
        if te[-1] >= 90.0 - 1e-9:
            ib[ib == S] = S - 1                        # theta = 90 exactly belongs to the last ring
        ib[x < 0] = -1
        return ib
    sin2 = np.maximum(F32(0), 1 - kz * kz).astype(np.float64)
    ib = np.searchsorted(te_sin2, sin2, side="right") - 1
    ib[sin2 >= te_sin2[-1]] = S - 1 if te_sin2[-1] >= 1.0 else S
    return ib


def _phi_bins(k: np.ndarray, pe: np.ndarray) -> np.ndarray:
    """Azimuth cell of each direction; uniform edges by arithmetic (float32), others by search."""
    d = np.diff(pe)
    n_full = 360.0 / d[0]
    if np.allclose(d, d[0]) and abs(n_full - round(n_full)) < 1e-9:
        # cells tile the circle: the cell count from the edge pe[0] in bin units, floor, and an
        # integer modulo (float np.mod is ~10x slower than the rest of the binning)
        x = np.arctan2(k[:, 1], k[:, 0])
        x *= F32(180.0 / np.pi / d[0])
        x -= F32(pe[0] / d[0])
        np.floor(x, out=x)
        ia = x.astype(np.int32)
        ia %= np.int32(round(n_full))
        ia[ia >= d.size] = d.size                    # beyond the last edge (span < 360): outside
        return ia
    if np.allclose(d, d[0]):
        phi = np.arctan2(k[:, 1], k[:, 0])
        phi *= F32(180.0 / np.pi)
        phi -= F32(pe[0])
        np.mod(phi, F32(360.0), out=phi)
        ia = np.floor(phi * F32(1.0 / d[0])).astype(np.int64)
        ia[ia >= d.size] = d.size                    # beyond the last edge (span < 360): outside
        return ia
    phi = np.mod(np.degrees(np.arctan2(k[:, 1], k[:, 0]).astype(np.float64)) - pe[0], 360.0)
    return np.searchsorted(pe - pe[0], phi, side="right") - 1


_MIRROR_DD = np.outer([1.0, 1.0, -1.0, -1.0], [1.0, 1.0, -1.0, -1.0])


def _incident_state(K: int, n: int) -> np.ndarray | None:
    if not K:
        return None
    A = np.zeros((4, 4, n), F32)
    for i in range(4):
        A[i, i] = 1
    return A


class _RayContext:
    """What every incidence task needs, shipped once per worker (`parallel.map_tasks` context).

    `tracer` (an already built `ReliefTracer`, e.g. from `reconstruct_with`) is used where the
    tasks run in this process; it is not pickled: a worker process or Dask worker builds its own
    once (`parallel.worker_cached`, keyed by `tracer_key`).  `digest()` names everything that
    changes the numbers (checkpoint keys); the refractive indices travel with each task.
    """

    def __init__(self, relief: Relief, opts: dict, request, tracer: "ReliefTracer | None" = None):
        self.relief = relief
        self.max_bounces = int(opts["max_bounces"])
        self.fill_holes = opts["fill_holes"]
        self.polarized = bool(opts["polarized"])
        self.first_hit_split = bool(opts["first_hit_split"])
        self.cos_tol = math.cos(opts["specular_tol_rad"])
        self.threads = opts["threads"]
        self.seed = int(request.seed)
        self.samples = int(request.samples)
        self.te = np.asarray(request.theta_s_edges_deg, float)
        self.pe = np.asarray(request.phi_s_edges_deg, float)
        self.tracer = tracer
        h = self._relief_hash(relief, tracer)
        self.tracer_key = ("ray.ReliefTracer", h.hexdigest())
        h.update(repr((self.polarized, self.first_hit_split, float(opts["specular_tol_rad"]), self.seed,
                       self.samples, self.te.tolist(), self.pe.tolist())).encode())
        self._digest = h.hexdigest()

    def digest(self) -> str:
        return self._digest

    def _relief_hash(self, relief: Relief, tracer):
        """sha256 of the heights and mesh options; kept on a tracer built for this very relief
        (hashing 8 MB of heights costs ~30 ms per request, e.g. in fits that reuse the tracer)."""
        key = (self.max_bounces, repr(self.fill_holes))
        cache = None
        if tracer is not None and tracer.relief is relief:
            cache = tracer.__dict__.setdefault("_relief_hash_cache", {})
            if key in cache:
                return cache[key].copy()
        h = hashlib.sha256()
        hm = np.ascontiguousarray(relief.heights_m, dtype=np.float64)
        h.update(hm)
        h.update(repr((hm.shape, float(relief.dx_m), float(relief.dy_m), bool(relief.periodic),
                       self.max_bounces, repr(self.fill_holes))).encode())
        if cache is not None:
            cache[key] = h.copy()
        return h

    def __getstate__(self):
        d = dict(self.__dict__)
        d["tracer"] = None                       # an Embree scene does not travel: rebuilt per worker
        return d

    def get_tracer(self) -> "ReliefTracer":
        if self.tracer is not None:
            return self.tracer
        return worker_cached(self.tracer_key, lambda: ReliefTracer(self.relief, self.max_bounces, self.fill_holes,
                                                                    threads=1 if in_worker() else self.threads))


def _incidence_task(ctx: _RayContext, task: tuple) -> dict:
    """Trace one (side, wavelength, incidence) with `ctx.samples` rays; its finished table rows.

    Module-level `map_tasks` function.  The rays go in fixed chunks of CHUNK, each with its own
    generator `task_rng(seed, side, wavelength, theta, phi, chunk)`, over one Embree thread in a
    pool worker and `threads` (default every core) in this process; chunk results are summed in
    chunk order, so the numbers do not depend on the backend or the thread count.
    Returns float32 arrays (vals, sig: (2, S, A); mue: (2, S, A, 4, 4) in the table's frame)
    and float scalars / (4, 4) float64 specular parts.
    """
    si, side, iw, ii, ip, n_out, n_in, ti, pi_ = task
    tracer = ctx.get_tracer()
    threads = 1 if in_worker() else int(ctx.threads or tracer.threads or default_workers())
    K = 4 if ctx.polarized else 0
    te, pe = ctx.te, ctx.pe
    S, A_ = te.size - 1, pe.size - 1
    cells = _CellIndex(te, pe)
    Lx, Ly = float(tracer.Lx), float(tracer.Ly)
    nxs, nys, strata_order = worker_cached(("ray.strata", ctx.samples, Lx, Ly),
                                           lambda: _beam_strata(ctx.samples, Lx, Ly))
    N = nxs * nys
    chunks = [(lo, min(N, lo + CHUNK)) for lo in range(0, N, CHUNK)]
    wi = direction(ti, pi_)                                    # table frame, toward the source
    k_in = -wi if side == "outside" else np.array([-wi[0], -wi[1], wi[2]])
    from_below = side == "inside"
    n_above = n_out.real
    n_below = n_in if n_in.imag > 0 else n_in.real
    s_init = _frame_s(k_in[None, :], math.radians(pi_))[0] if K else None
    # ideal directions of the flat mean plane (physical), for the delta parts
    spec_R = np.array([k_in[0], k_in[1], -k_in[2]])
    n1, n2 = (n_above, n_below) if not from_below else (n_below, n_above)
    eta = float(np.real(n1) / np.real(n2))
    sin2t = eta**2 * (1 - k_in[2] ** 2)
    spec_T = None
    if sin2t < 1 and not (np.iscomplexobj(n2) and np.imag(n2) > 0):
        spec_T = np.array([eta * k_in[0], eta * k_in[1], math.copysign(math.sqrt(1 - sin2t), k_in[2])])
    side_of_state = (0, 1) if side == "outside" else (1, 0)     # (ABOVE ->, BELOW ->) table side
    phi_exit = math.radians(pi_ + 180.0)

    def job(ci):
        lo, hi = chunks[ci]
        rng = task_rng(ctx.seed, si, iw, ii, ip, ci)
        st = strata_order[lo:hi]
        iy, ix = np.divmod(st, nxs)
        jit = rng.random((hi - lo, 2))
        o = np.empty((hi - lo, 3), F32)
        o[:, 0] = (ix + jit[:, 0]) * (tracer.Lx / nxs) - tracer.hx
        o[:, 1] = (iy + jit[:, 1]) * (tracer.Ly / nys) - tracer.hy
        o[:, 2] = tracer.z_bot if from_below else tracer.z_top
        k = np.broadcast_to(k_in.astype(F32), o.shape).copy()
        below = np.full(hi - lo, from_below)
        out = tracer._trace_chunk(o, k, below, _incident_state(K, hi - lo), rng, n_above, n_below,
                                  ctx.first_hit_split, s_init=s_init, phi_exit_rad=phi_exit)
        acc = _Accumulator(S, A_, bool(K))
        _bin_chunk(acc, out, side_of_state, cells, (spec_R, spec_T), ctx.cos_tol)
        return acc

    t0 = time.perf_counter()
    total = _Accumulator(S, A_, bool(K))
    if threads > 1 and len(chunks) > 1:
        with ThreadPoolExecutor(max_workers=min(threads, len(chunks))) as ex:
            for acc in ex.map(job, range(len(chunks))):       # chunk order: deterministic sums
                total.add(acc)
    else:
        for ci in range(len(chunks)):
            total.add(job(ci))
    psa = projected_solid_angle(te, pe)
    n = float(total.paths)
    mean = total.sum_w / n
    var = np.maximum(total.sum_w2 / n - mean**2, 0.0) / n
    out = {"vals": (mean.reshape(2, S, A_) / psa).astype(F32),
           "sig": (np.sqrt(var).reshape(2, S, A_) / psa).astype(F32),
           "specR": float(total.spec[0] / n), "specT": float(total.spec[1] / n),
           "lost": float((sum(total.lost.values()) + total.outside_table) / n),
           "mue": None, "smR": None, "smT": None}
    if K:
        # light from inside: the table's frame is mirrored (z -> -z); a mirror maps the physical
        # basis (s, p = s x k) to (s', -p'), so S2, S3 change sign: M_table = D M D, D = diag(1,1,-1,-1)
        dd = _MIRROR_DD if side == "inside" else 1.0
        m = (total.sum_M / n).reshape(4, 4, 2, S, A_).transpose(2, 3, 4, 0, 1)
        out["mue"] = (m / psa[None, :, :, None, None] * dd).astype(F32)
        out["smR"] = (total.spec_M[0] / n).reshape(4, 4) * dd
        out["smT"] = (total.spec_M[1] / n).reshape(4, 4) * dd
        out["vals"] = out["mue"][..., 0, 0].copy()
    out["diag"] = {"wavelength_nm": None, "theta_i_deg": float(ti), "phi_i_deg": float(pi_),
                   "rays": int(total.paths), "segments": int(total.segments),
                   "mean_bounces": total.bounce_sum / max(total.exits, 1),
                   "lost": {k_: v / n for k_, v in total.lost.items()},
                   "outside_table": total.outside_table / n,
                   "trace_s": time.perf_counter() - t0, "build_s": tracer.build_s}
    m = tracer.mesh
    out["mesh"] = {"rays": int(N), "triangles": m.n_triangles, "tile_samples": list(m.shape),
                   "mirror_extended": m.mirrored, "history": list(m.history)}
    return out


def reconstruct(relief: Relief, material, request, progress=None) -> list[BsdfTable]:
    """Ray-trace the relief for every (wavelength, incidence, side) of the request (module doc).

    Options (request.options): polarized (True: Mueller matrices per cell, see module doc),
    max_bounces (100), first_hit_split (True), specular_tol_rad (1e-5), fill_holes (None:
    refuse NaN; True or max gap in px: Laplace filling), threads (this process; default every
    core), backend (map_tasks backend; default as configured).  Each incidence is one
    `parallel.map_tasks` task; one BVH is built per worker process (or once here when the
    tasks run in this process).  `request.samples` rays per incidence.
    """
    opts = check_request(relief, material, request)
    return _reconstruct(None, relief, material, request, progress, opts)


def reconstruct_with(tracer: ReliefTracer, relief: Relief, material, request, progress=None) -> list[BsdfTable]:
    """`reconstruct` with an already built tracer (reuse one BVH across requests, e.g. in fits).

    The tracer is used for the tasks that run in this process (serial backend, a single
    incidence); worker processes build their own.
    """
    opts = check_request(relief, material, request)
    if opts["threads"]:
        tracer.threads = int(opts["threads"])
    return _reconstruct(tracer, relief, material, request, progress, opts)


def _reconstruct(tracer, relief, material, request, progress, opts) -> list[BsdfTable]:
    t0 = time.perf_counter()
    K = 4 if opts["polarized"] else 0
    te = np.asarray(request.theta_s_edges_deg, float)
    pe = np.asarray(request.phi_s_edges_deg, float)
    S, A_ = te.size - 1, pe.size - 1
    W, I, P = len(request.wavelengths_nm), len(request.theta_i_deg), len(request.phi_i_deg)
    ctx = _RayContext(relief, opts, request, tracer)
    tasks = []
    for si, side in enumerate(request.incident_from):
        for iw, wl in enumerate(request.wavelengths_nm):
            n_from, n_to = material.n_pair(wl, side)
            n_out, n_in = (n_from, n_to) if side == "outside" else (n_to, n_from)
            for ii, ti in enumerate(request.theta_i_deg):
                for ip, pi_ in enumerate(request.phi_i_deg):
                    tasks.append((si, side, iw, ii, ip, complex(n_out), complex(n_in), float(ti), float(pi_)))
    # the finished rows go straight into the tables (float32 for the big arrays)
    sides = []
    for _ in request.incident_from:
        sides.append({"vals": np.zeros((W, I, P, 2, S, A_), F32), "sig": np.zeros((W, I, P, 2, S, A_), F32),
                      "mue": np.zeros((W, I, P, 2, S, A_, 4, 4), F32) if K else None,
                      "specR": np.zeros((W, I, P)), "specT": np.zeros((W, I, P)), "lost": np.zeros((W, I, P)),
                      "smR": np.zeros((W, I, P, 4, 4)) if K else None, "smT": np.zeros((W, I, P, 4, 4)) if K else None,
                      "diag": {}})
    build_s = [tracer.build_s] if tracer is not None else []
    mesh_seen: list = []

    def collect(i, r):
        si, _, iw, ii, ip = tasks[i][:5]
        d = sides[si]
        for name in ("vals", "sig", "mue", "specR", "specT", "lost", "smR", "smT"):
            if d[name] is not None:
                d[name][iw, ii, ip] = r[name]
        diag = dict(r["diag"])
        diag["wavelength_nm"] = float(request.wavelengths_nm[iw])
        build_s.append(diag.pop("build_s"))
        if not mesh_seen:
            mesh_seen.append(r["mesh"])
        d["diag"][(iw, ii, ip)] = diag

    t_trace = time.perf_counter()
    try:
        map_tasks(_incidence_task, tasks, ctx, progress=progress or silent, label="ray tracing",
                  backend=opts.get("backend"), on_result=collect)
    finally:
        if tracer is None:
            forget_worker_cached(ctx.tracer_key)      # a BVH built here is not kept past the request
    t_trace = time.perf_counter() - t_trace

    tables = []
    for si, side in enumerate(request.incident_from):
        d = sides[si]
        diag = [d["diag"][key] for key in sorted(d["diag"])]
        mesh_info = dict(mesh_seen[0]) if mesh_seen else {}
        meta = {"request": {"samples_requested": int(request.samples), "rays_per_incidence": mesh_info.pop("rays", 0),
                            "seed": int(request.seed), "options": {k_: v for k_, v in opts.items()
                                                                   if k_ != "unknown"}},
                "unknown_options": opts["unknown"],
                "mesh": mesh_info,
                "max_bounces": int(opts["max_bounces"]),
                "timing_s": {"build": max(build_s) if build_s else 0.0, "trace_all_sides": t_trace,
                             "total": time.perf_counter() - t0},
                "parallel": last_run(),
                "tasks": diag,
                "notes": ["geometric optics: valid when relief features >> wavelength",
                          "Stokes bases: s = z x k / |z x k|, p = s x k with k the propagation direction, "
                          "in the table's frame (mirrored for light from inside, as bsdf.py)",
                          "lost = max bounces + numerical leaks + absorbed + exits outside the table's cells"]}
        tables.append(BsdfTable(
            wavelength_nm=np.asarray(request.wavelengths_nm, float), theta_i_deg=np.asarray(request.theta_i_deg),
            phi_i_deg=np.asarray(request.phi_i_deg), theta_s_edges_deg=te, phi_s_edges_deg=pe,
            values_per_sr=d["vals"], incident_from=side, specular_R=d["specR"], specular_T=d["specT"],
            lost=d["lost"], sigma_per_sr=d["sig"], mueller_per_sr=d["mue"], specular_mueller_R=d["smR"],
            specular_mueller_T=d["smT"], method="ray", material=material.describe(), relief=relief.describe(),
            metadata=meta))
    return tables
