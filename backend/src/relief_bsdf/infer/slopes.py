"""The facet-slope density of a rough face from the plate's transmitted lobe (geometric optics).

Geometry (the frame of formats.md: z is the plate's outward normal on the lit side, directions of
recording rows point away from the sample; a transmitted row's (theta_s, phi_s) has the direction
cosine pair u = sin(theta_s) (cos phi_s, sin phi_s), the xy components of the exit direction of
travel).  The relief z = h(x, y) is on the lit (front) face, a facet of slope s = (sx, sy) has the
outward unit normal m(s) = (-sx, -sy, 1) / sqrt(1 + |s|^2) (surface.stats, core.microfacet).

The map s -> u of one ray (`exit_cosines`):
    1. the beam arrives from w_i = (sin ti cos pi, sin ti sin pi, cos ti) (pointing at the source);
    2. Snell at the facet (air -> glass, eta = 1 / n):  c = w_i . m,
       t = -eta w_i + (eta c - sqrt(1 - eta^2 (1 - c^2))) m      (direction of travel in the glass);
    3. the flat back face (normal z): the tangential wave vector is conserved, so the exit
       direction in air has  u = n (t_x, t_y)                        (Snell at z);
       |u| >= 1 is total internal reflection at the back face (no single-pass exit).
    Small slopes at normal incidence: u = (n - 1) s + O(|s|^3).
The Jacobian J = du / ds (`jacobian`) is that map's derivative, evaluated by central differences
of the exact map (step 1e-6: relative error ~1e-9, far below anything measured); the inverse
u -> s (`invert_cosines`) is Newton's method on the same map, per direction cosine pair.

The density (`slope_density`): at (near) normal incidence the beam falls on every facet in
proportion to its projected area, times w_i . m / (m_z cos ti) (1 at normal incidence), and the
share of it that leaves through both faces in a single pass is the product of the two unpolarised
Fresnel transmittances T(s).  A plate BTDF f (1/sr, f = dP / (P_inc dOmega cos theta_s)) is the
power per unit area of the direction-cosine plane, dP / P_inc = f du_x du_y, so

    p(s) = f(u(s)) |det J(s)| / (T(s) w_i . m / (m_z cos ti))  / normalisation,

with p normalised to 1 over the slope box: the slope density per unit projected surface area of
surface.stats.slope_histogram.

Assumptions (stated in infer.json): single interaction with each face (the light reflected at the
back face and returned is a few per cent spread over the hemisphere, not inverted); no shadowing or
masking by neighbouring facets (slopes well below 1); the detector's cone is small beside the lobe
(its blur is not deconvolved: a 1 deg cone adds ~1e-4 to the variance of u per axis); the measured
lobe is read where it exceeds `SUPPORT_FRACTION` of its peak (the file's dim wings: noise and
multiply-reflected light, not single facets); the relief is on the lit face.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relief_bsdf.core.frames import direction
from relief_bsdf.core.fresnel import fresnel_reflectance, refract
from relief_bsdf.errors import InputError

#: readings at or above this fraction of the lobe's peak are the lobe (see module doc)
SUPPORT_FRACTION = 1e-3
#: the slope box: the inverted extent of the readings at or above this fraction of the peak ...
BOX_FRACTION = 1e-2
#: ... widened by this share (a Gaussian lobe's 1e-2 contour is at 3 sigma: the box reaches 4.5 sigma)
BOX_MARGIN = 0.5
#: bins per axis of the slope histogram
DEFAULT_BINS = 121
_JAC_STEP = 1e-6


def _incident(theta_i_deg: float, phi_i_deg: float) -> np.ndarray:
    return direction(theta_i_deg, phi_i_deg)         # toward the source (the contract's frame)


def _normals(s: np.ndarray) -> np.ndarray:
    s = np.asarray(s, float)
    m = np.concatenate([-s, np.ones(s.shape[:-1] + (1,))], axis=-1)
    return m / np.linalg.norm(m, axis=-1, keepdims=True)


def exit_cosines(s: Any, n: float, theta_i_deg: float = 0.0, phi_i_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(u (..., 2), ok (...)): the exit direction cosines of light through a facet of slope s (..., 2)
    on the front face and the flat back face (module doc); ok is False where the facet or the back
    face reflects it totally or the facet faces away from the beam."""
    m = _normals(s)
    wi = _incident(theta_i_deg, phi_i_deg)
    c = m @ wi
    t, refracted = refract(np.broadcast_to(wi, m.shape), m, 1.0 / n)   # the project's one Snell (core.fresnel)
    u = n * t[..., :2]
    ok = (c > 0) & refracted & (np.sum(u * u, axis=-1) < 1.0)
    return u, ok


