"""The relief as an Embree scene: one periodic tile of the surface, its BVH, and ray batches through it.

Surface: the height map triangulated by the ONE triangulation `surface.mesh.build_tile_mesh`
(a piecewise-linear periodic mesh; non-periodic maps are mirror-extended there).  The tile is
one period of an infinite surface: a ray leaving the tile sideways re-enters from the
opposite side (`wrap`), which removes the paper's boundary losses at grazing incidence.  The
relief layer is the slab between just above the highest and just below the lowest point;
a ray that reaches a slab face has left the relief.

BVH cache: `ReliefTracer` builds the BVH once (~1.5 s at 1024^2) and is reused for every
wavelength, incidence and side; `relief_key` names what changes it (heights, pitch, mesh
options) so that worker processes build one per relief (`parallel.worker_cached`).
"""
from __future__ import annotations

import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from relief_bsdf import kernels
from relief_bsdf.errors import RequestError
from relief_bsdf.methods.ray.embree_buffers import DirectMesh, Unavailable
from relief_bsdf.methods.ray.exits import ABOVE, Exits, padded_rows
from relief_bsdf.methods.ray.transport import Media, Rays, TraceSettings, carrier_for, trace_chunk
from relief_bsdf.parallel import default_workers, forget_worker_cached, worker_cached
from relief_bsdf.surface.digest import relief_hash as _relief_hash
from relief_bsdf.surface.mesh import TileMesh, build_tile_mesh, remesh_heights
from relief_bsdf.surface.relief import Relief

F32 = np.float32
CHUNK = 1 << 16                # rays per independent chunk (its own seed, one thread at a time)


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


@dataclass
class Query:
    """One Embree query of a batch: hits (facet normal Ng, distance) and, per ray, whether a tile side
    comes before the slab's faces along k (lat_first, uint8: t_lat < tz; a ray that hits nothing then
    re-enters, its distances from `ReliefTracer.side_distances`)."""

    hit: np.ndarray
    n_hit: int
    ng: np.ndarray
    t_hit: np.ndarray
    lat_first: np.ndarray


