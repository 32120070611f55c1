"""The `Relief` type: a measured or synthetic height map of a rough boundary.

Heights are in metres on a regular grid; row index is y (pitch dy_m), column
index is x (pitch dx_m).  Invalid (not measured) points are NaN and stay NaN:
nothing here fills them unless asked (`fill_holes`), and every such choice is
recorded in `history` so reports can state what was done to the data.

Operations return new reliefs (the type is immutable in spirit): levelling,
hole filling, Gaussian filtering, height scaling, cropping.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from relief_bsdf.errors import InputError


@dataclass(frozen=True)
class Relief:
    """A height map z(x, y) in metres.

    heights_m: (ny, nx) float64, NaN where the instrument gave no data.
    dx_m, dy_m: lateral pitch along x (columns) and y (rows).
    periodic: True when the tile repeats seamlessly (synthetic reliefs); measured
        maps are not periodic and methods that need periodicity window or mirror them.
    source: file the relief came from (or a description of how it was made).
    metadata: instrument / reader information (channel, units in the file, ...).
    history: processing steps applied since reading, in order, human readable.
    """

    heights_m: np.ndarray
    dx_m: float
    dy_m: float
    periodic: bool = False
    source: str = ""
    metadata: dict = field(default_factory=dict)
    history: tuple = ()

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_m, dtype=float)
        where = self.source or "relief"
        if h.ndim == 1:
            raise InputError(where, "this is a 1-D line profile, not a height map; "
                             "2-D work (BSDF reconstruction, plate simulation) needs an area scan")
        if h.ndim != 2:
            raise InputError(where, f"height map must be 2-D, got shape {h.shape}")
        if h.shape[0] < 2 or h.shape[1] < 2:
            raise InputError(where, f"height map of shape {h.shape} is too small (need at least 2 x 2)")
        for name in ("dx_m", "dy_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(where, f"lateral pitch {name} must be a positive number of metres, got {v!r}")
        h = np.where(np.isfinite(h), h, np.nan)
        object.__setattr__(self, "heights_m", h)

    # ------------------------------------------------------------ basic facts
    @property
    def shape(self) -> tuple[int, int]:
        return self.heights_m.shape  # (ny, nx)

    @property
    def valid(self) -> np.ndarray:
        """Boolean mask of measured points."""
        return np.isfinite(self.heights_m)

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())

    @property
    def size_m(self) -> tuple[float, float]:
        """Physical size (Lx, Ly) of the tile."""
        ny, nx = self.shape
        return nx * self.dx_m, ny * self.dy_m

    def require_valid(self, min_fraction: float = 0.0) -> None:
        """Raise InputError if there is no valid data (or less than `min_fraction`)."""
        vf = self.valid_fraction
        if vf == 0.0:
            raise InputError(self.source or "relief", "the height map has no valid points (all NaN)")
        if vf < min_fraction:
            raise InputError(self.source or "relief",
                             f"only {vf:.1%} of the height map is valid; need at least {min_fraction:.0%}")

    def with_heights(self, heights_m: np.ndarray, step: str, **changes: Any) -> "Relief":
        """New relief with other heights and one more history entry."""
        return replace(self, heights_m=heights_m, history=self.history + (step,), **changes)

    # ------------------------------------------------------------ processing
    def level(self, order: int = 1) -> "Relief":
        """Subtract the least-squares polynomial surface of total degree `order` (valid points only).

        order 0 removes the mean, 1 a plane (the default, as Gwyddion's mean-plane levelling),
        2 a quadric (bow of a bent sample), etc.
        """
        self.require_valid()
        if order < 0:
            raise InputError("level", f"polynomial order must be >= 0, got {order}")
        ny, nx = self.shape
        y, x = np.mgrid[0:ny, 0:nx]
        # scaled coordinates keep the normal equations well conditioned
        xs = (x - (nx - 1) / 2) / max(nx - 1, 1)
        ys = (y - (ny - 1) / 2) / max(ny - 1, 1)
        m = self.valid
        cols = [xs**i * ys**j for i in range(order + 1) for j in range(order + 1 - i)]
        A = np.stack([c[m] for c in cols], axis=1)
        # normal equations: A has few columns of scaled monomials, so A^T A is small and well conditioned
        coef = np.linalg.lstsq(A.T @ A, A.T @ self.heights_m[m], rcond=None)[0]
        surf = sum(c * k for c, k in zip(cols, coef))
        name = {0: "mean", 1: "plane"}.get(order, f"polynomial order {order}")
        return self.with_heights(self.heights_m - surf, f"levelled: subtracted least-squares {name}",
                                 periodic=self.periodic and order == 0)

    def fill_holes(self, max_gap_px: int | None = None) -> "Relief":
        """Fill invalid points by harmonic (Laplace) interpolation from their valid neighbours.

        The filled heights solve the discrete Laplace equation (each filled point is the mean
        of its four neighbours) with the valid points around each hole as fixed boundary
        values; at the map's edge the missing neighbour is left out (zero slope across the
        edge), a periodic tile wraps around.  The assumption: inside a hole the surface is
        the smoothest one that meets its rim, so a hole adds no roughness of its own (its
        slopes are at most those of the rim; it under-states the roughness of large holes).
        The linear system is solved exactly (sparse direct solve; above `DIRECT_FILL_MAX`
        unknowns by conjugate gradients to a relative residual of 1e-10), so the result does
        not depend on a starting guess or an iteration count.

        Only holes no wider than `max_gap_px` pixels (largest distance to the nearest valid
        point) are filled when given; wider holes stay NaN.  Filling large gaps invents relief
        (the FRT sample's rms grows 4x if its 31% of holes are interpolated), so this is
        never done implicitly.
        """
        self.require_valid()
        invalid = ~self.valid
        if not invalid.any():
            return self
        fill = invalid.copy()
        if max_gap_px is not None:
            dist = ndimage.distance_transform_edt(invalid)
            # a hole is filled only if every point of its connected region is within the limit
            labels, n = ndimage.label(invalid)
            too_far = ndimage.maximum(dist, labels, index=np.arange(1, n + 1)) > max_gap_px
            fill = invalid & ~np.isin(labels, np.nonzero(too_far)[0] + 1)
        n_fill = int(fill.sum())
        if n_fill == 0:
            return self
        out = self.heights_m.copy()
        out[fill] = harmonic_fill_values(self.heights_m, fill, self.periodic)
        how = "harmonic (Laplace) interpolation from the valid neighbours"
        return self.with_heights(out, f"filled {n_fill} invalid points ({n_fill / out.size:.2%}) by {how}"
                                 + (f" (holes <= {max_gap_px} px)" if max_gap_px is not None else ""))

    def downsampled(self, k: int) -> "Relief":
        """Block means of k x k points (NaN-aware: a block's valid points; none valid: NaN), pitch x k.

        A box average before decimation, so finer components are attenuated rather than
        aliased.  Rows and columns beyond the last whole block are dropped (then the tile
        is no longer periodic).
        """
        if isinstance(k, bool) or int(k) != k or k < 1:
            raise InputError("downsample", f"expected a whole factor >= 1, got {k!r}")
        k = int(k)
        if k == 1:
            return self
        ny, nx = self.shape
        by, bx = ny // k, nx // k
        if by < 2 or bx < 2:
            raise InputError(self.source or "relief", f"downsampling {ny} x {nx} points by {k} leaves fewer "
                             "than 2 x 2")
        h = self.heights_m[:by * k, :bx * k].reshape(by, k, bx, k)
        v = np.isfinite(h)
        n = v.sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(n > 0, np.where(v, h, 0.0).sum(axis=(1, 3)) / np.maximum(n, 1), np.nan)
        whole = by * k == ny and bx * k == nx
        step = f"downsampled by {k} (block means of {k} x {k} points)" + (
            "" if whole else f", dropping {ny - by * k} row(s) and {nx - bx * k} column(s) beyond the last block")
        return self.with_heights(out, step, dx_m=self.dx_m * k, dy_m=self.dy_m * k,
                                 periodic=self.periodic and whole)

    def scaled(self, factor: float) -> "Relief":
        """Heights multiplied by `factor` (paper sec. 3 step 6: scaling raises diffuse scattering)."""
        if not np.isfinite(factor) or factor < 0:
            raise InputError("height_scale", f"scale factor must be a finite number >= 0, got {factor}")
        return self.with_heights(self.heights_m * factor, f"heights scaled by {factor:.6g}")

    def gaussian_filtered(self, sigma_m: float) -> "Relief":
        """Gaussian low-pass with standard deviation `sigma_m` (metres) in both directions.

        Paper sec. 3 step 6: smoothing lowers diffuse scattering.  NaN-aware (normalised
        convolution: invalid points neither contribute nor get filled); periodic reliefs
        are filtered with wrap-around.
        """
        if not np.isfinite(sigma_m) or sigma_m < 0:
            raise InputError("filter_sigma", f"filter width must be >= 0, got {sigma_m}")
        if sigma_m == 0:
            return self
        sig = (sigma_m / self.dy_m, sigma_m / self.dx_m)
        mode = "wrap" if self.periodic else "reflect"
        m = self.valid.astype(float)
        num = ndimage.gaussian_filter(np.where(self.valid, self.heights_m, 0.0), sig, mode=mode)
        den = ndimage.gaussian_filter(m, sig, mode=mode)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(self.valid, num / den, np.nan)
        return self.with_heights(out, f"Gaussian filter sigma = {sigma_m * 1e6:.4g} um")

    def cropped(self, rows: slice, cols: slice) -> "Relief":
        h = self.heights_m[rows, cols]
        return self.with_heights(h, f"cropped to rows {rows.start}:{rows.stop}, cols {cols.start}:{cols.stop}",
                                 periodic=False)

    def describe(self) -> dict:
        """Metadata for tables and reports (no arrays)."""
        return {"source": self.source, "shape": list(self.shape), "pitch_m": [self.dx_m, self.dy_m],
                "periodic": self.periodic, "valid_fraction": self.valid_fraction,
                "history": list(self.history)}


#: above this many unknowns the harmonic fill iterates (conjugate gradients) instead of a direct solve,
#: whose fill-in grows faster than the map
DIRECT_FILL_MAX = 200_000


def harmonic_fill_values(heights_m: np.ndarray, fill: np.ndarray, periodic: bool) -> np.ndarray:
    """Heights at the points `fill` (row-major order) that solve the discrete Laplace equation.

    Each unknown is the mean of its available neighbours (4-neighbourhood; an invalid point
    outside `fill` and a point beyond a non-periodic edge are not available); valid
    neighbours enter as fixed values.  Every hole region touches a valid point (the caller
    fills whole connected regions of a map with valid points), so the system is regular.
    """
    from scipy import sparse
    from scipy.sparse.linalg import spsolve
    ny, nx = heights_m.shape
    idx = -np.ones((ny, nx), dtype=np.int64)
    rr, cc = np.nonzero(fill)
    idx[rr, cc] = np.arange(rr.size)
    known = np.isfinite(heights_m)
    rows, cols, vals = [], [], []
    diag = np.zeros(rr.size)
    rhs = np.zeros(rr.size)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        r2, c2 = rr + dr, cc + dc
        if periodic:
            r2, c2, inside = r2 % ny, c2 % nx, np.ones(rr.size, bool)
        else:
            inside = (r2 >= 0) & (r2 < ny) & (c2 >= 0) & (c2 < nx)
        r2, c2 = np.clip(r2, 0, ny - 1), np.clip(c2, 0, nx - 1)
        nb_known = inside & known[r2, c2]
        nb_unknown = inside & (idx[r2, c2] >= 0)
        diag += nb_known | nb_unknown
        rhs[nb_known] += heights_m[r2[nb_known], c2[nb_known]]
        rows.append(np.nonzero(nb_unknown)[0])
        cols.append(idx[r2[nb_unknown], c2[nb_unknown]])
        vals.append(-np.ones(int(nb_unknown.sum())))
    a = sparse.csr_matrix((np.concatenate(vals + [diag]),
                           (np.concatenate(rows + [np.arange(rr.size)]), np.concatenate(cols + [np.arange(rr.size)]))),
                          shape=(rr.size, rr.size))
    if rr.size <= DIRECT_FILL_MAX:
        return np.atleast_1d(spsolve(a.tocsc(), rhs))
    from scipy.sparse.linalg import cg
    x0 = np.full(rr.size, float(np.nanmean(heights_m)))
    scale = float(np.abs(rhs).max()) or 1.0
    x, info = cg(a, rhs / scale, x0=x0 / scale, rtol=1e-10, atol=0.0, maxiter=50_000,
                 M=sparse.diags(1.0 / diag))
    if info != 0:
        raise InputError("fill holes", f"the harmonic fill of {rr.size} points did not converge; crop the largest "
                         "holes away (relief crop) or fill only small ones (--max-gap-px)")
    return x * scale