def jacobian(s: Any, n: float, theta_i_deg: float = 0.0, phi_i_deg: float = 0.0) -> np.ndarray:
    """du/ds (..., 2, 2) of `exit_cosines` (J[..., a, b] = d u_a / d s_b), central differences."""
    s = np.asarray(s, float)
    cols = []
    for b in range(2):
        e = np.zeros(2)
        e[b] = _JAC_STEP
        up, _ = exit_cosines(s + e, n, theta_i_deg, phi_i_deg)
        dn, _ = exit_cosines(s - e, n, theta_i_deg, phi_i_deg)
        cols.append((up - dn) / (2 * _JAC_STEP))
    return np.stack(cols, axis=-1)


def invert_cosines(u: Any, n: float, theta_i_deg: float = 0.0, phi_i_deg: float = 0.0,
                   iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """(s (..., 2), ok): the facet slope whose single-pass exit direction is u (..., 2) (Newton on
    `exit_cosines`); ok is False where no facet sends light there (or Newton did not converge)."""
    u = np.asarray(u, float)
    u0, _ = exit_cosines(np.zeros(2), n, theta_i_deg, phi_i_deg)
    s = (u - u0) / (n - 1.0)                       # the small-slope map as the start
    for _ in range(iterations):
        f, ok = exit_cosines(s, n, theta_i_deg, phi_i_deg)
        J = jacobian(s, n, theta_i_deg, phi_i_deg)
        r = f - u
        step = np.linalg.solve(J, r[..., None])[..., 0]
        s = s - np.clip(step, -0.5, 0.5)
        if np.all(np.abs(r) < 1e-12):
            break
    f, ok = exit_cosines(s, n, theta_i_deg, phi_i_deg)
    ok = ok & np.all(np.abs(f - u) < 1e-9, axis=-1)
    return s, ok


def single_pass_transmittance(s: Any, n: float, theta_i_deg: float = 0.0, phi_i_deg: float = 0.0) -> np.ndarray:
    """T(s): unpolarised Fresnel transmittance of the facet (air -> glass) times that of the flat back
    face (glass -> air) for the ray of `exit_cosines`; 0 where it does not leave."""
    m = _normals(s)
    wi = _incident(theta_i_deg, phi_i_deg)
    c = np.clip(m @ wi, 0.0, 1.0)
    u, ok = exit_cosines(s, n, theta_i_deg, phi_i_deg)
    sin_g = np.sqrt(np.minimum(np.sum(u * u, axis=-1), 1.0)) / n          # sine of the glass angle at z
    cos_g = np.sqrt(1.0 - sin_g**2)
    T = (1.0 - fresnel_reflectance(c, 1.0, n)) * (1.0 - fresnel_reflectance(cos_g, n, 1.0))
    return np.where(ok, T, 0.0)


@dataclass(frozen=True)
class SlopeDensity:
    """A 2-D facet-slope density on a regular grid: density[i, j] at (centres_sx[i], centres_sy[j]),
    per unit slope-plane area, sum(density) dsx dsy = 1 (surface.stats.slope_histogram's convention)."""

    edges_sx: np.ndarray
    edges_sy: np.ndarray
    density: np.ndarray
    notes: tuple[str, ...] = field(default=())

    @property
    def centres_sx(self) -> np.ndarray:
        return 0.5 * (self.edges_sx[1:] + self.edges_sx[:-1])

    @property
    def centres_sy(self) -> np.ndarray:
        return 0.5 * (self.edges_sy[1:] + self.edges_sy[:-1])

    @property
    def cell_area(self) -> float:
        return float(np.diff(self.edges_sx)[0] * np.diff(self.edges_sy)[0])

    def moments(self) -> dict:
        """Mean slope per axis, rms slope per axis (about zero) and the rms magnitude."""
        w = self.density * self.cell_area
        SX, SY = np.meshgrid(self.centres_sx, self.centres_sy, indexing="ij")
        rx, ry = float(np.sqrt(np.sum(w * SX**2))), float(np.sqrt(np.sum(w * SY**2)))
        return {"mean_sx": float(np.sum(w * SX)), "mean_sy": float(np.sum(w * SY)),
                "rms_slope_x": rx, "rms_slope_y": ry, "rms_slope": float(np.hypot(rx, ry))}

    def marginals(self) -> tuple[np.ndarray, np.ndarray]:
        """(p_x(sx), p_y(sy)): the two 1-D densities (each integrates to 1)."""
        return (self.density.sum(axis=1) * np.diff(self.edges_sy)[0],
                self.density.sum(axis=0) * np.diff(self.edges_sx)[0])

    def separability(self) -> float:
        """Total-variation distance between the density and the product of its marginals (0: separable)."""
        px, py = self.marginals()
        return float(0.5 * np.sum(np.abs(self.density - np.outer(px, py))) * self.cell_area)


def _lobe_interpolator(theta_deg: np.ndarray, phi_deg: np.ndarray, f: np.ndarray):
    """f as a function of the direction cosine pair u (q, 2) -> (q,): bilinear in (theta_s, phi_s) when
    the rows form a full (theta, phi) grid (measured files do; azimuth wraps around), else linear
    over a triangulation of the direction-cosine plane (repeated directions averaged)."""
    th, ph = np.unique(theta_deg), np.unique(phi_deg)
    if th.size * ph.size == f.size and th.size >= 2 and ph.size >= 4:
        from scipy.interpolate import RegularGridInterpolator
        F = np.zeros((th.size, ph.size))
        F[np.searchsorted(th, theta_deg), np.searchsorted(ph, phi_deg)] = f
        F = np.concatenate([F[:, -1:], F, F[:, :1]], axis=1)            # azimuth wraps around
        P = np.concatenate([[ph[-1] - 360.0], ph, [ph[0] + 360.0]])
        rgi = RegularGridInterpolator((th, P), F, bounds_error=False, fill_value=0.0)

        def on_grid(u: np.ndarray) -> np.ndarray:
            t = np.degrees(np.arcsin(np.clip(np.hypot(u[:, 0], u[:, 1]), 0.0, 1.0)))
            p = np.degrees(np.arctan2(u[:, 1], u[:, 0])) % 360.0
            p = np.where(p < P[0], p + 360.0, p)
            return rgi(np.stack([t, p], axis=-1))
        return on_grid
    from scipy.interpolate import LinearNDInterpolator
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    u = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p)], axis=-1)
    key = np.round(u, 9)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    fm = np.bincount(inv, weights=f, minlength=len(uniq)) / np.bincount(inv, minlength=len(uniq))
    return LinearNDInterpolator(uniq, fm, fill_value=0.0)


