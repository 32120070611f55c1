"""Microfacet normal distributions and Smith shadowing: the ONE copy every model uses.

Distributions of the microfacet normal m over the macroscopic normal n = +z, both
normalised so that the projected area is conserved, int D(m) (m.n) dw_m = 1
(Walter, Marschner, Li & Torrance, EGSR 2007, cited W07):
- Beckmann (W07 eq. 25; paper eq. 3 normalised): D = exp(-tan^2 t / a^2) / (pi a^2 cos^4 t);
  its slope density is the isotropic Gaussian P22(s) = exp(-|s|^2 / a^2) / (pi a^2), i.e. per-axis
  slope standard deviation a / sqrt(2) and rms slope magnitude a.
- GGX / Trowbridge-Reitz (W07 eq. 33): D = a^2 / (pi cos^4 t (a^2 + tan^2 t)^2); slope density
  P22(s) = 1 / (pi a^2 (1 + |s|^2 / a^2)^2) (infinite rms slope).
- multi-lobe mixture (paper eq. 4): D = sum_j w_j D(a_j), sum w_j = 1.  Smith's Lambda is
  linear in the slope density, so the mixture's Lambda = sum_j w_j Lambda_j.
Smith masking (W07 eqs. 27 and 34, exact for these height-uncorrelated models):
  Beckmann Lambda = (erf(x) - 1)/2 + exp(-x^2) / (2 x sqrt(pi)), x = 1 / (a tan t);
  GGX      Lambda = (sqrt(1 + a^2 tan^2 t) - 1) / 2;   G1 = 1 / (1 + Lambda).
V-cavity (paper eq. 5, Cook & Torrance 1982): G1 = min(1, 2 (n.m)|n.v| / |v.m|).
Sampling: `sample_slopes` draws slopes from P22 (projected-area weighted facets, what a
height map's pixels are), `normals_from_slopes` turns them into unit normals (-sx, -sy, 1)/|.|.
Regime: geometric optics (facets >> wavelength), uncorrelated heights and slopes (Smith).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy import special

from relief_bsdf.errors import InputError

DISTRIBUTIONS = ("beckmann", "ggx")
_SQRT_PI = np.sqrt(np.pi)


def lobes(alpha: Any, weights: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Lobe roughnesses (L,) and weights (L,) normalised to sum 1."""
    a = np.atleast_1d(np.asarray(alpha, float))
    if a.ndim != 1 or a.size == 0 or np.any(~np.isfinite(a)) or np.any(a <= 0):
        raise InputError("alpha", f"roughness must be one or more positive numbers, got {alpha!r}")
    if weights is None:
        if a.size != 1:
            raise InputError("weights", "several lobes need their weights")
        return a, np.ones(1)
    w = np.atleast_1d(np.asarray(weights, float))
    if w.shape != a.shape or np.any(w < 0) or not w.sum() > 0:
        raise InputError("weights", f"lobe weights must be >= 0, one per lobe, not all zero; got {weights!r}")
    return a, w / w.sum()


def distribution_D(cos_m: Any, alpha: Any, distribution: str = "beckmann", weights: Any = None) -> np.ndarray:
    """Normal distribution D(m) (1/sr) for cos(theta_m) = m.n; 0 for m below the surface.

    Beckmann (W07 eq. 25, paper eq. 3 normalised) or GGX (W07 eq. 33); several lobes mix by
    paper eq. 4.
    """
    a, w = lobes(alpha, weights)
    c = np.asarray(cos_m, float)
    pos = c > 0
    cs = np.where(pos, c, 1.0)
    c2 = cs * cs
    t2 = (1.0 - c2) / c2                             # tan^2 theta_m
    a2 = (a * a).reshape((-1,) + (1,) * c.ndim)
    if distribution == "beckmann":
        d = np.exp(-t2 / a2) / (np.pi * a2 * c2 * c2)
    elif distribution == "ggx":
        d = a2 / (np.pi * c2 * c2 * (a2 + t2) ** 2)
    else:
        raise InputError("distribution", f"unknown distribution {distribution!r}; choose {DISTRIBUTIONS}")
    d = np.tensordot(w, d, axes=(0, 0))
    return np.where(pos, d, 0.0)


