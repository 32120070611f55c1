"""The q_z expansion of the Kirchhoff integral: exp(-i nu_z h) interpolated in nu_z.

The tangent-plane far field of a relief h(r) in a direction with wave-vector transfer
(nu_xy, nu_z) is (methods.kirchhoff)

    U(nu_xy; nu_z) = sum_r w(r) [exp(-i nu_z h(r)) - m(nu_z)] exp(-i nu_xy . r),

an entire function of nu_z for every nu_xy.  Each direction has its own nu_z, so one FFT is
exact only on one ring of directions.  Here U is interpolated *as a field* (linear in the
integrand) by the polynomial through n Chebyshev nodes nu_j of the interval [nu_lo, nu_hi]
that the requested directions span:

    U(nu_xy; nu_z) ~ sum_j L_j(nu_z) U(nu_xy; nu_j),   U(.; nu_j) = FFT[w (exp(-i nu_j h) - m_j)],

(barycentric Lagrange form, Berrut & Trefethen, SIAM Review 46 (2004) 501, eq. 4.2 with the
first-kind Chebyshev weights of their sec. 5): n FFTs give the integral at every direction with
its own nu_z.  Because the interpolant is linear in the integrand, the error in direction
nu_xy is the Fourier transform of the pointwise interpolation error of exp(-i nu_z h(r)),
which for n first-kind Chebyshev nodes on an interval of half-width D is bounded by
(e.g. Trefethen, *Approximation Theory and Approximation Practice* ch. 11; the classical
Chebyshev remainder) |d^n/dnu^n exp(-i nu h)| 2 (D / 2)^n / n! = 2 (D |h - h_c| / 2)^n / n!
(heights measured from the mid-range h_c, which changes only a common phase).  By Parseval,
at fixed nu_z the rms (over directions) of the field error is the rms over the map of that
pointwise bound, so

    eps_n = 2 (D / 2)^n sqrt(<(h - h_c)^(2n)>_w2) / n!,

with <.>_w2 the average weighted by the squared window (the same weights as the power).
`expansion_order` picks the smallest n (>= 2) with eps_n <= tol * a, where a is the rms
amplitude of the diffuse field, sqrt(1 - |m|^2), at the reference nu_z (the specular one):
the stated tolerance is the rms field error relative to the diffuse field, so the relative
error of the diffuse power is about 2 tol.  n grows with D times the height range: it is
small where q_z sigma is small (a narrow nu_z range or an optically smooth map) and is
chosen per incidence and side; heights with spikes raise it through the high moments.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln


def chebyshev_nodes(lo: float, hi: float, n: int) -> np.ndarray:
    """n first-kind Chebyshev points of [lo, hi], increasing."""
    k = np.arange(n)
    x = -np.cos((2 * k + 1) * np.pi / (2 * n))
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * x


def barycentric_weights(n: int) -> np.ndarray:
    """Barycentric weights of the n first-kind Chebyshev points in `chebyshev_nodes` order."""
    k = np.arange(n)
    return (-1.0) ** k * np.sin((2 * k + 1) * np.pi / (2 * n))


class LagrangeBasis:
    """The barycentric interpolant through first-kind Chebyshev `nodes`, evaluated at the points x.

    `basis(j)` is L_j(x) (float32, x's shape); a point on a node gets that node's value exactly.
    Computed in single precision on the interval scaled to [-1, 1] (the nodes are then at least
    ~1/n^2 apart, far above float32 resolution).
    """

    def __init__(self, nodes: np.ndarray, x: np.ndarray):
        nodes = np.asarray(nodes, float)
        mid, half = 0.5 * (nodes[0] + nodes[-1]), max(0.5 * float(nodes[-1] - nodes[0]), 1e-300)
        self.t = ((np.asarray(x, float) - mid) / half).astype(np.float32)
        self.tj = ((nodes - mid) / half).astype(np.float32)
        self.bw = barycentric_weights(nodes.size).astype(np.float32)
        self.hit = np.full(self.t.shape, -1, np.int16)
        den = np.zeros(self.t.shape, np.float32)
        for j, tj in enumerate(self.tj):
            d = self.t - tj
            on = np.abs(d) <= 1e-6
            self.hit[on] = j
            d[on] = 1.0
            den += self.bw[j] / d
        self.on_node = self.hit >= 0
        den[self.on_node] = 1.0
        self.inv_den = 1.0 / den

    def basis(self, j: int) -> np.ndarray:
        d = self.t - self.tj[j]
        d[self.on_node] = 1.0
        L = (self.bw[j] * self.inv_den) / d
        if self.on_node.any():
            L[self.on_node] = (self.hit[self.on_node] == j)
        return L


@dataclass(frozen=True)
class HeightMoments:
    """Histogram of |h - h_c| weighted by the squared window: the moments the error bound needs."""

    upper_m: np.ndarray          # bin upper edges (m)
    weight: np.ndarray           # normalised weights (sum 1)
    centre_m: float              # h_c, the mid-range

    @classmethod
    def of(cls, h: np.ndarray, w2: np.ndarray | None, bins: int = 256) -> "HeightMoments":
        valid = None if w2 is None else w2 > 0
        hv = h.ravel() if valid is None else h[valid]
        if hv.size == 0:
            return cls(np.zeros(1), np.ones(1), 0.0)
        lo, hi = float(hv.min()), float(hv.max())
        hc = 0.5 * (hi + lo)
        top = max(0.5 * (hi - lo), 1e-300)
        # uniform bins on [0, top] (np.histogram's rule, the last bin closed), by one bincount
        a = np.abs(hv - hc)
        a *= bins / top
        idx = a.astype(np.intp)
        np.minimum(idx, bins - 1, out=idx)
        cnt = np.bincount(idx, weights=None if w2 is None else w2[valid], minlength=bins).astype(float)
        edges = np.linspace(0.0, top, bins + 1)
        return cls(edges[1:], cnt / max(cnt.sum(), 1e-300), hc)

    def rms_power(self, n: int) -> float:
        """sqrt(<|h - h_c|^(2n)>) from the bins' upper edges (an upper estimate)."""
        m = self.weight > 0
        if not m.any() or self.upper_m[-1] <= 0:
            return 0.0
        lg = np.log(self.upper_m[m]) * (2 * n) + np.log(self.weight[m])
        top = lg.max()
        return float(np.exp(0.5 * (top + np.log(np.sum(np.exp(lg - top))))))


def error_bound(n: int, half_width: float, moments: HeightMoments) -> float:
    """eps_n of the module doc: rms field error of the n-node interpolation (unit incident amplitude)."""
    r = moments.rms_power(n)
    if r <= 0 or half_width <= 0:
        return 0.0
    return float(2.0 * np.exp(n * np.log(0.5 * half_width) + np.log(r) - gammaln(n + 1)))


def expansion_order(half_width: float, moments: HeightMoments, diffuse_amplitude: float, tol: float,
                    max_nodes: int) -> tuple[int, float]:
    """(n, eps_n / diffuse_amplitude): the fewest nodes (2..max_nodes) meeting tol (module doc)."""
    a = max(float(diffuse_amplitude), 1e-12)
    n = 2
    while True:
        e = error_bound(n, half_width, moments) / a
        if e <= tol or n >= max_nodes:
            return n, e
        n += 1
