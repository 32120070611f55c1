"""Volume scattering in the plate's bulk: the slab's reflection and transmission operators by
adding-doubling, per azimuthal Fourier mode, on the deterministic engine's internal direction cells.

Physics (radiative transfer in a homogeneous plane-parallel slab; van de Hulst 1980, "Multiple
Light Scattering", ch. 5; Hansen & Travis 1974, Space Sci. Rev. 16, 527, sec. 3.4): extinction
beta = a + mu_s (absorption + scattering, per metre of path), Henyey-Greenstein phase function
p(cos Theta) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos Theta)^1.5) (core.bulk.hg_phase).

Discretisation.  State = power per internal direction cell (theta cells of the tables x A
azimuth cells, azimuth relative to the beam: circulant, so each azimuthal Fourier mode m is an
independent N x N problem; the kernel is even in azimuth, so the modes are real).
`P(i, a | j)`: probability that a photon of cell j (centre direction) scattering once lands in
cell (i, a): p(cos Theta) x solid angle, averaged over 3 x 3 points of the target cell,
normalised to 1 over both hemispheres (energy conserved exactly).  Scattering that leaves the
photon in its own cell cannot be seen on this grid: it is removed from the phase function and
from the scattering coefficient (mu_s,j = mu_s (1 - P(j, 0 | j)): the cell-resolved analogue of
the delta-M truncation, Wiscombe 1977), so a forward-peaked g -> 1 becomes exactly "no
scattering", delta beams included.

Thin layer dz (energy-conserving single-scattering start): direct E_j = exp(-beta_j dz / mu_j);
of the rest, the fraction mu_s,j / beta_j is scattered once into P(. | j) (forward cells: T,
backward: R), the remainder absorbed.  Doubling (identical layers, mirror-symmetric slab):

    R' = R + T R (I - R R)^-1 T,    T' = T (I - R R)^-1 T

repeated k times to the thickness, k such that beta dz / mu_min <= 1e-4.  With a = 0 every
step conserves energy exactly (R + T column sums = 1).

Approximation stated: scalar transfer, the phase function acts on S0 and the Stokes vector is
carried unchanged through a volume event (as the validation engine and plate.photon assume).
Regime: incoherent multiple scattering, laterally infinite slab, cell resolution of the tables.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relief_bsdf.core.bulk import hg_phase
from relief_bsdf.plate.memory import current_memory

_SUB = 3                 # quadrature points per target-cell axis
_EPS_LAYER = 1e-4        # beta dz / mu_min of the starting layer


@dataclass(frozen=True)
class SlabOperators:
    """Slab operators on N internal cells, per azimuthal mode m (M = A // 2 + 1), power per cell.

    R[m, i, j]: diffuse reflection (down-going cell j -> up-going cell i, or up -> down: the slab
    is mirror-symmetric); T[m, i, j]: transmission, direct part included; direct[j]: the
    direct transmission exp(-(a + mu_s,j) t / mu_j); ext_per_m[j]: a + mu_s,j (beam attenuation);
    mu[j]: the cells' centre cosines; thickness_m: t.
    """

    R: np.ndarray
    T: np.ndarray
    direct: np.ndarray
    ext_per_m: np.ndarray
    mu: np.ndarray
    thickness_m: float

    @property
    def T_diffuse(self) -> np.ndarray:
        return self.T - np.eye(self.direct.size)[None] * self.direct[None, None, :]


def phase_cells(theta_edges_deg: np.ndarray, azimuth_cells: int, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(P_forward, P_backward), each (N_i, N_j, A): single-scattering cell probabilities (sum 1 per j).

    They depend on the cells and g alone, not on the absorption, the scattering coefficient or the
    thickness, so the memory owner keeps them (read-only arrays, 2 x N x N x A doubles: 9 MB on the
    default grid): a diagnosis screens the same probes of volume scattering at every step while the
    absorption named at the first step moves, and the phase function's quadrature is most of
    `slab_operators`."""
    key = ("phase cells", np.asarray(theta_edges_deg, float).tobytes(), int(azimuth_cells), float(g))
    return current_memory().get(key, lambda: _read_only(_phase_cells(theta_edges_deg, azimuth_cells, g)), "phase")


def _read_only(arrays: tuple) -> tuple:
    for a in arrays:
        a.flags.writeable = False
    return arrays


def _phase_cells(theta_edges_deg: np.ndarray, azimuth_cells: int, g: float) -> tuple[np.ndarray, np.ndarray]:
    e = np.radians(np.asarray(theta_edges_deg, float))
    N, A = e.size - 1, int(azimuth_cells)
    tc = 0.5 * (e[1:] + e[:-1])
    u = (np.arange(_SUB) + 0.5) / _SUB
    cos_sub = np.cos(e[:-1])[:, None] + u[None] * (np.cos(e[1:]) - np.cos(e[:-1]))[:, None]   # (N, sub) equal-solid-angle
    sin_sub = np.sqrt(np.clip(1 - cos_sub**2, 0, 1))
    dphi = 2 * np.pi / A
    phi_sub = (np.arange(A)[:, None] + u[None] - 0.5) * dphi                                  # (A, sub)
    omega = (np.cos(e[:-1]) - np.cos(e[1:])) * dphi                                           # (N,) per azimuth cell
    cj, sj = np.cos(tc), np.sin(tc)
    out = []
    for sign in (1.0, -1.0):
        # cos Theta between source centre (theta_j, 0) and target sub-point (theta_i', phi')
        ct = (sin_sub[:, None, :, None, None] * sj[None, :, None, None, None] * np.cos(phi_sub)[None, None, None, :, :]
              + sign * cos_sub[:, None, :, None, None] * cj[None, :, None, None, None])        # (N, N, sub, A, sub)
        p = hg_phase(np.clip(ct, -1, 1), g).mean(axis=(2, 4))                                 # (N_i, N_j, A)
        out.append(p * omega[:, None, None])
    tot = out[0].sum(axis=(0, 2)) + out[1].sum(axis=(0, 2))                                  # (N_j,)
    return out[0] / tot[None, :, None], out[1] / tot[None, :, None]


def _thin_layer(Pf: np.ndarray, Pb: np.ndarray, mu: np.ndarray, a: float, s_eff: np.ndarray, dz: float):
    """(R, T) per mode of a layer dz: energy-conserving single scattering (module doc)."""
    beta = a + s_eff
    E = np.exp(-beta * dz / mu)
    f = np.where(beta > 0, (1 - E) * s_eff / np.where(beta > 0, beta, 1.0), 0.0)
    Rm = np.fft.rfft(Pb * f[None, :, None], axis=2).real                                       # (N, N, M)
    Tm = np.fft.rfft(Pf * f[None, :, None], axis=2).real
    R = np.ascontiguousarray(np.moveaxis(Rm, 2, 0))
    T = np.ascontiguousarray(np.moveaxis(Tm, 2, 0))
    T[:, np.arange(mu.size), np.arange(mu.size)] += E[None, :]
    return R, T


def _double(R: np.ndarray, T: np.ndarray, times: int) -> tuple[np.ndarray, np.ndarray]:
    eye = np.eye(R.shape[1])[None]
    for _ in range(times):
        DT = np.linalg.solve(eye - R @ R, T)
        R, T = R + (T @ R) @ DT, T @ DT
    return R, T


def slab_operators(theta_edges_deg: np.ndarray, azimuth_cells: int, thickness_m: float, absorption_per_m: float,
                   scatter_per_m: float, g: float) -> SlabOperators:
    """The slab's R and T per azimuthal mode on the cells (adding-doubling, module doc)."""
    e = np.radians(np.asarray(theta_edges_deg, float))
    mu = np.maximum(np.cos(0.5 * (e[1:] + e[:-1])), 1e-6)
    N = mu.size
    Pf, Pb = phase_cells(theta_edges_deg, azimuth_cells, g)
    idx = np.arange(N)
    self_frac = np.clip(Pf[idx, idx, 0], 0.0, 1.0)
    s_eff = scatter_per_m * (1 - self_frac)
    Pf = Pf.copy()
    Pf[idx, idx, 0] = 0.0
    keep = np.where(self_frac < 1, 1 - self_frac, 1.0)
    Pf, Pb = Pf / keep[None, :, None], Pb / keep[None, :, None]
    beta_max = float(np.max((absorption_per_m + s_eff) / mu))
    k = int(np.clip(np.ceil(np.log2(max(beta_max * thickness_m / _EPS_LAYER, 1.0))), 0, 40))
    R, T = _thin_layer(Pf, Pb, mu, absorption_per_m, s_eff, thickness_m / 2**k)
    R, T = _double(R, T, k)
    ext = absorption_per_m + s_eff
    return SlabOperators(R, T, np.exp(-ext * thickness_m / mu), ext, mu, float(thickness_m))
