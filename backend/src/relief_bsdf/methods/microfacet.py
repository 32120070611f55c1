"""`microfacet`: analytic microfacet BSDFs of a rough dielectric (or metal) boundary.

Paper sec. 2.1 (Cook-Torrance, the multi-lobe mixture eq. 4, the V-cavity factor eq. 5)
and Walter, Marschner, Li & Torrance, "Microfacet models for refraction through rough
surfaces", EGSR 2007 (cited below as W07), which extends it to transmission.

Frame (formats.md): `wi` points toward the source, +z points into the medium the light
comes from (index n_i); `wo` is the scattered direction, z > 0 reflection (still in n_i),
z < 0 transmission (into n_t).  Light from inside the dielectric is handled by the caller
mirroring the frame (n_i = n_inside, n_t = n_outside).

Model (W07):
- reflection, eq. 20 with the half vector h_r = normalize(wi + wo) (eq. 13):
      f_r = F(wi.h) D(h) G(wi, wo, h) / (4 |wi.n| |wo.n|)
- transmission, eq. 21 with the generalised half vector h_t = -normalize(n_i wi + n_t wo)
  (eq. 16), oriented to +z:
      f_t = |wi.h| |wo.h| / (|wi.n| |wo.n|) * n_t^2 (1 - F(wi.h)) D(h) G / (n_i wi.h + n_t wo.h)^2
  This is a *radiance* BTDF: swapping the roles gives f_t(a->b) / n_b^2 = f_t(b->a) / n_a^2,
  the convention of formats.md, and its cosine-weighted integral over wo is the power
  transmittance (it equals Mitsuba 3's `roughdielectric` in importance transport).
- distributions (W07 eqs. 25, 28 / paper eq. 3): Beckmann D = exp(-tan^2 t / a^2) / (pi a^2 cos^4 t),
  GGX D = a^2 / (pi cos^4 t (a^2 + tan^2 t)^2), both normalised so that int D(m) (m.n) dw_m = 1.
- multi-lobe mixture (paper eq. 4): D = sum_j w_j D(a_j), sum w_j = 1.  The slope density of
  a mixture is the mixture of slope densities and Smith's Lambda is linear in the slope
  density, so the consistent Smith term is Lambda = sum_j w_j Lambda_j (used here).
- shadowing: "smith": separable G = G1(wi) G1(wo), G1 = chi+(v.m / v.n) / (1 + Lambda(v)) with
  Beckmann's exact Lambda = (erf(a) - 1)/2 + exp(-a^2) / (2 a sqrt(pi)), a = 1/(alpha tan t)
  (W07 eq. 27) and GGX's exact Lambda = (sqrt(1 + alpha^2 tan^2 t) - 1)/2 (W07 eq. 34);
  "vcavity": paper eq. 5, G = min(1, 2 (n.h)(n.wo)/|wo.h|, 2 (n.h)(n.wi)/|wi.h|) (for
  transmission the same expression with absolute values, an approximation: the V-cavity
  derivation is for reflection);
  "incident": G = G1(wi) only (no masking of wo) - what the `normals` Monte Carlo samples;
  "none": G = 1.
Uncertainty (lobes fitted to a relief, option tile_uncertainty, default True): the finite tile's
realisation uncertainty of the fitted lobe parameters p = (ln alpha_j, w_1 .. w_{L-1}) by sub-tile
batch means (the lobes refitted on each sub-tile of methods.realisation.subtile_grid: Cov(p_tile)
= Cov_g(p_g) / G, exact for alpha^2 = <s^2> of one Beckmann lobe, asymptotic for the EM mixture),
carried into every cell by central differences along the covariance's principal axes (2 extra
evaluations per parameter); sigma_per_sr, metadata["uncertainty"], and the too-few-correlation-areas
warning as the other methods.  Roughness given as an option has no tile: sigma_per_sr is None.
Regime of validity: geometric optics (relief heights and facet sizes >> wavelength), a
single scattering event per path (inter-reflections are neglected, so R + T < 1 at high
roughness and grazing angles; the deficit is reported as `lost`), facet slopes distributed
as the chosen analytic lobes.  Cook-Torrance (paper eqs. 1-6) is the reflection part with the
V-cavity G; note that its 1982 form F D G / (pi (n.l)(n.v)) with the paper's un-normalised D
(eq. 3) equals 4x the energy-consistent F D G / (4 (n.l)(n.v)) used here (W07 sec. 4).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy import optimize

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction, projected_solid_angle
from relief_bsdf.core.frames import dot as _dot, normalize as _normalize
from relief_bsdf.errors import InputError, RequestError
from relief_bsdf.core.fresnel import fresnel_unpolarized, mueller_interface
from relief_bsdf.core.index import Material
from relief_bsdf.parallel import default_workers, map_tasks
from relief_bsdf.core.microfacet import (  # the one copy of the distributions
    DISTRIBUTIONS, distribution_D, lobes as _lobes, smith_G1, smith_lambda, vcavity_G1)
from relief_bsdf.core.stokes import s_axis as _s_vector, stokes_rotation

from relief_bsdf.methods.options import SHADOWING, MicrofacetOptions  # the one list of shadowing terms


# ------------------------------------------------------------------ the BSDF


@dataclass(frozen=True)
class Roughness:
    """The statistical facet surface of the analytic BSDFs (module doc).

    `alpha`: one roughness, or the roughnesses of the lobes of a mixture (paper eq. 4) with
    their `weights`; `distribution`: "beckmann" or "ggx"; `shadowing`: "smith" (separable
    G1(wi) G1(wo)), "vcavity" (paper eq. 5, Cook-Torrance's), "incident" (G1(wi) only) or "none".
    """

    alpha: Any
    distribution: str = "beckmann"
    weights: Any = None
    shadowing: str = "smith"


@dataclass
class WalterTerms:
    """Pieces of the Walter BSDF at a batch of direction pairs (for scalar and Mueller use)."""

    f: np.ndarray           # (N,) BSDF in 1/sr
    geom: np.ndarray        # (N,) f without its Fresnel factor (F for R, 1 - F for T)
    h: np.ndarray           # (N, 3) microfacet normal, +z side
    is_T: np.ndarray        # (N,) bool
    cos_ih: np.ndarray      # (N,) wi.h (> 0 where valid)


def walter_terms(wi: Any, wo: Any, n_i: Any, n_t: Any, rough: Roughness) -> WalterTerms:
    """Evaluate W07 eqs. 20-21 and return the value and its geometric part (see `walter_bsdf`)."""
    alpha, distribution, shadowing, weights = rough.alpha, rough.distribution, rough.shadowing, rough.weights
    wi = np.atleast_2d(np.asarray(wi, float))
    wo = np.atleast_2d(np.asarray(wo, float))
    wi, wo = np.broadcast_arrays(wi, wo)
    if shadowing not in SHADOWING:
        raise InputError("shadowing", f"unknown shadowing {shadowing!r}; choose {SHADOWING}")
    n_i = np.real(np.asarray(n_i, complex)) if np.iscomplexobj(n_i) else np.asarray(n_i, float)
    n_t_c = np.asarray(n_t, complex)
    n_t_re = np.real(n_t_c)
    absorbing = np.imag(n_t_c) > 0
    ci = wi[..., 2]
    co = wo[..., 2]
    is_T = co < 0
    # half vectors: eq. 13 (reflection) and eq. 16 (transmission), oriented to +z
    h_r = wi + wo
    h_t = -(np.asarray(n_i)[..., None] * wi + np.asarray(n_t_re)[..., None] * wo)
    h = _normalize(np.where(is_T[..., None], h_t, h_r))
    h = h * np.where(h[..., 2] < 0, -1.0, 1.0)[..., None]
    ih = _dot(wi, h)
    oh = _dot(wo, h)
    mn = h[..., 2]
    D = distribution_D(mn, alpha, distribution, weights)
    # facet side tests (chi+ of W07 eq. 19): wi in front of the facet; wo in front (R) or behind (T)
    ok = (ci > 0) & (ih > 0) & (mn > 0) & np.where(is_T, oh < 0, oh > 0) & (co != 0)
    if shadowing == "smith":
        G = smith_G1(ci, alpha, distribution, weights) * smith_G1(co, alpha, distribution, weights)
    elif shadowing == "incident":
        G = smith_G1(ci, alpha, distribution, weights)
    elif shadowing == "vcavity":
        G = np.minimum(vcavity_G1(ci, ih, mn), vcavity_G1(co, oh, mn))
    else:
        G = np.ones_like(ci)
    F = fresnel_unpolarized(np.clip(ih, 0.0, 1.0), n_i, n_t_c)
    aci = np.abs(ci)
    aco = np.where(co == 0, 1.0, np.abs(co))
    with np.errstate(divide="ignore", invalid="ignore"):
        geom_r = D * G / (4.0 * aci * aco)
        denom = (n_i * ih + n_t_re * oh) ** 2
        geom_t = np.abs(ih * oh) / (aci * aco) * n_t_re**2 * D * G / denom
    geom = np.where(is_T, geom_t, geom_r)
    geom = np.where(ok & np.isfinite(geom) & ~(is_T & absorbing), geom, 0.0)
    f = geom * np.where(is_T, 1.0 - F, F)
    return WalterTerms(f=f, geom=geom, h=h, is_T=is_T, cos_ih=ih)


def walter_bsdf(wi: Any, wo: Any, n_i: Any, n_t: Any, rough: Roughness) -> np.ndarray:
    """Rough-dielectric BSDF f(wi -> wo) in 1/sr (W07 eqs. 20-21; module doc for conventions).

    wi (N, 3) toward the source with wi.z > 0 in the incident medium n_i; wo (N, 3) with
    wo.z > 0 reflection, wo.z < 0 transmission into n_t.  `rough.alpha` is one roughness or the
    lobe roughnesses of a mixture with `rough.weights` (paper eq. 4).  A complex n_t (metal)
    reflects with its complex Fresnel factor and transmits nothing (absorbed).
    """
    return walter_terms(wi, wo, n_i, n_t, rough).f


CT_SHADOWING = "vcavity"        # Cook-Torrance's shadowing term (paper eq. 5)


def cook_torrance_brdf(wi: Any, wo: Any, n_i: Any, n_t: Any, rough: Roughness, diffuse: float = 0.0) -> np.ndarray:
    """Cook-Torrance reflection (paper eqs. 1-6) for opaque or metal surfaces, in 1/sr.

    Specular part: F D G / (4 (n.l)(n.v)) with D a single or multi-lobe (eq. 4) distribution
    of rms slope `rough.alpha` and G = `rough.shadowing` (Cook-Torrance's own is the V-cavity
    G of eq. 5, `Roughness(m, shadowing=CT_SHADOWING)`); F from the complex index n_t.  Plus an
    optional Lambertian part `diffuse` / pi (the d R_d term of eq. 1, albedo in [0, 1]).
    Transmission directions (wo.z < 0) get 0.
    """
    wo = np.atleast_2d(np.asarray(wo, float))
    f = walter_bsdf(wi, wo, n_i, n_t, rough)
    f = np.where(wo[..., 2] > 0, f, 0.0)
    if diffuse:
        f = f + np.where(wo[..., 2] > 0, diffuse / np.pi, 0.0)
    return f


# ------------------------------------------------------------------ polarisation


def walter_mueller(wi: Any, wo: Any, n_i: Any, n_t: Any, rough: Roughness, phi_i_rad: float = 0.0,
                   phi_o_rad: Any = 0.0) -> np.ndarray:
    """Mueller BSDF (N, 4, 4) in 1/sr: W07's geometric factor times the facet's Fresnel Mueller matrix.

    The Fresnel Mueller matrix (optics.mueller_interface) acts in the s/p basis of the facet's
    plane of incidence (wi, h); it is rotated from the table's incident basis (s = z x wi) and
    into the scattered basis (s = z x wo), the frames documented in bsdf.py.  Element [0, 0]
    equals `walter_bsdf`.  Single scattering off one facet, so no depolarisation by multiple
    bounces is modelled.  phi_i_rad / phi_o_rad: azimuths of the s-axes of directions along z
    (core.stokes.s_axis fallback).
    """
    t = walter_terms(wi, wo, n_i, n_t, rough)
    wi = np.broadcast_to(np.atleast_2d(np.asarray(wi, float)), t.h.shape)
    wo = np.broadcast_to(np.atleast_2d(np.asarray(wo, float)), t.h.shape)
    ki = -wi
    s_tab_i = _s_vector(wi, np.asarray(phi_i_rad, float))
    s_tab_o = _s_vector(wo, np.asarray(phi_o_rad, float))
    s_m = np.cross(t.h, wi)
    nm = np.linalg.norm(s_m, axis=-1, keepdims=True)
    s_m = np.where(nm > 1e-12, s_m / np.where(nm > 1e-12, nm, 1.0), s_tab_i)
    cos_ih = np.clip(t.cos_ih, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):   # cos = 0 only where geom is 0 anyway
        MR = mueller_interface(cos_ih, n_i, n_t, "R")
        MT = mueller_interface(cos_ih, n_i, n_t, "T")
    MF = np.where(t.is_T[..., None, None], MT, MR)
    MF = np.nan_to_num(MF)
    L_in = stokes_rotation(ki, s_tab_i, s_m)
    L_out = stokes_rotation(wo, s_m, s_tab_o)
    M = L_out @ MF @ L_in
    return t.geom[..., None, None] * M


# ------------------------------------------------------------------ cell averages


def cell_directions(theta_edges_deg: Any, phi_edges_deg: Any, side: str, subsamples: int = 4):
    """Sub-sample directions (S, A, K*K, 3) uniform in projected solid angle within each cell.

    Midpoints of a K x K grid in (sin^2 theta, phi): equal projected solid angle each, so a
    plain mean is the cell average the tables store.  Side "T" points to z < 0.  Also returns
    the azimuths (S, A, K*K) in radians.
    """
    k = int(subsamples)
    te = np.radians(np.asarray(theta_edges_deg, float))
    pe = np.radians(np.asarray(phi_edges_deg, float))
    u_lo, u_hi = np.sin(te[:-1]) ** 2, np.sin(te[1:]) ** 2
    frac = (np.arange(k) + 0.5) / k
    u = u_lo[:, None] + (u_hi - u_lo)[:, None] * frac[None, :]             # (S, K)
    ph = pe[:-1, None] + np.diff(pe)[:, None] * frac[None, :]               # (A, K)
    st = np.sqrt(u)
    ct = np.sqrt(np.maximum(0.0, 1.0 - u))
    S, A = u.shape[0], ph.shape[0]
    st4 = st[:, None, :, None]
    ct4 = ct[:, None, :, None]
    ph4 = ph[None, :, None, :]
    x = st4 * np.cos(ph4)
    y = st4 * np.sin(ph4)
    z = np.broadcast_to(ct4, x.shape)
    if side == "T":
        z = -z
    d = np.stack(np.broadcast_arrays(x, y, z), axis=-1).reshape(S, A, k * k, 3)
    phis = np.broadcast_to(ph4, x.shape).reshape(S, A, k * k)
    return d, phis


def _subset_directions(theta_edges_deg: Any, phi_edges_deg: Any, side: str, k: int, s_idx: np.ndarray,
                       a_idx: np.ndarray):
    """Sub-sample directions (n, K*K, 3), azimuths (n, K*K) and quadrature weights (n, K*K, summing
    to 1 per cell) for the listed cells (s_idx, a_idx).

    Midpoints in sin^2 theta (equal weights), except in polar-cap cells (lower edge at theta = 0):
    there a lobe centred on the pole (normal incidence) decays within the first sin^2 theta step
    and the midpoint rule in sin^2 theta misses it (96 % of a 0.2 degree wide T lobe in 3 degree
    cells), so those cells use midpoints in sin theta with weights proportional to sin theta (the
    projected solid angle of each ring, 2 s ds / s_hi^2).
    """
    te = np.radians(np.asarray(theta_edges_deg, float))
    pe = np.radians(np.asarray(phi_edges_deg, float))
    frac = (np.arange(k) + 0.5) / k
    u_lo, u_hi = np.sin(te[s_idx]) ** 2, np.sin(te[s_idx + 1]) ** 2
    u = u_lo[:, None] + (u_hi - u_lo)[:, None] * frac[None, :]                 # (n, K)
    wt = np.full(u.shape, 1.0 / k)
    cap = u_lo == 0.0
    if np.any(cap):
        s_cap = np.sqrt(u_hi[cap])[:, None] * frac[None, :]
        u[cap] = s_cap ** 2
        wt[cap] = 2.0 * frac[None, :] / k * np.ones((int(cap.sum()), 1))   # 2 s_j ds / s_hi^2
    ph = pe[a_idx][:, None] + (pe[a_idx + 1] - pe[a_idx])[:, None] * frac[None, :]
    st = np.sqrt(u)[:, :, None]
    ct = np.sqrt(np.maximum(0.0, 1.0 - u))[:, :, None]
    phb = ph[:, None, :]
    x, y = st * np.cos(phb), st * np.sin(phb)
    z = np.broadcast_to(-ct if side == "T" else ct, x.shape)
    n = s_idx.size
    d = np.stack([x, y, z], axis=-1).reshape(n, k * k, 3)
    w = np.broadcast_to(wt[:, :, None] / k, x.shape).reshape(n, k * k)
    return d, np.broadcast_to(phb, x.shape).reshape(n, k * k), w


def cell_average(fn: Callable, theta_edges_deg: Any, phi_edges_deg: Any, side: str, subsamples: int = 4,
                 refine: tuple | None = None, with_phi: bool = False, mirror: bool = False) -> np.ndarray:
    """Average of fn(wo) over each scatter cell in projected solid angle, shape (S, A) (+ fn's trailing dims).

    `fn` takes (M, 3) directions (and their (M,) azimuths in radians when `with_phi`) and
    returns (M,) or (M, ...) values, e.g. `lambda wo: walter_bsdf(wi, wo, 1.0, 1.5, Roughness(0.1))`.
    Midpoint rule on a K x K grid in (sin^2 theta, phi) per cell (in (sin theta, phi) with
    sin theta weights for polar-cap cells, see `_subset_directions`).  `refine = (K_fine, frac)`
    recomputes with K_fine the cells holding more than `frac` of the side's total energy
    (f * projected solid angle of the first value), where a narrow lobe needs it.  Analytic
    tables averaged this way compare cell for cell with Monte-Carlo tables that bin exit
    directions.  `mirror`: fn is even in the azimuth (fn(x, -y, z) = fn(x, y, z): an axis-aligned
    slope distribution lit from the plane phi = 0 or 180 deg, intensity only); when the azimuth edges
    are symmetric too, each cell's mirror image (the same sub-samples mirrored) is copied instead of
    computed, which halves the work.
    """
    te = np.asarray(theta_edges_deg, float)
    pe = np.asarray(phi_edges_deg, float)
    S, A = te.size - 1, pe.size - 1
    partner = _azimuth_mirror(pe) if mirror else None
    if partner is None:
        partner = np.arange(A)                                # every cell its own: all computed
    keep = np.nonzero(np.arange(A) <= partner)[0]             # one cell of each mirror pair
    s_idx, a_idx = (g.ravel() for g in np.meshgrid(np.arange(S), keep, indexing="ij"))
    first = _cells(fn, te, pe, side, int(subsamples), s_idx, a_idx, with_phi)
    v = np.empty((S, A) + first.shape[1:])
    v[s_idx, a_idx] = first
    v[s_idx, partner[a_idx]] = first
    if refine is not None and int(refine[0]) > int(subsamples):
        e = np.abs(v.reshape(S, A, -1)[..., 0]) * projected_solid_angle(te, pe)
        sel = np.nonzero(e[s_idx, a_idx] > float(refine[1]) * e.sum())[0]
        if sel.size:
            fine = _cells(fn, te, pe, side, int(refine[0]), s_idx[sel], a_idx[sel], with_phi)
            v[s_idx[sel], a_idx[sel]] = fine
            v[s_idx[sel], partner[a_idx[sel]]] = fine
    return v


def _azimuth_mirror(phi_edges_deg: np.ndarray) -> np.ndarray | None:
    """partner[j]: the azimuth cell that is cell j mirrored (phi -> -phi, modulo 360 deg), for every j,
    or None when the edges have no such symmetry (then `cell_average` computes every cell)."""
    pe = np.asarray(phi_edges_deg, float)
    lo, hi = np.mod(pe[:-1], 360.0), np.mod(pe[1:], 360.0)
    m_lo, m_hi = np.mod(-pe[1:], 360.0), np.mod(-pe[:-1], 360.0)

    def same(a, b):
        d = np.abs(a[:, None] - b[None, :])
        return np.minimum(d, 360.0 - d) < 1e-9
    match = same(m_lo, lo) & same(m_hi, hi)
    if not np.all(match.sum(axis=1) == 1):
        return None
    return np.argmax(match, axis=1)


def _cells(fn: Callable, te: np.ndarray, pe: np.ndarray, side: str, k: int, s_idx: np.ndarray, a_idx: np.ndarray,
           with_phi: bool) -> np.ndarray:
    """`cell_average`'s midpoint rule on the listed cells (n, + fn's trailing dims)."""
    d, ph, wq = _subset_directions(te, pe, side, k, s_idx, a_idx)
    n, K = ph.shape
    v = np.asarray(fn(d.reshape(-1, 3), ph.reshape(-1)) if with_phi else fn(d.reshape(-1, 3)))
    v = v.reshape((n, K) + v.shape[1:])
    return np.einsum("nk,nk...->n...", wq, v)


def auto_subsamples(theta_edges_deg: Any, phi_edges_deg: Any, alpha_min: float, n_ratio: float = 1.5) -> tuple:
    """(K, K_fine): sub-samples per cell axis everywhere, and in the cells that hold the lobe.

    The transmitted lobe is narrower than the facet spread by about (1 - 1/n_ratio) (n_ratio the
    larger over the smaller index: a facet tilt t deviates the refracted ray by ~t (1 - 1/n)),
    and the midpoint error of the cell averages falls as 1 / K^2; K = 15 cell widths per
    effective lobe width keeps the hemispherical error near 1e-3 (measured: alpha = 0.14,
    n = 1.5, 1-degree cells: 0.25 % at K = 3, 0.06 % at K = 6).  K is capped at 6 everywhere;
    the cells holding the lobe (see `cell_average`'s refine) get up to 128.
    """
    te = np.radians(np.asarray(theta_edges_deg, float))
    width = float(np.max(np.diff(te)))
    n_ratio = max(float(n_ratio), 1.0)
    a_eff = max(alpha_min, 1e-4) * max(1.0 - 1.0 / n_ratio, 0.05)
    need = int(np.ceil(15.0 * width / a_eff))
    return int(np.clip(need, 3, 6)), int(np.clip(need, 3, 128))


# ------------------------------------------------------------------ slopes and lobe fits


def relief_slopes(relief) -> tuple[np.ndarray, np.ndarray]:
    """Facet slopes (dz/dx, dz/dy) of a relief, valid facets only, mean slope removed.

    The facets are the triangles of the piecewise-linear surface (`surface.stats.facet_slopes`,
    the one slope definition, what the ray tracer sees); every triangle covers the same
    projected area, so these samples are drawn from the slope density P22 weighted by
    *projected* area, which is exactly the density behind D(m) (D(m) cos(theta_m) d w_m is
    the projected-area fraction of facets).  The mean slope (an instrument tilt) is removed:
    the lobes are centred on the macroscopic normal by construction.
    """
    from relief_bsdf.surface.stats import facet_slopes
    sx, sy = (a.ravel() for a in facet_slopes(relief))
    ok = np.isfinite(sx) & np.isfinite(sy)
    if ok.sum() < 16:
        raise InputError(relief.source or "relief", "too few valid points to measure facet slopes "
                         "(need at least 16 facets with valid corners)")
    sx, sy = sx[ok], sy[ok]
    return sx - sx.mean(), sy - sy.mean()


def _slope_pdf_magnitude(s2: np.ndarray, alpha: float, distribution: str) -> np.ndarray:
    """Density of the slope magnitude s for an isotropic lobe, divided by s (depends on s^2 only)."""
    a2 = alpha * alpha
    if distribution == "beckmann":
        return 2.0 / a2 * np.exp(-s2 / a2)
    return 2.0 * a2 / (a2 + s2) ** 2


@dataclass
class Lobes:
    """A mixture of isotropic microfacet lobes (paper eq. 4)."""

    alpha: np.ndarray                 # (L,)
    weight: np.ndarray                # (L,) sum 1
    distribution: str = "beckmann"
    info: dict = field(default_factory=dict)

    def describe(self) -> dict:
        return {"distribution": self.distribution, "alpha": self.alpha.tolist(), "weight": self.weight.tolist(),
                **self.info}


def fit_lobes(relief_or_slopes: Any, n_lobes: int = 1, distribution: str = "beckmann",
              iterations: int = 200) -> Lobes:
    """Fit paper eq. 4's weights and roughnesses to a relief's measured facet slopes.

    Maximum likelihood on the slope magnitudes s = |grad z| (isotropic lobes: the slope
    density of one lobe is P22(s) and the magnitude density 2 pi s P22(s)) by expectation-
    maximisation.  Beckmann's M-step is closed form, alpha_j^2 = <s^2>_j (for one lobe
    alpha = rms slope magnitude, the usual Beckmann identity); GGX's is a 1-D likelihood
    maximisation.  Lobes start at quantiles of s.  `relief_or_slopes` is a Relief or a pair
    (sx, sy) of slope arrays.
    """
    if distribution not in DISTRIBUTIONS:
        raise InputError("distribution", f"unknown distribution {distribution!r}; choose {DISTRIBUTIONS}")
    n_lobes = int(n_lobes)
    if n_lobes < 1 or n_lobes > 8:
        raise InputError("lobes", f"number of lobes must be 1..8, got {n_lobes}")
    if isinstance(relief_or_slopes, tuple):
        sx, sy = (np.asarray(v, float).ravel() for v in relief_or_slopes)
    else:
        sx, sy = relief_slopes(relief_or_slopes)
    s2 = sx * sx + sy * sy
    s2 = s2[np.isfinite(s2)]
    if s2.size < 16 or not np.any(s2 > 0):
        where = getattr(relief_or_slopes, "source", "") or "relief"      # the height-map file, when read from one
        raise InputError(where, "the relief has no measurable slopes (flat or too few points)")
    if s2.size > 400_000:      # a deterministic thinning keeps EM fast on big maps
        s2 = s2[:: int(np.ceil(s2.size / 400_000))]
    rms = float(np.sqrt(s2.mean()))
    if n_lobes == 1 and distribution == "beckmann":
        return Lobes(np.array([rms]), np.ones(1), distribution, {"rms_slope": rms, "n_slopes": int(s2.size)})
    q = np.quantile(np.sqrt(s2), (np.arange(n_lobes) + 0.5) / n_lobes)
    alpha = np.maximum(q * 1.2, 1e-4 * max(rms, 1e-12))
    weight = np.full(n_lobes, 1.0 / n_lobes)
    prev = -np.inf
    for _ in range(iterations):
        p = np.stack([w * _slope_pdf_magnitude(s2, a, distribution) for a, w in zip(alpha, weight)])
        tot = p.sum(axis=0)
        tot = np.where(tot > 0, tot, 1e-300)
        ll = float(np.mean(np.log(tot)))
        r = p / tot
        nj = r.sum(axis=1)
        weight = nj / nj.sum()
        for j in range(n_lobes):
            if nj[j] <= 0:
                continue
            if distribution == "beckmann":
                alpha[j] = np.sqrt(max((r[j] * s2).sum() / nj[j], 1e-30))
            else:
                rj = r[j]

                def nll(la):
                    return -float((rj * np.log(_slope_pdf_magnitude(s2, np.exp(la), "ggx"))).sum())
                res = optimize.minimize_scalar(nll, bracket=(np.log(alpha[j]) - 0.3, np.log(alpha[j]) + 0.3))
                alpha[j] = float(np.exp(res.x))
        if abs(ll - prev) < 1e-10 * max(1.0, abs(ll)):
            break
        prev = ll
    order = np.argsort(alpha)
    return Lobes(alpha[order], weight[order], distribution,
                 {"rms_slope": rms, "n_slopes": int(s2.size), "log_likelihood": ll})


# ------------------------------------------------------------------ fit to any table


@dataclass
class TableFit:
    """A compact microfacet form of a BsdfTable, per incidence and side.

    f_k(wi -> wo) ~= sum_j weight[..., k, j] * walter_bsdf(wi, wo; alpha[..., k, j]) for side k
    (R, T), with the table's own indices (so the Fresnel factor is built in and a pure
    Walter table fits with weight 1).  Arrays are (W, I, P, 2, L); `rms_rel` (W, I, P, 2) is the
    rms residual in projected-solid-angle-weighted energy relative to the side's diffuse total.
    """

    alpha: np.ndarray
    weight: np.ndarray
    rms_rel: np.ndarray
    distribution: str
    n_i: np.ndarray          # (W,)
    n_t: np.ndarray          # (W,)
    specular_R: np.ndarray
    specular_T: np.ndarray
    incident_from: str

    def eval(self, iw: int, ii: int, ip: int, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        wo = np.atleast_2d(wo)
        out = np.zeros(wo.shape[0])
        for k in (0, 1):
            sel = (wo[:, 2] < 0) if k else (wo[:, 2] >= 0)
            for a, w in zip(self.alpha[iw, ii, ip, k], self.weight[iw, ii, ip, k]):
                if w > 0:
                    out += np.where(sel, w * walter_bsdf(wi, wo, self.n_i[iw], self.n_t[iw],
                                                         Roughness(a, self.distribution)), 0.0)
        return out


def fit_table(table: BsdfTable, n_lobes: int = 1, distribution: str = "ggx", subsamples: int = 3) -> TableFit:
    """Fit weights and roughnesses of `n_lobes` Walter lobes per incidence and side to any table.

    Variable projection: the roughnesses (log scale) by a bounded scalar search (one lobe) or
    scipy.optimize.least_squares (several), the non-negative weights for given roughnesses by
    NNLS.  Residuals are (model - table) cell
    values times sqrt(projected solid angle), i.e. an energy-weighted L2 error.  The table's
    specular (delta) parts are not fitted; they are passed through.  Used by the Blender
    bake (GGX: Cycles' microfacet distribution, roughness = sqrt(alpha)).
    """
    if not table.material:
        raise InputError("table", "the table records no material; cannot build Fresnel factors")
    mat = Material.from_dict(table.material)
    psa = table.projected_solid_angle_sr
    sq = np.sqrt(psa).ravel()
    W, I, P = table.values_per_sr.shape[:3]
    L = int(n_lobes)
    alpha = np.zeros((W, I, P, 2, L))
    weight = np.zeros((W, I, P, 2, L))
    rms = np.zeros((W, I, P, 2))
    n_i = np.zeros(W)
    n_t = np.zeros(W)
    dirs = {k: cell_directions(table.theta_s_edges_deg, table.phi_s_edges_deg, side, subsamples)[0].reshape(-1, 3)
            for k, side in enumerate(("R", "T"))}
    ncell = psa.size
    for iw, wl in enumerate(table.wavelength_nm):
        a_n, b_n = mat.n_pair(float(wl), table.incident_from)
        n_i[iw], n_t[iw] = np.real(a_n), np.real(b_n)
        for ii, ti in enumerate(table.theta_i_deg):
            for ip, pi in enumerate(table.phi_i_deg):
                wi = direction(ti, pi)[None, :]
                for k in (0, 1):
                    target = table.values_per_sr[iw, ii, ip, k].ravel()
                    tot = float((target * psa.ravel()).sum())
                    if tot <= 0:
                        continue

                    def basis(log_a):
                        cols = []
                        for a in np.exp(log_a):
                            v = walter_bsdf(wi, dirs[k], a_n, b_n, Roughness(a, distribution))
                            cols.append(v.reshape(ncell, -1).mean(axis=1))
                        return np.stack(cols, axis=1)

                    def resid(log_a):
                        B = basis(log_a) * sq[:, None]
                        w, _ = optimize.nnls(B, target * sq)
                        return B @ w - target * sq

                    lo_b, hi_b = np.log(1e-3), np.log(3.0)
                    if L == 1:
                        r1 = optimize.minimize_scalar(lambda x: 0.5 * float(np.sum(resid(np.array([x])) ** 2)),
                                                      bounds=(lo_b, hi_b), method="bounded",
                                                      options={"xatol": 2e-3})
                        la = np.array([r1.x])
                    else:
                        best = None
                        starts = np.log(np.geomspace(0.05, 0.6, L))
                        for x0 in (starts, starts + np.log(0.25)):
                            r = optimize.least_squares(resid, x0, bounds=(lo_b, hi_b), x_scale=1.0)
                            if best is None or r.cost < best.cost:
                                best = r
                        la = best.x
                    B = basis(la) * sq[:, None]
                    w, _ = optimize.nnls(B, target * sq)
                    alpha[iw, ii, ip, k] = np.exp(la)
                    weight[iw, ii, ip, k] = w
                    norm = float(np.sqrt(np.sum((target * sq) ** 2)))
                    rms[iw, ii, ip, k] = float(np.sqrt(np.sum((B @ w - target * sq) ** 2))) / norm
    return TableFit(alpha, weight, rms, distribution, n_i, n_t, table.specular_R.copy(), table.specular_T.copy(),
                    table.incident_from)


# ------------------------------------------------------------------ reconstruct


def check_indices(material: Material, request) -> None:
    """RequestError for an unphysical index at any requested wavelength, or light from inside a metal."""
    material.check_incidence(request.wavelengths_nm, request.incident_from)


def _task(ctx: dict, task: tuple) -> dict:
    """One incidence of one lobe variant (0: the fitted lobes; others: the uncertainty's perturbations,
    unpolarised)."""
    side_from, iw, ii, ip, var = task
    req = ctx["request"]
    wl = req.wavelengths_nm[iw]
    n_a, n_b = ctx["material"].n_pair(float(wl), side_from)
    wi = direction(req.theta_i_deg[ii], req.phi_i_deg[ip])[None, :]
    lob = ctx["variants"][var]
    rough = Roughness(lob.alpha, lob.distribution, lob.weight, ctx["shadowing"])
    out = {}
    k, k_fine = ctx["subsamples"]
    refine = (k_fine, 1e-5) if k_fine > k else None
    for s, side in enumerate(("R", "T")):
        if ctx["polarized"] and var == 0:
            M = cell_average(lambda wo, ph: walter_mueller(wi, wo, np.real(n_a), n_b, rough,
                                                           np.radians(req.phi_i_deg[ip]), ph),
                             req.theta_s_edges_deg, req.phi_s_edges_deg, side, k, refine, with_phi=True)
            out[side + "_mueller"] = M
            out[side] = M[..., 0, 0].copy()
        else:
            out[side] = cell_average(lambda wo: walter_bsdf(wi, wo, np.real(n_a), n_b, rough),
                                     req.theta_s_edges_deg, req.phi_s_edges_deg, side, k, refine,
                                     mirror=float(req.phi_i_deg[ip]) % 180.0 == 0.0)
    return out


def _evaluate(ctx: dict, tasks: list, shape: tuple, progress=None) -> list:
    """Per lobe variant of ctx["variants"]: {side of incidence: (values (W, I, P, 2, S, A), Mueller or
    None)}; every variant's tasks in one map_tasks call."""
    res = map_tasks(_task, tasks, ctx, progress=progress, label="microfacet", threads=default_workers())
    out = [{} for _ in ctx["variants"]]
    for (sf, iw, ii, ip, var), r in zip(tasks, res):
        if sf not in out[var]:
            pol = ctx["polarized"] and var == 0
            out[var][sf] = (np.zeros(shape), np.zeros(shape + (4, 4)) if pol else None)
        vals, mu = out[var][sf]
        vals[iw, ii, ip, 0], vals[iw, ii, ip, 1] = r["R"], r["T"]
        if mu is not None:
            mu[iw, ii, ip, 0], mu[iw, ii, ip, 1] = r["R_mueller"], r["T_mueller"]
    return out


def _lobe_params(lobes: Lobes) -> np.ndarray:
    return np.concatenate([np.log(lobes.alpha), lobes.weight[:-1]])


def _lobes_at(p: np.ndarray, like: Lobes) -> Lobes:
    L = like.alpha.size
    w = np.clip(np.append(p[L:], 1.0 - p[L:].sum()), 0.0, None)
    return Lobes(np.exp(p[:L]), w / w.sum(), like.distribution)


def lobe_covariance(relief, lobes: Lobes) -> tuple[np.ndarray | None, tuple]:
    """(Cov of the tile's lobe parameters over realisations, sub-tile grid) by sub-tile batch means
    (module doc); None when the tile holds fewer than two sub-tiles."""
    from relief_bsdf.methods.realisation import facet_groups, subtile_grid
    grid = subtile_grid(relief)[0]
    if grid[0] * grid[1] < 2:
        return None, grid
    sx, sy = relief_slopes(relief)
    g = facet_groups(relief, grid)
    P = np.array([_lobe_params(fit_lobes((sx[g == k], sy[g == k]), lobes.alpha.size, lobes.distribution))
                  for k in range(grid[0] * grid[1]) if np.count_nonzero(g == k) >= 16])
    if P.shape[0] < 2:
        return None, grid
    return np.atleast_2d(np.cov(P, rowvar=False, ddof=1)) / P.shape[0], grid


def _perturbed(cov: np.ndarray | None, lobes: Lobes) -> list:
    """Lobes at p0 + s and p0 - s for every principal axis s = sqrt(lambda) v of Cov (module doc)."""
    if cov is None:
        return []
    lam, vec = np.linalg.eigh(cov)
    p0 = _lobe_params(lobes)
    return [_lobes_at(p0 + sgn * np.sqrt(l_) * v, lobes) for l_, v in zip(lam, vec.T) if l_ > 0 for sgn in (1.0, -1.0)]


def _tile_sigma(evaluated: list) -> dict:
    """{side: sigma (W, I, P, 2, S, A)}: the central differences of the perturbed variants (pairs after
    the fitted lobes) added in quadrature (exact to first order, correlations included)."""
    var: dict = {}
    for up, down in zip(evaluated[1::2], evaluated[2::2]):
        for sf in up:
            var[sf] = var.get(sf, 0.0) + (0.5 * (up[sf][0] - down[sf][0])) ** 2
    return {sf: np.sqrt(v) for sf, v in var.items()}


def _uncertainty(side: str, vals, sigma, relief, opts: MicrofacetOptions, grid, edges) -> tuple[dict, list]:
    """metadata["uncertainty"] and the too-few-correlation-areas warnings (methods.realisation)."""
    if sigma is None:
        return {"sigma": "none: roughness given as an option (no tile)" if opts.alpha is not None else
                "none (option tile_uncertainty=False, or the tile holds one sub-tile)"}, []
    from relief_bsdf.methods.realisation import correlation_areas, uncertainty_meta
    unc, warn = uncertainty_meta("microfacet", side, vals, sigma, "sub-tile batch means of the fitted lobe "
                                 "parameters", correlation_areas(relief), edges, stacklevel=4)
    return {**unc, "subtiles": list(grid)}, warn


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """Analytic Walter / Cook-Torrance tables for every side in `request.incident_from`.

    Roughness: the options (MicrofacetOptions) may give `alpha` (one value or a list with `weights`),
    `distribution` ("beckmann" default, "ggx"), `shadowing` ("smith" default, "vcavity",
    "incident", "none"), `lobes` (number of mixture lobes fitted to the relief's slopes when no
    alpha is given; default 1, i.e. alpha = rms slope magnitude for Beckmann), `subsamples`
    (per cell axis; default from the lobe width), `polarized` (fill the Mueller matrices).
    Values are cell averages (see `cell_average`); the model has no delta part (specular = 0);
    `lost` = 1 - R - T is the energy the single-scattering model does not conserve (plus the
    quadrature error of the cell averages, small when cells resolve the lobe).
    For light from inside, the relief is seen mirrored: its slopes flip sign, which leaves an
    isotropic lobe unchanged.
    """
    request.validate()
    opts = MicrofacetOptions.from_request(request)
    check_indices(material, request)
    dist = opts.distribution
    if opts.alpha is not None:
        a, w = _lobes(opts.alpha, opts.weights)
        lobes = Lobes(a, w, dist, {"source": "request options"})
    else:
        if relief is None:
            raise RequestError("no relief and no alpha given: the microfacet roughness must come from one of them",
                               "options.alpha")
        relief.require_valid()
        lobes = fit_lobes(relief, opts.lobes, dist)
        lobes.info["source"] = "fitted to the relief's facet slopes"
    polarized = opts.polarized
    n_ratio = 1.0
    for wl in request.wavelengths_nm:
        a, b = (np.real(v) for v in material.n_pair(float(wl), "outside"))
        n_ratio = max(n_ratio, a / b, b / a)
    if opts.subsamples:
        sub = (opts.subsamples, opts.subsamples)
    else:
        sub = auto_subsamples(request.theta_s_edges_deg, request.phi_s_edges_deg, float(lobes.alpha.min()), n_ratio)
    ctx = {"request": request, "material": material, "shadowing": opts.shadowing,
           "polarized": polarized, "subsamples": sub}
    W, I, P = len(request.wavelengths_nm), len(request.theta_i_deg), len(request.phi_i_deg)
    tables = []
    sides = list(request.incident_from)
    cov, grid = lobe_covariance(relief, lobes) if opts.alpha is None and opts.tile_uncertainty else (None, None)
    ctx["variants"] = [lobes] + _perturbed(cov, lobes)
    tasks = [(sf, iw, ii, ip, v) for v in range(len(ctx["variants"])) for sf in sides for iw in range(W)
             for ii in range(I) for ip in range(P)]
    te, pe = np.asarray(request.theta_s_edges_deg), np.asarray(request.phi_s_edges_deg)
    shape = (W, I, P, 2, te.size - 1, pe.size - 1)
    evaluated = _evaluate(ctx, tasks, shape, progress)
    sigma = _tile_sigma(evaluated)
    psa = projected_solid_angle(te, pe)
    for sf in sides:
        vals, mu = evaluated[0][sf]
        unc, warn = _uncertainty(sf, vals, sigma.get(sf), relief, opts, grid, (te, pe))
        tot = np.einsum("wipksa,sa->wip", vals, psa)
        lost = 1.0 - tot
        desc = relief.describe() if relief is not None else {}
        desc["lobes"] = lobes.describe()
        tables.append(BsdfTable(request.wavelengths_nm,
                                request.theta_i_deg, request.phi_i_deg, te, pe, vals, incident_from=sf,
                                lost=lost, mueller_per_sr=mu, sigma_per_sr=sigma.get(sf),
                                specular_mueller_R=np.zeros((W, I, P, 4, 4)) if polarized else None,
                                specular_mueller_T=np.zeros((W, I, P, 4, 4)) if polarized else None,
                                method="microfacet", material=material.describe(), relief=desc,
                                metadata={"model": "Walter et al. 2007 rough dielectric (paper sec. 2.1)",
                                          "distribution": dist, "shadowing": ctx["shadowing"],
                                          "subsamples_per_cell_axis": list(sub),
                                          "lost_meaning": "1 - R - T: energy the single-scattering model does not "
                                                          "conserve (inter-reflections neglected) plus cell "
                                                          "quadrature error",
                                          "polarized": polarized, "uncertainty": unc, "warnings": warn}))
    return tables
