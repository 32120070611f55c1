"""Realisation uncertainty of a wave-optics table computed on one finite tile (speckle statistics).

A table made from one height map of finite size L x L is one realisation: another tile of the same
statistics gives other cell values.  For the wave methods this scatter is the speckle of the
tile's far field (Kirchhoff) or of its periodogram (Rayleigh-Rice), and it is known in closed
form (Goodman, *Speckle Phenomena in Optics*, 2007, ch. 3-4; for the periodogram Priestley,
*Spectral Analysis and Time Series*, 1981, sec. 6.1):

- at one frequency sample (spacing 1/L, a "grain" of area a = (lambda / (n_s L_x)) (lambda /
  (n_s L_y)) in direction cosines) the diffuse power of a tile holding many correlation areas is
  a circular-Gaussian field's intensity: exponentially distributed (chi^2 with 2 degrees of
  freedom / 2), standard deviation = mean; neighbouring samples are independent for a periodic
  tile, and correlated over N sum(w^4) / (sum w^2)^2 samples for a windowed map (2-D Hann:
  (35/18)^2 = 3.78), which multiplies the grain area a;
- the table smooths the samples with a Gaussian of standard deviation s (direction cosines) and
  averages the result over the cell.  For a smooth mean density D the variance of that linear
  estimate is a D^2 / (4 pi s^2) times, per axis of a cell of extent c, the factor
  F(c, s) = (1 / c^2) int_0^c int_0^c exp(-(x - y)^2 / (4 s^2)) dx dy
          = (sqrt(pi) u erf(u) + exp(-u^2) - 1) / u^2,   u = c / (2 s),
  which is 1 for a cell much smaller than the filter and 2 sqrt(pi) s / c for a much larger one
  (then the relative variance is a / (cell area): one over the number of grains in the cell).
  A cell of the (theta, phi) grid is taken as the rectangle of its radial extent
  d(sin theta) and the equal-area azimuthal extent.

So `relative_sigma` = sqrt(a / (4 pi s^2) F(c_r, s) F(c_phi, s)), and sigma_per_sr = that times
the cell value (the measured value standing in for the mean).  This is the *tile's* realisation
uncertainty; it does not cover the model's own error (tangent plane, first order).  It is honest
when the tile holds many correlation areas (Gaussian speckle); with few, the speckle is not yet
Gaussian and a `warning` says the tile is too small for the cells (relative sigma of the lobe's
cells above TILE_WARN_REL, the ray method's threshold).
"""
from __future__ import annotations

import contextlib
import warnings

import numpy as np
from scipy.special import erf

TILE_WARN_REL = 0.10          # as methods.ray: warn when the lobe's cells scatter more than this between tiles
LOBE_FRACTION = 0.01          # the lobe: cells above this fraction of the table's largest diffuse value
MIN_DIFFUSE = 1e-3            # rows with less diffuse power than this (of the incident) are not warned about
SUBTILE_CORR = 4.0            # sub-tile side in correlation lengths (sampling methods: sub-tile batch means)
MAX_SUBTILES = 8              # per axis (64 groups: sigma known to ~10 %)


def window_grain_factor(window: np.ndarray | None) -> float:
    """N sum(w^4) / (sum w^2)^2: how many frequency samples one speckle grain spans (1 without a window)."""
    if window is None:
        return 1.0
    w2 = np.asarray(window, float) ** 2
    s = float(w2.sum())
    return float(w2.size * np.sum(w2 * w2) / (s * s)) if s > 0 else 1.0


def _box_factor(c, s) -> np.ndarray:
    """F(c, s) of the module doc (per axis), vectorised."""
    u = np.asarray(c, float) / (2.0 * np.maximum(s, 1e-300))
    u = np.maximum(u, 1e-6)
    small = u < 1e-3
    f = (np.sqrt(np.pi) * u * erf(u) + np.exp(-u * u) - 1.0) / (u * u)
    return np.where(small, 1.0 - u * u / 6.0, f)


def cell_extents_dcos(theta_edges_deg, phi_edges_deg) -> tuple[np.ndarray, np.ndarray]:
    """(c_r, c_phi) of every (theta, phi) cell in direction cosines, shape (S, A): radial extent
    d(sin theta) and the azimuthal extent that gives the cell's projected-solid-angle area."""
    te = np.radians(np.asarray(theta_edges_deg, float))
    pe = np.radians(np.asarray(phi_edges_deg, float))
    se = np.sin(te)
    cr = np.diff(se)[:, None]
    area = 0.5 * (se[1:] ** 2 - se[:-1] ** 2)[:, None] * np.diff(pe)[None, :]
    cr = np.broadcast_to(cr, area.shape)
    return cr, area / np.maximum(cr, 1e-300)


def relative_sigma(grain_area: float, width: float, theta_edges_deg, phi_edges_deg) -> np.ndarray:
    """(S, A) relative 1-sigma of every cell's realisation (module doc); grain_area and width in
    direction cosines (or both in the same frequency units with extents scaled alike)."""
    cr, cp = cell_extents_dcos(theta_edges_deg, phi_edges_deg)
    return relative_sigma_extents(grain_area, width, cr, cp)


def relative_sigma_extents(grain_area: float, width: float, c_r: np.ndarray, c_phi: np.ndarray) -> np.ndarray:
    """relative_sigma for given cell extents (same units as width; grain_area in their square)."""
    s = max(float(width), np.sqrt(grain_area / (4 * np.pi)))     # no filter: one grain per point
    return np.sqrt(grain_area / (4 * np.pi * s * s) * _box_factor(c_r, s) * _box_factor(c_phi, s))


