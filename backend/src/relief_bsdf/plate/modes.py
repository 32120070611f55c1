"""Azimuthal Fourier modes of the plate's loop: the circulant kernels' blocks, the exits' circular convolutions,
the round-trip system's LU factors (LAPACK getrf / getrs)."""
from __future__ import annotations

import numpy as np


def _reflect_up(ops: dict, at: np.ndarray) -> np.ndarray:
    """(q, N, A, c) power per cell arriving back at the rough face from inside: `at` (power per cell at the
    flat face) times the flat face's cell-averaged Fresnel R (Mueller for c = 4) and one traversal."""
    absorb = ops["absorb"]
    if ops["c"] == 1:
        return (at[..., 0] * (ops["RF"][:, 0, 0] * absorb)[None, :, None])[..., None]
    return np.einsum("jab,qjkb->qjka", ops["RF"], at) * absorb[None, :, None, None]


def _exit_modes(U: np.ndarray) -> np.ndarray:
    """(q, N, A, c) cells -> (M, q, N c) azimuthal Fourier modes."""
    nI, N, _, c = U.shape
    Uh = np.fft.rfft(U, axis=2)
    return np.moveaxis(Uh, 2, 0).reshape(Uh.shape[2], nI, N * c)


def _rough_exit(Um: np.ndarray, GhT: np.ndarray, A: int) -> np.ndarray:
    """(q, O, A) BSDF leaving through the rough face of the light arriving from inside in modes Um (M, q, J c),
    by the exit kernel GhT (M, J c, O): a circular convolution over azimuth."""
    return np.fft.irfft(np.moveaxis(Um @ GhT, 0, 2), n=A, axis=2)


def _blocks(Xh: np.ndarray, c: int, out: np.ndarray | None = None) -> np.ndarray:
    """(T, J, M[, 4, 4]) kernel in Fourier space -> (M, T c, J c) matrices; written into `out` (a view of
    that shape, e.g. a slice of a bigger array) when given, without an intermediate copy."""
    view = np.moveaxis(Xh, 2, 0) if c == 1 else np.transpose(Xh, (2, 0, 3, 1, 4))      # (M, T[, 4], J[, 4])
    if out is None:
        return view if c == 1 else view.reshape(view.shape[0], view.shape[1] * 4, view.shape[3] * 4)
    target = out.view()
    target.shape = view.shape                # raises rather than copy: the numbers must land in `out`
    target[...] = view
    return out


def _block_diag(D: np.ndarray, c: int) -> np.ndarray:
    """(N, 4, 4) per-cell Mueller matrices -> (N c, N c) block-diagonal (c = 1: the M00 diagonal)."""
    N = D.shape[0]
    if c == 1:
        return np.diag(D[:, 0, 0])
    out = np.zeros((N, 4, N, 4))
    idx = np.arange(N)
    out[idx, :, idx, :] = D
    return out.reshape(N * 4, N * 4)


def _loop_solve(ops: dict, rhs: np.ndarray) -> np.ndarray:
    """X = (I - K D)^-1 rhs per azimuthal mode, (M, N c, nI).  The LU factors of the round-trip
    system are kept in `ops`: the operators are shared by every solve on the same tables and plate
    (`_reused_solver`: a source polarisation, stray light, cone, blur or tilt changes only the
    sources), so an evaluation that changes only those solves with the factors instead of
    factoring the (M, N c, N c) system again."""
    if "sys_lu" not in ops:
        ops["sys_lu"] = _lu_factors(ops.pop("sys"))          # the factors replace the system (memory)
    return _lu_apply(ops["sys_lu"], rhs)


def _lu_factors(mats: np.ndarray) -> list:
    """LU factors (LAPACK getrf) of each matrix of a stack (M, n, n)."""
    from scipy.linalg import lu_factor
    return [lu_factor(a, check_finite=False) for a in mats]


def _lu_apply(factors: list, rhs: np.ndarray) -> np.ndarray:
    """A_m^-1 rhs_m for each matrix m of the stack whose `_lu_factors` are given (getrs), (M, n, k)."""
    from scipy.linalg import lu_solve
    return np.stack([lu_solve(f, b, check_finite=False) for f, b in zip(factors, rhs)])
