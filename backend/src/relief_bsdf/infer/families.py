"""Relief families with few parameters, as facet-slope densities, beside the non-parametric one.

In geometric optics a rough face acts on light through its facet-slope density (infer.slopes: the
single-pass map from slope to exit direction); what the spatial arrangement adds (shadowing, a second
hit on a neighbouring facet) is small at the slopes these plates carry (rms slope below ~0.3).  So a
family is named here by its slope density, each axis's marginal p(s) with few parameters (the
synthesis, infer.synth, realises the product of the two marginals):

    gaussian    p = N(0, sigma^2) per axis, sigma_x = sigma_y (1 parameter).  The facet slopes of a
                Gaussian random relief, whatever its correlation function: a Gaussian-correlated
                and an exponentially correlated relief sampled at a pitch both have Gaussian slopes
                (the derivative of a Gaussian field), so the two are one candidate here; they differ in
                how the rms slope depends on the sampling pitch, which a lobe does not see.
    two-scale   p = (1 - w) N(0, sigma_1^2) + w N(0, sigma_2^2) per axis (3 parameters): a relief with
                two scales of roughness (the fine one spread over the coarse one's facets).
    dots        p = f delta(0) + (1 - f) N(0, sigma^2) per axis (2 parameters): light-guide dots, a
                flat share of the face (the plate's specular beam) beside the dots' flanks (the share
                of flat area is f^2 in the product of the two axes).
    top-hat     p = uniform on [-a_x, a_x] x [-a_y, a_y] (2 parameters): random lenslets of an engineered
                top-hat diffuser (each lenslet's slope runs uniformly through its range: a square
                far-field pattern with sharp edges).
    non-parametric  the inverted density's own marginals (one parameter per slope bin that carries mass).

Each family's parameters are fitted to the inverted density's marginals (`fit_family`: least squares
of the family's cumulative distribution at the bin edges against the inverted one's, the Kolmogorov
geometry of infer.synth.density_check), in the slope plane and without the plate; the plate then
judges every candidate through the one forward model (infer.refine).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from relief_bsdf.infer.slopes import SlopeDensity

NONPARAMETRIC = "non-parametric"
FAMILIES = ("gaussian", "two-scale", "dots", "top-hat")
#: the name of each family in infer.json's "family" (what the relief is), by candidate
FAMILY_NAMES = {NONPARAMETRIC: "random crossed lenslets (non-parametric slope density)",
                "gaussian": "Gaussian slopes (a Gaussian or exponentially correlated random relief)",
                "two-scale": "two-scale Gaussian slopes", "dots": "light-guide dots (flat share + Gaussian flanks)",
                "top-hat": "random lenslets, top-hat slopes (engineered diffuser)"}


@dataclass(frozen=True)
class Candidate:
    """A family fitted to the inverted density: its name, parameters (slopes are dimensionless
    rise / run; shares are fractions), the number of parameters it adds, and its slope density on the
    inverted density's bins."""

    name: str
    parameters: dict
    k: int
    density: SlopeDensity


def _cdf(name: str, p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Each family's cumulative distribution of one axis's slope at s (module doc)."""
    if name == "gaussian":
        return ndtr(s / p[0])
    if name == "two-scale":
        w = p[2]
        return (1 - w) * ndtr(s / p[0]) + w * ndtr(s / p[1])
    if name == "dots":
        f = p[0]
        return f * (s >= 0) + (1 - f) * ndtr(s / p[1])
    if name == "top-hat":
        return np.clip((s + p[0]) / (2 * p[0]), 0.0, 1.0)
    raise ValueError(name)


def _start_bounds(name: str, rms: float, kurt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if name == "gaussian":
        return np.array([rms]), np.array([1e-4]), np.array([5.0])
    if name == "two-scale":
        return np.array([0.7 * rms, 2.0 * rms, 0.2]), np.array([1e-4, 1e-4, 0.0]), np.array([5.0, 5.0, 1.0])
    if name == "dots":
        f0 = float(np.clip(1 - 3 / max(kurt, 3.0 + 1e-6), 0.01, 0.95))
        return np.array([f0, rms / np.sqrt(1 - f0)]), np.array([0.0, 1e-4]), np.array([0.999, 5.0])
    if name == "top-hat":
        return np.array([np.sqrt(3) * rms]), np.array([1e-4]), np.array([5.0])
    raise ValueError(name)


def _fit_axis(name: str, edges: np.ndarray, marginal: np.ndarray) -> np.ndarray:
    """The family's parameters for one axis: least squares of its CDF at the bin edges (module doc)."""
    c = 0.5 * (edges[1:] + edges[:-1])
    mass = np.clip(marginal, 0, None) * np.diff(edges)
    mass = mass / mass.sum()
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    rms = float(np.sqrt(np.sum(mass * c**2)))
    kurt = float(np.sum(mass * c**4) / max(rms**4, 1e-300))
    x0, lo, hi = _start_bounds(name, rms, kurt)
    res = least_squares(lambda p: _cdf(name, p, edges) - cdf, np.clip(x0, lo, hi), bounds=(lo, hi))
    return res.x


def _binned(name: str, p: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The family's density of one axis averaged over each bin (a delta falls into its bin)."""
    mass = np.diff(_cdf(name, p, edges))
    mass = np.clip(mass, 0, None)
    return mass / mass.sum() / np.diff(edges)


def fit_family(name: str, inverted: SlopeDensity) -> Candidate:
    """The family `name` (FAMILIES or NONPARAMETRIC) fitted to the inverted density (module doc)."""
    px, py = inverted.marginals()
    if name == NONPARAMETRIC:
        k = int(np.count_nonzero(px > 0) + np.count_nonzero(py > 0))
        return Candidate(name, {"bins_x": int(np.count_nonzero(px > 0)), "bins_y": int(np.count_nonzero(py > 0))},
                         k, inverted)
    ex, ey = inverted.edges_sx, inverted.edges_sy
    if name == "top-hat":                 # two half-widths: the engineered pattern may be a rectangle
        ax, ay = _fit_axis(name, ex, px), _fit_axis(name, ey, py)
        params, k = {"half_width_x": float(ax[0]), "half_width_y": float(ay[0])}, 2
        mx, my = _binned(name, ax, ex), _binned(name, ay, ey)
    else:                                 # isotropic families: one parameter set fitted to both axes together
        both = 0.5 * (px + np.interp(0.5 * (ex[1:] + ex[:-1]), 0.5 * (ey[1:] + ey[:-1]), py, left=0, right=0))
        p = _fit_axis(name, ex, both)
        names = {"gaussian": ("sigma",), "two-scale": ("sigma_1", "sigma_2", "weight_2"),
                 "dots": ("flat_share_per_axis", "sigma")}[name]
        params, k = {a: float(v) for a, v in zip(names, p)}, len(names)
        mx, my = _binned(name, p, ex), _binned(name, p, ey)
    dens = np.outer(mx, my)
    dens = dens / (dens.sum() * inverted.cell_area)
    note = f"{FAMILY_NAMES[name]}: " + ", ".join(f"{a} {v:.4g}" for a, v in params.items())
    return Candidate(name, params, k, SlopeDensity(ex, ey, dens, (note,)))


def candidates(inverted: SlopeDensity) -> list[Candidate]:
    """The non-parametric candidate first, then every family of FAMILIES fitted to it."""
    return [fit_family(NONPARAMETRIC, inverted)] + [fit_family(f, inverted) for f in FAMILIES]