def slope_density(rows: Any, n: float, bins: int = DEFAULT_BINS) -> SlopeDensity:
    """Invert the transmitted rows of ONE incidence (near normal) into the facet-slope density (module doc).

    `rows`: a Recording (or any object with its columns) holding the T rows of one (theta_i, phi_i).
    """
    side = np.asarray(rows.side)
    T = side == "T"
    ti = np.unique(np.asarray(rows.theta_i_deg)[T])
    pi = np.unique(np.asarray(rows.phi_i_deg)[T])
    if ti.size != 1 or pi.size != 1:
        raise InputError("recording", f"the slope inversion takes the transmitted rows of one incidence; "
                                      f"got {ti.size} polar and {pi.size} azimuth incidences")
    theta_i, phi_i = float(ti[0]), float(pi[0])
    ts, ps = np.radians(np.asarray(rows.theta_s_deg)[T]), np.radians(np.asarray(rows.phi_s_deg)[T])
    f = np.asarray(rows.bsdf_sr, float)[T]
    u = np.stack([np.sin(ts) * np.cos(ps), np.sin(ts) * np.sin(ps)], axis=-1)
    peak = float(np.percentile(f, 99.5))
    if not peak > 0:
        raise InputError("recording", "the transmitted readings are all zero: no lobe to invert")
    lit = f >= SUPPORT_FRACTION * peak
    # the slope box: the inverted extent of the lobe's bright part, with a margin
    s_lit, ok = invert_cosines(u[f >= BOX_FRACTION * peak], n, theta_i, phi_i)
    if not ok.any():
        raise InputError("recording", "no reading of the lobe is reachable by a single facet at this index")
    s_max = float(np.max(np.abs(s_lit[ok]))) * (1.0 + BOX_MARGIN)
    edges = np.linspace(-s_max, s_max, bins + 1)
    c = 0.5 * (edges[1:] + edges[:-1])
    S = np.stack(np.meshgrid(c, c, indexing="ij"), axis=-1)
    uS, okS = exit_cosines(S, n, theta_i, phi_i)
    interp = _lobe_interpolator(np.asarray(rows.theta_s_deg)[T], np.asarray(rows.phi_s_deg)[T], np.where(lit, f, 0.0))
    fS = np.where(okS, interp(np.ascontiguousarray(uS.reshape(-1, 2))).reshape(okS.shape), 0.0)
    detJ = np.abs(np.linalg.det(jacobian(S, n, theta_i, phi_i)))
    m = _normals(S)
    lit_area = np.clip(m @ _incident(theta_i, phi_i), 0, None) / (m[..., 2] * np.cos(np.radians(theta_i)))
    weight = single_pass_transmittance(S, n, theta_i, phi_i) * lit_area
    p = np.where(okS & (weight > 0), fS * detJ / np.where(weight > 0, weight, 1.0), 0.0)
    p = np.clip(p, 0.0, None)
    area = (edges[1] - edges[0]) ** 2
    total = p.sum() * area
    if not total > 0:
        raise InputError("recording", "the inverted slope density is empty")
    notes = (f"inverted from the T rows at incidence {theta_i:g}/{phi_i:g} deg with n = {n:g}: single pass "
             "through the facet and the flat back face, no shadowing, detector blur not deconvolved",
             f"lobe read where f >= {SUPPORT_FRACTION:g} x its peak ({peak:.4g} 1/sr); slope box +-{s_max:.4g} "
             f"(the slopes of the readings >= {BOX_FRACTION:g} x the peak, +{BOX_MARGIN:.0%}), {bins} x {bins} bins")
    return SlopeDensity(edges, edges.copy(), p / total, notes)


