"""Optics of one flat interface: Snell's law, Fresnel coefficients, Mueller matrices.

Conventions (pbrt style, see ../shared/formats.md): directions are unit vectors pointing
*away* from the surface point; the interface normal points into the medium the light
arrives from.  Indices may be complex (n + i k, k >= 0) for absorbing media; metals then
reflect by the same Fresnel formulas.

Physics: Fresnel amplitude coefficients for s (TE) and p (TM) polarisation, Born & Wolf,
*Principles of Optics*, sec. 1.5.2 eqs. (20)-(21); the transmitted power factor
Re(n2 cos t) / (n1 cos i) (B&W 1.5.27); Snell's law; total internal reflection when
(n1/n2) sin(theta_i) > 1 for real indices.  Mueller matrices act on Stokes vectors
(S0, S1 = I_s - I_p, S2, S3) in the s/p basis of the plane of incidence (frame rotation:
`core.stokes`).  Valid for a locally flat interface (facet size >> wavelength).

Two implementations of the same physics live here:
- reference versions (float64 / complex, any broadcastable shapes): `fresnel_amplitudes`,
  `fresnel_power`, `fresnel_unpolarized`, `mueller_interface`;
- fast float32 kernels for the ray tracer's inner loop, real arithmetic only:
  `interface_coefficients_f32` (the four distinct Mueller entries of R and T, TIR included)
  and `reflectance_unpolarized_f32`.  tests/backend/core/test_fresnel.py checks that they
  equal the reference to float32 precision.
All functions are numpy-vectorised.
"""
from __future__ import annotations

from typing import Any

import numpy as np

F32 = np.float32

def cos_transmitted(cos_i: Any, n1: Any, n2: Any) -> np.ndarray:
    """Complex cosine of the refraction angle (Snell's law), branch with Im >= 0.

    Past the critical angle (real indices) the result is purely imaginary (evanescent).
    """
    cos_i = np.asarray(cos_i, dtype=float)
    eta = np.asarray(n1, dtype=complex) / np.asarray(n2, dtype=complex)
    ct = np.sqrt(1.0 - eta**2 * (1.0 - cos_i**2) + 0j)
    return np.where(np.imag(ct) < 0, -ct, ct)


def fresnel_amplitudes(cos_i: Any, n1: Any, n2: Any):
    """Fresnel amplitude coefficients (r_s, r_p, t_s, t_p) for light in medium n1 hitting n2.

    `cos_i` is the cosine of the incidence angle (>= 0).  Born & Wolf (1.5.20-21):
    r_s = (n1 c_i - n2 c_t)/(n1 c_i + n2 c_t),  r_p = (n2 c_i - n1 c_t)/(n2 c_i + n1 c_t),
    t_s = 2 n1 c_i/(n1 c_i + n2 c_t),           t_p = 2 n1 c_i/(n2 c_i + n1 c_t).
    """
    ci = np.abs(np.asarray(cos_i, dtype=float))
    n1 = np.asarray(n1, dtype=complex)
    n2 = np.asarray(n2, dtype=complex)
    ct = cos_transmitted(ci, n1, n2)
    a = n1 * ci
    b = n2 * ct
    c = n2 * ci
    d = n1 * ct
    rs = (a - b) / (a + b)
    rp = (c - d) / (c + d)
    ts = 2 * a / (a + b)
    tp = 2 * a / (c + d)
    return rs, rp, ts, tp


def fresnel_power(cos_i: Any, n1: Any, n2: Any):
    """Power reflectances and transmittances (R_s, R_p, T_s, T_p) of a flat interface.

    For a real n2 the transmittances are 1 - R (energy conservation); past the
    critical angle they are 0.  For an absorbing n2 (metal) the transmitted power
    is absorbed in the medium and T is reported as 1 - R (the power entering it).
    """
    rs, rp, _, _ = fresnel_amplitudes(cos_i, n1, n2)
    Rs = np.abs(rs) ** 2
    Rp = np.abs(rp) ** 2
    Rs = np.clip(Rs, 0.0, 1.0)
    Rp = np.clip(Rp, 0.0, 1.0)
    return Rs, Rp, 1.0 - Rs, 1.0 - Rp


def fresnel_unpolarized(cos_i: Any, n1: Any, n2: Any) -> np.ndarray:
    """Unpolarised power reflectance (R_s + R_p) / 2."""
    Rs, Rp, _, _ = fresnel_power(cos_i, n1, n2)
    return 0.5 * (Rs + Rp)


