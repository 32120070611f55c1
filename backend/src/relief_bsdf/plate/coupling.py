"""Coupling of the scattering slab (`plate.slab`) to the faces, per azimuthal mode (adding equations, van de
Hulst 1980): the round trip with the slab's operators in place of the diagonal traversal, and the diffuse
sources the delta beams shed in the slab."""
from __future__ import annotations

from typing import Any

import numpy as np

from relief_bsdf.plate.memory import current_memory
from relief_bsdf.plate.slab import slab_operators


def _kron4(X: np.ndarray) -> np.ndarray:
    """(M, N, N) scalar operators -> (M, 4N, 4N) acting on Stokes vectors unchanged (scalar phase function)."""
    M, N, _ = X.shape
    return np.einsum("mij,ab->miajb", X, np.eye(4)).reshape(M, 4 * N, 4 * N)


def _slab_system(m: Any, theta_edges: np.ndarray, A: int, Kb: np.ndarray, R2: np.ndarray, c: int) -> dict:
    """Adding of the scattering slab to the faces, per azimuthal mode (adding equations, van de Hulst 1980).

    X (down-going at the top of the slab, leaving the first face) reaches the second face as
    B X, B = (I - Rv R2)^-1 Tv, and returns to the first face as Rc X, Rc = Rv + Tv R2 B
    (R2: the second face's reflection; Rv, Tv: the slab's).  Round trip: X = S + Kb Rc X.
    Without scattering Rv = 0, Tv = diag(exp(-a t / mu)) and this is the diagonal loop.
    """
    key = ("slab", tuple(np.round(theta_edges, 9)), int(A), m.thickness_m, m.absorption_per_m, m.scatter_per_m, m.hg_g)
    sl = current_memory().get(key, lambda: slab_operators(theta_edges, A, m.thickness_m, m.absorption_per_m,
                                                          m.scatter_per_m, m.hg_g), "slab")
    Rv, Tv, Td = (sl.R, sl.T, sl.T_diffuse) if c == 1 else (_kron4(sl.R), _kron4(sl.T), _kron4(sl.T_diffuse))
    eye = np.eye(Rv.shape[1])[None]
    B = np.linalg.solve(eye - Rv @ R2, Tv)
    Rc = Rv + Tv @ R2 @ B
    Q = np.linalg.inv(eye - R2 @ Rv)
    return dict(slab=sl, Rv=Rv, Tv=Tv, Td=Td, R2=R2, B=B, Q=Q, Rtrip=Rc, sys=eye - Kb @ Rc)


def _cell_of(theta_edges: np.ndarray, theta_deg: float) -> int:
    return int(np.clip(np.searchsorted(theta_edges, theta_deg, side="right") - 1, 0, theta_edges.size - 2))


def _beam_extinction(m: Any, slab: dict | None, theta_edges: np.ndarray, theta_deg: float) -> float:
    """Attenuation coefficient of a delta beam: a, plus the cell-visible scattering mu_s,j with a slab."""
    if slab is None:
        return m.absorption_per_m
    return float(slab["slab"].ext_per_m[_cell_of(theta_edges, theta_deg)])


def _slab_sources(slab: dict, Wh: np.ndarray, beams: np.ndarray, theta_edges: np.ndarray, thetas: np.ndarray,
                  n0: float, n: float, c: int) -> tuple[np.ndarray, np.ndarray]:
    """(U_x, D_x): extra diffuse light arriving at the first face (up) and at the second face (down).

    Sources: Wh (M, N c, q) leaving the second face upward (a back-face table's diffuse reflection
    of the beam); the delta beams shed into the slab what it scatters out of them: the down beam
    y (leaving the first face) gives Td y down at the second face and Rv y up at the first; the up
    beam b (leaving the second face) gives Td b up and Rv b down.  A beam at internal angle t is
    given its cell's columns, scaled so that it sheds exactly the power its exact attenuation
    removes.  Then W = Q (Wh + R2 s_down), U_x = u_up + Tv W, D_x = s_down + Rv W.
    """
    sl = slab["slab"]
    Rv, Td = slab["Rv"], slab["Td"]
    M, Nc, nI = Wh.shape
    s_down = np.zeros_like(Wh)
    u_up = np.zeros_like(Wh)
    for q, ti in enumerate(thetas):
        tt = float(np.degrees(np.arcsin(min(np.sin(np.radians(abs(ti))) * n0 / n, 1.0))))
        j = _cell_of(theta_edges, tt)
        mu_t = max(np.cos(np.radians(tt)), 1e-6)
        cols = slice(j * c, (j + 1) * c)
        y, b = beams[q, 0][:c], beams[q, 1][:c]
        scale = _shed_scale(sl, j, mu_t)
        s_down[:, :, q] = (Td[:, :, cols] @ y + Rv[:, :, cols] @ b) * scale
        u_up[:, :, q] = (Rv[:, :, cols] @ y + Td[:, :, cols] @ b) * scale
    W = slab["Q"] @ (Wh + slab["R2"] @ s_down)
    return u_up + slab["Tv"] @ W, s_down + Rv @ W


def _shed_scale(sl: Any, j: int, mu_beam: float) -> float:
    """Power a beam at mu_beam loses in the slab over what its cell's operators remove (1 at the centre)."""
    lost_cell = 1 - sl.direct[j]
    if lost_cell <= 0:
        return 0.0
    return float((1 - np.exp(-sl.ext_per_m[j] * sl.thickness_m / mu_beam)) / lost_cell)
