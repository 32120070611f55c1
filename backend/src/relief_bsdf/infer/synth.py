"""A periodic random relief whose facet-slope density follows a given one: random crossed lenslets.

Why lenslets (and not a slope field made curl-free by a Poisson solve): the least-squares projection
of independent slope draws onto gradient fields removes their curl part and averages neighbours, so
the slope density it leaves is smoothed towards a Gaussian: a top-hat (the engineered diffusers this
serves first) loses its sharp edges, and getting them back needs an iteration with no guarantee.  A
lenslet whose slope runs monotonically through the quantiles of the density reproduces that density
EXACTLY, whatever its width, which is how engineered top-hat diffusers are built.

Construction (one axis): a cell of width w carries the profile whose slope at x is the quantile
function Q of the marginal density, s(x) = Q(x / w) (convex), or Q(1 - x / w) (concave, drawn at
random), so its slopes are distributed exactly as the marginal; its heights H(x) = w int_0^{x/w} Q
return to the start at the cell's end because the density is centred (mean slope 0: a periodic
surface has no mean slope; the measured density's mean, a tilt of the sample, is removed and
reported).  On the pixel grid each pixel's forward difference is the mean of Q over its 1/m share
of the quantiles (m pixels per cell), i.e. an exact m-point discretisation.  Cell widths are drawn
uniformly in [0.5, 1.5] x the mean width (seeded), so no period repeats and no grating orders form;
the chain wraps around the tile (periodic).  The relief is h(x, y) = f(x) + g(y): its facet slopes
(sx, sy) = (f', g') follow p_x(sx) p_y(sy), the product of the density's marginals, so a density that
is not separable is reproduced only in its marginals; `SlopeDensity.separability()` (the total-
variation distance of p from that product) is reported with the result.

Lateral scale (no diffraction structure): a cell of width w spreads light by lambda / w in direction
cosine (the far field of its aperture); the mean width is chosen as w = lambda / `DIFFRACTION_DU`
(0.002: ten times below the 1-deg detector cone's 0.017 and below the lobe-edge tolerance 0.005),
i.e. 320 um at 633 nm, ~64 pixels.  Its heights (a cell's sag ~ w rms_slope / 4, tens of um) are
then many wavelengths: the geometric-optics regime the ray tracer solves.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relief_bsdf.infer.slopes import SlopeDensity
from relief_bsdf.surface.relief import Relief

#: diffraction spread lambda / w of a mean-width cell, in direction cosine (module doc)
DIFFRACTION_DU = 0.002
#: mean cell width in pixels (the quantile discretisation per cell)
CELL_PX = 64
#: quantile samples of Q when integrating H
_Q_SAMPLES = 20001


@dataclass(frozen=True)
class LensletPlan:
    """What `lenslet_relief` makes: grid, pitch, mean cell width and the seed."""

    n: int
    pitch_m: float
    cell_px: int
    seed: int

    @property
    def mean_cell_m(self) -> float:
        return self.cell_px * self.pitch_m


def plan_for(wavelength_nm: float, n: int = 512, cell_px: int = CELL_PX, seed: int = 0) -> LensletPlan:
    """The grid for a wavelength: mean cell width lambda / DIFFRACTION_DU, `cell_px` pixels per cell."""
    w = wavelength_nm * 1e-9 / DIFFRACTION_DU
    return LensletPlan(int(n), w / cell_px, int(cell_px), int(seed))


def quantile_function(edges: np.ndarray, density: np.ndarray):
    """Q(t), t in [0, 1]: the inverse of the CDF of a binned 1-D density, uniform within each bin
    (bins without mass hold no quantile: Q jumps across them)."""
    mass = np.clip(density, 0, None) * np.diff(edges)
    cdf = np.concatenate([[0.0], np.cumsum(mass)]) / mass.sum()
    nz = mass > 0
    starts, lefts = cdf[:-1][nz], edges[:-1][nz]
    widths, share = np.diff(edges)[nz], (mass / mass.sum())[nz]

    def Q(t: np.ndarray) -> np.ndarray:
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, starts.size - 1)
        return lefts[k] + np.clip((t - starts[k]) / share[k], 0.0, 1.0) * widths[k]
    return Q


def cell_profile(Q, m: int, centre: float) -> np.ndarray:
    """Heights (in slope x pixel units) at the m + 1 nodes of one cell of m pixels, slope Q - centre."""
    t = np.linspace(0.0, 1.0, _Q_SAMPLES)
    q = Q(t) - centre
    H = np.concatenate([[0.0], np.cumsum(0.5 * (q[1:] + q[:-1]) * np.diff(t))])   # int_0^t (Q - centre)
    prof = m * np.interp(np.arange(m + 1) / m, t, H)
    return prof - np.linspace(0.0, prof[-1], m + 1)     # closes the cell exactly (its quadrature error)


def cell_widths(n: int, cell_px: int, rng: np.random.Generator) -> list[int]:
    """Random cell widths in [0.5, 1.5] x cell_px pixels summing to n (the last remainder joins its
    neighbour when it is narrower than half a cell)."""
    lo, hi = max(2, cell_px // 2), max(3, (3 * cell_px) // 2)
    out: list[int] = []
    while sum(out) < n:
        out.append(int(rng.integers(lo, hi + 1)))
    extra = sum(out) - n
    out[-1] -= extra
    if out[-1] < lo and len(out) > 1:
        last = out.pop()
        out[-1] += last
    return out


def lenslet_chain(edges: np.ndarray, density: np.ndarray, n: int, pitch_m: float, cell_px: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """(heights in m at the n nodes of one periodic axis, the removed mean slope) (module doc)."""
    Q = quantile_function(edges, density)
    c = 0.5 * (edges[1:] + edges[:-1])
    w = np.clip(density, 0, None) * np.diff(edges)
    mean = float(np.sum(w * c) / np.sum(w))
    f = np.zeros(n)
    x = 0
    for m in cell_widths(n, cell_px, rng):
        prof = cell_profile(Q, m, mean)
        if rng.random() < 0.5:                   # concave lenslet: the same slopes in reverse order
            prof = prof[::-1] - prof[-1]
        f[x:x + m] = prof[:m]
        x += m
    return f * pitch_m, mean


def lenslet_relief(density: SlopeDensity, plan: LensletPlan) -> tuple[Relief, dict]:
    """(periodic relief h = f(x) + g(y) of random crossed lenslets, facts for infer.json) (module doc)."""
    rng = np.random.default_rng(plan.seed)
    px, py = density.marginals()
    fx, mx = lenslet_chain(density.edges_sx, px, plan.n, plan.pitch_m, plan.cell_px, rng)
    gy, my = lenslet_chain(density.edges_sy, py, plan.n, plan.pitch_m, plan.cell_px, rng)
    h = fx[None, :] + gy[:, None]
    h -= h.mean()
    relief = Relief(h, plan.pitch_m, plan.pitch_m, periodic=True,
                    source=f"relief infer: random crossed lenslets, seed {plan.seed}",
                    metadata={"family": "random crossed lenslets"},
                    history=(f"synthesised: random crossed lenslets following the inverted slope density, "
                             f"mean cell {plan.mean_cell_m * 1e6:.4g} um ({plan.cell_px} px), seed {plan.seed}",))
    facts = {"removed_mean_slope": [mx, my], "separability_tv": density.separability(),
             "mean_cell_um": plan.mean_cell_m * 1e6, "cell_px": plan.cell_px, "pitch_um": plan.pitch_m * 1e6,
             "tile_px": plan.n, "diffraction_du": DIFFRACTION_DU}
    return relief, facts


def density_check(relief: Relief, density: SlopeDensity) -> dict:
    """How well the relief's facet slopes (surface.stats.facet_slopes, the triangles the ray tracer
    meets) follow the density: the Kolmogorov distance of each axis from the density's marginal (a cell
    of m pixels discretises its quantiles to within 1 / (2 m)), and the rms slopes of both."""
    from relief_bsdf.surface.stats import facet_slopes, rms_slope
    sx, sy = facet_slopes(relief)
    px, py = density.marginals()
    out = {}
    for name, got, edges, marginal in (("x", sx, density.edges_sx, px), ("y", sy, density.edges_sy, py)):
        v = np.sort(got[np.isfinite(got)].ravel())
        cdf = np.concatenate([[0.0], np.cumsum(marginal * np.diff(edges))])
        out[f"ks_{name}"] = float(np.max(np.abs(np.interp(v, edges, cdf / cdf[-1]) - (np.arange(v.size) + 0.5) / v.size)))
    out["rms_slope_relief"] = rms_slope(relief)
    out["rms_slope_density"] = density.moments()["rms_slope"]
    return out
