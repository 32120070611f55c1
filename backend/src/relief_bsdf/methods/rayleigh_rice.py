"""`rayleigh-rice`: first-order vector perturbation theory of a slightly rough interface.

Physics (Rice 1951; Elson & Bennett 1979; Stover, *Optical Scattering*, 3rd ed., eq. 5.17
and Table 5.1 for reflection; Germer's SCATMECH "Microroughness_BRDF_Model" for the
general interface).  The interface z = h(x, y) between medium 1 (index n1, the light's
side, z > 0) and medium 2 (n2) is replaced by a sheet of polarisation proportional to
(eps2 - eps1) h located on the flat mean plane.  By reciprocity the first-order
scattering amplitude from incident polarisation a to scattered polarisation b is

    A_ba = (eps2 - eps1) [ E_t^(a) . E_t^(b)  +  D_z^(a) D_z^(b) / (eps1 eps2) ]

where E^(a) is the zeroth-order (flat-interface, Fresnel) field at the interface produced
by the incident plane wave of unit amplitude and E^(b) the one produced by a unit wave
arriving from the scattering direction (time-reversed detection); the tangential E and
the normal D are continuous across the interface, so either side may be used.  The
Nicodemus BSDF is

    f_ba = (pi^2 / lambda0^4) X |A_ba|^2 S(f) / (cos t_i cos t_s),    X = n_b / n_1
    f    = (n_1 sin t_i (cos p_i, sin p_i) + n_b sin t_s (cos p_s, sin p_s)) / lambda0

with S the two-sided 2-D PSD of the heights (int S d^2f = sigma^2, m^4), theta_i in medium 1
and theta_s in the medium of exit b (n_b = n1 for R, n2 for T).  For reflection from vacuum
this is exactly Stover's f = (16 pi^2 / lambda^4) cos t_i cos t_s Q S with his Q_ss, Q_sp,
Q_ps, Q_pp; the medium factor X = n_b / n_1 makes f(a->b)/n_b^2 = f(b->a)/n_a^2 (the
radiance-BTDF reciprocity of formats.md: |A|^2, S and the cosines are symmetric) and was
checked against SCATMECH's Microroughness_BRDF_Model for light from outside and inside,
R and T, in and out of the plane, to 4 digits (tests/backend/test_rayleigh_rice.py).
Light from inside uses the mirrored frame (formats.md): n1 = n_inside, heights -h (the PSD
is unchanged).  Past the critical angle the transmitted zeroth-order field is evanescent
and the formulas continue analytically (complex cosines): the field at the interface is
then enhanced, which is why inside scattering at 60 deg is ~5x that at 30 deg.

Polarisation: the Jones matrix J[b, a] (b, a in s, p) gives the Mueller matrix per cell
(`mueller_per_sr`, Stokes in the s/p bases of BsdfTable's module doc, p = s x propagation
direction, S1 = I_s - I_p, the convention of optics.mueller_interface: towards the specular /
undeviated direction the normalised cell Mueller matrix tends to the flat interface's, so
diffuse and specular parts of one table agree).  Against SCATMECH's "psps" Mueller matrices:
identical for light from inside; for light from outside identical up to the sign of S2 and
S3 (conjugation by diag(1, 1, -1, -1): the handedness of its basis).  `values_per_sr` is M00
for unpolarised light, M00 + M01 / M00 - M01 for request.polarization "s" / "p".

Specular parts: the Fresnel reflectance / transmittance of the mean plane times the
Debye-Waller factors exp(-(4 pi sigma n1 cos t_i / lambda)^2) and
exp(-(2 pi sigma (n1 cos t_i - n2 cos t_t) / lambda)^2) (first-order energy bookkeeping,
Stover eq. 2.xx / Beckmann), so R + T close to 1 is a genuine check, not a definition.

Regime of validity: (4 pi sigma cos t_i / lambda)^2 << 1 (sigma << lambda/10) and slopes
small; any lateral scale.  No multiple scattering (second order) terms.  Every table carries
the check (`regime_check`) in metadata["validity"]: the Rayleigh parameter
g = (4 pi n1 sigma cos t_i / lambda0)^2 per wavelength and incidence (n1 the index of the
light's side, sigma the rms height of the levelled relief), the rms slope m, and booleans
for g < 0.1 (Stover, *Optical Scattering*, sec. 4: the neglected second order is ~ g; 0.1
keeps it near 5 %) and m < 0.15 -- the limits `methods/auto.py` applies.  When a table falls
outside them a RuntimeWarning (warnings module) names the worst wavelength and incidence.

PSD estimate (`estimate_psd`): periodogram |FFT(h w)|^2 dx dy / sum(w^2) after levelling
(plane; mean only for periodic reliefs), w = 1 for periodic reliefs and a 2-D Hann window
otherwise; invalid points are set to 0 and excluded from the normalisation.  Smoothing:
for an isotropic relief (detected from the eigenvalues of the PSD's slope tensor, ratio of
rms slopes < 1.25, or forced by the option psd_isotropic) the periodogram is averaged in
annuli of width max(df, w / lambda) (w: the request's filter width in direction cosines,
so the smoothing matches the cell size and is the same for every wavelength in
direction-cosine terms at the shortest wavelength); otherwise the 2-D periodogram is
Gaussian-smoothed with that width.  Between annuli S is linearly interpolated.

Uncertainty: sigma_per_sr is the tile's realisation uncertainty of the PSD estimate (`cell_sigma`:
chi^2_2 periodogram samples, the window's grain factor, annulus averages combined exactly into each
cell; methods.realisation), with a warning when the lobe's cells scatter by more than 10 %.

Options (methods.options.RayleighRiceOptions): psd_isotropic (bool), smoothing_dcos (float),
polarized (bool, default True: fill mueller_per_sr), backend.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.fresnel import cos_transmitted, fresnel_amplitudes, mueller_interface
from relief_bsdf.core.index import Material
from relief_bsdf.parallel import map_tasks
from relief_bsdf.methods.options import RayleighRiceOptions
from relief_bsdf.methods.realisation import (cell_extents_dcos, correlation_areas, uncertainty_meta,
                                             window_grain_factor)
from relief_bsdf.methods.wave_filter import cell_samples, check_sides, energy_defect, smoothing_width_dcos

# ------------------------------------------------------------------ PSD


@dataclass
class Psd:
    """Smoothed 2-D height PSD (m^4) of a relief; `at(fx, fy)` with f in 1/m."""

    sigma_m: float
    isotropic: bool
    df: float
    radial_f: np.ndarray | None = None         # isotropic: annulus centres (1/m)
    radial_s: np.ndarray | None = None         # isotropic: annulus means (m^4)
    grid: np.ndarray | None = None             # anisotropic: fftshifted smoothed periodogram
    f0: tuple = (0.0, 0.0)
    dfxy: tuple = (1.0, 1.0)
    description: str = ""
    radial_n: np.ndarray | None = None         # isotropic: periodogram samples per annulus
    grain_factor: float = 1.0                  # samples one periodogram grain spans (window; realisation)
    smoothing_df: float = 0.0                  # anisotropic: Gaussian smoothing sigma (1/m)

    def at(self, fx, fy) -> np.ndarray:
        fx = np.asarray(fx, float)
        fy = np.asarray(fy, float)
        if self.isotropic:
            fr = np.hypot(fx, fy)
            return np.interp(fr, self.radial_f, self.radial_s, left=self.radial_s[0], right=0.0)
        ci = (fx - self.f0[0]) / self.dfxy[0]
        cj = (fy - self.f0[1]) / self.dfxy[1]
        shape = np.broadcast(ci, cj).shape
        ci, cj = np.broadcast_arrays(ci, cj)
        v = ndimage.map_coordinates(self.grid, [cj.ravel(), ci.ravel()], order=1, mode="constant", cval=0.0)
        return v.reshape(shape)


def prepared_heights(relief) -> tuple[np.ndarray, np.ndarray]:
    """Levelled heights with invalid points set to 0, and the window (Hann, or 1 if periodic).

    The window is zero on invalid points so they take no part in any estimate.
    """
    relief.require_valid(0.5)
    r = relief.level(0) if relief.periodic else relief.level(1)
    h = r.heights_m
    ny, nx = h.shape
    if relief.periodic:
        w = np.ones((ny, nx))
    else:
        w = np.outer(np.hanning(ny + 2)[1:-1], np.hanning(nx + 2)[1:-1])
    valid = np.isfinite(h)
    w = np.where(valid, w, 0.0)
    h = np.where(valid, h, 0.0)
    # remove the window-weighted mean so the windowed field has no DC leakage
    h = h - np.sum(h * w) / np.sum(w)
    return h, w


def estimate_psd(relief, smoothing_df: float = 0.0, isotropic: bool | None = None) -> Psd:
    """Windowed periodogram of the relief, smoothed as described in the module doc."""
    h, w = prepared_heights(relief)
    ny, nx = h.shape
    dx, dy = relief.dx_m, relief.dy_m
    F = np.fft.fft2(h * w)
    P = np.abs(F) ** 2 * dx * dy / np.sum(w ** 2)
    fx = np.fft.fftfreq(nx, dx)
    fy = np.fft.fftfreq(ny, dy)
    FX, FY = np.meshgrid(fx, fy)
    sigma = float(np.sqrt(np.sum(w ** 2 * h ** 2) / np.sum(w ** 2)))
    dfx, dfy = 1.0 / (nx * dx), 1.0 / (ny * dy)
    if isotropic is None:
        m = np.array([[np.sum(P * FX * FX), np.sum(P * FX * FY)], [np.sum(P * FX * FY), np.sum(P * FY * FY)]])
        ev = np.linalg.eigvalsh(m)
        isotropic = bool(ev[0] > 0 and np.sqrt(ev[1] / ev[0]) < 1.25)
    width = max(dfx, dfy, smoothing_df)
    if isotropic:
        fr = np.hypot(FX, FY).ravel()
        p = P.ravel()
        keep = fr > 0
        nb = int(np.ceil(fr.max() / width)) + 1
        k = np.floor(fr[keep] / width).astype(int)
        cnt = np.bincount(k, minlength=nb)
        s = np.bincount(k, weights=p[keep], minlength=nb)
        fm = np.bincount(k, weights=fr[keep], minlength=nb)
        ok = cnt > 0
        rf = fm[ok] / cnt[ok]
        rs = s[ok] / cnt[ok]
        desc = (f"periodogram ({'periodic, no window' if relief.periodic else '2-D Hann window'}), "
                f"annulus average, width {width:.4g} 1/m")
        return Psd(sigma, True, width, radial_f=np.concatenate([[0.0], rf]),
                   radial_s=np.concatenate([[rs[0]], rs]), description=desc,
                   radial_n=np.concatenate([[cnt[ok][0]], cnt[ok]]).astype(float),
                   grain_factor=_grain_factor(w, relief.periodic))
    Ps = np.fft.fftshift(P)
    sig = (smoothing_df / dfy, smoothing_df / dfx)
    if max(sig) > 0.3:
        Ps = ndimage.gaussian_filter(Ps, sig, mode="wrap")
    fxs, fys = np.fft.fftshift(fx), np.fft.fftshift(fy)
    desc = (f"periodogram ({'periodic, no window' if relief.periodic else '2-D Hann window'}), "
            f"anisotropic, Gaussian smoothing sigma {smoothing_df:.4g} 1/m")
    return Psd(sigma, False, width, grid=Ps, f0=(fxs[0], fys[0]), dfxy=(dfx, dfy), description=desc,
               grain_factor=_grain_factor(w, relief.periodic), smoothing_df=smoothing_df if max(sig) > 0.3 else 0.0)


def _grain_factor(w: np.ndarray, periodic: bool) -> float:
    return window_grain_factor(None if periodic else w)


# ------------------------------------------------------------------ zeroth-order fields


def _interface_field(theta, phi, n_from, n_to, from_below: bool):
    """Zeroth-order field at the flat interface for unit s and p waves (lab frame of medium 1 = z>0).

    Returns (E_s, E_p), each a (..., 3) complex array whose x, y part is the tangential E and
    whose z entry is the normal D / (eps1 eps2)^(1/2) * ... (see `_amplitude`): here we return
    the tangential field and D_z separately packed as (Ex, Ey, Dz).
    The wave comes from direction (theta, phi) (pointing toward its source) in medium n_from;
    from_below=True means that medium is z < 0 (the frame is mirrored for the computation).
    """
    ci = np.cos(theta)
    si = np.sin(theta)
    cp, sp = np.cos(phi), np.sin(phi)
    rs, rp, ts, tp = fresnel_amplitudes(ci, n_from, n_to)
    ct = cos_transmitted(ci, n_from, n_to)
    eta = n_from / n_to
    # transmitted propagation direction (computational frame: source side z > 0)
    dt = np.stack(np.broadcast_arrays(-eta * si * cp + 0j, -eta * si * sp + 0j, -ct + 0j), axis=-1)
    s_hat = np.stack(np.broadcast_arrays(-sp + 0j, cp + 0j, 0j * cp), axis=-1)
    p_t = np.cross(s_hat, dt)
    eps_to = n_to ** 2
    Es = ts[..., None] * s_hat
    Ep = tp[..., None] * p_t
    sign = -1.0 if from_below else 1.0
    out = []
    for E in (Es, Ep):
        out.append(np.stack([E[..., 0], E[..., 1], sign * eps_to * E[..., 2]], axis=-1))
    return out


def rr_jones(theta_i, phi_i, theta_s, phi_s, side: str, n1, n2) -> np.ndarray:
    """Perturbation amplitudes A[..., b, a] (b, a in s, p) of module doc; dimensionless.

    Light in medium n1 (z > 0) from (theta_i, phi_i); scattered into (theta_s, phi_s) on
    `side` 'R' (medium 1) or 'T' (medium 2).  Sign convention of the outgoing p: s x w_s.
    """
    eps1, eps2 = n1 ** 2, n2 ** 2
    a_s, a_p = _interface_field(theta_i, phi_i, n1, n2, from_below=False)
    if side == "R":
        b_s, b_p = _interface_field(theta_s, phi_s, n1, n2, from_below=False)
    else:
        b_s, b_p = _interface_field(theta_s, phi_s, n2, n1, from_below=True)

    def amp(a, b):
        return (eps2 - eps1) * (a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2] / (eps1 * eps2))

    J = np.empty(np.broadcast(np.asarray(theta_i), np.asarray(theta_s), np.asarray(phi_s)).shape + (2, 2), complex)
    # outgoing p = s x w_s (w_s = propagation direction of the scattered wave).  The reverse
    # (detection) wave's p vector is -(s x w_s) for R; for T it was built in the mirrored frame,
    # where mirroring the cross product flips it to +(s x w_s).
    sp = -1.0 if side == "R" else 1.0
    J[..., 0, 0] = amp(a_s, b_s)
    J[..., 0, 1] = amp(a_p, b_s)
    J[..., 1, 0] = sp * amp(a_s, b_p)
    J[..., 1, 1] = sp * amp(a_p, b_p)
    return J


def jones_to_mueller(J: np.ndarray) -> np.ndarray:
    """Mueller matrices (..., 4, 4) of Jones matrices (..., 2, 2) in the s/p basis.

    Stokes convention of optics.mueller_interface: S1 = I_s - I_p, S2 = 2 Re(E_s E_p*),
    S3 = -2 Im(E_s E_p*).
    """
    T = np.array([[1, 0, 0, 1], [1, 0, 0, -1], [0, 1, 1, 0], [0, 1j, -1j, 0]])
    Ti = np.linalg.inv(T)
    K = np.einsum("...ac,...bd->...abcd", J, np.conj(J)).reshape(J.shape[:-2] + (4, 4))
    return np.real(T @ K @ Ti)


def medium_factor(side: str, n1, n2) -> float:
    """X = n_b / n_1 of the module doc (1 for reflection)."""
    nb = n1 if side == "R" else n2
    return float(np.real(nb) / np.real(n1))


@dataclass(frozen=True)
class RoughInterface:
    """The first-order problem of the module doc: the flat interface between n1 (the medium of
    incidence, z > 0) and n2, lit at the vacuum wavelength `wavelength_m`, perturbed by a relief
    whose height PSD is `psd`."""

    n1: complex
    n2: complex
    wavelength_m: float
    psd: Psd


def rr_mueller(theta_i, phi_i, theta_s, phi_s, side: str, surface: RoughInterface) -> np.ndarray:
    """Mueller BSDF (..., 4, 4) in 1/sr at the given directions (angles in radians) of `surface`."""
    n1, n2, wavelength_m, psd = surface.n1, surface.n2, surface.wavelength_m, surface.psd
    J = rr_jones(theta_i, phi_i, theta_s, phi_s, side, n1, n2)
    fx, fy = scatter_frequency(theta_i, phi_i, theta_s, phi_s, side, surface)
    S = psd.at(fx, fy)
    ci = np.cos(theta_i)
    cs = np.maximum(np.cos(theta_s), 1e-12)
    pref = np.pi ** 2 / wavelength_m ** 4 * medium_factor(side, n1, n2) * S / (ci * cs)
    return jones_to_mueller(J) * pref[..., None, None]


def scatter_frequency(theta_i, phi_i, theta_s, phi_s, side: str, surface: RoughInterface):
    """(fx, fy) in 1/m: the relief frequency that scatters (theta_i, phi_i) into (theta_s, phi_s) (module doc)."""
    n1, nb = surface.n1, (surface.n1 if side == "R" else surface.n2)
    lam = surface.wavelength_m
    fx = (np.real(n1) * np.sin(theta_i) * np.cos(phi_i) + np.real(nb) * np.sin(theta_s) * np.cos(phi_s)) / lam
    fy = (np.real(n1) * np.sin(theta_i) * np.sin(phi_i) + np.real(nb) * np.sin(theta_s) * np.sin(phi_s)) / lam
    return fx, fy


def cell_sigma(m00_sub: np.ndarray, theta_i, phi_i, cells, side: str, surface: RoughInterface,
               extents_dcos: tuple) -> np.ndarray:
    """(S, A) realisation 1-sigma of the cell averages of m00_sub (S, A, M): the PSD estimate's
    periodogram statistics (methods.realisation: chi^2_2 per sample, the grain factor of the window).

    Isotropic PSD: every annulus mean of n_j samples has relative variance grain / n_j, annuli are
    independent, and a cell value is a linear combination of them (each sub-point interpolates two
    neighbouring annuli), so its variance is sum_j c_j^2 var_j exactly.  Anisotropic: the Gaussian-
    smoothed periodogram averaged over the cell (realisation.relative_sigma_extents in frequency units)."""
    from relief_bsdf.methods.realisation import relative_sigma_extents
    psd = surface.psd
    fx, fy = scatter_frequency(theta_i, phi_i, cells.theta, cells.phi, side, surface)
    S = psd.at(fx, fy)
    pref = np.where(S > 0, m00_sub / np.where(S > 0, S, 1.0), 0.0)
    Sc, A, M = m00_sub.shape
    if not psd.isotropic:
        nb = float(np.real(surface.n1 if side == "R" else surface.n2))
        k = nb / surface.wavelength_m
        a = psd.dfxy[0] * psd.dfxy[1] * psd.grain_factor
        rel = relative_sigma_extents(a, max(psd.smoothing_df, np.sqrt(a / (4 * np.pi))),
                                     extents_dcos[0] * k, extents_dcos[1] * k)
        return rel * m00_sub.mean(axis=-1)
    rf, J = psd.radial_f, psd.radial_f.size
    fr = np.hypot(fx, fy).ravel()
    j1 = np.clip(np.searchsorted(rf, fr, side="right"), 1, J - 1)
    t = np.clip((fr - rf[j1 - 1]) / np.maximum(rf[j1] - rf[j1 - 1], 1e-300), 0.0, 1.0)
    inside = fr <= rf[-1]
    p = (pref.ravel() / M) * inside
    cell = np.repeat(np.arange(Sc * A), M)
    ann = lambda j: np.maximum(j, 1)        # noqa: E731  (node 0 repeats annulus 1 at f = 0)
    keys = np.concatenate([cell * J + ann(j1 - 1), cell * J + ann(j1)])
    c = np.bincount(keys, weights=np.concatenate([p * (1 - t), p * t]), minlength=Sc * A * J).reshape(Sc * A, J)
    var_j = psd.radial_s ** 2 * psd.grain_factor / np.maximum(psd.radial_n, 1.0)
    return np.sqrt((c * c) @ var_j).reshape(Sc, A)


def rr_bsdf(theta_i, phi_i, theta_s, phi_s, side: str, surface: RoughInterface) -> np.ndarray:
    """Unpolarised BSDF (1/sr)."""
    return rr_mueller(theta_i, phi_i, theta_s, phi_s, side, surface)[..., 0, 0]


# ------------------------------------------------------------------ regime of validity

RAYLEIGH_LIMIT = 0.1      # g = (4 pi n1 sigma cos t_i / lambda0)^2 below this (module doc)
SLOPE_LIMIT = 0.15        # rms slope magnitude below this


def rayleigh_parameter(sigma_m: float, n1, theta_i_deg, wavelength_nm) -> np.ndarray:
    """g = (4 pi n1 sigma cos t_i / lambda0)^2: the phase variance of the specular reflection
    (Debye-Waller exponent); broadcast over incidence and wavelength."""
    ci = np.cos(np.radians(np.asarray(theta_i_deg, float)))
    return (4 * np.pi * np.real(n1) * sigma_m * ci / (np.asarray(wavelength_nm, float) * 1e-9)) ** 2


def relief_sigma_slope(relief) -> tuple[float, float]:
    """rms height and rms slope magnitude of the levelled relief, valid points only (the
    figures of relief_bsdf.surface.stats, which methods/auto.py decides on); 0 where undefined."""
    from relief_bsdf.surface.stats import rms_height_and_slope
    return tuple(float(v) if np.isfinite(v) else 0.0 for v in rms_height_and_slope(relief))


def regime_check(sigma_m: float, rms_slope: float, n1_per_wavelength, wavelengths_nm, theta_i_deg) -> dict:
    """metadata["validity"] of a table (module doc): Rayleigh parameter [wavelength][incidence],
    rms slope, the limits and whether each holds."""
    wl = np.asarray(wavelengths_nm, float)
    n1 = np.real(np.asarray(n1_per_wavelength, complex))
    g = rayleigh_parameter(sigma_m, n1[:, None], np.asarray(theta_i_deg, float)[None, :], wl[:, None])
    ok_g = g < RAYLEIGH_LIMIT
    ok_m = bool(rms_slope < SLOPE_LIMIT)
    return {"criterion": f"first-order perturbation: Rayleigh parameter (4 pi n1 sigma cos theta_i / lambda)^2 "
                         f"< {RAYLEIGH_LIMIT:g} and rms slope < {SLOPE_LIMIT:g}",
            "rms_height_m": float(sigma_m), "rms_slope": float(rms_slope),
            "wavelength_nm": wl.tolist(), "theta_i_deg": [float(t) for t in theta_i_deg],
            "n_incident": n1.tolist(),
            "rayleigh_parameter": g.tolist(), "rayleigh_parameter_max": float(g.max()),
            "rayleigh_limit": RAYLEIGH_LIMIT, "slope_limit": SLOPE_LIMIT,
            "valid_per_incidence": (ok_g & ok_m).tolist(), "rayleigh_ok": bool(ok_g.all()), "slope_ok": ok_m,
            "valid": bool(ok_g.all() and ok_m)}


def _regime_warning(v: dict, incident_from: str) -> str | None:
    """One line naming the worst case when the table is outside the regime, else None."""
    if v["valid"]:
        return None
    g = np.asarray(v["rayleigh_parameter"])
    iw, it = np.unravel_index(int(np.argmax(g)), g.shape)
    parts = []
    if not v["rayleigh_ok"]:
        parts.append(f"Rayleigh parameter (4 pi n1 sigma cos theta_i / lambda)^2 = {g[iw, it]:.3g} at "
                     f"{v['wavelength_nm'][iw]:g} nm, theta_i = {v['theta_i_deg'][it]:g} deg "
                     f"(>= {RAYLEIGH_LIMIT:g} at {int(np.sum(g >= RAYLEIGH_LIMIT))} of {g.size} wavelength x "
                     f"incidence pairs; rms height {v['rms_height_m'] * 1e9:.3g} nm)")
    if not v["slope_ok"]:
        parts.append(f"rms slope {v['rms_slope']:.3g} (>= {SLOPE_LIMIT:g})")
    return (f"rayleigh-rice (light from {incident_from}) outside its regime of validity: " + "; ".join(parts)
            + ". The first-order result is unreliable there (use kirchhoff or ray, or --method auto); "
              "see metadata['validity'].")


# ------------------------------------------------------------------ method


def _task(ctx, task):
    psd, cells, frame_n = ctx["psd"], ctx["cells"], ctx["n"]
    iw, it, ip, side_from = task
    wl_nm = ctx["wavelengths"][iw]
    n1, n2 = frame_n[(iw, side_from)]
    ti = np.radians(ctx["theta_i"][it])
    pi_ = np.radians(ctx["phi_i"][ip])
    polarized = ctx["polarized"]
    out = {}
    for k, side in enumerate(("R", "T")):
        nb = n1 if side == "R" else n2
        if side == "T" and np.imag(nb) > 0:
            M = np.zeros(cells.alpha.shape[:2] + (4, 4))
        else:
            surface = RoughInterface(n1, n2, wl_nm * 1e-9, psd)
            Msub = rr_mueller(ti, pi_, cells.theta, cells.phi, side, surface)
            M = Msub.mean(axis=2)
            out["sigma_" + side] = cell_sigma(_intensity(Msub, ctx["polarization"]), ti, pi_, cells, side, surface,
                                              ctx["extents"])
        out[side] = M if polarized else _intensity(M, ctx["polarization"])
        out.setdefault("sigma_" + side, np.zeros(cells.alpha.shape[:2]))
    # specular parts with Debye-Waller factors
    lam = wl_nm * 1e-9
    ci = np.cos(ti)
    ct = cos_transmitted(ci, n1, n2)
    sig = psd.sigma_m
    dw_r = np.exp(-(4 * np.pi * sig * np.real(n1) * ci / lam) ** 2)
    tir = np.abs(np.real(ct)) < 1e-12
    dw_t = 0.0 if tir else float(np.exp(-(2 * np.pi * sig * np.real(n1 * ci - n2 * ct) / lam) ** 2))
    MR = mueller_interface(ci, n1, n2, "R") * dw_r
    MT = mueller_interface(ci, n1, n2, "T") * dw_t if np.imag(n2) == 0 else np.zeros((4, 4))
    return out, MR, MT


def _intensity(M: np.ndarray, polarization: str) -> np.ndarray:
    """BSDF for the request's incident polarisation: unpolarised M00, s: M00 + M01, p: M00 - M01."""
    if polarization == "s":
        return M[..., 0, 0] + M[..., 0, 1]
    if polarization == "p":
        return M[..., 0, 0] - M[..., 0, 1]
    return M[..., 0, 0]


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """Rayleigh-Rice tables, one per side of incidence in request.incident_from (module doc)."""
    request.validate()
    check_sides(material, request, "rayleigh-rice")
    opts = RayleighRiceOptions.from_request(request)
    wls = np.asarray(request.wavelengths_nm, float)
    # filter width: cell scale (no speckle here; the PSD is smoothed instead)
    w = smoothing_width_dcos(0.0, request.theta_s_edges_deg, opts.smoothing_dcos)
    cells = cell_samples(request.theta_s_edges_deg, request.phi_s_edges_deg, w, max_per_axis=6)
    psd = estimate_psd(relief, smoothing_df=w / (wls.min() * 1e-9), isotropic=opts.psd_isotropic)
    polarized = opts.polarized
    sigma_rel, slope_rel = relief_sigma_slope(relief)
    frame_n = {}
    for iw, wl in enumerate(wls):
        for fr in request.incident_from:
            frame_n[(iw, fr)] = material.n_pair(wl, fr)
    ctx = {"psd": psd, "cells": cells, "n": frame_n, "wavelengths": wls, "theta_i": request.theta_i_deg,
           "phi_i": request.phi_i_deg, "polarized": polarized, "polarization": request.polarization,
           "extents": cell_extents_dcos(request.theta_s_edges_deg, request.phi_s_edges_deg)}
    tables = []
    W, I, P = len(wls), len(request.theta_i_deg), len(request.phi_i_deg)
    S, A = cells.alpha.shape[:2]
    for fr in request.incident_from:
        validity = regime_check(sigma_rel, slope_rel, [frame_n[(iw, fr)][0] for iw in range(W)], wls,
                                request.theta_i_deg)
        msg = _regime_warning(validity, fr)
        if msg:
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
        tasks = [(iw, it, ip, fr) for iw in range(W) for it in range(I) for ip in range(P)]
        res = map_tasks(_task, tasks, ctx, progress=progress, label=f"rayleigh-rice {fr}",
                        backend=opts.backend)
        shape = (W, I, P, 2, S, A)
        mu = np.zeros(shape + (4, 4)) if polarized else None
        vals = np.zeros(shape)
        sig = np.zeros(shape)
        sR, sT = np.zeros((W, I, P)), np.zeros((W, I, P))
        mR, mT = np.zeros((W, I, P, 4, 4)), np.zeros((W, I, P, 4, 4))
        for (iw, it, ip, _), (out, MR, MT) in zip(tasks, res):
            for k, side in enumerate(("R", "T")):
                sig[iw, it, ip, k] = out["sigma_" + side]
                if polarized:
                    mu[iw, it, ip, k] = out[side]
                    vals[iw, it, ip, k] = _intensity(out[side], request.polarization)
                else:
                    vals[iw, it, ip, k] = out[side]
            mR[iw, it, ip], mT[iw, it, ip] = MR, MT
            sR[iw, it, ip], sT[iw, it, ip] = _intensity(MR, request.polarization), _intensity(MT, request.polarization)
        tab = BsdfTable(
            wavelength_nm=wls, theta_i_deg=request.theta_i_deg, phi_i_deg=request.phi_i_deg,
            theta_s_edges_deg=request.theta_s_edges_deg, phi_s_edges_deg=request.phi_s_edges_deg,
            values_per_sr=vals, sigma_per_sr=sig, incident_from=fr, specular_R=sR, specular_T=sT,
            mueller_per_sr=mu, specular_mueller_R=mR if polarized else None,
            specular_mueller_T=mT if polarized else None, method="rayleigh-rice",
            material=material.describe(), relief=relief.describe(),
            metadata={"psd_estimate": psd.description, "psd_isotropic": psd.isotropic,
                      "rms_height_m": psd.sigma_m, "smoothing_dcos": w,
                      "rayleigh_parameter_max": validity["rayleigh_parameter_max"],
                      "validity": validity})
        energy_defect(tab, material, "rayleigh-rice", "first-order perturbation")   # signed; absorbed for a metal
        unc, warn = uncertainty_meta("rayleigh-rice", fr, vals, sig, "periodogram statistics: chi^2_2 per sample, "
                                     "averaged over the PSD smoothing and the cell; methods.realisation",
                                     correlation_areas(relief),
                                     (request.theta_s_edges_deg, request.phi_s_edges_deg), stacklevel=3)
        tab.metadata["uncertainty"] = unc
        tab.metadata["warnings"] = warn
        tables.append(tab)
    return tables
