"""One boundary table seen by the deterministic engine: `_TableView` samples a table at one wavelength on the
engine's angles (linear in theta_i, moving lobes between an inside table's incidences), through the one
table interpolation of `bsdf.table` (`interpolation_matrix`) and the gathers of `_apply`."""
from __future__ import annotations

from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable, interpolation_matrix, linear_weights
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.errors import InputError


_DEPOL = np.diag([1.0, 0.0, 0.0, 0.0])


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


def _fresnel(cos_i: np.ndarray, n1: float, n2: float, kind: str) -> np.ndarray:
    return mueller_interface(np.asarray(cos_i, float), n1, n2, kind)


def _snell_deg(theta_deg: Any, n1: float, n2: float) -> np.ndarray:
    s = np.sin(np.radians(theta_deg)) * n1 / n2
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))
