"""Light in the bulk of the plate: Beer-Lambert absorption and Henyey-Greenstein scattering.

Absorption (Beer-Lambert-Bouguer): a path of length L in a medium with absorption
coefficient a (1/m, power) keeps exp(-a L) of its power; a straight traversal of a slab of
thickness t at internal angle theta has L = t / |cos theta|.  a = 4 pi k / lambda for an
index n + i k.  Valid for a homogeneous medium and incoherent power (no thin-film interference).

Volume scattering: the Henyey-Greenstein phase function (Henyey & Greenstein, ApJ 93, 70 (1941))
    p(cos t) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos t)^(3/2))     (1/sr, int p dw = 1)
with asymmetry g = <cos t> in (-1, 1).  Sampling by the inverse of its CDF (e.g. pbrt-v4
sec. 11.3.1):  cos t = (1 + g^2 - ((1 - g^2) / (1 - g + 2 g u))^2) / (2 g), u uniform in
[0, 1); cos t = 2 u - 1 for g = 0.  The azimuth about the incoming direction is uniform.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from relief_bsdf.core.frames import any_perpendicular


def beer_lambert(absorption_per_m: Any, path_m: Any) -> np.ndarray:
    """Power fraction exp(-a L) kept over paths of length `path_m` (Beer-Lambert)."""
    return np.exp(-np.asarray(absorption_per_m, float) * np.asarray(path_m, float))


def slab_transmittance(absorption_per_m: Any, thickness_m: Any, cos_theta: Any,
                       min_cos: float = 1e-9) -> np.ndarray:
    """exp(-a t / |cos theta|): one straight traversal of a slab at internal angle theta.

    |cos theta| is floored at `min_cos` (a grazing path is then very long, not infinite).
    """
    c = np.maximum(np.abs(np.asarray(cos_theta, float)), min_cos)
    return beer_lambert(absorption_per_m, np.asarray(thickness_m, float) / c)


def hg_phase(cos_theta: Any, g: float) -> np.ndarray:
    """Henyey-Greenstein phase function p(cos theta) in 1/sr (module doc)."""
    c = np.asarray(cos_theta, float)
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * c) ** 1.5)


def sample_hg_cos(g: float, u: Any) -> np.ndarray:
    """cos(theta) of the Henyey-Greenstein phase function for uniform numbers u (inverse CDF)."""
    u = np.asarray(u, float)
    if abs(g) < 1e-6:
        return 2 * u - 1
    t = (1 - g * g) / (1 - g + 2 * g * u)
    return np.clip((1 + g * g - t * t) / (2 * g), -1.0, 1.0)


def scatter_directions(d: np.ndarray, g: float, rng: np.random.Generator) -> np.ndarray:
    """New unit directions (n, 3) after one Henyey-Greenstein scattering of directions d (n, 3)."""
    d = np.asarray(d, float)
    n = d.shape[0]
    ct = sample_hg_cos(g, rng.random(n))
    st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
    ph = 2 * np.pi * rng.random(n)
    e1 = any_perpendicular(d)
    e2 = np.cross(d, e1)
    return (ct[:, None] * d + (st * np.cos(ph))[:, None] * e1 + (st * np.sin(ph))[:, None] * e2)
