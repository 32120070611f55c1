"""Stokes vectors and their reference frames: the ONE definition of the frame rotation.

Convention (the same for every method, table and photon engine): a beam propagating along
the unit vector k carries the Stokes vector (S0, S1 = I_s - I_p, S2, S3) in an orthonormal
basis (s, p) transverse to k with p = s x k, so (p, s, k) is right-handed as in Born & Wolf,
*Principles of Optics*, sec. 1.4.2.  The default s-axis of a direction k is
s = z x k / |z x k| (perpendicular to the plane containing the normal z and k; for k along
z the azimuthal fallback (-sin phi, cos phi, 0)), the frame of the BSDF tables' Mueller
matrices (bsdf/table.py).

Rotation of the frame (Chandrasekhar, *Radiative Transfer* (1950), ch. I sec. 15;
Born & Wolf 1.4.2): re-expressing the beam in a basis (s', p') with
s' = cos(psi) s + sin(psi) p (a rotation by psi about k) transforms the field components
as E_s' = cos(psi) E_s + sin(psi) E_p, E_p' = -sin(psi) E_s + cos(psi) E_p, hence

    S0' = S0,   S1' = cos(2 psi) S1 + sin(2 psi) S2,   S2' = -sin(2 psi) S1 + cos(2 psi) S2,   S3' = S3.

cos(2 psi), sin(2 psi) are computed from c = s.s', d = p.s' as (c^2 - d^2) / r, 2 c d / r with
r = c^2 + d^2 (no trigonometry; robust when s' is not exactly transverse to k, r = 0 gives
the identity).  Rotating by psi then by -psi is the identity; by 90 degrees it swaps s and p,
so S1 -> -S1.  Exact (pure geometry), valid for any fully or partially polarised beam.

Fast kernels beside the references (design.md: tested equal, tests/backend/core/test_stokes.py):
the ray method's bounce loop keeps K Stokes columns per ray in a (4, K, n) float32 array and
updates them in place; `s_axis_rows`, `rotate_stokes_columns` and `apply_interface_mueller_columns`
are the same formulas as `s_axis`, `rotate_stokes` and `apply_interface_mueller`, written as
column multiply-adds on that layout (no 4 x 4 matrices, no einsum, no BLAS call).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from relief_bsdf.core.frames import cross_rows, dot_rows


def s_axis(k: np.ndarray, phi_fallback_rad: Any = 0.0) -> np.ndarray:
    """Default s-axis z x k / |z x k| of directions k (..., 3); (-sin phi, cos phi, 0) where k is along z."""
    k = np.asarray(k)
    s = np.stack([-k[..., 1], k[..., 0], np.zeros(k.shape[:-1], k.dtype)], axis=-1)
    n = np.hypot(s[..., 0], s[..., 1])[..., None]
    small = n < 1e-7
    phi = np.asarray(phi_fallback_rad, float)[..., None]
    fb = np.concatenate(np.broadcast_arrays(-np.sin(phi), np.cos(phi), np.zeros_like(phi)), axis=-1)
    return np.where(small, np.broadcast_to(fb, s.shape), s / np.where(small, 1.0, n)).astype(k.dtype, copy=False)


def _double_angle(k: np.ndarray, s_from: np.ndarray, s_to: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos 2 psi, sin 2 psi) of the rotation taking s_from to s_to about k (module doc)."""
    c = np.einsum("...k,...k->...", s_from, s_to)
    d = np.einsum("...k,...k->...", np.cross(s_from, k), s_to)     # p_from . s_to, p = s x k
    r = c * c + d * d
    r = np.where(r == 0, 1, r)
    return (c * c - d * d) / r, 2 * c * d / r


def stokes_rotation(k: np.ndarray, s_from: np.ndarray, s_to: np.ndarray) -> np.ndarray:
    """Mueller matrix (..., 4, 4) re-expressing Stokes vectors of a beam along k from basis s_from to s_to."""
    c2, s2 = _double_angle(np.asarray(k, float), np.asarray(s_from, float), np.asarray(s_to, float))
    L = np.zeros(np.shape(c2) + (4, 4))
    L[..., 0, 0] = 1.0
    L[..., 3, 3] = 1.0
    L[..., 1, 1] = c2
    L[..., 1, 2] = s2
    L[..., 2, 1] = -s2
    L[..., 2, 2] = c2
    return L


def rotation_by_angle(psi_deg: Any) -> np.ndarray:
    """Mueller matrix (..., 4, 4) of a frame rotation by psi (degrees) about the beam (module doc)."""
    p = 2 * np.radians(np.asarray(psi_deg, float))
    L = np.zeros(p.shape + (4, 4))
    L[..., 0, 0] = L[..., 3, 3] = 1.0
    L[..., 1, 1] = L[..., 2, 2] = np.cos(p)
    L[..., 1, 2] = np.sin(p)
    L[..., 2, 1] = -np.sin(p)
    return L


def rotate_stokes(S: np.ndarray, k: np.ndarray, s_from: np.ndarray, s_to: np.ndarray) -> np.ndarray:
    """Stokes vectors S (..., 4) of beams along k (..., 3) re-expressed from basis s_from to s_to.

    Same result as `stokes_rotation(k, s_from, s_to) @ S` without forming 4 x 4 matrices;
    keeps the dtype of S (float32 batches stay float32).
    """
    c2, s2 = _double_angle(k, s_from, s_to)
    c2 = c2.astype(S.dtype, copy=False)
    s2 = s2.astype(S.dtype, copy=False)
    out = S.copy()
    out[..., 1] = c2 * S[..., 1] + s2 * S[..., 2]
    out[..., 2] = -s2 * S[..., 1] + c2 * S[..., 2]
    return out


