"""The ONE table builder: sampled exit directions and weights -> BSDF table cells.

Every method that *samples* paths (`ray`, `normals`) hands its exits here; the wave methods
and `microfacet` integrate a continuous density over the cells instead (quadrature on
sub-points, `methods.wave_filter.cell_average` / `methods.microfacet.cell_average`) and do
not come through this module.

Estimator (formats.md units, 1/sr).  N paths are started per incidence, each with the
incident beam's power 1/N spread uniformly over the tile; a path's exits carry power weights
w (and, polarised, the exit Mueller columns M, so w M is the exit Mueller matrix).  The
table cell (theta_s, phi_s) holds the cell average of the BSDF in projected solid angle,

    f_cell = sum_{exits in cell} w / (N Omega_proj(cell)),    Omega_proj = (sin^2 t1 - sin^2 t0)(p1 - p0) / 2,

so that `BsdfTable.hemispherical()` returns the power fractions of the beam.  Its Monte-Carlo
standard error is the sample standard deviation of the per-path contribution,
sigma = sqrt((sum w^2 / N - (sum w / N)^2) / N) / Omega_proj (one exit per path and cell).
Realisation uncertainty of a finite tile (sub-tile batch means).  The cell value of one tile is
itself a random draw: another tile of the same surface statistics gives another value (a cell
that a few facets fill scatters by tens of percent however many rays are traced).  When the
method tags every path with the sub-tile g = 1..G of its first hit (sub-tiles several
correlation lengths wide, so that their contributions are nearly independent), the cell value
is the ratio estimator f = sum_g S_g / sum_g n_g (S_g: the weights of the cell's exits of group
g; n_g: paths of group g), whose variance over both the rays and the surface's realisations is
estimated by the cluster-sampling (batch-means) formula

    V_block = G / (G - 1) sum_g (S_g - f n_g)^2 / N^2        (Cochran 1977, Sampling Techniques, eq. 6.9),

the analytic limit of a bootstrap over sub-tiles.  V_block contains the Monte-Carlo variance
V_mc above; the tile part is V_tile = max(V_block - V_mc, 0) (`sigma_tile_per_sr`) and the
table's sigma is sqrt(V_mc + V_tile).  Assumes the tile is one realisation of a stationary
surface and sub-tiles decorrelate (side >= ~4 correlation lengths: the estimate is then
~10 % low in sigma); G >= 16 gives sigma to ~20 %.
Exits flagged as coherent / specular (along the flat mean plane's mirror or refraction
direction, `specular_flags`) go to the delta parts specular_R/T (power fractions) instead.
`lost` = power of paths that did not leave (named by the method: absorbed, max bounces, ...)
plus exits outside the table's cells, over N: nothing is dropped silently.
Sides: 0 = the side of incidence (R), 1 = the other side (T).
Binning is vectorised (np.bincount) on cells from `CellIndex` (float32 arithmetic and lookup
tables for uniform grids, a search for others); float32 batches go through the kernels
(`relief_bsdf.kernels`: the cell index after numpy's arccos and arctan2, and the weights, their squares
and the 16 Mueller entries into the cells in one pass, `kernels.bin_cells`, the sums of np.bincount in
the same order).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from relief_bsdf import kernels
from relief_bsdf.core.frames import projected_solid_angle

F32 = np.float32
# how far numpy's float32 arccos and arctan2 may be from the angles of `kernels.cells_of_directions`
# (radians): their few-ulp error (<= 4 ulp: 1e-6 rad at pi) plus the kernel's (float32 arithmetic: < 1.5e-6,
# decision record 014) and the float32 rounding of angle +- margin (1.2e-7), with a factor 8 to spare; a
# direction this close to a cell edge takes numpy's angles
ANGLE_MARGIN_RAD = 2e-5


# ----------------------------------------------------------------------------- cells


class CellIndex:
    """Scatter cell of exit directions for the (theta_s, phi_s) edges (degrees), built once per task.

    Uniform edges (the default 1-degree rings x 5-degree azimuths, and any uniform grid): float32
    arithmetic on arccos |k_z| and atan2(k_y, k_x) in units of the cell width, truncation, and
    small lookup tables that fold the azimuth modulo 360 degrees and mark cells beyond the edges
    (no float modulo, no search).  Other edges: a search.  `__call__(k)` returns int32
    cell = ring * A + azimuth, or -1 outside the table (|k_z| is used: the ring of either side).
    """

    def __init__(self, theta_edges_deg, phi_edges_deg):
        te = np.asarray(theta_edges_deg, float)
        pe = np.asarray(phi_edges_deg, float)
        self.S, self.A = te.size - 1, pe.size - 1
        self.te, self.pe = te, pe
        self.te_sin2 = np.sin(np.radians(te)) ** 2
        dt, dp = np.diff(te), np.diff(pe)
        n_full = 360.0 / dp[0]
        self.fast = bool(np.allclose(dt, dt[0], rtol=1e-9, atol=1e-9) and np.allclose(dp, dp[0])
                         and abs(n_full - round(n_full)) < 1e-9)
        if self.fast:
            self._ring_table(dt[0])
            self._azimuth_table(dp[0], int(round(n_full)))

    def _ring_table(self, dt: float) -> None:
        """x = (theta - te0) / dt, shifted by one ring so that truncation == floor for x > -1."""
        te, S = self.te, self.S
        self.t_scale = F32(180.0 / np.pi / dt)
        self.t_off = F32(1.0 - te[0] / dt)
        nt = int(math.ceil(90.0 / dt + 1.0 - te[0] / dt)) + 2
        ring = np.arange(nt) - 1                       # truncated value j -> ring j - 1
        if te[-1] >= 90.0 - 1e-9:
            ring[ring == S] = S - 1                    # theta = 90 exactly belongs to the last ring
        ring[(ring < 0) | (ring >= S)] = -1
        self.ring_lut = ring.astype(np.int32)

    def _azimuth_table(self, dp: float, nf: int) -> None:
        """x = (phi - pe0) / dp + shift, shift a multiple of the full turn making x >= 0."""
        pe = self.pe
        lo = -180.0 / dp - pe[0] / dp
        shift = nf * int(math.ceil(max(0.0, -lo) / nf + 1e-9))
        self.p_scale = F32(180.0 / np.pi / dp)
        self.p_off = F32(shift - pe[0] / dp)
        npl = int(math.ceil(180.0 / dp - pe[0] / dp + shift)) + 2
        az = np.arange(npl) % nf
        az[az >= self.A] = -1                          # beyond the last edge (span < 360)
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

    def with_side(self, k: np.ndarray, side: np.ndarray) -> np.ndarray:
        """cell + side * S * A (the table's two sides), -1 outside the table: `__call__` and the side's
        offset.  For float32 directions on uniform edges, `kernels.cells_of_directions` settles every
        direction whose angles lie farther than ANGLE_MARGIN_RAD from a cell edge without numpy's arccos
        and arctan2 (the index is non-decreasing in the angle); the few others take numpy's angles
        (`_cells_of_numpy_angles`): the numbers of `__call__` in both cases."""
        S, A = self.S, self.A
        if not (self.fast and k.dtype == F32):
            cell = self(k)
            out = cell >= 0
            cell += side.astype(np.int32) * np.int32(S * A)
            cell[~out] = -1
            return cell
        n = k.shape[0]
        side8 = side.astype(np.int8, copy=False)
        cell, exact = np.empty(n, np.int32), np.empty(n, np.int64)
        ne = kernels.cells_of_directions(k, self.t_scale, self.t_off, self.p_scale, self.p_off, self.ring_lut,
                                         self.az_lut, A, side8, S * A, ANGLE_MARGIN_RAD, cell, exact)
        if ne:
            idx = exact[:ne]
            cell[idx] = self._cells_of_numpy_angles(np.take(k, idx, axis=0), np.take(side8, idx))
        return cell

    def _cells_of_numpy_angles(self, k: np.ndarray, side8: np.ndarray) -> np.ndarray:
        """`with_side` from numpy's float32 arccos min(|k_z|, 1) and arctan2(k_y, k_x) (`kernels.direction_parts`
        and `kernels.cells_of_angles` around them)."""
        n = k.shape[0]
        x, kx, ky = np.empty(n, F32), np.empty(n, F32), np.empty(n, F32)
        kernels.direction_parts(k, x, kx, ky)
        np.arccos(x, out=x)
        y = np.arctan2(ky, kx, out=ky)
        cell = np.empty(n, np.int32)
        kernels.cells_of_angles(x, y, self.t_scale, self.t_off, self.p_scale, self.p_off, self.ring_lut, self.az_lut,
                                self.A, side8, self.S * self.A, cell)
        return cell


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


def specular_flags(dirs: np.ndarray, side: np.ndarray, ideal_dirs: tuple, cos_tol: float) -> np.ndarray | None:
    """Exits within acos(cos_tol) of the flat mean plane's ideal direction of their side.

    ideal_dirs: (mirror direction, refraction direction or None), unit, in the frame of `dirs`.
    A float32 prefilter, then float64 with renormalisation (a float32 unit vector's norm is off
    by ~1e-8 >> 1 - cos(tol)).  Returns a bool mask, or None when no exit is specular.
    """
    spec = None
    both = None
    if dirs.dtype == F32 and ideal_dirs[0] is not None and ideal_dirs[1] is not None:
        a, b = (np.asarray(d, np.float64).astype(F32) for d in ideal_dirs)     # both prefilters in one pass
        out_a, out_b = np.empty(dirs.shape[0], np.int64), np.empty(dirs.shape[0], np.int64)
        na, nb = kernels.near_two_directions(dirs, *a, *b, F32(0.9999), out_a, out_b)
        both = (out_a[:na], out_b[:nb])
    for sd in (0, 1):
        if ideal_dirs[sd] is None:
            continue
        d = np.asarray(ideal_dirs[sd], np.float64)
        # explicit multiply-adds, not `k @ d`: a BLAS matrix-vector product wakes OpenBLAS's
        # thread pool, whose spinning threads cost as much CPU as the whole binning
        cand = both[sd] if both is not None else _near_direction(dirs, d.astype(F32), F32(0.9999))
        if cand.size:
            kc = dirs[cand].astype(np.float64)
            ok = np.einsum("ij,j->i", kc, d) > cos_tol * np.sqrt(np.einsum("ij,ij->i", kc, kc))
            ok &= side[cand] == sd
            if ok.any():
                if spec is None:
                    spec = np.zeros(dirs.shape[0], bool)
                spec[cand[ok]] = True
    return spec


def _near_direction(dirs: np.ndarray, d32: np.ndarray, cos_min: np.float32) -> np.ndarray:
    """Indices of the directions whose dot product with d32 (multiply-adds in the directions' precision)
    exceeds cos_min (float32 directions: `kernels.near_direction`, the same operations)."""
    if dirs.dtype == F32:
        out = np.empty(dirs.shape[0], np.int64)
        return out[:kernels.near_direction(dirs, *d32, cos_min, out)]
    c = dirs[:, 0] * d32[0]
    c += dirs[:, 1] * d32[1]
    c += dirs[:, 2] * d32[2]
    return np.flatnonzero(c > cos_min)


# ----------------------------------------------------------------------------- accumulation


@dataclass
class ExitSamples:
    """Exits of a batch of paths that left through the boundary.

    dirs (n, 3) unit directions (float32 or float64) in the table's frame up to the z sign;
    weight (n,) power weights; side (n,) 0 (incidence side) or 1; mueller (16, n) float32 exit
    Mueller columns (row-major 4 x 4 per exit, w M is the exit matrix) or None; specular (n,)
    bool: coherent / specular exits (delta parts), or None for none; group (n,) int: the sub-tile
    of the path's first hit (0..G-1), for the realisation uncertainty (module doc), or None;
    compact (n,) uint8 or None: exits whose mueller holds the compact form the ray kernels write (flag 1:
    `methods.ray.exits.Exits`), which the kernels' binning expands (`whole_mueller` for the others).
    """

    dirs: np.ndarray
    weight: np.ndarray
    side: np.ndarray
    mueller: np.ndarray | None = None
    specular: np.ndarray | None = None
    group: np.ndarray | None = None
    compact: np.ndarray | None = None
    group_of_path: tuple | None = None      # (group per path (n_paths,), path id per exit (n,), n_paths): group lazily

    def groups(self) -> np.ndarray | None:
        """The sub-tile group of each exit: `group`, or from `group_of_path` (exit i's path is its id mod
        n_paths: the first-hit split's second branch has id + n_paths)."""
        if self.group is not None or self.group_of_path is None:
            return self.group
        g, ids, n = self.group_of_path
        return np.take(np.concatenate([g, g]), ids)

    def whole_mueller(self, idx: np.ndarray | None = None) -> np.ndarray:
        """The Mueller columns (16, n) of the exits idx (None: all) written whole (a copy where any is compact)."""
        M = self.mueller if idx is None else np.take(self.mueller, idx, axis=1)
        c = None if self.compact is None else (self.compact if idx is None else self.compact[idx])
        if c is None or not c.any():
            return M
        M = np.array(M, F32, order="C")
        kernels.expand_compact(M, c.copy())
        return M


@dataclass
class TableCells:
    """One incidence's table rows: values / sigma (2, S, A) float32 1/sr, Mueller (2, S, A, 4, 4)
    float32 1/sr or None, delta parts (power fractions) and their Mueller matrices, `lost` and its
    detail (power fractions).  sigma_per_sr is the total (Monte-Carlo and, with sub-tile groups,
    the tile's realisation uncertainty); sigma_tile_per_sr the tile part alone (None without groups)."""

    values_per_sr: np.ndarray
    sigma_per_sr: np.ndarray
    specular_R: float
    specular_T: float
    lost: float
    lost_detail: dict
    outside_table: float
    sigma_tile_per_sr: np.ndarray | None = None
    mueller_per_sr: np.ndarray | None = None
    specular_mueller_R: np.ndarray | None = None
    specular_mueller_T: np.ndarray | None = None


@dataclass
class CellAccumulator:
    """Per-incidence sums of weights (w, w^2 and w M) per cell, delta parts and lost power.

    `add` one batch of exits at a time, `lose` the power of paths that did not leave, `merge`
    partial accumulators in a fixed order (deterministic sums), then `cells(n_paths)`.  With
    n_groups > 0 the weights are also summed per (sub-tile group, cell) and `count_paths` counts
    the paths of each group (realisation uncertainty, module doc).  sum_M is (cells, 16): a cell's
    16 Mueller sums side by side (row-major 4 x 4).
    """

    cells: CellIndex
    polarized: bool = False
    lost_names: tuple = ()
    n_groups: int = 0
    sum_w: np.ndarray = field(init=False)
    sum_w2: np.ndarray = field(init=False)
    sum_M: np.ndarray | None = field(init=False)
    spec: np.ndarray = field(init=False)
    spec_M: np.ndarray | None = field(init=False)
    lost: dict = field(init=False)
    outside_table: float = field(init=False, default=0.0)
    paths_group: np.ndarray | None = field(init=False)
    _group_parts: list = field(init=False)          # (key = group * cells + cell, weight) per batch
    _untouched: bool = field(init=False, default=True)   # every sum still exactly zero (nothing added)

    def __post_init__(self):
        nc = 2 * self.cells.S * self.cells.A
        self.sum_w = np.zeros(nc)
        self.sum_w2 = np.zeros(nc)
        G = int(self.n_groups)
        self.paths_group = np.zeros(G) if G else None
        self._group_parts = []
        self.sum_M = np.zeros((nc, 16)) if self.polarized else None
        self.spec = np.zeros(2)
        self.spec_M = np.zeros((2, 16)) if self.polarized else None
        self.lost = {name: 0.0 for name in self.lost_names}

    def lose(self, name: str, weight_sum: float) -> None:
        self.lost[name] = self.lost.get(name, 0.0) + float(weight_sum)

    def count_paths(self, group_of_path: np.ndarray) -> None:
        """Count started paths per sub-tile group (one entry per path: the group of its first hit)."""
        if self.paths_group is not None:
            self.paths_group += np.bincount(group_of_path, minlength=self.paths_group.size)[:self.paths_group.size]

    def merge(self, other: "CellAccumulator") -> None:
        self._untouched = False
        self.sum_w += other.sum_w
        self.sum_w2 += other.sum_w2
        if self.paths_group is not None:
            self._group_parts.extend(other._group_parts)    # summed once, in merge order, by `sum_w_group`
            self.paths_group += other.paths_group
        if self.sum_M is not None:
            self.sum_M += other.sum_M
            self.spec_M += other.spec_M
        self.spec += other.spec
        for k_, v in other.lost.items():
            self.lost[k_] = self.lost.get(k_, 0.0) + v
        self.outside_table += other.outside_table

    def add(self, ex: ExitSamples) -> None:
        """Bin one batch of exits (float32: `kernels.bin_cells`; others np.bincount: module doc)."""
        wd, side, spec = ex.weight, ex.side, ex.specular
        if wd.size == 0:
            return
        cell = self.cells.with_side(ex.dirs, side)
        inside = cell >= 0
        if spec is not None:
            inside &= ~spec
            self._add_specular(ex)
        n_in = int(np.count_nonzero(inside))
        if wd.size - n_in - (0 if spec is None else int(np.count_nonzero(spec))):
            self.outside_table += float(wd[~inside & (True if spec is None else ~spec)].sum(dtype=np.float64))
        full = n_in == wd.size
        if self._kernel_takes(ex):
            if not full:
                cell[~inside] = -1                  # the kernel skips them: no gather of the Mueller columns
            self._bin_kernel(cell, ex)
        else:
            c_in = cell if full else cell[inside]
            w_in = (wd if full else wd[inside]).astype(np.float64)
            M = None
            if self.sum_M is not None:
                M = ex.whole_mueller(None if full else np.flatnonzero(inside))
            self._bin_numpy(c_in, w_in, M)
            if self.paths_group is not None:
                g = ex.groups() if full else ex.groups()[inside]
                gc = g.astype(np.int64) * self.sum_w.size
                gc += c_in
                self._group_parts.append((gc, w_in))
        self._untouched = False

    def _kernel_takes(self, ex: ExitSamples) -> bool:
        """Whether `kernels.bin_cells` takes this batch (float32 weights and Mueller columns)."""
        return ex.weight.dtype == F32 and (self.sum_M is None or ex.mueller.dtype == F32)

    def _bin_numpy(self, c_in: np.ndarray, w_in: np.ndarray, M: np.ndarray | None) -> None:
        """The binning of batches in other precisions: np.bincount per sum (M: the Mueller columns (16, n) of
        the exits c_in)."""
        nc = self.sum_w.size
        self.sum_w += np.bincount(c_in, weights=w_in, minlength=nc)
        self.sum_w2 += np.bincount(c_in, weights=w_in * w_in, minlength=nc)
        if self.sum_M is not None:
            M16 = M * w_in.astype(F32)
            for e in range(16):
                self.sum_M[:, e] += np.bincount(c_in, weights=M16[e], minlength=nc)

    def _bin_kernel(self, cell: np.ndarray, ex: ExitSamples) -> None:
        """`_bin_numpy` in one pass, `kernels.bin_cells` (cells < 0 skipped).  The kernel adds exit by exit;
        into sums that already hold something it adds a batch's own sums (as `+= np.bincount`), so that both give the
        same numbers bit for bit."""
        polar = self.sum_M is not None
        if self._untouched:
            sums = (self.sum_w, self.sum_w2, self.sum_M)
        else:
            sums = (np.zeros_like(self.sum_w), np.zeros_like(self.sum_w2), np.zeros_like(self.sum_M) if polar else None)
        compact = ex.compact if polar else None
        if self.paths_group is None:
            kernels.bin_cells(cell, ex.weight, ex.mueller if polar else None, *sums, compact=compact)
        else:                                       # the group keys and float64 weights of the binned exits too
            keys, w64 = np.empty(cell.size, np.int32), np.empty(cell.size, F32)     # float32 weights: exact
            if ex.group is None and ex.group_of_path is not None:     # the exit's group from its path's
                g, ids, n = ex.group_of_path
                j = kernels.bin_cells(cell, ex.weight, ex.mueller if polar else None, *sums,
                                       g.astype(np.int32, copy=False), keys, w64, compact, ids, n)
            else:
                j = kernels.bin_cells(cell, ex.weight, ex.mueller if polar else None, *sums,
                                       ex.group.astype(np.int32, copy=False), keys, w64, compact)
            self._group_parts.append((keys[:j], w64[:j]))
        if not self._untouched:
            self.sum_w += sums[0]
            self.sum_w2 += sums[1]
            if polar:
                self.sum_M += sums[2]

    def _add_specular(self, ex: ExitSamples) -> None:
        for sd in (0, 1):
            msk = ex.specular & (ex.side == sd)
            if msk.any():
                self.spec[sd] += float(ex.weight[msk].sum(dtype=np.float64))
                if self.sum_M is not None:
                    Ms = ex.whole_mueller(np.flatnonzero(msk))
                    self.spec_M[sd] += (Ms * ex.weight[msk]).sum(axis=1, dtype=np.float64)

    def table_cells(self, n_paths: float) -> TableCells:
        """The finished rows for `n_paths` started paths (module doc: estimator and sigma)."""
        S, A_ = self.cells.S, self.cells.A
        psa = projected_solid_angle(self.cells.te, self.cells.pe)
        n = float(n_paths)
        mean = self.sum_w / n
        var = np.maximum(self.sum_w2 / n - mean**2, 0.0) / n
        var_tile = self._tile_variance(mean, var, n)
        sig_tile = None
        if var_tile is not None:
            sig_tile = (np.sqrt(var_tile).reshape(2, S, A_) / psa).astype(F32)
            var = var + var_tile
        out = TableCells(values_per_sr=(mean.reshape(2, S, A_) / psa).astype(F32),
                         sigma_per_sr=(np.sqrt(var).reshape(2, S, A_) / psa).astype(F32),
                         sigma_tile_per_sr=sig_tile,
                         specular_R=float(self.spec[0] / n), specular_T=float(self.spec[1] / n),
                         lost=float((sum(self.lost.values()) + self.outside_table) / n),
                         lost_detail={k_: v / n for k_, v in self.lost.items()},
                         outside_table=self.outside_table / n)
        if self.sum_M is not None:
            m = (self.sum_M / n).reshape(2, S, A_, 4, 4)
            out.mueller_per_sr = (m / psa[None, :, :, None, None]).astype(F32)
            out.specular_mueller_R = (self.spec_M[0] / n).reshape(4, 4)
            out.specular_mueller_T = (self.spec_M[1] / n).reshape(4, 4)
            out.values_per_sr = out.mueller_per_sr[..., 0, 0].copy()
        return out

    def sum_w_group(self) -> np.ndarray:
        """Sums of the weights per (group, cell), (n_groups, cells) (the batches' parts added once:
        a dense array per batch would cost more than the binning itself)."""
        nc = self.sum_w.size
        G = int(self.n_groups)
        if not self._group_parts:
            return np.zeros((G, nc))
        out = np.zeros(G * nc)                      # np.bincount's sums in its order, without concatenating
        for k_, w_ in self._group_parts:
            kernels.add_at(k_, w_, out)
        return out.reshape(G, nc)

    def _tile_variance(self, mean: np.ndarray, var_mc: np.ndarray, n: float) -> np.ndarray | None:
        """V_tile = max(V_block - V_mc, 0) per cell (module doc; power fractions squared), or None
        without groups (or fewer than two non-empty ones)."""
        if self.paths_group is None:
            return None
        n_g = self.paths_group
        used = n_g > 0
        G = int(np.count_nonzero(used))
        if G < 2:
            return None
        # a cell no ray reached has V_block = 0; a cell's group sums are all zero iff its sum of w^2 is (w real)
        lit = np.flatnonzero(self.sum_w2 != 0)
        S_g = self.sum_w_group()[np.ix_(np.flatnonzero(used), lit)]
        dev = S_g - mean[None, lit] * (n_g[used] * 1.0)[:, None]   # mean = f (power fraction per path)
        v_block = np.zeros_like(mean)
        v_block[lit] = G / (G - 1) * np.einsum("gc,gc->c", dev, dev) / (n * n)
        return np.maximum(v_block - var_mc, 0.0)
