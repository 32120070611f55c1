"""Photon interactions the faces share: a Fresnel event at a plane or a facet, and photons drawn from a face's
isotropic tables (`TableSampler`)."""
from __future__ import annotations

from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.core.fresnel import mueller_interface
from relief_bsdf.errors import InputError
from relief_bsdf.plate.faces.base import FaceEvent, PhotonContext
from relief_bsdf.plate.memory import current_memory


def fresnel_event(d: np.ndarray, S: np.ndarray, n_above: float, n_below: float, rng: np.random.Generator,
                  normal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fresnel reflect / refract at a plane of normal `normal` (default +z) with Stokes vectors.

    Reflection or transmission is drawn with probability (M S)_0 / S_0 and the Stokes vector
    renormalised to the incoming S_0, so the weight is unchanged (Mueller matrices of
    core.fresnel.mueller_interface, s/p frame of the plane of incidence = s = n x k).  With a
    tilted `normal` (a microfacet) the Stokes frame is taken as the facet's plane of incidence
    (the rotation into it is neglected: the microfacet face's photons are depolarised anyway).
    Returns (new directions, new Stokes).
    """
    nrm = np.broadcast_to(np.array([0.0, 0.0, 1.0]) if normal is None else normal, d.shape)
    c = np.sum(d * nrm, axis=1)                                  # < 0: coming from above
    from_above = c < 0
    n1 = np.where(from_above, n_above, n_below)
    n2 = np.where(from_above, n_below, n_above)
    cos_i = np.abs(c)
    out_S = np.empty_like(S)
    trans = np.zeros(d.shape[0], bool)
    for fa in (True, False):
        m = from_above == fa
        if not m.any():
            continue
        a, b = (n_above, n_below) if fa else (n_below, n_above)
        ST = np.einsum("nab,nb->na", mueller_interface(cos_i[m], a, b, "T"), S[m])
        SR = np.einsum("nab,nb->na", mueller_interface(cos_i[m], a, b, "R"), S[m])
        pT = np.clip(ST[:, 0] / np.maximum(S[m, 0], 1e-300), 0.0, 1.0)
        t = rng.random(pT.size) < pT
        trans[m] = t
        new = np.where(t[:, None], ST, SR)
        out_S[m] = new * (S[m, 0] / np.maximum(new[:, 0], 1e-300))[:, None]
    eta = n1 / n2
    refl = d - 2 * c[:, None] * nrm
    sin2_t = eta**2 * (1 - cos_i**2)
    cos_t = np.sqrt(np.clip(1 - sin2_t, 0, 1))
    refr = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * nrm * np.where(from_above, 1.0, -1.0)[:, None]
    new_d = np.where(trans[:, None], refr, refl)
    return new_d / np.linalg.norm(new_d, axis=1, keepdims=True), out_S


class TableSampler:
    """Draws photon exits from an isotropic BsdfTable (diffuse cells + delta parts), one wavelength.

    Incidence: the two tabulated incidences around the photon's theta are chosen with the
    linear-interpolation weights (exact linear interpolation in expectation).  Outcome: a cell of
    R or T or a delta part, with probability proportional to its power (M00 f Omega_proj); the
    Stokes vector becomes M S P_total / P_outcome (unbiased).  Diffuse cells without Mueller
    matrices depolarise (M = f diag(1, 0, 0, 0)), delta parts without them keep S.  Direction:
    uniform in projected solid angle inside the cell, azimuth relative to the incident plane.
    """

    def __init__(self, table: BsdfTable, wavelength_nm: float):
        if not table.is_isotropic:
            raise InputError("table", "photon sampling needs an isotropic table (one phi_i)")
        t = table
        w = int(np.argmin(np.abs(t.wavelength_nm - wavelength_nm)))
        self.table, self.theta_i = t, np.asarray(t.theta_i_deg, float)
        psa = projected_solid_angle_cells(t.theta_s_edges_deg, t.phi_s_edges_deg)        # (S, P)
        v = t.values_per_sr[w, :, 0] * psa[None, None]                                      # (I, 2, S, P)
        sR = t.specular_R[w, :, 0]
        sT = t.specular_T[w, :, 0]
        self.power = np.concatenate([v.reshape(v.shape[0], -1), sR[:, None], sT[:, None]], axis=1)
        self.total = self.power.sum(axis=1)
        self.cdf = np.cumsum(self.power, axis=1) / np.maximum(self.total[:, None], 1e-300)
        self.mueller = None if t.mueller_per_sr is None else t.mueller_per_sr[w, :, 0]     # (I, 2, S, P, 4, 4)
        self.spec_m = [getattr(t, f"specular_mueller_{k}") for k in "RT"]
        self.spec_m = [None if m is None else m[w, :, 0] for m in self.spec_m]
        self.w, self.shape = w, v.shape[1:]
        self.phi0 = float(t.phi_i_deg[0])

    def sample(self, theta_in_deg: np.ndarray, phi_in_deg: np.ndarray, S: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(reflected?, delta?, theta_out deg (cells only), phi_out deg, new S) per photon."""
        ti = self.theta_i
        x = np.clip(theta_in_deg, ti[0], ti[-1])
        if ti.size > 1:
            i1 = np.clip(np.searchsorted(ti, x, side="right"), 1, ti.size - 1)
            f = (x - ti[i1 - 1]) / (ti[i1] - ti[i1 - 1])
            inc = np.where(rng.random(x.size) < f, i1, i1 - 1)
        else:
            inc = np.zeros(x.size, int)
        o = np.minimum(_rowwise_searchsorted(self.cdf, inc, rng.random(x.size)), self.power.shape[1] - 1)
        return self._outcome(inc, o, phi_in_deg, S, rng)

    def _outcome(self, inc, o, phi_in_deg, S, rng):
        ncell = self.power.shape[1] - 2
        t = self.table
        scale = self.total[inc] / np.maximum(self.power[inc, o], 1e-300)
        cell = o < ncell
        k, s_, a_ = np.unravel_index(np.where(cell, o, 0), self.shape)
        te = np.radians(np.asarray(t.theta_s_edges_deg, float))
        pe = np.asarray(t.phi_s_edges_deg, float)
        s2 = np.sin(te[s_]) ** 2 + rng.random(o.size) * (np.sin(te[s_ + 1]) ** 2 - np.sin(te[s_]) ** 2)
        th = np.degrees(np.arcsin(np.sqrt(np.clip(s2, 0, 1))))
        ph_cell = pe[a_] + rng.random(o.size) * (pe[a_ + 1] - pe[a_]) - self.phi0
        refl = np.where(cell, k == 0, o == ncell)
        ph = np.where(cell, ph_cell + phi_in_deg, phi_in_deg + 180.0)   # delta parts: specular / undeviated
        newS = np.zeros_like(S)
        if self.mueller is not None:
            psa = projected_solid_angle_cells(t.theta_s_edges_deg, t.phi_s_edges_deg)
            M = self.mueller[inc[cell], k[cell], s_[cell], a_[cell]] * psa[s_[cell], a_[cell]][:, None, None]
            newS[cell] = np.einsum("nab,nb->na", M, S[cell]) * scale[cell, None]
        else:
            newS[cell, 0] = S[cell, 0] * self.total[inc[cell]]
        for j, side in ((ncell, 0), (ncell + 1, 1)):
            m = o == j
            if m.any():
                sm = self.spec_m[side]
                newS[m] = (S[m] * self.total[inc[m], None] if sm is None
                           else np.einsum("nab,nb->na", sm[inc[m]], S[m]) * scale[m, None])
        return refl, ~cell, th, ph, newS


def _rowwise_searchsorted(cdf: np.ndarray, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """searchsorted of u[k] in cdf[rows[k]] for every k (vectorised: offset rows onto one axis)."""
    n = cdf.shape[1]
    flat = (cdf + np.arange(cdf.shape[0])[:, None] * 2.0).ravel()
    return np.searchsorted(flat, u + rows * 2.0) - rows * n


def projected_solid_angle_cells(theta_edges_deg: Any, phi_edges_deg: Any) -> np.ndarray:
    return projected_solid_angle(theta_edges_deg, phi_edges_deg)


def _sample_from_tables(out_t: BsdfTable | None, in_t: BsdfTable, d: np.ndarray, S: np.ndarray, ctx: PhotonContext,
                        rng: np.random.Generator) -> FaceEvent:
    """Face event drawn from the face's (outside, inside) tables (TableSampler) for photons `d`."""
    nd = np.empty_like(d)
    nS = np.empty_like(S)
    outside = np.zeros(d.shape[0], bool)
    from_in = d[:, 2] > 0
    for inside, table in ((False, out_t), (True, in_t)):
        m = from_in == inside
        if not m.any():
            continue
        if table is None:
            raise InputError("plate", "this face has no table for light from outside")
        memory = current_memory()
        key = ("sampler", id(table), ctx.wavelength_nm)
        held = memory.peek(key)
        if held is None or held[0] is not table:         # the table is held beside it: its id is not reused
            held = (table, TableSampler(table, ctx.wavelength_nm))
            memory.put(key, held, "sampler")
        dm = d[m]
        th_in = np.degrees(np.arccos(np.clip(np.abs(dm[:, 2]), 0, 1)))
        ph_in = np.degrees(np.arctan2(-dm[:, 1], -dm[:, 0]))          # azimuth of the incident direction
        refl, is_delta, th, ph, S2 = held[1].sample(th_in, ph_in, S[m], rng)
        n1, n2 = (ctx.n_glass, ctx.n_outside) if inside else (ctx.n_outside, ctx.n_glass)
        snell = np.degrees(np.arcsin(np.clip(np.sin(np.radians(th_in)) * n1 / n2, 0, 1)))
        th = np.where(is_delta, np.where(refl, th_in, snell), th)
        w = np.stack([np.sin(np.radians(th)) * np.cos(np.radians(ph)), np.sin(np.radians(th)) * np.sin(np.radians(ph)),
                      np.cos(np.radians(th))], 1)
        # incident side: outside = +z; R stays on the incident side, T crosses
        up = refl != inside
        w[:, 2] *= np.where(up, 1.0, -1.0)
        nd[m], nS[m], outside[m] = w, S2, up
    return FaceEvent(nd, nS, outside, np.zeros(d.shape[0], bool))
