"""The scatter cells of the ray method's exits on edges that are not uniform, compiled.

A relief-scale request asks for graded edges (rings of 0.17 to 0.25 degree, azimuths of 1 and 5 degrees
around a detector's aperture): `bsdf.builder.CellIndex` then finds the cell of each exit by searches
(`_theta_bins` on sin^2 theta, `_phi_bins` on the float64 degrees of numpy's float32 arctan2), a dozen
numpy passes per chunk that cost a fifth of such a table's time.  `SearchedCells.with_side` gives the
same cells in one compiled pass (`kernels.cells_of_edges`): the ring by the same search on the same
float32 sin^2 (exact), the azimuth from a float64 arctan2 wherever numpy's float32 angle (within 1e-6
rad of it) cannot fall in another cell (2e-5 rad from every edge, `builder.ANGLE_MARGIN_RAD`); the few
others take the builder's numpy code.  The same cells bit for bit (tests/backend/kernels).
"""
from __future__ import annotations

import math

import numpy as np

from relief_bsdf import kernels
from relief_bsdf.bsdf.builder import ANGLE_MARGIN_RAD, CellIndex

F32 = np.float32
MARGIN_DEG = math.degrees(ANGLE_MARGIN_RAD)
LUT_T, LUT_P = 8192, 7200     # buckets of the searches: sin^2 theta in [0, 1]; azimuth in [0, 360) (0.05 degree)


class SearchedCells(CellIndex):
    """`CellIndex` whose `with_side` runs `kernels.cells_of_edges` on float32 directions when both the rings
    and the azimuths are searched (edges that are not uniform: the builder's search branches); the
    builder's code otherwise, and for the directions the kernel leaves."""

    def __init__(self, theta_edges_deg, phi_edges_deg):
        super().__init__(theta_edges_deg, phi_edges_deg)
        te_deg = np.degrees(np.arcsin(np.sqrt(np.clip(self.te_sin2, 0.0, 1.0))))   # as builder._theta_bins
        dt, dp = np.diff(te_deg), np.diff(self.pe)
        self.searched = (not self.fast and not np.allclose(dt, dt[0], rtol=1e-9, atol=1e-9)
                         and not np.allclose(dp, dp[0]))                          # as builder._phi_bins
        self.pe_rel = self.pe - self.pe[0]
        self.last_ring = self.S - 1 if self.te_sin2[-1] >= 1.0 else self.S
        # look-up tables of the searches (`kernels.cells_of_edges`): bucket j of x counts the edges <= (j - 1) / scale
        self.scale_t, self.scale_p = float(LUT_T), float(LUT_P) / 360.0
        self.lut_t = _count_table(self.te_sin2, LUT_T, self.scale_t)
        self.lut_p = _count_table(self.pe_rel, LUT_P, self.scale_p)

    def with_side(self, k: np.ndarray, side: np.ndarray) -> np.ndarray:
        if not (self.searched and k.dtype == F32):
            return super().with_side(k, side)
        n = k.shape[0]
        side8 = side.astype(np.int8, copy=False)
        cell, exact = np.empty(n, np.int32), np.empty(n, np.int64)
        ne = kernels.cells_of_edges(k, self.te_sin2, self.last_ring, self.lut_t, self.scale_t, self.pe_rel, self.lut_p,
                                    self.scale_p, float(self.pe[0]), MARGIN_DEG, side8, self.S * self.A, cell, exact)
        if ne:
            idx = exact[:ne]
            cell[idx] = super().with_side(np.take(k, idx, axis=0), np.take(side8, idx))
        return cell


def _count_table(edges: np.ndarray, n: int, scale: float) -> np.ndarray:
    """(n,) int32: entry j the number of edges <= (j - 1) / scale (0 for j = 0)."""
    lo = (np.arange(n, dtype=np.float64) - 1.0) / scale
    out = np.searchsorted(edges, lo, side="right").astype(np.int32)
    out[0] = 0
    return out


def cell_index(theta_edges_deg, phi_edges_deg) -> CellIndex:
    """The cell index of a ray task: `SearchedCells` (the builder's `CellIndex` with a compiled search)."""
    return SearchedCells(theta_edges_deg, phi_edges_deg)