def lobe_relative_sigma(values: np.ndarray, sigma: np.ndarray, psa: np.ndarray | None = None) -> float:
    """The lobe's relative sigma as the ray method states it: per table row (incidence and side; the last
    two axes are the cells) the median of sigma / value over the lobe's cells (above LOBE_FRACTION of the
    row's largest value); the worst row.  With psa (the cells' projected solid angles) rows whose diffuse
    power is below MIN_DIFFUSE of the incident power are left out (a negligible lobe, e.g. near the flat
    limit, is not worth a warning)."""
    v = np.asarray(values, float)
    sg = np.asarray(sigma, float)
    S, A = v.shape[-2:]
    v = v.reshape(-1, S * A)
    sg = sg.reshape(-1, S * A)
    power = (v * np.ravel(psa)[None, :]).sum(axis=1) if psa is not None else np.ones(v.shape[0])
    worst = 0.0
    for row, srow, pw in zip(v, sg, power):
        top = row.max()
        lobe = row > LOBE_FRACTION * top
        if top > 0 and lobe.any() and pw >= MIN_DIFFUSE:
            worst = max(worst, float(np.median(srow[lobe] / row[lobe])))
    return worst


def uncertainty_meta(method: str, side: str, values, sigma, how: str, correlation_areas: float | None,
                     edges: tuple | None = None, stacklevel: int = 3) -> tuple[dict, list]:
    """metadata["uncertainty"] and the warnings (also issued as RuntimeWarning) of a wave table; edges:
    (theta_s, phi_s) cell edges in degrees (rows with a negligible diffuse part are then not warned about)."""
    psa = None
    if edges is not None:
        te, pe = np.radians(np.asarray(edges[0], float)), np.radians(np.asarray(edges[1], float))
        psa = 0.5 * (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None] * np.diff(pe)[None, :]
    worst = lobe_relative_sigma(values, sigma, psa)
    areas = "an unknown number of" if correlation_areas is None else f"{correlation_areas:.0f}"
    info = {"sigma": f"the finite tile's realisation uncertainty ({how})", "correlation_areas": correlation_areas,
            "lobe_relative_tile_sigma_max": worst}
    warn = []
    if worst > TILE_WARN_REL:
        warn.append(f"{method} table ({side}): the tile holds {areas} correlation areas, too few for the cells "
                     f"asked for: the lobe's cells scatter by {100 * worst:.0f} % (median) between tile realisations "
                     "(included in sigma_per_sr); use a larger tile or coarser cells")
    for w in warn:
        warnings.warn(w, RuntimeWarning, stacklevel=stacklevel)
    return info, warn


TILE_WARNING = r"[\w+-]+ table \((inside|outside)\): the tile holds"   # the start of every tile warning


@contextlib.contextmanager
def tile_warnings_quiet():
    """Within: the tables' finite-tile warnings (`uncertainty_meta`, methods.ray) are not issued; what they
    say stays in each table's metadata["uncertainty"] and sigma_per_sr.  For the many tables one run
    derives of a relief already warned about (a diagnosis's probes: the same tile scaled or filtered);
    every other warning passes."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=TILE_WARNING, category=RuntimeWarning)
        yield


def correlation_areas(relief) -> float | None:
    """Number of correlation areas l^2 in the tile (surface.stats correlation length), None if undefined."""
    from relief_bsdf.surface.stats import relief_stats
    with np.errstate(invalid="ignore", divide="ignore"):
        st = relief_stats(relief)
    lc = st.correlation_length_m
    if not (np.isfinite(lc) and lc > 0):
        return None
    ny, nx = relief.shape
    return float(nx * relief.dx_m * ny * relief.dy_m / lc ** 2)


# ---------------------------------------------------------------- sampling methods (ray, normals)

def subtile_grid(relief) -> tuple:
    """((gx, gy) sub-tiles of at least SUBTILE_CORR correlation lengths, at most MAX_SUBTILES per
    axis, over the relief's own extent; number of correlation areas l^2 in it; l in metres)."""
    from relief_bsdf.surface.stats import relief_stats

    with np.errstate(invalid="ignore", divide="ignore"):      # a flat relief has no correlation length
        st = relief_stats(relief)
    ny, nx = relief.shape
    ext = (nx * relief.dx_m, ny * relief.dy_m)
    ls = (st.correlation_length_x_m, st.correlation_length_y_m)
    grid = []
    for e, l_m in zip(ext, ls):
        g = MAX_SUBTILES if not (np.isfinite(l_m) and l_m > 0) else int(e // (SUBTILE_CORR * l_m))
        grid.append(int(min(MAX_SUBTILES, max(1, g))))
    lc = st.correlation_length_m
    if not (np.isfinite(lc) and lc > 0):                    # e.g. a flat relief: no correlation length
        return tuple(grid), None, None
    return tuple(grid), float(ext[0] * ext[1] / lc**2), float(lc)


def facet_groups(relief, grid: tuple) -> np.ndarray:
    """Sub-tile (0 .. gx gy - 1, row-major over a (gx, gy) grid of the map) of every valid facet
    triangle, in the order of surface.stats.facet_slopes raveled with its invalid facets dropped
    (the order of normals.triangle_slopes and microfacet.relief_slopes)."""
    from relief_bsdf.surface.stats import facet_slopes
    sx, sy = facet_slopes(relief)
    ok = (np.isfinite(sx) & np.isfinite(sy)).ravel()
    _, R, C = sx.shape
    gx, gy = grid
    r, c = np.indices((R, C))
    g = (r * gy // R) * gx + c * gx // C
    return np.broadcast_to(g, sx.shape).ravel()[ok]
