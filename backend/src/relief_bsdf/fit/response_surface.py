"""The least-squares optimum of a sampled forward model from a design of points around an estimate:
regressions of the residual vector on the parameters (a response surface in the residuals; Box &
Wilson 1951, for the residual vector rather than the objective).

Why.  The relief fit's forward model traces its boundary tables with a fixed set of random
numbers (common random numbers), so its objective f(x) = z(x) @ z(x) is deterministic but not
smooth: the tables' Monte-Carlo noise moves with the relief, and f carries bumps on the scale of
the parameters' own 68 % interval.  On the demo fit (ray tables, inside tables averaged over
+-45 deg of azimuth, ray seed 0) chi^2 along the filter at scale 1.2 read 0.984 um:
749.0, 0.990: 752.7, 0.997: 742.8, 1.000: 743.9, 1.010: 749.2 (curvature of the interval: a rise
of 1 over 0.006 um), and Gauss-Newton steps with central differences (steps of a few thousandths
of the interval) settled in the local minimum at 0.984, 2.8 half-widths off the truth.  A
quadratic fit of chi^2 over the twelve cached points within 60 of the best put the optimum at
(1.1982, 0.9984), the truth inside one half-width.

What.  Around the estimate x0 the residuals are evaluated on a design (2 parameters: the 3 x 3
grid at +-h minus its centre; 1 parameter: +-h/2, +-h) and regressed per row on the parameters:
linearly, z(x0 + dx) ~ a + J dx, whose slope J is the Jacobian averaged over the design (the
bumps' slopes average out instead of steering the step; for residuals quadratic in x the symmetric
design gives the Jacobian at x0 exactly), and quadratically, whose intercept z_bar is the residual
vector at x0 with the bumps smoothed and the design's curvature taken out (a linear regression's
intercept a carries half the curvature times the design's second moment: on test_fit's noise-free
stand-in model, whose specular peak bends strongly over 2 standard deviations, that moved the
answer 1.2 % off the exact optimum).  The estimate is x0 + d with J d = -z_bar in the least-squares
sense (a Gauss-Newton step with the regression's Jacobian).  When d leaves the design (|d_j| > h_j
in some coordinate), the design moves to x0 + d (clipped to REACH = 2 half-widths) and is evaluated
again, at most `rounds` times: the bumps' error in J enters the answer times the step's length, so
the last design should be centred near the optimum.  On residuals with sinusoidal bumps of a period
of 1.5 standard deviations and 0.15 of the noise (tests/backend/fit/test_response_surface.py),
started 3 standard deviations off, the answer lies within 0.4 standard deviations of the smooth
optimum (median of 20 realisations), where steps on central differences stay near the start;
trusting steps up to 2 half-widths without a new design (one design fewer on the demo fit at ray
seed 0, where the second moved the answer by 0.2 standard deviations) raised that median to 0.51.

Regime.  h should span the bumps (a few of them) and stay where the residuals are nearly
quadratic: the caller takes h = 2 standard deviations of the estimate (fit.optimise._smoothed).
Deterministic: the same points for the same inputs (a resumed fit retraces its checkpoint)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


REACH = 2.0        # the longest step from one design, in its half-widths (module doc)


@dataclass
class Surface:
    """The regression's answer: x, the estimate (module doc); jacobian, the regression's dz/dx
    (rows x parameters) over the last design; points, the design's distinct points (its centre
    included) in the last round; rounds, designs evaluated; scatter, the rms of the residuals about
    the linear model per row over the last design (the objective's roughness, in units of sigma)."""

    x: np.ndarray
    jacobian: np.ndarray
    points: int
    rounds: int
    scatter: float


def design_offsets(dim: int) -> np.ndarray:
    """The design's offsets in units of h (module doc): (points, dim)."""
    if dim == 1:
        return np.array([[-1.0], [-0.5], [0.5], [1.0]])
    if dim == 2:
        g = np.array([(a, b) for a in (-1.0, 0.0, 1.0) for b in (-1.0, 0.0, 1.0) if (a, b) != (0.0, 0.0)])
        return g
    raise ValueError(f"a design for {dim} parameters is not defined (1 or 2)")


def _features(u: np.ndarray) -> np.ndarray:
    """The quadratic model's regressors at design coordinates u (points, dim), in units of h:
    1, u_j, and u_j u_k for j <= k."""
    cols = [np.ones(len(u))] + [u[:, j] for j in range(u.shape[1])]
    cols += [u[:, j] * u[:, k] for j in range(u.shape[1]) for k in range(j, u.shape[1])]
    return np.column_stack(cols)


def smoothed_optimum(residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, lower: np.ndarray,
                     upper: np.ndarray, half_width: np.ndarray, rounds: int = 2) -> Surface:
    """The least-squares optimum of residuals(x) -> z by a regression of z over a design of
    half-width `half_width` around x0, moved at most `rounds` times (module doc).  Points are clipped
    to [lower, upper]; duplicates after clipping are evaluated once.  Rank-deficient regressions (a
    parameter the rows do not see, or a design squeezed flat against a bound) give the minimum-norm
    solution, so an undetermined parameter does not move."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    h = np.asarray(half_width, float)
    if np.any(h <= 0) or not np.all(np.isfinite(h)):
        raise ValueError(f"the design's half-widths must be positive and finite, got {h}")
    x = np.clip(np.asarray(x0, float), lo, hi)
    offs = design_offsets(x.size)
    for k in range(1, max(int(rounds), 1) + 1):
        pts = [x]
        for o in offs:
            p = np.clip(x + o * h, lo, hi)
            if not any(np.array_equal(p, q) for q in pts):
                pts.append(p)
        P = np.stack(pts)
        Z = np.stack([np.asarray(residuals(p), float) for p in P])           # (points, rows)
        U = (P - x) / h
        lin = np.column_stack([np.ones(len(P)), U])
        B = np.linalg.lstsq(lin, Z, rcond=1e-10)[0]                          # (1 + dim, rows)
        J = B[1:].T / h                                                        # dz/dx
        quad = _features(U)
        Bq = np.linalg.lstsq(quad, Z, rcond=1e-10)[0]
        z_bar = Bq[0]                      # the residuals at x, the design's curvature taken out
        scatter = float(np.sqrt(np.mean((Z - lin @ B) ** 2))) if len(P) > lin.shape[1] else 0.0
        d = np.linalg.lstsq(J, -z_bar, rcond=1e-10)[0]
        within = bool(np.all(np.abs(d) <= h))
        x = np.clip(x + np.clip(d, -REACH * h, REACH * h), lo, hi)
        if within:
            break
    return Surface(x, J, len(P), k, scatter)
