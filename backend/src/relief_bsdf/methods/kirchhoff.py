"""`kirchhoff`: scalar Kirchhoff (tangent-plane) diffraction by the measured height map.

Paper sec. 2.4 ("smooth reliefs ... Tangent Plane Approximation ... propagated away from it
using the Kirchhoff integral") with partial coherence modelled by random phase screens.

Model.  Light of vacuum wavelength lambda arrives in medium n1 from direction w_i (pointing
toward the source, formats.md frame; for light from inside the frame is mirrored and the
heights change sign).  Each point of the relief z = h(x, y) reflects / transmits like its
tangent plane, and the far field in direction w_s (medium n_s: n1 for R, n2 for T) is the
Kirchhoff integral (Beckmann & Spizzichino 1963 ch. 3; Ogilvy, *Theory of wave scattering
from random rough surfaces*, 1991, eqs. 4.13-4.20)

    U(w_s) ~ F_loc * K(w_i, w_s) * int exp(-i (nu_xy . r + nu_z h(r))) dr,
    nu = k1 w_i + k_s w_s   (k = 2 pi n / lambda; nu_z = k1 cos t_i + k_s cos t_s for R,
                              k1 cos t_i - k_2 cos t_t for T).

Normalisation.  In direction cosines (alpha, beta) d alpha d beta = cos t d omega, so the
BSDF equals the scattered power fraction per unit d alpha d beta.  The phase-only
integral is a 2-D FFT (nu_xy = 2 pi f on the FFT grid) and by Parseval its power, divided
by N sum(w^2), is a fraction of the incident power; dividing that fraction by the sample's
area in direction cosines, (lambda / (n_s L_x)) (lambda / (n_s L_y)), gives the BSDF.
Two factors multiply it:
- Fresnel: the unpolarised (or s / p, request.polarization) power reflectance F of the
  *local tangent plane at the stationary-phase facet*, whose normal is h = nu / |nu|, at
  the local incidence cos = |w_i . h|; transmission gets 1 - F (0 past the local critical
  angle, and 0 where w_i, w_s are on the same side of that facet, which no refraction links).
- Obliquity: K = |w_i.h| |w_s.h| |nu|^2 / (nu_z^2 cos t_i cos t_s).  It is the factor by
  which the stationary-phase (geometric-optics) limit of the tangent-plane integral becomes
  Walter et al. 2007 eqs. 20-21 with G = 1 (no shadowing), for R and T alike; it is 1 at
  the specular and undeviated directions, and in the small-roughness limit it gives
  f = (16 pi^2 / lambda^4) |w_i.h|^4 / (cos t_i cos t_s) F S(f), Rayleigh-Rice's form with
  Q ~ F close to the specular direction.
No shadowing or multiple scattering (tangent-plane approximation: radius of curvature >> lambda,
moderate slopes, not too grazing).

Coherent specular part.  The mean field m = sum(w^2 u) / sum(w^2) of u = exp(-i nu_z h) at the
specular (undeviated) nu_z - weighted by the squared window, the same weights as the power, so
that |m|^2 + sum(w^2 |u - m|^2) / sum(w^2) = 1 exactly for a windowed map too - is removed from
the field (FFT(w (u - m)) = FFT(w u) - m FFT(w); for a periodic tile the DC term); |m|^2 F is
reported as `specular_R` / `specular_T` (a delta, not smeared into cells), computed from the
map's own heights (no Gaussian Debye-Waller factor).

The nu_z dependence.  nu_z changes with the scattering direction, so one FFT is exact only on
one ring of directions.  The field is interpolated in nu_z, exactly to a stated tolerance, by
methods.qz_expansion: n FFTs of w exp(-i nu_j h) at the Chebyshev nodes nu_j of the nu_z interval
the requested directions span (plus the filter margin), combined at every frequency with the
barycentric Lagrange weights of its own nu_z.  n is the fewest nodes whose error bound (rms field
error / rms diffuse field, from the map's height moments) is at most the option qz_tolerance
(default 1e-3; about 2e-3 on the diffuse power); it is chosen per incidence from the nu_z span
times the height range (few nodes where q_z sigma is small), and R and T share one node set
when their touching intervals need fewer FFTs together.  Past the critical angle the tolerance's
reference amplitude is taken 10x lower (the side sees only the field's weak far tail).  Checked
against direct integration at every diffraction order (tests/backend/methods/kirchhoff_oracle.py:
in-lobe cells within 3 %, totals within 1 %, Gaussian / exponential / light-guide-dot reliefs,
0-60 deg from both sides).  The bound reached is reported per side (info qz_error_bound_R/T).
FFTs are single precision (complex64) with scipy.fft, workers = the option fft_workers (default
2; 1 inside a pool worker, where the pool already fills the cores).

Partial coherence (request.coherence_length_m = Lc).  The incident field is multiplied by
exp(i psi), psi a Gaussian random phase screen of rms pi rad and Gaussian correlation length
pi Lc, so the illumination's mutual coherence is exp(-pi^2 (1 - exp(-r^2 / (pi Lc)^2))) ~
exp(-r^2 / Lc^2): coherent over ~Lc, angular spread ~ lambda / (pi Lc) (1/e half width in
direction cosines).  The ensemble average over `coherence_instances` screens (option,
default 8; reported with its convergence) of the diffuse field (u - m) exp(i psi) and of the
coherent part |m|^2 |FFT(exp(i psi) w)|^2 gives a specular *lobe* (Phong-like peak) in the
cells instead of a delta (specular_R/T = 0) and washes out interference structure.

Sampling limits (RequestError before work): the pitch must resolve the requested
directions, |k1 sin t_i + k_s sin t_s,max| <= pi / dx (and dy) unless
the option band_limited = True (then the relief is taken as band-limited and directions
beyond are left with no scattered power); the tile must resolve the cells,
lambda / (n_s L) <= the finest theta cell (rad); the field exp(-i nu_z h) must not alias
(|nu_z| |dh| <= pi between neighbouring pixels for 99% of them); Lc must lie between 2
pixels and a quarter of the tile.  Periodic reliefs are used as they are (the FFT is then
exact: diffraction orders of the periodic tile); measured ones are levelled and multiplied
by a 2-D Hann window (normalised by sum(w^2)), which suppresses the edge discontinuity.

Filtering into cells: `wave_filter` (one Gaussian width in direction cosines for the whole
request, from the coarsest speckle grain and the finest cell).  The power of every FFT sample,
times its own obliquity and facet Fresnel factor, is first summed in blocks (power conserving) to
a grid spacing of at most 0.7 of that width (the block sum adds < 4 % to the Gaussian's
variance); the filter is a normalised convolution inside the propagating disc (no power is
spread beyond the rim), and the cell averages are rescaled band of rings by band to the power
the grid holds there (`wave_filter.ring_factors`), so the hemispherical totals are the integral's.

Energy.  R + T of the tangent-plane model is not 1 in general (no shadowing or multiple
scattering; grazing incidence and light past the critical angle are the worst): the defect
1 - R - T is stored signed in `lost` and in metadata["energy_defect"], and a RuntimeWarning is
raised above 1 % for a lossless boundary (for a metal `lost` is the absorption).

Uncertainty.  sigma_per_sr is the finite tile's realisation uncertainty of every cell: the
speckle statistics of the far field (chi^2_2 per frequency sample, grain lambda / (n_s L) times the
window's grain factor), averaged by the filter and the cell, with the lobe's inhomogeneity over the
cell (methods.realisation; checked against the spread over independently seeded tiles in
tests/backend/methods/test_tile_sigma.py); metadata["uncertainty"] says so, and a warning (also in
metadata["warnings"]) when the lobe's cells scatter by more than 10 % between tiles.  The q_z
expansion's error is the separate bound qz_error_bound_R/T.

Polarisation (option polarized = True, CLI --polarized): the scalar Fresnel factor is
replaced by the Fresnel Mueller matrix of the stationary-phase facet, rotated from the
table's incident s/p basis into the facet's plane of incidence and out into the scattered
basis (bsdf.py frames; the vector tangent-plane approximation in its single-facet form, as
microfacet.walter_mueller), giving `mueller_per_sr` with M00 = the unpolarised values.

Options (methods.options.KirchhoffOptions, read from request.options): qz_tolerance (default
1e-3), max_qz_nodes (default 64), fft_workers, band_limited, coherence_instances, smoothing_dcos,
polarized, backend.

Code layout: `solve_incidence(Surface, Incidence, SolveSettings)` solves one incidence: per side
`_side_setup` (specular part, nu_z range, crops, every frequency's nu_z and obliquity-Fresnel
factor), `_plan_nodes` (the q_z nodes, shared or per side), `_side_power` (the node FFTs and the
interpolation), `_finish_side` (coherent lobe under partial coherence, `_cells`: filtering).
`order_powers` gives the unfiltered power of every diffraction order (what the oracle checks).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import RequestError
from relief_bsdf.core.fresnel import cos_transmitted, mueller_interface
from relief_bsdf.core.fresnel import fresnel_reflectance as _fresnel
from relief_bsdf.core.index import Material
from relief_bsdf.parallel import in_worker, map_tasks, task_rng
from relief_bsdf.methods import realisation
from relief_bsdf.methods.options import KirchhoffOptions
from relief_bsdf.methods.wave_filter import (DcosGrid, cell_samples, check_sides, energy_defect,
                                             ring_factors,
                                             smoothing_width_dcos)
from relief_bsdf.methods.rayleigh_rice import prepared_heights
from relief_bsdf.methods.qz_expansion import HeightMoments, LagrangeBasis, chebyshev_nodes, expansion_order

# ------------------------------------------------------------------ helpers


def _gaussian_screen(shape, pitch, corr_m, rms, rng) -> np.ndarray:
    """Periodic Gaussian random field, autocovariance rms^2 exp(-r^2 / corr^2): surface.synth's one generator.

    Its zero mean (a constant phase of the screen) does not change any intensity.
    """
    from relief_bsdf.surface.synth import RandomFieldSpec, gaussian_field
    ny, nx = shape
    spec = RandomFieldSpec(nx=int(nx), ny=int(ny), pitch_m=float(pitch[0]), pitch_y_m=float(pitch[1]),
                           rms_height_m=float(rms), corr_length_m=float(corr_m))
    return gaussian_field(spec, rng)


def _pool_factor(n: int, target: int) -> int:
    """Largest power of two <= target that divides n / 2 (n even), else 1."""
    if n % 2 or target < 2:
        return 1
    b = 1
    while b * 2 <= target and (n // 2) % (b * 2) == 0:
        b *= 2
    return b


def _pool(p: np.ndarray, by: int, bx: int) -> np.ndarray:
    if by == 1 and bx == 1:
        return p
    ny, nx = p.shape
    return p.reshape(ny // by, by, nx // bx, bx).sum(axis=(1, 3))


# ------------------------------------------------------------------ checks


def check_sampling(relief, material: Material, request, width_dcos: float, band_limited: bool = False) -> None:
    """Raise RequestError when the relief cannot resolve what the request asks (module doc).

    band_limited (option): directions beyond the pitch's band are allowed (they get no power).
    """
    ny, nx = relief.shape
    dx, dy = relief.dx_m, relief.dy_m
    Lx, Ly = nx * dx, ny * dy
    te = np.radians(np.asarray(request.theta_s_edges_deg, float))
    finest = float(np.min(np.diff(te)))
    s_max = np.sin(te[-1])
    t_max = np.radians(max(request.theta_i_deg))
    band = bool(band_limited)
    for wl in request.wavelengths_nm:
        lam = wl * 1e-9
        for fr in request.incident_from:
            c1, c2 = material.n_pair(wl, fr)
            n1, n2 = np.real(c1), np.real(c2)
            for side, ns in (("R", n1), ("T", n2)):
                if side == "T" and np.imag(c2) > 0:
                    continue                      # absorbed: nothing to resolve
                need = n1 * np.sin(t_max) + ns * s_max           # |nu_x| / k0 at the worst direction
                have = lam / (2 * max(dx, dy))
                if need > have and not band:
                    smax = (have - n1 * np.sin(t_max)) / ns
                    hint = (f"request theta_s up to {np.degrees(np.arcsin(smax)):.1f} deg" if 0 < smax < 1
                            else "use a finer-pitch relief")
                    raise RequestError(
                        f"kirchhoff: the pitch {max(dx, dy) * 1e6:.4g} um resolves |n1 sin t_i + n_s sin t_s| <= "
                        f"lambda / (2 dx) = {have:.3f} at {wl:g} nm, but {fr} incidence up to "
                        f"{np.degrees(t_max):.1f} deg with {side} scattering up to {np.degrees(np.arcsin(s_max)):.1f} deg "
                        f"needs {need:.3f}; {hint}, or set option band_limited=true to take the relief as "
                        f"band-limited (no scatter beyond)", "theta_s_edges_deg")
                res = lam / (ns * min(Lx, Ly))
                if res > finest:
                    raise RequestError(
                        f"kirchhoff: the tile ({min(Lx, Ly) * 1e6:.4g} um) resolves angles of lambda / (n L) = "
                        f"{np.degrees(res):.3g} deg at {wl:g} nm, coarser than the finest requested theta_s cell "
                        f"({np.degrees(finest):.3g} deg); use coarser cells or a larger relief", "theta_s_edges_deg")
    Lc = request.coherence_length_m
    if Lc is not None:
        if Lc > 0.25 * min(Lx, Ly):
            raise RequestError(f"coherence length {Lc * 1e6:.4g} um exceeds a quarter of the tile "
                               f"({min(Lx, Ly) * 1e6:.4g} um): the tile cannot show partial coherence; "
                               "omit --coherence-length-um (coherent) or use a larger relief",
                               "--coherence-length-um")
        if np.pi * Lc < 2 * max(dx, dy):
            raise RequestError(f"coherence length {Lc * 1e6:.4g} um is not resolved by the pitch "
                               f"{max(dx, dy) * 1e6:.4g} um", "--coherence-length-um")


def check_aliasing(h: np.ndarray, w: np.ndarray, nu_max: float, where: str = "relief") -> float:
    """Fraction of neighbour steps where the phase nu_max |dh| exceeds pi; RequestError above 1%."""
    m = w > 0
    dxs = np.abs(np.diff(h, axis=1))[m[:, 1:] & m[:, :-1]]
    dys = np.abs(np.diff(h, axis=0))[m[1:, :] & m[:-1, :]]
    steps = np.concatenate([dxs, dys])
    frac = float(np.mean(nu_max * steps > np.pi)) if steps.size else 0.0
    if frac > 0.01:
        raise RequestError(
            f"kirchhoff: the relief's slopes are too steep for its pitch at this wavelength: the phase "
            f"nu_z dh exceeds pi between {frac:.1%} of neighbouring pixels, so the diffracted field is aliased; "
            "use a longer wavelength check, a finer-pitch relief or method ray", where)
    return frac


# ------------------------------------------------------------------ the per-incidence solver


def _side_geometry(side, fd, n1, ns, shape_c, f0, df):
    """Coarse-grid direction cosines and nu for one side (fd: the incidence's _Field). Returns dict of arrays."""
    ci, ai, bi, k0 = fd.ci, fd.ai, fd.bi, fd.k0
    ncy, ncx = shape_c
    fxc = f0[0] + df[0] * np.arange(ncx)
    fyc = f0[1] + df[1] * np.arange(ncy)
    k1, ks = k0 * n1, k0 * ns
    a = (2 * np.pi * fxc[None, :] - k1 * ai) / ks
    b = (2 * np.pi * fyc[:, None] - k1 * bi) / ks
    r2 = a * a + b * b
    prop = r2 < 1.0
    cs = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    sgn = 1.0 if side == "R" else -1.0
    nuz = k1 * ci + sgn * ks * cs
    return {"alpha0": float(a[0, 0]), "beta0": float(b[0, 0]), "dalpha": 2 * np.pi * df[0] / ks,
            "dbeta": 2 * np.pi * df[1] / ks, "a": a, "b": b, "cs": cs, "prop": prop, "nuz": nuz,
            "k1": k1, "ks": ks, "sgn": sgn}


def _obliquity_fresnel(geo, wi, n1, n2, side, polarization):
    """K * F_loc on the grid of geo (module doc), 0 where not propagating or not realisable.

    Single precision (the factor is smooth; 1e-6 relative is far below the method's tolerance)."""
    prop = geo["prop"]
    f4 = np.float32
    a = np.broadcast_to(geo["a"], prop.shape)[prop].astype(f4)
    b = np.broadcast_to(geo["b"], prop.shape)[prop].astype(f4)
    cs = np.broadcast_to(geo["cs"], prop.shape)[prop].astype(f4)
    k1, ks, sgn = f4(geo["k1"]), f4(geo["ks"]), f4(geo["sgn"])
    w0, w1, w2 = f4(wi[0]), f4(wi[1]), f4(wi[2])
    nux = k1 * w0 + ks * a
    nuy = k1 * w1 + ks * b
    nuz = k1 * w2 + (ks * sgn) * cs
    nn2 = np.maximum(nux * nux + nuy * nuy + nuz * nuz, f4(1e-30))
    inn = 1.0 / np.sqrt(nn2)
    ih_signed = (w0 * nux + w1 * nuy + w2 * nuz) * inn
    oh_signed = (a * nux + b * nuy + sgn * cs * nuz) * inn
    ih, oh = np.abs(ih_signed), np.abs(oh_signed)
    K = ih * oh * nn2 / (np.maximum(nuz * nuz, f4(1e-12) * nn2) * w2 * np.maximum(cs, f4(1e-12)))
    r1 = np.real(n1) if np.imag(n1) == 0 else n1
    r2 = np.real(n2) if np.imag(n2) == 0 else n2
    F = _fresnel(ih, r1, r2, polarization)
    if side == "R":
        fac = K * F
    else:
        fac = np.where(ih_signed * oh_signed < 0, K * (1.0 - F), 0.0)
    out = np.zeros(prop.shape)
    out[prop] = fac
    return out


def _facet_mueller(geo, wi, n1, n2, side, phi_i_rad):
    """Rotated Fresnel Mueller matrix of the stationary-phase facet, normalised by its [0, 0].

    The facet normal is h = +-nu / |nu| (toward the incident side); its Fresnel Mueller matrix
    (optics.mueller_interface, s/p of the facet's plane of incidence (w_i, h)) is rotated from
    the table's incident basis (s = z x w_i) and into the scattered basis (s = z x w_s), with
    p = s x k (bsdf.py).  Shape (ny, nx, 4, 4); zeros where not propagating.
    """
    from relief_bsdf.core.stokes import stokes_rotation
    prop = geo["prop"]
    a = np.broadcast_to(geo["a"], prop.shape)[prop]
    b = np.broadcast_to(geo["b"], prop.shape)[prop]
    cs = geo["cs"][prop]
    k1, ks, sgn = geo["k1"], geo["ks"], geo["sgn"]
    wo = np.stack([a, b, sgn * cs], axis=-1)
    nu = k1 * np.asarray(wi)[None, :] + ks * wo
    h = nu / np.maximum(np.linalg.norm(nu, axis=-1, keepdims=True), 1e-300)
    h = h * np.where(h @ np.asarray(wi) < 0, -1.0, 1.0)[:, None]
    wi_b = np.broadcast_to(np.asarray(wi, float), wo.shape)

    def s_vec(w, phi):
        v = np.stack([-w[..., 1], w[..., 0], np.zeros(w.shape[:-1])], axis=-1)
        nv = np.linalg.norm(v, axis=-1, keepdims=True)
        fb = np.stack(np.broadcast_arrays(-np.sin(phi), np.cos(phi), 0.0 * phi), axis=-1)
        return np.where(nv > 1e-12, v / np.where(nv > 1e-12, nv, 1.0), fb)

    s_i = s_vec(wi_b, np.full(a.shape, phi_i_rad))
    s_o = s_vec(wo, np.arctan2(b, a))
    s_m = np.cross(h, wi_b)
    nm = np.linalg.norm(s_m, axis=-1, keepdims=True)
    s_m = np.where(nm > 1e-12, s_m / np.where(nm > 1e-12, nm, 1.0), s_i)
    cos_ih = np.clip(h @ np.asarray(wi), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        MF = np.nan_to_num(mueller_interface(cos_ih, n1, n2, side))
    M = stokes_rotation(wo, s_m, s_o) @ MF @ stokes_rotation(-wi_b, s_i, s_m)
    m00 = MF[:, 0, 0]
    Mn = np.where(m00[:, None, None] > 0, M / np.where(m00 > 0, m00, 1.0)[:, None, None], 0.0)
    out = np.zeros(prop.shape + (4, 4))
    out[prop] = Mn
    return out


@dataclass(frozen=True)
class Surface:
    """The prepared height map one incidence is solved on.

    heights_m: heights in the frame of the incident medium (already sign-flipped for light from
    inside); window: the weights w (1 for a periodic tile, a 2-D Hann window otherwise);
    pitch_m: (dx, dy).
    """

    heights_m: np.ndarray
    window: np.ndarray
    pitch_m: tuple
    periodic: bool


@dataclass(frozen=True)
class Incidence:
    """One incidence: vacuum wavelength, direction (formats.md frame) and the indices (n1 lit, n2 other)."""

    wavelength_nm: float
    theta_i_deg: float
    phi_i_deg: float
    n1: complex
    n2: complex


@dataclass(frozen=True)
class SolveSettings:
    """What one incidence is asked for and how it is computed (shared by all incidences of a request).

    cells: the cell samples (wave_filter.cell_samples); width_dcos: the filter width;
    coherence_length_m / instances / seed: partial coherence by random phase screens (key: the
    incidence's seed key); tau / max_nodes: the q_z node rule (qz_nodes); workers: FFT workers;
    theta_s_range_deg: the requested theta_s span; polarized: also the Mueller matrices.
    """

    cells: object
    width_dcos: float
    polarization: str = "unpolarized"
    coherence_length_m: float | None = None
    instances: int = 8
    seed: int = 0
    key: tuple = (0,)
    tau: float = 1e-3
    max_nodes: int = 64
    workers: int = 2
    sides: tuple = ("R", "T")
    theta_s_range_deg: tuple = (0.0, 90.0)
    polarized: bool = False
    theta_edges_deg: tuple = (0.0, 90.0)
    phi_edges_deg: tuple = (0.0, 360.0)


@dataclass(frozen=True)
class _Field:
    """Per-incidence quantities shared by both sides: wave numbers, window sums, float32 copies."""

    lam: float
    k0: float
    ci: float
    ai: float
    bi: float
    wi: np.ndarray
    phi_i_rad: float
    sw: float
    sw2: float
    sigma: float
    h32: np.ndarray
    w32: np.ndarray | None
    fxs: np.ndarray
    fys: np.ndarray
    w2: np.ndarray | None
    moments: HeightMoments

    @property
    def shape(self):
        return self.h32.shape


def _field(surface: Surface, inc: Incidence) -> _Field:
    """Heights from their mid-range h_c (a common phase only), the squared-window weights and the
    height moments of the q_z expansion."""
    h, w = surface.heights_m, surface.window
    ny, nx = h.shape
    dx, dy = surface.pitch_m
    lam = inc.wavelength_nm * 1e-9
    ti, pi_ = np.radians(inc.theta_i_deg), np.radians(inc.phi_i_deg)
    ci = np.cos(ti)
    ai, bi = np.sin(ti) * np.cos(pi_), np.sin(ti) * np.sin(pi_)
    w2 = None if surface.periodic else w * w
    sw2 = float(np.sum(w * w))
    mom = HeightMoments.of(h, w2)
    hc = h - mom.centre_m
    hbar = float(np.sum(w * w * hc) / sw2)
    return _Field(lam=lam, k0=2 * np.pi / lam, ci=ci, ai=ai, bi=bi, wi=np.array([ai, bi, ci]), phi_i_rad=pi_,
                  sw=float(np.sum(w)), sw2=sw2, sigma=float(np.sqrt(np.sum(w * w * (hc - hbar) ** 2) / sw2)),
                  h32=hc.astype(np.float32), w32=None if surface.periodic else w.astype(np.float32),
                  fxs=np.fft.fftshift(np.fft.fftfreq(nx, dx)), fys=np.fft.fftshift(np.fft.fftfreq(ny, dy)),
                  w2=None if w2 is None else w2.astype(np.float32), moments=mom)


def _phase_screens(shape, pitch_m, st: SolveSettings) -> list:
    """exp(i psi) of the partial-coherence screens (module doc), shared by both sides and all nodes."""
    screens = []
    if st.coherence_length_m is None:
        return screens
    for k in range(st.instances):
        rng = task_rng(st.seed, *st.key, 7919, k)
        psi = _gaussian_screen(shape, pitch_m, np.pi * st.coherence_length_m, np.pi, rng)
        e = np.empty(shape, np.complex64)
        np.cos(psi, out=e.real)
        np.sin(psi, out=e.imag)
        screens.append(e)
    return screens


def _specular(side, fd: _Field, inc: Incidence, ks, polarization):
    """(nu_z of the specular / undeviated direction or None past the critical angle, its Fresnel factor)."""
    k1 = fd.k0 * np.real(inc.n1)
    if side == "R":
        return 2 * k1 * fd.ci, float(_fresnel(fd.ci, inc.n1, inc.n2, polarization))
    ct = cos_transmitted(fd.ci, inc.n1, inc.n2)
    tir = abs(np.real(ct)) < 1e-12
    nu_spec = None if tir else float(k1 * fd.ci - ks * np.real(ct))
    return nu_spec, 0.0 if tir else 1.0 - float(_fresnel(fd.ci, inc.n1, inc.n2, polarization))


@dataclass(frozen=True)
class _Coarse:
    """The pooled, cropped nu_xy grid of one side: pooling (by, bx), spacing df (pooled), the crop
    tb of the pooled, fftshifted grid (origin f0t), and the matching full-resolution rows and
    columns (indices into the unshifted FFT, and their frequencies)."""

    by: int
    bx: int
    df: tuple
    dF: float
    tb: tuple
    f0t: tuple
    rows: np.ndarray
    cols: np.ndarray
    fx_full: np.ndarray
    fy_full: np.ndarray


def _crop(fb, f0, df, ncx, ncy):
    """Index slices of the coarse grid covering the frequency box fb ((fx0, fx1), (fy0, fy1)); None = all."""
    if fb is None:
        return slice(0, ncy), slice(0, ncx)
    i0 = int(np.clip(np.floor((fb[0][0] - f0[0]) / df[0]) - 1, 0, ncx))
    i1 = int(np.clip(np.ceil((fb[0][1] - f0[0]) / df[0]) + 2, 0, ncx))
    j0 = int(np.clip(np.floor((fb[1][0] - f0[1]) / df[1]) - 1, 0, ncy))
    j1 = int(np.clip(np.ceil((fb[1][1] - f0[1]) / df[1]) + 2, 0, ncy))
    return slice(j0, j1), slice(i0, i1)


def _coarse_grid(fd: _Field, pitch_m, k1, ks, ns, st: SolveSettings) -> _Coarse:
    """Pooling: coarse spacing in direction cosines <= 0.7 x the filter width (adds < 4 % to its
    variance); crop: the requested disc plus the filter margin (4 widths)."""
    ny, nx = fd.shape
    dx, dy = pitch_m
    te = np.radians(np.asarray(st.theta_s_range_deg, float))
    dal = fd.lam / (ns * nx * dx)
    dbe = fd.lam / (ns * ny * dy)
    bx = _pool_factor(nx, int(max(1, 0.7 * st.width_dcos / dal)))
    by = _pool_factor(ny, int(max(1, 0.7 * st.width_dcos / dbe)))
    f0 = (fd.fxs[: (nx // bx) * bx].reshape(-1, bx).mean(axis=1)[0],
          fd.fys[: (ny // by) * by].reshape(-1, by).mean(axis=1)[0])
    df = (bx / (nx * dx), by / (ny * dy))
    reach = min(np.sin(te[-1]) + 4 * st.width_dcos, 1.0 + 4 * st.width_dcos)
    fxb = ((k1 * fd.ai - ks * reach) / (2 * np.pi), (k1 * fd.ai + ks * reach) / (2 * np.pi))
    fyb = ((k1 * fd.bi - ks * reach) / (2 * np.pi), (k1 * fd.bi + ks * reach) / (2 * np.pi))
    tb = _crop((fxb, fyb), f0, df, nx // bx, ny // by)
    rs = np.arange(tb[0].start * by, tb[0].stop * by)          # rows of the fftshifted full grid
    cs = np.arange(tb[1].start * bx, tb[1].stop * bx)
    return _Coarse(by=by, bx=bx, df=df, dF=(2 * np.pi) ** 2 * df[0] * df[1], tb=tb,
                   f0t=(f0[0] + tb[1].start * df[0], f0[1] + tb[0].start * df[1]),
                   rows=np.fft.fftshift(np.arange(ny))[rs], cols=np.fft.fftshift(np.arange(nx))[cs],
                   fx_full=fd.fxs[cs], fy_full=fd.fys[rs])


def _coherent_lobe(fd: _Field, cg: _Coarse, screens, workers):
    """The illumination's angular spectrum |FFT(exp(i psi) w)|^2 on the target grid, per half of
    the screens: the specular delta spread into a Phong-like peak; and the number of FFTs."""
    ny, nx = fd.shape
    ntot = nx * ny
    acc = [None, None]
    for k, e in enumerate(screens):
        v = e if fd.w32 is None else e * fd.w32
        F = sfft.fft2(v, workers=workers)
        p = _pool(F.real * F.real + F.imag * F.imag, cg.by, cg.bx)
        acc[k % 2] = p if acc[k % 2] is None else acc[k % 2] + p
    lobes = [np.fft.fftshift(acc[k])[cg.tb].astype(float) / (len(screens[k::2]) * ntot * fd.sw2 * cg.dF)
             for k in range(2)]
    return lobes, len(screens)


def _cells(side, dens, geo, fd: _Field, inc: Incidence, st: SolveSettings, specular: tuple, out):
    """Filter the densities (obliquity and facet Fresnel already in) into the cells; fills out[side] and,
    when polarised, out[mueller_side] and out[spec_mueller_side]; returns the per-half values.
    specular: (coherent specular power, its Fresnel factor)."""
    n1, n2, ks = inc.n1, inc.n2, geo["ks"]
    spec, F_spec = specular
    disc = geo["disc"]
    cells, width = st.cells, st.width_dcos

    def smooth(d, conserving=True):           # power-conserving filter inside the disc (or plain)
        return DcosGrid(d, geo["alpha0"], geo["beta0"], geo["dalpha"], geo["dbeta"]).smoothed(
            width, disc if conserving else None)

    inhom = []

    def power_cells(d):                       # cell averages of the power, and their ring factors
        g = smooth(d)
        sub = g.extended(disc).at(cells.alpha, cells.beta)
        v = sub.mean(axis=-1)
        # <D^2> / <D>^2 over the cell's sub-points: the realisation variance's inhomogeneity factor
        inhom.append(np.where(v > 0, (sub * sub).mean(axis=-1) / np.where(v > 0, v * v, 1.0), 1.0))
        f = ring_factors(v, g, st.theta_edges_deg, st.phi_edges_deg)[:, None]
        return v * f, f

    if st.polarized:
        # the stationary-phase facet's Mueller matrix at every cell sub-point (its own direction), averaged
        # over the cell with the filtered power as weight; M00 is the power itself (rotation-covariant:
        # the matrix of a direction does not depend on how the FFT grid meets the rim)
        a_s, b_s = cells.alpha, cells.beta
        geo_s = {"a": a_s, "b": b_s, "cs": np.sqrt(np.clip(1 - a_s * a_s - b_s * b_s, 0, 1)),
                 "prop": a_s * a_s + b_s * b_s < 1.0, "k1": geo["k1"], "ks": ks, "sgn": geo["sgn"]}
        Mn = _facet_mueller(geo_s, fd.wi, n1, n2, side, fd.phi_i_rad)          # (S, A, M, 4, 4)
        mus = []
        for d in dens:
            m00, _ = power_cells(ks * ks * d)
            w_sub = smooth(ks * ks * d).extended(disc).at(a_s, b_s)                # (S, A, M)
            wsum = w_sub.sum(axis=-1)
            avg = np.where(wsum[..., None, None] > 0,
                           np.einsum("sam,samrc->sarc", w_sub, Mn) / np.where(wsum > 0, wsum, 1.0)[..., None, None],
                           Mn.mean(axis=2))
            mus.append(avg * m00[..., None, None])
        out[f"mueller_{side}"] = sum(mus) / len(mus)
        sgn_pol = {"s": 1.0, "p": -1.0}.get(st.polarization, 0.0)
        vals = [m[..., 0, 0] + sgn_pol * m[..., 0, 1] for m in mus]
        ms = mueller_interface(fd.ci, n1, n2, side) if F_spec > 0 else np.zeros((4, 4))
        out[f"spec_mueller_{side}"] = np.nan_to_num(ms) * (spec / F_spec if F_spec > 0 else 0.0)
    else:
        vals = [power_cells(ks * ks * d)[0] for d in dens]
    out[side] = sum(vals) / len(vals)
    out[f"inhom_{side}"] = sum(inhom) / len(inhom)
    return vals


def _absorbed_side(out, cells) -> None:
    """Transmission into an absorbing medium: nothing propagates, nothing to compute."""
    out["T"] = np.zeros(cells.alpha.shape[:2])
    out["inhom_T"] = np.ones(cells.alpha.shape[:2])
    out["spec_T"] = 0.0
    out["mueller_T"] = np.zeros(cells.alpha.shape[:2] + (4, 4))
    out["spec_mueller_T"] = np.zeros((4, 4))


def _nu_range(side, fd: _Field, k1, ks, st: SolveSettings):
    """(nu_lo, nu_hi): the nu_z of the requested directions plus the filter margin."""
    te = np.radians(np.asarray(st.theta_s_range_deg, float))
    s_hi = min(np.sin(te[-1]) + 4 * st.width_dcos, 1.0)
    s_lo = max(np.sin(te[0]) - 4 * st.width_dcos, 0.0) if te[0] > 0 else 0.0
    sgn = 1.0 if side == "R" else -1.0
    ends = k1 * fd.ci + sgn * ks * np.sqrt(1.0 - np.array([s_lo, s_hi]) ** 2)
    return float(ends.min()), float(ends.max())


def _mean_field(fd: _Field, nu: float) -> complex:
    """m(nu) = <exp(-i nu h)> with the squared-window weights (module doc, coherent part)."""
    ph = fd.h32 * np.float32(-nu)
    c, s = np.cos(ph), np.sin(ph)
    if fd.w2 is None:
        return complex(c.mean(dtype=np.float64), s.mean(dtype=np.float64))
    return complex(np.dot(c.ravel(), fd.w2.ravel()) / fd.sw2, np.dot(s.ravel(), fd.w2.ravel()) / fd.sw2)


def _node_field(fd: _Field, nu: float, bufs: dict) -> tuple[np.ndarray, complex | None]:
    """(w exp(-i nu (h - h_c)) as complex64, its mean field m with the squared-window weights);
    m is None for a periodic tile, where it is the FFT's DC term (removed there).  bufs: work arrays
    reused from node to node (a fresh 2048^2 array costs its page faults every time)."""
    ph = bufs.setdefault("phase", np.empty(fd.shape, np.float32))
    tmp = bufs.setdefault("trig", np.empty(fd.shape, np.float32))
    u = bufs.setdefault("field", np.empty(fd.shape, np.complex64))
    np.multiply(fd.h32, np.float32(-nu), out=ph)
    np.cos(ph, out=tmp)                       # contiguous ufuncs, then strided copies (faster than out=)
    u.real[...] = tmp
    np.sin(ph, out=tmp)
    u.imag[...] = tmp
    if fd.w32 is None:
        return u, None
    m = complex(np.dot(u.real.ravel(), fd.w2.ravel()) / fd.sw2, np.dot(u.imag.ravel(), fd.w2.ravel()) / fd.sw2)
    u *= fd.w32
    return u, m


@dataclass
class _Side:
    """One side (R or T) of one incidence before its FFTs: geometry, specular part, crops, the
    full-resolution nu_z and obliquity-Fresnel factor of every frequency."""

    side: str
    ns: float
    nu_spec: float | None
    F_spec: float
    m_spec: complex
    amp: float
    lo: float
    hi: float
    cg: _Coarse
    nu_full: np.ndarray
    fac_full: np.ndarray
    geo: dict


def _side_setup(side, surface: Surface, inc: Incidence, st: SolveSettings, fd: _Field) -> _Side:
    ns = np.real(inc.n1) if side == "R" else np.real(inc.n2)
    k1, ks = fd.k0 * np.real(inc.n1), fd.k0 * ns
    sgn = 1.0 if side == "R" else -1.0
    nu_spec, F_spec = _specular(side, fd, inc, ks, st.polarization)
    lo, hi = _nu_range(side, fd, k1, ks, st)
    m_spec = _mean_field(fd, nu_spec) if nu_spec is not None else 0.0
    m_ref = m_spec if nu_spec is not None else _mean_field(fd, lo if abs(lo) > abs(hi) else hi)
    cg = _coarse_grid(fd, surface.pitch_m, k1, ks, ns, st)
    a = (2 * np.pi * cg.fx_full[None, :] - k1 * fd.ai) / ks
    b = (2 * np.pi * cg.fy_full[:, None] - k1 * fd.bi) / ks
    cs = np.sqrt(np.clip(1.0 - a * a - b * b, 0.0, 1.0))
    prop = a * a + b * b < 1.0
    geo_full = {"a": a, "b": b, "cs": cs, "prop": prop, "k1": k1, "ks": ks, "sgn": sgn}
    fac_full = _obliquity_fresnel(geo_full, fd.wi, inc.n1, inc.n2, side,
                                  "unpolarized" if st.polarized else st.polarization).astype(np.float32)
    shape_t = (cg.tb[0].stop - cg.tb[0].start, cg.tb[1].stop - cg.tb[1].start)
    geo = _side_geometry(side, fd, np.real(inc.n1), ns, shape_t, cg.f0t, cg.df)
    geo["disc"] = _pool(prop.astype(float), cg.by, cg.bx) > 0
    # the reference diffuse amplitude of the tolerance; without a specular direction (transmission
    # past the critical angle) the side only sees the weak far tail of the field: 10x lower
    amp = float(np.sqrt(max(1.0 - abs(m_ref) ** 2, 0.0))) * (1.0 if nu_spec is not None else 0.1)
    return _Side(side=side, ns=ns, nu_spec=nu_spec, F_spec=F_spec, m_spec=m_spec, amp=amp, lo=lo, hi=hi, cg=cg,
                 nu_full=np.clip(k1 * fd.ci + sgn * ks * cs, lo, hi), fac_full=fac_full, geo=geo)


def _plan_nodes(sides: list, fd: _Field, st: SolveSettings) -> list:
    """[(nodes, error bound, [sides served])]: one node set per side, or one for the union of their
    nu_z intervals when that needs fewer FFTs in all (the R and T intervals of an incidence touch at
    nu_z = k1 cos t_i, so the union is about their sum and saves the fixed part of the count)."""
    own = []
    for sd in sides:
        n, e = expansion_order(0.5 * (sd.hi - sd.lo), fd.moments, sd.amp, st.tau, st.max_nodes)
        own.append((chebyshev_nodes(sd.lo, sd.hi, n), e, [sd]))
    if len(sides) < 2:
        return own
    lo, hi = min(sd.lo for sd in sides), max(sd.hi for sd in sides)
    n, e = expansion_order(0.5 * (hi - lo), fd.moments, min(sd.amp for sd in sides), st.tau, st.max_nodes)
    if n < sum(o[0].size for o in own) and e <= max(o[1] for o in own):
        return [(chebyshev_nodes(lo, hi, n), e, list(sides))]
    return own


def _side_power(fd: _Field, sides: list, nodes, screens, workers):
    """Diffuse power density (per unit nu_xy area, times the obliquity-Fresnel factor of every
    full-resolution frequency) on each side's pooled target grid, the field interpolated in nu_z
    to every frequency's own nu_z (qz_expansion) from one FFT per node shared by the sides; per
    side one array per half of the screens (one when coherent); and the number of FFTs.  The mean
    field is removed in the transform: FFT(w (u - m)) = FFT(w u) - m FFT(w) (for a periodic tile
    FFT(w) is N at DC only)."""
    ny, nx = fd.shape
    ntot = nx * ny
    nscr = len(screens) or 1
    bases = [LagrangeBasis(nodes, sd.nu_full) for sd in sides]
    # each side's crop is a contiguous block of the fftshifted grid: one shift per FFT, then views
    ix = [(slice(sd.cg.tb[0].start * sd.cg.by, sd.cg.tb[0].stop * sd.cg.by),
           slice(sd.cg.tb[1].start * sd.cg.bx, sd.cg.tb[1].stop * sd.cg.bx)) for sd in sides]
    accs = [[np.zeros(sd.nu_full.shape, np.complex64) for _ in range(nscr)] for sd in sides]
    periodic_coherent = fd.w32 is None and not screens
    dcs = [np.nonzero((sd.cg.rows == 0)[:, None] & (sd.cg.cols == 0)[None, :]) for sd in sides]
    win = [None] * nscr
    n_fft = 0
    bufs = {}
    for j, nu in enumerate(nodes):
        v, m = _node_field(fd, nu, bufs)
        Ls = [lb.basis(j) for lb in bases]
        for k, e in enumerate(screens or [None]):
            if not periodic_coherent and win[k] is None:
                ww = fd.w32.astype(np.complex64) if e is None else (e if fd.w32 is None else e * fd.w32)
                win[k] = np.fft.fftshift(sfft.fft2(ww, workers=workers))
                n_fft += 1
            if m is None and e is not None:
                m = complex(v.mean(dtype=np.complex128))
            F = _shifted(sfft.fft2(v if e is None else v * e, workers=workers, overwrite_x=e is None), bufs)
            n_fft += 1
            for i, sd in enumerate(sides):
                if periodic_coherent:
                    Fc = np.multiply(F[ix[i]], Ls[i])
                    Fc[dcs[i]] = 0.0                 # the mean field is the DC term
                else:
                    Fc = F[ix[i]] - np.complex64(m) * win[k][ix[i]]
                    np.multiply(Fc, Ls[i], out=Fc)
                accs[i][k] += Fc
    halves = 2 if screens else 1
    out = []
    for i, sd in enumerate(sides):
        acc_p = [None] * halves
        for k, acc in enumerate(accs[i]):
            p = _pool((acc.real.astype(float) ** 2 + acc.imag.astype(float) ** 2) * sd.fac_full, sd.cg.by, sd.cg.bx)
            acc_p[k % halves] = p if acc_p[k % halves] is None else acc_p[k % halves] + p
        cnt = [len(screens[k::2]) if screens else 1 for k in range(halves)]
        out.append([acc_p[k] / (cnt[k] * ntot * fd.sw2 * sd.cg.dF) for k in range(halves)])
    return out, n_fft


def _shifted(F: np.ndarray, bufs: dict) -> np.ndarray:
    """np.fft.fftshift(F) written into a reused buffer (four block copies)."""
    out = bufs.get("shifted")
    if out is None or out.shape != F.shape:
        out = bufs["shifted"] = np.empty(F.shape, F.dtype)
    ny, nx = F.shape
    hy, hx = ny - ny // 2, nx - nx // 2          # fftshift moves index k to (k + n // 2) mod n
    out[ny // 2:, nx // 2:] = F[:hy, :hx]
    out[ny // 2:, :nx // 2] = F[:hy, hx:]
    out[:ny // 2, nx // 2:] = F[hy:, :hx]
    out[:ny // 2, :nx // 2] = F[hy:, hx:]
    return out


def _densities(sides: list, fd: _Field, st: SolveSettings, screens) -> tuple[dict, dict, int]:
    """{side: density list}, {side: (nodes, error bound)} and the FFT count, over the node plan."""
    dens, plan_of, n_fft = {}, {}, 0
    for nodes, bound, served in _plan_nodes(sides, fd, st):
        d, n = _side_power(fd, served, nodes, screens, st.workers)
        n_fft += n
        for sd, di in zip(served, d):
            dens[sd.side] = di
            plan_of[sd.side] = (nodes, bound)
    return dens, plan_of, n_fft


def order_powers(surface: Surface, inc: Incidence, st: SolveSettings, side: str) -> dict:
    """Unfiltered result of one side, one value per FFT frequency (per diffraction order of a
    periodic tile): direction cosines alpha, beta, the diffuse power fraction (obliquity and facet
    Fresnel included) and the coherent specular fraction.  Coherent illumination only."""
    st = dataclasses.replace(st, width_dcos=0.0, coherence_length_m=None)
    fd = _field(surface, inc)
    sd = _side_setup(side, surface, inc, st, fd)
    dens, plan_of, _ = _densities([sd], fd, st, [])
    shape = sd.geo["prop"].shape
    return {"alpha": np.broadcast_to(sd.geo["a"], shape), "beta": np.broadcast_to(sd.geo["b"], shape),
            "power": dens[side][0] * sd.cg.dF, "specular": abs(sd.m_spec) ** 2 * sd.F_spec,
            "qz_nodes": int(plan_of[side][0].size), "error_bound": plan_of[side][1]}


def _finish_side(sd: _Side, dens, nodes_bound, inc: Incidence, st: SolveSettings, fd: _Field, screens, out) -> int:
    """Coherent part, filtering into the cells and the side's info into `out`; returns extra FFTs."""
    side, geo, n_fft = sd.side, sd.geo, 0
    spec = abs(sd.m_spec) ** 2 * sd.F_spec
    if screens and sd.nu_spec is not None:
        # coherent part spread by the illumination's angular spectrum (the Phong-like peak);
        # centred on nu_xy = 0 (the specular direction), times obliquity and facet Fresnel
        lobes, n_fft = _coherent_lobe(fd, sd.cg, screens, st.workers)
        kf = _obliquity_fresnel(geo, fd.wi, inc.n1, inc.n2, side, "unpolarized" if st.polarized else st.polarization)
        dens = [dens[k] + abs(sd.m_spec) ** 2 * lobes[k] * kf for k in range(2)]
        out["info"][f"coherent_specular_{side}"] = spec
        spec = 0.0
    vals = _cells(side, dens, geo, fd, inc, st, (spec, sd.F_spec), out)
    if screens:
        big = out[side] > 0.01 * out[side].max()
        diff = (vals[0] - vals[1])[big]
        out["info"][f"coherence_rel_error_{side}"] = float(
            0.5 * np.sqrt(np.mean(diff ** 2)) / np.sqrt(np.mean(out[side][big] ** 2))) if big.any() else 0.0
    out[f"spec_{side}"] = spec
    out["info"][f"qz_nodes_{side}"] = int(nodes_bound[0].size)
    out["info"][f"qz_error_bound_{side}"] = float(nodes_bound[1])
    out["info"][f"pool_{side}"] = [sd.cg.by, sd.cg.bx]
    return n_fft


def solve_incidence(surface: Surface, inc: Incidence, st: SolveSettings) -> dict:
    """Kirchhoff tables for one incidence: {'R': (S, A), 'T': (S, A), 'spec_R', 'spec_T', 'info'}
    (plus 'mueller_R/T', 'spec_mueller_R/T' when polarised); the physics is in the module doc."""
    t0 = time.perf_counter()
    fd = _field(surface, inc)
    screens = _phase_screens(fd.shape, surface.pitch_m, st)
    out = {"info": {}}
    sides = []
    for side in st.sides:
        if side == "T" and np.imag(inc.n2) > 0:
            _absorbed_side(out, st.cells)
        else:
            sides.append(_side_setup(side, surface, inc, st, fd))
    dens, plan_of, n_fft = _densities(sides, fd, st, screens)
    for sd in sides:
        n_fft += _finish_side(sd, dens[sd.side], plan_of[sd.side], inc, st, fd, screens, out)
    out["info"]["ffts"] = n_fft
    out["info"]["seconds"] = time.perf_counter() - t0
    out["info"]["rms_height_m"] = fd.sigma
    return out


# ------------------------------------------------------------------ method entry point


def _task(ctx, task):
    iw, it, ip, fr = task
    wl = ctx["wavelengths"][iw]
    n1, n2 = ctx["n"][(iw, fr)]
    surface = ctx["surface"]
    if fr != "outside":
        surface = dataclasses.replace(surface, heights_m=-surface.heights_m)
    inc = Incidence(wl, ctx["theta_i"][it], ctx["phi_i"][ip], n1, n2)
    st = ctx["settings"]
    st = dataclasses.replace(st, key=(iw, it, ip, 0 if fr == "outside" else 1),
                             workers=1 if in_worker() else st.workers)
    return solve_incidence(surface, inc, st)


def speckle_dcos(relief, material: Material, request) -> float:
    """Coarsest speckle grain lambda / (n L) over the request (direction cosines)."""
    ny, nx = relief.shape
    L = min(nx * relief.dx_m, ny * relief.dy_m)
    worst = 0.0
    for wl in request.wavelengths_nm:
        for fr in request.incident_from:
            for n in material.n_pair(wl, fr):
                if np.imag(n) == 0:
                    worst = max(worst, wl * 1e-9 / (np.real(n) * L))
    return worst


def _prepare(relief, material: Material, request, opts: KirchhoffOptions) -> tuple[dict, dict]:
    """Checks (RequestError before work), the prepared surface and the solve settings: (ctx, metadata)."""
    width = smoothing_width_dcos(speckle_dcos(relief, material, request), request.theta_s_edges_deg,
                                 opts.smoothing_dcos)
    check_sampling(relief, material, request, width, opts.band_limited)
    wls = np.asarray(request.wavelengths_nm, float)
    band = None
    if opts.band_limit_heights:
        relief, band = _band_limit(relief, material, request, width)
    h, w = prepared_heights(relief)
    nmax = max(np.real(n) for wl in wls for fr in request.incident_from for n in material.n_pair(wl, fr))
    nu_max = 2 * nmax * 2 * np.pi / (wls.min() * 1e-9)
    alias = check_aliasing(h, w, nu_max, relief.source or "relief")
    cells = cell_samples(request.theta_s_edges_deg, request.phi_s_edges_deg, width)
    lc = request.coherence_length_m
    if lc is not None and opts.coherence_instances < 2:
        raise RequestError("coherence_instances must be >= 2 (the convergence estimate needs two halves)",
                           "options.coherence_instances")
    settings = SolveSettings(cells=cells, width_dcos=width, polarization=request.polarization, coherence_length_m=lc,
                             instances=opts.coherence_instances, seed=request.seed, tau=opts.qz_tolerance,
                             max_nodes=opts.max_qz_nodes, workers=opts.fft_workers,
                             theta_s_range_deg=(request.theta_s_edges_deg[0], request.theta_s_edges_deg[-1]),
                             polarized=opts.polarized, theta_edges_deg=tuple(request.theta_s_edges_deg),
                             phi_edges_deg=tuple(request.phi_s_edges_deg))
    ctx = {"surface": Surface(h, w, (relief.dx_m, relief.dy_m), relief.periodic), "wavelengths": wls,
           "theta_i": request.theta_i_deg, "phi_i": request.phi_i_deg, "settings": settings,
           "n": {(iw, fr): material.n_pair(wl, fr) for iw, wl in enumerate(wls) for fr in request.incident_from}}
    meta = {"smoothing_dcos": width, "window": "none (periodic)" if relief.periodic else "2-D Hann",
            "aliased_step_fraction": alias, "coherence_length_m": lc,
            "coherence_instances": opts.coherence_instances if lc is not None else 0,
            "height_band_limit": band}
    return ctx, meta


def _band_limit(relief, material: Material, request, width_dcos: float):
    """The relief low-passed to the spatial frequencies that can scatter into a requested direction
    (any wavelength, side and incidence of the request, plus the filter margin), and the statement
    of what was removed (None when the pitch's band is already inside).  Finer components
    (profilometer noise, tip artefacts) would only scatter into evanescent orders, yet in the
    tangent-plane phase exp(-i nu_z h) they would lower the coherent part and book their power as
    an energy defect; first-order theory (rayleigh-rice) shows they take no power from it."""
    from relief_bsdf.surface.stats import band_limited
    lam = min(request.wavelengths_nm) * 1e-9
    n_in = max(float(np.real(material.n_pair(wl, fr)[0])) for wl in request.wavelengths_nm
               for fr in request.incident_from)
    n_any = max(float(np.real(n)) for wl in request.wavelengths_nm for fr in request.incident_from
                for n in material.n_pair(wl, fr) if np.imag(n) == 0)
    s_max = min(np.sin(np.radians(request.theta_s_edges_deg[-1])) + 4 * width_dcos, 1.0 + 4 * width_dcos)
    f_max = (n_in * np.sin(np.radians(max(request.theta_i_deg))) + n_any * s_max) / lam
    if f_max >= 0.5 / max(relief.dx_m, relief.dy_m):
        return relief, None
    bl = band_limited(relief, f_max)
    return bl.relief, {"f_max_per_m": bl.f_max_per_m, "removed_rms_m": bl.removed_rms_m,
                       "removed_rms_slope": bl.removed_rms_slope, "statement": bl.statement()}


def _collect(ctx, request, tasks, res) -> dict:
    """Stack the per-incidence results of one side of incidence into table arrays."""
    wls, pol = ctx["wavelengths"], ctx["settings"].polarized
    W, I, P = len(wls), len(request.theta_i_deg), len(request.phi_i_deg)
    S, A = ctx["settings"].cells.alpha.shape[:2]
    a = {"values_per_sr": np.zeros((W, I, P, 2, S, A)), "specular_R": np.zeros((W, I, P)),
         "specular_T": np.zeros((W, I, P)), "mueller_per_sr": np.zeros((W, I, P, 2, S, A, 4, 4)) if pol else None,
         "specular_mueller_R": np.zeros((W, I, P, 4, 4)) if pol else None,
         "specular_mueller_T": np.zeros((W, I, P, 4, 4)) if pol else None}
    a["inhomogeneity"] = np.ones((W, I, P, 2, S, A))
    infos = []
    for (iw, it, ip, _), r in zip(tasks, res):
        a["values_per_sr"][iw, it, ip, 0] = r["R"]
        a["values_per_sr"][iw, it, ip, 1] = r["T"]
        a["inhomogeneity"][iw, it, ip, 0] = r["inhom_R"]
        a["inhomogeneity"][iw, it, ip, 1] = r["inhom_T"]
        if pol:
            a["mueller_per_sr"][iw, it, ip, 0], a["mueller_per_sr"][iw, it, ip, 1] = r["mueller_R"], r["mueller_T"]
            a["specular_mueller_R"][iw, it, ip] = r["spec_mueller_R"]
            a["specular_mueller_T"][iw, it, ip] = r["spec_mueller_T"]
        a["specular_R"][iw, it, ip], a["specular_T"][iw, it, ip] = r["spec_R"], r["spec_T"]
        infos.append({"wavelength_nm": float(wls[iw]), "theta_i_deg": float(request.theta_i_deg[it]),
                      "phi_i_deg": float(request.phi_i_deg[ip]), **r["info"]})
    a["infos"] = infos
    return a


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """Kirchhoff tables, one per side of incidence in request.incident_from (module doc)."""
    request.validate()
    check_sides(material, request, "kirchhoff")
    opts = KirchhoffOptions.from_request(request)
    ctx, meta = _prepare(relief, material, request, opts)
    W, I, P = len(ctx["wavelengths"]), len(request.theta_i_deg), len(request.phi_i_deg)
    tables = []
    for fr in request.incident_from:
        tasks = [(iw, it, ip, fr) for iw in range(W) for it in range(I) for ip in range(P)]
        res = map_tasks(_task, tasks, ctx, progress=progress, label=f"kirchhoff {fr}", backend=opts.backend)
        a = _collect(ctx, request, tasks, res)
        infos = a.pop("infos")
        inhom = a.pop("inhomogeneity")
        tab = BsdfTable(
            wavelength_nm=ctx["wavelengths"], theta_i_deg=request.theta_i_deg, phi_i_deg=request.phi_i_deg,
            theta_s_edges_deg=request.theta_s_edges_deg, phi_s_edges_deg=request.phi_s_edges_deg,
            incident_from=fr, method="kirchhoff", material=material.describe(), relief=relief.describe(),
            metadata={**meta, "incidences": infos,
                      "validity": "tangent-plane approximation: radius of curvature >> lambda, no shadowing, "
                                  "single scattering"}, **a)
        energy_defect(tab, material, "kirchhoff", "tangent-plane")
        tab.sigma_per_sr = _tile_sigma(tab, ctx, material, inhom)
        unc, warn = realisation.uncertainty_meta("kirchhoff", fr, tab.values_per_sr, tab.sigma_per_sr,
                                                 "speckle statistics: chi^2_2 per frequency sample, averaged over "
                                                 "the filter and the cell; methods.realisation",
                                                 realisation.correlation_areas(relief),
                                                 (request.theta_s_edges_deg, request.phi_s_edges_deg), stacklevel=3)
        tab.metadata["uncertainty"] = unc
        tab.metadata["warnings"] = tab.metadata.get("warnings", []) + warn
        tables.append(tab)
    return tables


def _tile_sigma(tab: BsdfTable, ctx: dict, material: Material, inhom: np.ndarray) -> np.ndarray:
    """sigma_per_sr: the finite tile's realisation uncertainty of every cell (methods.realisation).

    The speckle grain of side s (R: n1, T: n2) is (lambda / (n_s L_x)) (lambda / (n_s L_y)) in direction
    cosines, times the window's grain factor; the filter is the table's Gaussian of width w, widened
    under partial coherence by the illumination's angular spectrum (1/e half width lambda / (pi n_s Lc),
    standard deviation that / sqrt(2)), which averages the speckle further.  inhom: <D^2> / <D>^2 of the
    filtered density over each cell's sub-points (a lobe narrower than the cell holds fewer grains than
    the cell's area: variance a int D^2 / A^2, not a <D>^2 / A)."""
    st, surf = ctx["settings"], ctx["surface"]
    ny, nx = surf.heights_m.shape
    Lx, Ly = nx * surf.pitch_m[0], ny * surf.pitch_m[1]
    gf = realisation.window_grain_factor(None if surf.periodic else surf.window)
    sig = np.zeros_like(tab.values_per_sr)
    for iw, wl in enumerate(tab.wavelength_nm):
        lam = wl * 1e-9
        for k, ns in enumerate(material.n_pair(wl, tab.incident_from)):
            if np.imag(ns) > 0:
                continue
            ns = float(np.real(ns))
            a = (lam / (ns * Lx)) * (lam / (ns * Ly)) * gf
            width2 = st.width_dcos ** 2
            if st.coherence_length_m is not None:
                width2 += 0.5 * (lam / (np.pi * ns * st.coherence_length_m)) ** 2
            rel = realisation.relative_sigma(a, np.sqrt(width2), tab.theta_s_edges_deg, tab.phi_s_edges_deg)
            sig[iw, :, :, k] = rel * np.sqrt(inhom[iw, :, :, k]) * tab.values_per_sr[iw, :, :, k]
    return sig