#: azimuth step of the direction-plane grid an in-plane cut is spread over (`isotropic_reading`)
ISOTROPIC_PHI_STEP_DEG = 2.0


@dataclass(frozen=True)
class LobeRows:
    """Transmitted rows of one incidence as `slope_density` reads them (the columns of a Recording)."""

    side: np.ndarray
    theta_i_deg: np.ndarray
    phi_i_deg: np.ndarray
    theta_s_deg: np.ndarray
    phi_s_deg: np.ndarray
    bsdf_sr: np.ndarray

    def __len__(self) -> int:
        return int(self.bsdf_sr.size)


def isotropic_reading(rows: Any, phi_step_deg: float = ISOTROPIC_PHI_STEP_DEG) -> tuple[LobeRows, dict]:
    """The transmitted lobe over the whole direction plane from an in-plane cut at normal incidence,
    read as isotropic; (rows on a full (theta_s, phi_s) grid, facts).

    Assumption: the relief is statistically isotropic, so at normal incidence its transmitted lobe
    depends on the exit direction's polar angle alone, f(u) = g(|u|) (the facet-slope density is a
    function of |s|, and the single-pass map s -> u of `exit_cosines` is rotationally symmetric about
    the normal).  The cut (rows in one plane of scatter, both halves phi_s and phi_s + 180) then is g:
    the two halves are averaged at each theta_s (an isotropic lobe is even), and g is spread over the
    azimuths 0, phi_step_deg, ... of a full grid, which `slope_density` inverts as it inverts a measured
    file's grid.  What the cut cannot show: an anisotropic relief's other axis (its slopes across the
    plane of scatter are read as equal to those along it) and any azimuthal structure (a square top-hat
    is read as a round one).  `facts`: the plane, the readings per half and their asymmetry (the largest
    difference of the halves at equal theta_s over the peak: a tilt or an asymmetric relief)."""
    side = np.asarray(rows.side)
    T = side == "T"
    ti = np.unique(np.asarray(rows.theta_i_deg)[T])
    if ti.size != 1 or abs(float(ti[0])) > 1e-9:
        raise InputError("recording", "the isotropic reading of an in-plane scan takes its rows at normal "
                                      f"incidence (theta_i = 0); got theta_i {', '.join(f'{t:g}' for t in ti)} deg")
    th = np.asarray(rows.theta_s_deg, float)[T]
    ph = np.asarray(rows.phi_s_deg, float)[T]
    f = np.asarray(rows.bsdf_sr, float)[T]
    off = th > 0
    planes = np.unique(np.round(np.mod(ph[off], 180.0), 6))
    if planes.size != 1:
        raise InputError("recording", f"an in-plane scan lies in one plane of scatter; these rows lie in {planes.size}")
    plane = float(planes[0])
    half_a = off & np.isclose(np.mod(ph, 360.0), plane)
    half_b = off & ~half_a
    thetas = np.unique(th)
    g = np.zeros(thetas.size)
    asym = 0.0
    for k, t in enumerate(thetas):
        at = th == t
        if t == 0:
            g[k] = float(np.mean(f[at]))
            continue
        a, b = f[at & half_a], f[at & half_b]
        vals = [float(np.mean(x)) for x in (a, b) if x.size]
        g[k] = float(np.mean(vals))
        if len(vals) == 2:
            asym = max(asym, abs(vals[0] - vals[1]))
    if thetas[0] != 0.0:
        raise InputError("recording", "the in-plane scan has no reading at theta_s = 0 (the lobe's centre at "
                                      "normal incidence): the isotropic reading needs it")
    phis = np.arange(0.0, 360.0, float(phi_step_deg))
    TH, PH = np.meshgrid(thetas, phis, indexing="ij")
    G = np.broadcast_to(g[:, None], TH.shape)
    n = TH.size
    out = LobeRows(np.full(n, "T"), np.zeros(n), np.zeros(n), TH.reshape(-1), PH.reshape(-1),
                   np.ascontiguousarray(G).reshape(-1))
    peak = float(np.max(g)) if g.size else 0.0
    facts = {"reading": "isotropic reading of an in-plane scan", "plane_phi_s_deg": plane,
             "readings_per_half": [int(np.count_nonzero(half_a)), int(np.count_nonzero(half_b))],
             "half_asymmetry_over_peak": asym / peak if peak > 0 else 0.0,
             "lobe_readings": int(np.count_nonzero(g >= SUPPORT_FRACTION * peak)) if peak > 0 else 0,
             "assumption": "the relief is statistically isotropic: at normal incidence the lobe depends on the "
                           "exit polar angle alone, so the in-plane cut (both halves averaged) is the lobe over "
                           "every azimuth; an anisotropic relief's slopes across the plane are read as equal to "
                           "those along it"}
    return out, facts