def smith_lambda(cos_v: Any, alpha: Any, distribution: str = "beckmann", weights: Any = None) -> np.ndarray:
    """Smith's Lambda(v) for a direction with cos(theta_v) = |v.n| (exact forms, see module doc)."""
    a, w = lobes(alpha, weights)
    c = np.clip(np.abs(np.asarray(cos_v, float)), 0.0, 1.0)
    s = np.sqrt(np.maximum(0.0, 1.0 - c * c))
    with np.errstate(divide="ignore", invalid="ignore"):
        tan_t = np.where(c > 0, s / np.where(c > 0, c, 1.0), np.inf)
    ar = a.reshape((-1,) + (1,) * c.ndim)
    if distribution == "beckmann":
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            x = 1.0 / (ar * tan_t)                      # a = cot / alpha; inf at normal incidence
            lam = 0.5 * (np.exp(-x * x) / (x * _SQRT_PI) - special.erfc(x))
        lam = np.where(tan_t == 0, 0.0, np.where(np.isinf(tan_t), np.inf, lam))
        lam = np.maximum(lam, 0.0)
    elif distribution == "ggx":
        with np.errstate(invalid="ignore", over="ignore"):
            lam = 0.5 * (np.sqrt(1.0 + (ar * tan_t) ** 2) - 1.0)
    else:
        raise InputError("distribution", f"unknown distribution {distribution!r}; choose {DISTRIBUTIONS}")
    return np.tensordot(w, lam, axes=(0, 0))


def smith_G1(cos_v: Any, alpha: Any, distribution: str = "beckmann", weights: Any = None) -> np.ndarray:
    """Smith masking 1 / (1 + Lambda) (without the facet back-facing test)."""
    return 1.0 / (1.0 + smith_lambda(cos_v, alpha, distribution, weights))


def vcavity_G1(v_dot_n: Any, v_dot_m: Any, m_dot_n: Any) -> np.ndarray:
    """One direction's V-cavity factor min(1, 2 (n.m)|n.v| / |v.m|) (paper eq. 5)."""
    vm = np.abs(np.asarray(v_dot_m, float))
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * np.asarray(m_dot_n, float) * np.abs(v_dot_n) / vm
    return np.where(vm > 0, np.minimum(1.0, g), 0.0)


def sample_slopes(alpha: float, n: int, rng: np.random.Generator, distribution: str = "beckmann") -> np.ndarray:
    """n slope vectors (n, 2) drawn from the slope density P22 of the distribution (module doc).

    Beckmann: isotropic Gaussian with per-axis standard deviation alpha / sqrt(2).  GGX: radial
    inverse CDF of P22, |s| = alpha sqrt(u / (1 - u)), uniform azimuth.  A slope drawn this way is
    a facet weighted by its projected area (one pixel of a height map).
    """
    if distribution == "beckmann":
        return rng.normal(0.0, alpha / np.sqrt(2.0), (int(n), 2))
    if distribution == "ggx":
        u = rng.random(int(n))
        r = alpha * np.sqrt(u / np.maximum(1.0 - u, 1e-300))
        ph = 2 * np.pi * rng.random(int(n))
        return np.stack([r * np.cos(ph), r * np.sin(ph)], axis=-1)
    raise InputError("distribution", f"unknown distribution {distribution!r}; choose {DISTRIBUTIONS}")


def normals_from_slopes(sx: Any, sy: Any) -> np.ndarray:
    """Unit facet normals (..., 3) = (-sx, -sy, 1) / sqrt(1 + sx^2 + sy^2) of slopes dz/dx, dz/dy."""
    sx = np.asarray(sx, float)
    n = np.stack([-sx, -np.asarray(sy, float), np.ones_like(sx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def sample_normals(alpha: float, n: int, rng: np.random.Generator, distribution: str = "beckmann") -> np.ndarray:
    """n unit facet normals (n, 3) of a rough surface with slope density P22 (projected-area weighted)."""
    s = sample_slopes(alpha, n, rng, distribution)
    return normals_from_slopes(s[:, 0], s[:, 1])