class ReliefTracer:
    """Periodic relief mesh in an Embree BVH, built once; traces ray batches through the layer.

    Thread-safe: `scatter` and the transport loop may run on several threads at once (Embree
    queries release the GIL; each call works on its own arrays).
    """

    def __init__(self, relief: Relief, max_bounces: int = 100, fill_holes: bool | int | None = None,
                 threads: int | None = None, _mesh: TileMesh | None = None, direct_buffers: bool = True):
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        if int(max_bounces) < 1:
            raise RequestError(f"max_bounces must be >= 1, got {max_bounces}", "max_bounces")
        self.relief = relief
        self.max_bounces = int(max_bounces)
        self.fill_holes = fill_holes
        self.threads = int(threads or default_workers())
        t0 = time.perf_counter()
        self.mesh: TileMesh = build_tile_mesh(relief, fill_holes) if _mesh is None else _mesh
        t1 = time.perf_counter()
        self.scene = rtcs.EmbreeScene()
        self._direct = None
        if direct_buffers:
            try:                                       # numpy-filled Embree buffers (embree_buffers doc)
                self._direct = DirectMesh(self.scene, self.mesh.vertices, self.mesh.triangles)
            except Unavailable:
                self._direct = None
        if self._direct is None:
            self._embree_mesh = TriangleMesh(self.scene, self.mesh.vertices, self.mesh.triangles)
        t2 = time.perf_counter()
        self._set_bounds()
        self.build_s = time.perf_counter() - t0
        # where the build time goes: mesh (numpy), Embree buffers (embreex copies element by element
        # under the GIL; numpy-filled with the direct path), BVH build (Embree, all cores)
        self.build_split_s = {"mesh": t1 - t0, "embree_buffers": t2 - t1, "bvh_commit": self.build_s - (t2 - t0)}
        self.record_segments: list | None = None
        self._relief_hash_cache: dict = {}

    @property
    def direct_buffers(self) -> bool:
        """True when Embree's buffers are numpy-written and `update_heights` refits in place."""
        return self._direct is not None

    def _set_bounds(self) -> None:
        """Tile period, slab faces and the ray-origin offset from the mesh; commit the BVH now (first
        query) so that timings of later calls are clean."""
        m = self.mesh
        self.Lx, self.Ly = (F32(m.period[0]), F32(m.period[1]))
        self.hx, self.hy = F32(m.period[0] / 2), F32(m.period[1] / 2)
        big = max(m.period[0] / 2, m.period[1] / 2, abs(m.z_min), abs(m.z_max), 1.0)
        # offset of a new ray origin from its hit point: 64 float32 ulps of the largest coordinate
        self.eps = F32(64 * big * 2.0**-24)
        self.z_top = F32(m.z_max + 8 * self.eps)
        self.z_bot = F32(m.z_min - 8 * self.eps)
        self.scene.run(np.array([[0, 0, self.z_top + 1]], F32), np.array([[0, 0, -1]], F32))

    def with_heights(self, heights_m: np.ndarray | Relief, step: str = "heights replaced") -> "ReliefTracer":
        """A tracer of the same grid with new heights (a fit's scaled / filtered relief).

        Reuses the mesh topology (triangle index buffer, vertex x, y); only z is rewritten.  The
        Embree scene itself is rebuilt: embreex (4.4) copies the buffers into Embree once in
        `TriangleMesh(...)` and binds neither rtcGetGeometryBufferData / rtcUpdateGeometryBuffer
        nor a scene re-commit, so vertex buffers cannot be updated in place and the BVH cannot be
        refitted from Python; `build_split_s` says where the rebuild's time goes.  Random numbers:
        tables traced with a given seed use the same ones for every height map (common random
        numbers; `method` module doc), so a fit sees a smooth objective.
        """
        relief = heights_m if isinstance(heights_m, Relief) else self.relief.with_heights(
            np.asarray(heights_m, dtype=np.float64), step)
        mesh = remesh_heights(self.mesh, relief, self.fill_holes)
        return ReliefTracer(relief, self.max_bounces, self.fill_holes, self.threads, _mesh=mesh,
                            direct_buffers=self.direct_buffers)

    def update_heights(self, heights_m: np.ndarray | Relief, step: str = "heights replaced") -> float:
        """In place: new heights on the same grid, the BVH refitted (no index buffer, no new scene).

        Only with `direct_buffers` (else RuntimeError: use `with_heights`).  Not while another
        thread traces with this tracer.  Returns the seconds it took (z written + BVH refit).
        """
        if self._direct is None:
            raise RuntimeError("this tracer's Embree buffers are embreex's own: use with_heights")
        t0 = time.perf_counter()
        relief = heights_m if isinstance(heights_m, Relief) else self.relief.with_heights(
            np.asarray(heights_m, dtype=np.float64), step)
        self.mesh = remesh_heights(self.mesh, relief, self.fill_holes)
        self.relief = relief
        self._relief_hash_cache = {}
        self._direct.update_z(self.mesh.vertices[:, 2])
        self._set_bounds()                             # new slab faces; the query commits (refits) the BVH
        return time.perf_counter() - t0

    # ------------------------------------------------------------------ geometry of the tile
    def query(self, o: np.ndarray, k: np.ndarray) -> Query:
        """Intersect rays (o, k) (float32) with the relief up to the nearest tile side or slab face
        (`kernels.slab_far`: that limit and whether a tile side comes first; `Query` doc)."""
        n = k.shape[0]
        tfar, lat_first = np.empty(n, F32), np.empty(n, np.uint8)
        zh, zc = self._slab_faces()
        kernels.slab_far(o, k, self.hx, self.hy, zh, zc, tfar, lat_first)
        if self.record_segments is not None:          # benchmark hook: replay the same batches
            self.record_segments.append((o.copy(), k.copy(), tfar.copy()))
        res = self.scene.run(o, k, dists=tfar, output=1)
        hit = res["primID"] >= 0
        return Query(hit, int(np.count_nonzero(hit)), res["Ng"], res["tfar"], lat_first)

    def reentry_points(self, o: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Where rays (o, k) that reach a tile side re-enter (`wrap` at their `side_distances`)."""
        return self.wrap(o, k, *self.side_distances(o, k))

    def side_distances(self, o: np.ndarray, k: np.ndarray) -> tuple:
        """(t_lat, tx, ty) of rays (o, k) (float32): the distances to the tile's sides (`kernels.slab_distances`)."""
        n = k.shape[0]
        T, t_lat, tfar = padded_rows((3,), n), np.empty(n, F32), np.empty(n, F32)
        zh, zc = self._slab_faces()
        kernels.slab_distances(o, k, self.hx, self.hy, zh, zc, T, t_lat, tfar)
        return t_lat, T[0], T[1]

    def wrap(self, o: np.ndarray, k: np.ndarray, t: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
        """Origins re-entering the tile: advance to the side reached (t) and move to the opposite side."""
        ow = o + t[:, None] * k
        bx = tx <= t
        by = ty <= t
        ow[bx, 0] = -np.copysign(self.hx, k[bx, 0])
        ow[by, 1] = -np.copysign(self.hy, k[by, 1])
        return ow

    def _slab_faces(self) -> tuple:
        """(zh, zc): the slab's half height and centre, float32."""
        return (self.z_top - self.z_bot) / F32(2), (self.z_top + self.z_bot) / F32(2)

    def subtile_of(self, p: np.ndarray, grid: tuple) -> np.ndarray:
        """Sub-tile index iy * gx + ix (int32) of points p (n, >= 2, tile coordinates) on a gx x gy
        grid of the *relief's own* extent: on a mirror-extended tile the coordinates are folded
        back onto the measured map first, so that mirror images share their sub-tile."""
        out = np.empty(p.shape[0], np.int32)
        kernels.subtile_index(np.asarray(p, F32), *self.subtile_grid(grid), out)
        return out

    def subtile_grid(self, grid: tuple) -> tuple:
        """The numbers of `subtile_of` (`kernels.subtile_index`, `kernels.split_rays`): hx, hy, the half extents,
        the float32 scales (the sub-tile count over the relief's own extent: half the tile when mirror-extended,
        where the coordinates are folded back), mirrored, gx, gy."""
        gx, gy = int(grid[0]), int(grid[1])
        half_x, half_y = self.Lx / F32(2), self.Ly / F32(2)
        if self.mesh.mirrored:
            scale_x, scale_y = F32(gx) / half_x, F32(gy) / half_y
        else:
            scale_x, scale_y = F32(gx) / self.Lx, F32(gy) / self.Ly
        return self.hx, self.hy, half_x, half_y, scale_x, scale_y, bool(self.mesh.mirrored), gx, gy

    def relief_key(self, relief: Relief, mesh_options: tuple) -> "hashlib._Hash":
        """sha256 of the heights and mesh options (kept when `relief` is this tracer's own relief:
        hashing 8 MB of heights costs ~30 ms per request, e.g. in fits that reuse the tracer)."""
        own = relief is self.relief
        if own and mesh_options in self._relief_hash_cache:
            return self._relief_hash_cache[mesh_options].copy()
        h = relief_hash(relief, mesh_options)
        if own:
            self._relief_hash_cache[mesh_options] = h.copy()
        return h

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
        k = _check_dirs(dirs)
        n = k.shape[0]
        n_above, n_below = check_index_pair(n_above, n_below)
        if n == 0:
            return ScatterResult(dirs=np.zeros((0, 3)), weight=np.zeros(0), above=np.zeros(0, bool),
                                 stokes=np.zeros((0, 4)) if (stokes is not None or polarized) else None,
                                 lost=np.zeros(0, bool), bounces=np.zeros(0, np.int64), state=np.zeros(0, np.int8))
        from_below = k[:, 2] > 0
        if from_below.any() and np.iscomplexobj(n_below) and np.imag(n_below) > 0:
            raise RequestError("rays cannot arrive from inside an absorbing medium", "dirs")
        xy = self._entry_points(n, rng, origins_xy)
        weight, st = _initial_stokes(stokes, polarized, n)
        order = _block_order(xy, self.hx, self.hy)    # coherence: sort by 32 x 32 px blocks of the entry point
        o = np.empty((n, 3), F32)
        o[:, :2] = xy[order]
        o[:, 2] = np.where(from_below[order], self.z_bot, self.z_top)
        A = None if st is None else (st[order] / st[order, :1]).T.astype(F32)[:, None, :]  # (4, 1, n)
        seeds = rng.integers(0, 2**63 - 1, size=max(1, -(-n // CHUNK)))
        exits = self.run_chunks(Rays(o, k[order].astype(F32), from_below[order], np.ones(n, F32),
                                     np.zeros(n, np.int16), np.arange(n, dtype=np.int64), A),
                                seeds, Media(n_above, n_below), TraceSettings(self.max_bounces, False))
        return _scatter_result(exits, order, weight, st is not None)

    def _entry_points(self, n: int, rng, origins_xy) -> np.ndarray:
        if origins_xy is None:
            xy = rng.random((n, 2))
            xy[:, 0] = (xy[:, 0] - 0.5) * self.Lx
            xy[:, 1] = (xy[:, 1] - 0.5) * self.Ly
            return xy
        xy = np.asarray(origins_xy, dtype=np.float64) / self.mesh.unit_m
        if xy.shape != (n, 2):
            raise RequestError(f"origins_xy must have shape ({n}, 2), got {xy.shape}", "origins_xy")
        return np.mod(xy + [self.hx, self.hy], [self.Lx, self.Ly]) - [self.hx, self.hy]

    def run_chunks(self, rays: Rays, seeds, media: Media, settings: TraceSettings) -> list[Exits]:
        """Trace `rays` in fixed chunks of CHUNK (chunk c with generator PCG64(seeds[c])) over a
        thread pool; the chunks' exits in chunk order (deterministic for given seeds)."""
        n = rays.size
        bounds = [(i, min(n, i + CHUNK)) for i in range(0, n, CHUNK)]
        K = 0 if rays.A is None else rays.A.shape[1]

        def job(ci):
            lo, hi = bounds[ci]
            rng = np.random.Generator(np.random.PCG64(int(seeds[ci])))
            sub = Rays(rays.o[lo:hi].copy(), rays.k[lo:hi].copy(), rays.below[lo:hi].copy(), rays.w[lo:hi].copy(),
                       rays.nb[lo:hi].copy(), rays.ids[lo:hi] - lo,
                       None if rays.A is None else np.ascontiguousarray(rays.A[:, :, lo:hi]))
            return trace_chunk(self, sub, carrier_for(K), media, settings, rng)

        if self.threads > 1 and len(bounds) > 1:
            with ThreadPoolExecutor(max_workers=self.threads) as ex:
                return list(ex.map(job, range(len(bounds))))
        return [job(ci) for ci in range(len(bounds))]


# ----------------------------------------------------------------------------- helpers


_SIGN_BIT = np.uint32(0x80000000)


def copysign_positive(mag: np.ndarray, sgn: np.ndarray) -> np.ndarray:
    """np.copysign(mag, sgn) for float32 arrays whose mag has a clear sign bit (mag >= 0, as the slab's
    half-extents): sgn's sign bit or-ed into mag's bits, bit for bit np.copysign's result (numpy's
    copysign has no vector loop: ~4x the time of a multiply on the query's 3 n numbers)."""
    r = np.bitwise_and(sgn.view(np.uint32), _SIGN_BIT)
    r |= mag.view(np.uint32)
    return r.view(F32)


def _check_dirs(dirs) -> np.ndarray:
    k = np.asarray(dirs, dtype=np.float64)
    if k.ndim != 2 or k.shape[1] != 3:
        raise RequestError(f"dirs must have shape (N, 3), got {k.shape}", "dirs")
    k = k / np.sqrt(np.einsum("ij,ij->i", k, k))[:, None]
    if np.any(np.abs(k[:, 2]) < 1e-9) or not np.all(np.isfinite(k)):
        raise RequestError("ray directions must be finite and cross the mean plane (dz != 0)", "dirs")
    return k


def _initial_stokes(stokes, polarized: bool, n: int):
    """(weight (n,), Stokes (n, 4) or None): given Stokes (S0 = weight), unpolarised, or none."""
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
        return weight, st
    if polarized:
        st = np.zeros((n, 4))
        st[:, 0] = 1
        return weight, st
    return weight, None


def _scatter_result(exits: list[Exits], order: np.ndarray, weight: np.ndarray, polarized: bool) -> ScatterResult:
    """Chunks' exits back in input order."""
    parts = [e.ordered() for e in exits]
    out_k = np.concatenate([p[0] for p in parts])
    out_w = np.concatenate([p[2] for p in parts])
    out_state = np.concatenate([p[3] for p in parts])
    out_b = np.concatenate([p[4] for p in parts])
    n = order.size
    inv = np.empty(n, np.int64)
    inv[order] = np.arange(n)
    state = out_state[inv]
    stokes_out = None
    if polarized:
        out_A = np.concatenate([p[1] for p in parts], axis=2)
        stokes_out = out_A[:, 0, :].T[inv].astype(np.float64) * weight[:, None]
    return ScatterResult(dirs=out_k[inv].astype(np.float64), weight=weight * out_w[inv], above=state == ABOVE,
                         stokes=stokes_out, lost=state >= 2, bounces=out_b[inv].astype(np.int64), state=state,
                         segments=sum(e.segments for e in exits))


def check_index_pair(n_above, n_below):
    """(n_above real, n_below real or complex) after refusing unphysical indices."""
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


def relief_hash(relief: Relief, mesh_options: tuple) -> "hashlib._Hash":
    """sha256 of the heights, pitch, periodicity and mesh options (what changes a BVH): the relief's one
    content digest (`surface.digest`) with the mesh options."""
    return _relief_hash(relief, tuple(mesh_options))


def cached_tracer(key: tuple, relief: Relief, max_bounces: int, fill_holes, threads: int | None) -> ReliefTracer:
    """The BVH cache: this worker's one `ReliefTracer` for `key` (built on first use,
    `parallel.worker_cached`; key from `relief_hash`, so a worker builds one per relief)."""
    return worker_cached(key, lambda: ReliefTracer(relief, max_bounces, fill_holes, threads=threads))


def forget_tracer(key: tuple) -> None:
    """Drop this process's cached tracer for `key` (a BVH built for one request is not kept)."""
    forget_worker_cached(key)