def fresnel_reflectance(cos_i: Any, n1: Any, n2: Any, polarization: str = "unpolarized") -> np.ndarray:
    """Power reflectance R_s ("s"), R_p ("p") or (R_s + R_p) / 2 ("unpolarized") of a flat interface.

    Same values as `fresnel_power`; real indices take a real float64 path (no complex
    arithmetic), with R = 1 past the critical angle and where the expression is 0/0 (grazing).
    """
    if np.imag(n1) == 0 and np.imag(n2) == 0:
        c = np.clip(np.asarray(cos_i, float), 0.0, 1.0)
        n1r, n2r = np.real(n1), np.real(n2)
        ct2 = 1.0 - (n1r / n2r) ** 2 * (1.0 - c * c)
        tir = ct2 <= 0
        ct = np.sqrt(np.where(tir, 0.0, ct2))
        a, b, cc, d = n1r * c, n2r * ct, n2r * c, n1r * ct
        with np.errstate(invalid="ignore", divide="ignore"):
            Rs = np.nan_to_num(np.where(tir, 1.0, ((a - b) / (a + b)) ** 2), nan=1.0)
            Rp = np.nan_to_num(np.where(tir, 1.0, ((cc - d) / (cc + d)) ** 2), nan=1.0)
    else:
        Rs, Rp, _, _ = fresnel_power(cos_i, n1, n2)
    if polarization == "s":
        return Rs
    if polarization == "p":
        return Rp
    return 0.5 * (Rs + Rp)


def critical_angle_deg(n1: float, n2: float) -> float:
    """Critical angle for light in n1 hitting n2 < n1; 90 when there is none."""
    if np.real(n2) >= np.real(n1):
        return 90.0
    return float(np.degrees(np.arcsin(np.real(n2) / np.real(n1))))