def apply_interface_mueller(S: np.ndarray, a: Any, b: Any, c: Any, d: Any) -> np.ndarray:
    """M S for Stokes vectors S (..., 4) and the interface Mueller matrix of `core.fresnel`.

    M = [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]] per beam (the form of
    `fresnel.mueller_interface` and `fresnel.interface_coefficients_f32`), S in the s/p
    basis of the plane of incidence.
    """
    out = np.empty(np.broadcast_shapes(np.shape(S), np.shape(a) + (4,)), dtype=np.result_type(S, a))
    out[..., 0] = a * S[..., 0] + b * S[..., 1]
    out[..., 1] = b * S[..., 0] + a * S[..., 1]
    out[..., 2] = c * S[..., 2] + d * S[..., 3]
    out[..., 3] = -d * S[..., 2] + c * S[..., 3]
    return out


# ----------------------------------------------------------------------------- fast kernels


def s_axis_rows(k: np.ndarray, phi_fallback_rad: float = 0.0) -> np.ndarray:
    """Fast kernel of `s_axis` for (n, 3) batches k: s = z x k / |z x k|; (-sin phi, cos phi, 0) along z.

    The same frame as `s_axis` (tested equal) with one scalar fallback azimuth, a few times
    faster on the ray loop's float32 batches; keeps the dtype of k.
    """
    s = np.empty(k.shape, dtype=k.dtype)
    s[:, 0] = -k[:, 1]
    s[:, 1] = k[:, 0]
    s[:, 2] = 0
    nrm = np.hypot(s[:, 0], s[:, 1])
    small = nrm < 1e-7
    if small.any():
        nrm[small] = 1
        s[small, 0] = -math.sin(phi_fallback_rad)
        s[small, 1] = math.cos(phi_fallback_rad)
    s[:, 0] /= nrm
    s[:, 1] /= nrm
    return s


def rotate_stokes_columns(A: np.ndarray, s_from: np.ndarray, k: np.ndarray, s_to: np.ndarray) -> None:
    """In place: Stokes columns A (4, K, n) of beams k (n, 3) from basis (s_from, s_from x k) to (s_to, s_to x k).

    Fast kernel of `rotate_stokes` (the same Chandrasekhar rotation of the module doc:
    c = s_from . s_to, d = p_from . s_to, cos 2psi = (c^2 - d^2) / r, sin 2psi = 2 c d / r,
    r = c^2 + d^2, r = 0 gives the identity) on the (4, K, n) layout; tested equal to it.
    """
    c = dot_rows(s_from, s_to)
    d = dot_rows(cross_rows(s_from, k), s_to)          # p_from . s_to, p_from = s_from x k
    rotate_stokes_columns_cd(A, c, d)


def double_angle_cd(c: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos 2 psi, sin 2 psi) from c ~ s_from . s_to, d ~ p_from . s_to (any common positive factor):
    (c^2 - d^2) / r, 2 c d / r, r = c^2 + d^2 (r = 0: the identity); keeps the dtype."""
    c2 = c * c
    d2 = d * d
    r = c2 + d2
    r[r == 0] = 1
    sin2 = c * d
    sin2 += sin2
    sin2 /= r
    c2 -= d2
    c2 /= r
    return c2, sin2


def rotate_stokes_columns_cd(A: np.ndarray, c: np.ndarray, d: np.ndarray) -> None:
    """In place: the rotation of `rotate_stokes_columns` given c ~ s_from . s_to and d ~ p_from . s_to
    up to a common positive factor per beam (only the ratio matters); c and d are overwritten."""
    c2, sin2 = double_angle_cd(c, d)
    a1 = A[1]
    a2 = A[2]
    new1 = c2 * a1
    new1 += sin2 * a2
    a2 *= c2
    a1 *= sin2
    a2 -= a1
    A[1] = new1


def apply_interface_mueller_columns(A: np.ndarray, a: Any, b: Any, c: Any, d: Any, inv_p: Any) -> None:
    """In place: A <- M A / p for Stokes columns A (4, K, n), M = [[a,b,0,0],[b,a,0,0],[0,0,c,d],[0,0,-d,c]].

    Fast kernel of `apply_interface_mueller` (per-beam coefficients a, b, c, d of shape (n,),
    e.g. from `fresnel.interface_coefficients_f32`) on the (4, K, n) layout, with the
    renormalisation 1 / p of a Russian-roulette choice folded in; tested equal to it.
    """
    a = a * inv_p
    b = b * inv_p
    c = c * inv_p
    d = d * inv_p
    r0, r1, r2, r3 = A[0], A[1], A[2], A[3]
    n0 = a * r0
    n0 += b * r1                   # a r0 + b r1
    r0 *= b
    r1 *= a
    r1 += r0                       # b r0 + a r1
    r0[...] = n0
    n2 = c * r2
    n2 += d * r3                   # c r2 + d r3
    r3 *= c
    r2 *= d
    r3 -= r2                       # c r3 - d r2
    r2[...] = n2
