"""Turning a diffraction result (power on a grid of direction cosines) into BSDF cells.

Shared by the wave methods (`kirchhoff`, `rayleigh_rice`).  Everything here works in
*direction-cosine space* (alpha, beta) = (sin t cos p, sin t sin p) of the scattered
direction, measured in the medium the light leaves into.  The element d alpha d beta
equals cos(theta) d omega, the projected solid angle, so

    BSDF (1/sr) = scattered power fraction per unit d alpha d beta,

and a table cell value (the average over the cell in projected solid angle, the
convention of `BsdfTable`) is the mean of that density over the cell's area in the
(alpha, beta) disc.  Cells are sampled by sub-points spread uniformly in
(sin^2 theta, phi), i.e. uniformly in projected solid angle.

Filtering (paper sec. 2.4, "conversion to BDF includes adaptive filtering"): a coherent
far field is speckled (speckle grain = lambda / (n L) in direction cosines for a tile of
size L).  It is smoothed with a Gaussian kernel of one width `w` in direction cosines,
chosen ONCE per request from the coarsest speckle grain over all wavelengths and sides
and from the finest requested cell (`smoothing_width_dcos`), so adjacent wavelengths and
incidences are filtered identically in physical (direction-cosine) terms - the
inconsistency the paper warns about does not arise.  Inside the propagating disc the
smoothing is a normalised convolution (`DcosGrid.smoothed(width, mask)`): every sample's
power stays in the disc, so filtering moves no energy out of the hemisphere; the cell
averages are then brought to the power the grid holds, ring band by ring band
(`ring_factors`), which removes the quadrature error of the sub-point averages where the
tangent-plane density grows toward the rim.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from relief_bsdf.errors import RequestError


@dataclass(frozen=True)
class CellSamples:
    """Sub-points of every table cell: alpha, beta, theta (rad), phi (rad), shape (S, A, M).

    The points are the centres of an m_t x m_p grid in (sin^2 theta, phi) inside each cell,
    so their plain mean is the projected-solid-angle average over the cell.
    """

    alpha: np.ndarray
    beta: np.ndarray
    theta: np.ndarray
    phi: np.ndarray

    @property
    def cos_theta(self) -> np.ndarray:
        return np.cos(self.theta)


def cell_samples(theta_edges_deg, phi_edges_deg, width_dcos: float, max_per_axis: int = 12,
                 min_per_axis: int = 2) -> CellSamples:
    """Sub-points for cell averages, spaced at most about `width_dcos` in direction cosines
    (radially at most half of it).

    The number per axis is the same for all cells (so arrays stay rectangular): enough for
    the largest cell, capped at `max_per_axis`.  Radially the midpoint rule in sin^2 theta
    needs the finer spacing: a lobe about as narrow as the cells (a transmitted lobe at
    normal incidence, concentrated in the polar cells) was under-integrated by ~1 % with
    one sub-point per filter width (R + T = 0.992 instead of 1.000; tests/backend/test_cross_methods.py).
    """
    te = np.radians(np.asarray(theta_edges_deg, float))
    pe = np.radians(np.asarray(phi_edges_deg, float))
    u_lo, u_hi = np.sin(te[:-1]) ** 2, np.sin(te[1:]) ** 2
    # radial extent in direction cosines and arc length of the widest cells
    radial = np.max(np.diff(np.sin(te)))
    arc = np.max(np.sin(te[1:])) * np.max(np.diff(pe))
    w = max(width_dcos, 1e-6)
    m_t = int(np.clip(np.ceil(2.0 * radial / w), min_per_axis, max_per_axis))
    m_p = int(np.clip(np.ceil(arc / w), min_per_axis, max_per_axis))
    ft = (np.arange(m_t) + 0.5) / m_t
    fp = (np.arange(m_p) + 0.5) / m_p
    u = u_lo[:, None] + (u_hi - u_lo)[:, None] * ft[None, :]                 # (S, m_t)
    ph = pe[:-1, None] + np.diff(pe)[:, None] * fp[None, :]                  # (A, m_p)
    S, A = u.shape[0], ph.shape[0]
    uu = np.broadcast_to(u[:, None, :, None], (S, A, m_t, m_p)).reshape(S, A, m_t * m_p)
    pp = np.broadcast_to(ph[None, :, None, :], (S, A, m_t, m_p)).reshape(S, A, m_t * m_p)
    s = np.sqrt(uu)
    theta = np.arcsin(np.clip(s, 0.0, 1.0))
    return CellSamples(alpha=s * np.cos(pp), beta=s * np.sin(pp), theta=theta, phi=pp)


def smoothing_width_dcos(speckle_dcos: float, theta_edges_deg, smoothing_dcos: float | None = None) -> float:
    """Gaussian filter width (standard deviation, direction cosines) for a whole request.

    w = max(2 x speckle grain, half the finest theta cell in direction cosines near the pole
    (d(sin theta) ~ d theta there)), unless the option `smoothing_dcos` sets it (not None).
    Pass the coarsest speckle grain lambda / (n L) over the request's wavelengths and sides.
    """
    if smoothing_dcos is not None:
        w = float(smoothing_dcos)
        if not (np.isfinite(w) and w >= 0):
            raise RequestError(f"smoothing_dcos must be >= 0, got {w}", "options.smoothing_dcos")
        return w
    te = np.radians(np.asarray(theta_edges_deg, float))
    finest = float(np.min(np.diff(te)))
    return max(2.0 * speckle_dcos, 0.5 * finest)


@dataclass
class DcosGrid:
    """A power density on a regular grid of direction cosines: density[j, i] at
    (alpha0 + i dalpha, beta0 + j dbeta), in power fraction per unit d alpha d beta."""

    density: np.ndarray
    alpha0: float
    beta0: float
    dalpha: float
    dbeta: float

    def smoothed(self, width_dcos: float, mask: np.ndarray | None = None) -> "DcosGrid":
        """Gaussian-filtered copy.

        Without `mask` a plain convolution (integral preserved on an unbounded grid; what is
        spread beyond the grid is lost).  With `mask` (True inside the propagating disc) a
        *normalised* convolution that keeps every sample's power inside the mask:
        out = mask * G * (d / (G * mask)) - each sample is spread by the kernel truncated to the
        disc and renormalised there, so sum(out) = sum(d) for d zero outside the mask.
        """
        if width_dcos <= 0:
            return self
        sig = (width_dcos / self.dbeta, width_dcos / self.dalpha)
        if max(sig) < 0.3:
            return self
        if mask is None:
            d = ndimage.gaussian_filter(self.density, sig, mode="constant", cval=0.0, truncate=4.0)
            return DcosGrid(d, self.alpha0, self.beta0, self.dalpha, self.dbeta)
        m = np.asarray(mask, float)
        norm = ndimage.gaussian_filter(m, sig, mode="constant", cval=0.0, truncate=4.0)
        src = np.where(norm > 1e-12, self.density * m / np.where(norm > 1e-12, norm, 1.0), 0.0)
        d = m * ndimage.gaussian_filter(src, sig, mode="constant", cval=0.0, truncate=4.0)
        return DcosGrid(d, self.alpha0, self.beta0, self.dalpha, self.dbeta)

    def extended(self, mask: np.ndarray) -> "DcosGrid":
        """Copy with every sample outside `mask` set to its nearest sample inside (for interpolation
        only: bilinear look-ups just inside the disc's rim then do not mix in the zeros beyond it)."""
        m = np.asarray(mask, bool)
        if m.all() or not m.any():
            return self
        idx = ndimage.distance_transform_edt(~m, return_distances=False, return_indices=True)
        return DcosGrid(self.density[tuple(idx)], self.alpha0, self.beta0, self.dalpha, self.dbeta)

    def at(self, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of the density (0 outside the grid)."""
        ci = (np.asarray(alpha) - self.alpha0) / self.dalpha
        cj = (np.asarray(beta) - self.beta0) / self.dbeta
        shape = np.shape(ci)
        out = ndimage.map_coordinates(self.density, [cj.ravel(), ci.ravel()], order=1, mode="constant",
                                      cval=0.0, prefilter=False)
        return out.reshape(shape)


def cell_average(grid: DcosGrid, cells: CellSamples, extra=None) -> np.ndarray:
    """(S, A) cell averages of grid density x `extra` (an optional factor on the sub-points)."""
    v = grid.at(cells.alpha, cells.beta)
    if extra is not None:
        v = v * extra
    return v.mean(axis=-1)


def ring_conserving(values: np.ndarray, grid: DcosGrid, theta_edges_deg, phi_edges_deg) -> np.ndarray:
    """Cell averages rescaled, band of theta rings by band, to the power the grid holds there
    (`ring_factors`)."""
    return values * ring_factors(values, grid, theta_edges_deg, phi_edges_deg)[:, None]


BAND_SPACINGS = 8        # a band of rings is at least this many grid spacings wide ...
BAND_SAMPLES = 400       # ... and holds at least this many grid samples (assignment by centre: ~ 1/sqrt(N))


def ring_factors(values: np.ndarray, grid: DcosGrid, theta_edges_deg, phi_edges_deg) -> np.ndarray:
    """Per theta ring, the factor that brings the cell averages to the power the grid holds there.

    The sub-point averages of `cell_average` are a quadrature of the (smoothed) density; near the
    rim of the disc, where the tangent-plane density grows like 1 / cos theta_s, a bilinear grid
    under-resolves it and the quadrature misses a few % of the power.  Here each grid sample's
    power (density x d alpha d beta) is assigned to the theta ring holding its direction (samples
    beyond the rim to the last ring when it reaches 90 deg), rings are merged outward into bands at
    least BAND_SPACINGS grid spacings wide holding BAND_SAMPLES samples (so that assigning a sample
    by its centre errs by well under 1 % of a band), and each band's cells are scaled so that their power (value x
    projected solid angle) equals the grid's power in that band: the hemispherical total is then
    the grid's exactly, and the shape within a band is the quadrature's.  Only for a full 360 deg
    azimuth span (otherwise all factors are 1).
    """
    te = np.radians(np.asarray(theta_edges_deg, float))
    pe = np.radians(np.asarray(phi_edges_deg, float))
    fac = np.ones(te.size - 1)
    if abs((pe[-1] - pe[0]) - 2 * np.pi) > 1e-9:
        return fac
    ny, nx = grid.density.shape
    al = grid.alpha0 + grid.dalpha * np.arange(nx)
    be = grid.beta0 + grid.dbeta * np.arange(ny)
    r = np.hypot(al[None, :], be[:, None]).ravel()
    p = grid.density.ravel() * grid.dalpha * grid.dbeta
    se = np.sin(te)
    top = se[-1] if te[-1] < np.pi / 2 - 1e-12 else np.inf
    keep = (r >= se[0]) & (r < top)
    ring = np.clip(np.searchsorted(se, r[keep], side="right") - 1, 0, te.size - 2)
    grid_ring = np.bincount(ring, weights=p[keep], minlength=te.size - 1)
    psa = 0.5 * (se[1:] ** 2 - se[:-1] ** 2)[:, None] * np.diff(pe)[None, :]
    cell_ring = np.sum(values * psa, axis=1)
    step = BAND_SPACINGS * max(grid.dalpha, grid.dbeta)
    count = np.bincount(ring, minlength=te.size - 1)
    start = 0
    while start < te.size - 1:
        stop = start + 1
        while stop < te.size - 1 and (se[stop] - se[start] < step or count[start:stop].sum() < BAND_SAMPLES):
            stop += 1
        if te.size - 1 - stop > 0 and (se[-1] - se[stop] < step or count[stop:].sum() < BAND_SAMPLES):
            stop = te.size - 1                   # a too thin last band joins this one
        have, want = cell_ring[start:stop].sum(), grid_ring[start:stop].sum()
        if have > 0:
            fac[start:stop] = want / have
        start = stop
    return fac


ENERGY_DEFECT_WARN = 0.01


def energy_defect(tab, material, method: str, model: str) -> None:
    """tab.lost = 1 - R - T, signed: absorption into a metal, otherwise the model's own energy defect
    (negative = more power out than in).  Stored in metadata["energy_defect"] too; a RuntimeWarning
    above 1 % for a lossless boundary."""
    import warnings
    h_ = tab.hemispherical()
    lost = 1.0 - h_["R"] - h_["T"]
    tab.lost = lost
    absorbing = tab.incident_from == "outside" and any(
        np.imag(material.n_pair(w, "outside")[1]) > 0 for w in tab.wavelength_nm)
    k = int(np.argmax(np.abs(lost)))
    worst = float(lost.flat[k])
    tab.metadata["energy_defect"] = {"max_abs": abs(worst), "worst_signed": worst,
                                     "meaning": "absorption" if absorbing else f"{model} energy defect"}
    if not absorbing and abs(worst) > ENERGY_DEFECT_WARN:
        w, i, p = np.unravel_index(k, lost.shape)
        warnings.warn(f"{method} ({tab.incident_from}): R + T differs from 1 by {-worst:+.2%} at "
                      f"{tab.wavelength_nm[w]:g} nm, theta_i {tab.theta_i_deg[i]:g} deg: the {model} model does not "
                      "conserve energy here; the table stores it signed as 'lost'", RuntimeWarning, stacklevel=4)


def check_sides(material, request, method: str) -> None:
    """RequestError for an unphysical index, or light asked to arrive from inside an absorbing material."""
    material.check_incidence(request.wavelengths_nm, request.incident_from, method)