def reflect(w: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror direction of w (pointing away) about normal n: 2 (w.n) n - w.  Shapes (..., 3)."""
    d = np.sum(w * n, axis=-1, keepdims=True)
    return 2.0 * d * n - w


def refract(w: np.ndarray, n: np.ndarray, eta: Any):
    """Refract w (pointing away, on the side of n) through the interface.

    eta = n_incident / n_transmitted (real).  Returns (w_t, ok) where w_t points away on the
    other side and ok is False where total internal reflection occurs (w_t undefined there).
    pbrt-v4 sec. 9.3 convention.
    """
    eta = np.asarray(eta, dtype=float)
    cos_i = np.sum(w * n, axis=-1)
    sin2_t = eta**2 * np.maximum(0.0, 1.0 - cos_i**2)
    ok = sin2_t < 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin2_t))
    wt = -eta[..., None] * w + (eta * cos_i - cos_t)[..., None] * n if eta.ndim else \
        -eta * w + (eta * cos_i - cos_t)[..., None] * n
    return wt, ok


def mueller_interface(cos_i: Any, n1: Any, n2: Any, kind: str) -> np.ndarray:
    """Mueller matrix (..., 4, 4) of reflection ('R') or transmission ('T') at a flat interface.

    Stokes vectors in the s/p basis of the plane of incidence (S0, S1 = I_s - I_p, S2, S3).
    Reflection: amplitudes r_s, r_p; transmission: t_s, t_p with the power factor
    Re(n2 c_t)/(n1 c_i) so that M00 is the power transmittance (Born & Wolf 1.5.27).
    """
    rs, rp, ts, tp = fresnel_amplitudes(cos_i, n1, n2)
    if kind == "R":
        a, b = rs, rp
        scale = 1.0
    elif kind == "T":
        ci = np.abs(np.asarray(cos_i, dtype=float))
        ct = cos_transmitted(ci, n1, n2)
        a, b = ts, tp
        scale = np.real(np.asarray(n2, dtype=complex) * ct) / np.real(np.asarray(n1, dtype=complex) * ci)
    else:
        raise ValueError("kind must be 'R' or 'T'")
    A = np.abs(a) ** 2
    B = np.abs(b) ** 2
    C = a * np.conj(b)
    M = np.zeros(np.broadcast(A, B).shape + (4, 4))
    M[..., 0, 0] = 0.5 * (A + B)
    M[..., 0, 1] = 0.5 * (A - B)
    M[..., 1, 0] = 0.5 * (A - B)
    M[..., 1, 1] = 0.5 * (A + B)
    M[..., 2, 2] = np.real(C)
    M[..., 2, 3] = np.imag(C)
    M[..., 3, 2] = -np.imag(C)
    M[..., 3, 3] = np.real(C)
    return M * np.asarray(scale)[..., None, None]


# ---------------------------------------------------------------- fast float32 kernels


def interface_coefficients_f32(cos_i: np.ndarray, n1: Any, n2: Any):
    """Mueller coefficients (a, b, c, d) of reflection and transmission at a flat facet, float32.

    The Mueller matrix is [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]], the form
    of `mueller_interface` (Born & Wolf 1.5.20-21, 1.5.27); returns (R: (aR, bR, cR, dR),
    T: (aT, bT, cT, dT)).  Real indices: float32 real arithmetic, total internal reflection
    handled (|r_s| = |r_p| = 1, the phase difference in c, d; T = 0).  A complex index falls
    back to the complex reference `fresnel_amplitudes` (float64) and T is the power entering
    the absorbing medium (1 - R; its c, d are 0 since the light is absorbed there).
    """
    if np.iscomplexobj(n1) or np.iscomplexobj(n2):
        return _coefficients_complex(cos_i, n1, n2)
    ci = cos_i
    sin2_t = (n1 / n2) ** 2 * np.maximum(0, 1 - ci * ci)
    tir = sin2_t >= 1
    ct = np.sqrt(np.maximum(0, 1 - sin2_t))
    a, b, c, d = n1 * ci, n2 * ct, n2 * ci, n1 * ct
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (a - b) / (a + b)
        rp = (c - d) / (c + d)
        aR = 0.5 * (rs * rs + rp * rp)
        bR = 0.5 * (rs * rs - rp * rp)
        cR = rs * rp
        dR = np.zeros_like(aR)
        ts = 2 * a / (a + b)
        tp = 2 * a / (c + d)
        cT = (b / a) * ts * tp                      # power factor (n2 ct)/(n1 ci) times t_s t_p
    aT = 1 - aR
    bT = -bR
    if tir.any():
        _total_internal_reflection(ci, n1, n2, sin2_t, tir, (aR, bR, cR, dR), (aT, bT, cT))
    cT = np.where(tir | ~np.isfinite(cT), 0, cT).astype(F32)
    for arr in (aR, bR, cR):
        np.nan_to_num(arr, copy=False)
    return (aR, bR, cR, dR), (aT, bT, cT, np.zeros_like(aT))


def _coefficients_complex(cos_i: np.ndarray, n1: Any, n2: Any):
    """Complex-index branch of `interface_coefficients_f32` (reference amplitudes, cast to float32)."""
    rs, rp, _, _ = fresnel_amplitudes(np.asarray(cos_i, np.float64), n1, n2)
    A, B = np.abs(rs) ** 2, np.abs(rp) ** 2
    C = rs * np.conj(rp)
    R = (0.5 * (A + B), 0.5 * (A - B), np.real(C), np.imag(C))
    aT, bT = 1.0 - R[0], -R[1]                      # transmitted power, absorbed in a metal
    R = tuple(np.asarray(x, dtype=F32) for x in R)
    z = np.zeros_like(R[0])
    return R, (aT.astype(F32), bT.astype(F32), z, z)


def _total_internal_reflection(ci, n1, n2, sin2_t, tir, R, T) -> None:
    """Fill R (aR, bR, cR, dR) and T (aT, bT, cT) in place past the critical angle.

    r = (X - iY) / (X + iY) has unit modulus; with g = sqrt(sin^2 t - 1) the s and p
    amplitudes use X, Y = (n1 ci, n2 g) and (n2 ci, n1 g); c + i d = r_s conj(r_p).
    """
    aR, bR, cR, dR = R
    aT, bT, cT = T
    g = np.sqrt(np.maximum(0, sin2_t - 1))
    A1 = (n1 * ci)[tir] if np.ndim(n1) else n1 * ci[tir]
    B1 = (n2 * g)[tir] if np.ndim(n2) else n2 * g[tir]
    P1 = (n2 * ci)[tir] if np.ndim(n2) else n2 * ci[tir]
    Q1 = (n1 * g)[tir] if np.ndim(n1) else n1 * g[tir]
    den = (A1 * A1 + B1 * B1) * (P1 * P1 + Q1 * Q1)
    ab, pq = A1 * A1 - B1 * B1, P1 * P1 - Q1 * Q1
    aR[tir], bR[tir] = 1, 0
    cR[tir] = (ab * pq + 4 * A1 * B1 * P1 * Q1) / den
    dR[tir] = (2 * P1 * Q1 * ab - 2 * A1 * B1 * pq) / den
    aT[tir], bT[tir], cT[tir] = 0, 0, 0


def reflectance_unpolarized_f32(ci: np.ndarray, n1: Any, n2: Any, ct: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance (r_s^2 + r_p^2) / 2 in float32 for real indices, below TIR.

    `ct` is the (real) cosine of the refraction angle the caller already has; where the
    expression is undefined (grazing, 0/0) the reflectance is 1.  Equals `fresnel_unpolarized`.
    """
    a, b, c, d = n1 * ci, n2 * ct, n2 * ci, n1 * ct
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (a - b) / (a + b)
        rp = (c - d) / (c + d)
    out = F32(0.5) * (rs * rs + rp * rp)
    return np.nan_to_num(out, copy=False, nan=1.0)
