"""Direct Monte-Carlo plate: photons traced through the REAL relief and the plate until they leave.

Independent of plate.py (no tables, no angular grid): every interaction with the rough face
is a ray trace through the triangulated height field (`methods.ray.ReliefTracer`: Fresnel
with Stokes vectors on each facet, shadowing, interreflection); the flat face is Fresnel
(`optics.mueller_interface`) with the reflect/transmit choice drawn with probability
(M S)_0 / S_0 and the Stokes vector renormalised, so a photon's weight changes only by bulk
absorption exp(-a t / |k_z|) per traversal (Beer-Lambert).  Stokes frame: s = z x k / |z x k|
(the tracer's frame), which is the plane of incidence at the flat face, so no rotation is
needed there.

Geometry as plate.py: plate -t < z < 0, light from z > 0.  Front relief: the tracer of the
relief (air above, glass below).  Back relief: the relief seen from the glass is the height
map negated (its outward normal is -z), traced with glass above and air below.

Detection (formats.md): a row's value is sum(weights of photons leaving inside its detector
cone) / (N Omega cos theta_s), Omega = 2 pi (1 - cos half_angle); its 1-sigma error is
sqrt(sum w^2) / (N Omega cos theta_s).  Laterally infinite plate, incoherent paths.

Effects (the hook the diagnosis uses): PlateModel.absorption_per_m, .polarization (source
Stokes) and .tilt_deg (sample normal rotated about y; source and exits rotated) are honoured; background_per_sr is added to every row; blur_deg jitters the exit
directions by a 2-D Gaussian (instrument blur).  Photons still inside after `max_round_trips`
are counted as lost (reported).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.core.optics import mueller_interface
from relief_bsdf.plate.solver import SOURCE_STOKES, PlateModel, check_rows, rot_y, row_arrays
from relief_bsdf.surface.relief import Relief


@dataclass
class Exits:
    """Photons that left the plate: side 0 = R (z > 0), 1 = T; propagation dirs; weights."""

    side: np.ndarray
    dirs: np.ndarray
    weight: np.ndarray
    n_photons: int
    lost_weight: float


def _flat_event(k: np.ndarray, S: np.ndarray, n1: float, n2: float, rng: np.random.Generator):
    """Fresnel at a z-plane for photons in medium n1 hitting n2; returns (k, S, transmitted)."""
    cos_i = np.abs(k[:, 2])
    MR = mueller_interface(cos_i, n1, n2, "R")
    MT = mueller_interface(cos_i, n1, n2, "T")
    SR = np.einsum("nab,nb->na", MR, S)
    ST = np.einsum("nab,nb->na", MT, S)
    pT = np.clip(ST[:, 0] / np.maximum(S[:, 0], 1e-300), 0.0, 1.0)
    trans = rng.random(k.shape[0]) < pT
    knew = k.copy()
    knew[~trans, 2] *= -1.0
    if trans.any():
        kt = k[trans]
        h = kt[:, :2] * (n1 / n2)
        kz = np.sqrt(np.clip(1.0 - np.sum(h**2, axis=1), 0.0, 1.0)) * np.sign(kt[:, 2])
        knew[trans] = np.column_stack([h, kz])
    Snew = np.where(trans[:, None], ST, SR)
    Snew *= (S[:, 0] / np.maximum(Snew[:, 0], 1e-300))[:, None]
    return knew, Snew, trans


def _absorb(k: np.ndarray, S: np.ndarray, model: PlateModel) -> np.ndarray:
    if model.absorption_per_m <= 0:
        return S
    return S * np.exp(-model.absorption_per_m * model.thickness_m / np.maximum(np.abs(k[:, 2]), 1e-9))[:, None]


def make_tracer(relief: Relief, rough_face: str):
    """The ReliefTracer of the rough face as seen in the plate frame (negated heights for the back face)."""
    from relief_bsdf.methods.ray import ReliefTracer
    if rough_face == "back":
        relief = relief.with_heights(-relief.heights_m, "negated: back face seen from the glass")
    return ReliefTracer(relief)


def trace_plate(tracer: Any, model: PlateModel, wavelength_nm: float, theta_i_deg: float, phi_i_deg: float,
                n_photons: int, rng: np.random.Generator, max_round_trips: int = 500) -> Exits:
    """Trace `n_photons` through the plate for one incidence; return what left it."""
    n = float(np.real(model.index.n(wavelength_nm)))
    n0 = float(np.real(model.outside_index.n(wavelength_nm)))
    t = np.radians(theta_i_deg)
    p = np.radians(phi_i_deg)
    # propagation direction of the source, in the (possibly tilted) sample's frame
    k0 = rot_y(model.tilt_deg).T @ np.array([-np.sin(t) * np.cos(p), -np.sin(t) * np.sin(p), -np.cos(t)])
    k = np.tile(k0, (n_photons, 1))
    S = np.tile(SOURCE_STOKES[model.polarization], (n_photons, 1)).astype(float)
    out_side, out_dirs, out_w = [], [], []
    front = model.rough_face == "front"

    def leave(side: int, kk: np.ndarray, SS: np.ndarray) -> None:
        if kk.shape[0]:
            out_side.append(np.full(kk.shape[0], side, np.int8))
            out_dirs.append(kk)
            out_w.append(SS[:, 0].copy())

    lost = 0.0
    # first interaction: the lit face
    if front:
        r = tracer.scatter(k, n0, n, rng, stokes=S)
        ok = ~r.lost
        lost += float(np.sum(r.weight[r.lost])) if r.lost.any() else 0.0
        leave(0, r.dirs[ok & r.above], r.stokes[ok & r.above])
        k, S = r.dirs[ok & ~r.above], r.stokes[ok & ~r.above]        # in the glass, going down to the flat back
        to_rough = False
    else:
        k, S, tr = _flat_event(k, S, n0, n, rng)
        leave(0, k[~tr], S[~tr])
        k, S = k[tr], S[tr]                                            # in the glass, going down to the relief
        to_rough = True
    for _ in range(max_round_trips):
        if k.shape[0] == 0:
            break
        S = _absorb(k, S, model)
        if to_rough:
            r = tracer.scatter(k, n0 if front else n, n if front else n0, rng, stokes=S)
            ok = ~r.lost
            lost += float(np.sum(S[r.lost, 0])) if r.lost.any() else 0.0
            if front:   # exits upward into air (R), stays in glass going down
                leave(0, r.dirs[ok & r.above], r.stokes[ok & r.above])
                keep = ok & ~r.above
            else:       # exits downward into air (T), stays in glass going up
                leave(1, r.dirs[ok & ~r.above], r.stokes[ok & ~r.above])
                keep = ok & r.above
            k, S = r.dirs[keep], r.stokes[keep]
        else:
            k, S, tr = _flat_event(k, S, n, n0, rng)
            leave(1 if front else 0, k[tr], S[tr])
            k, S = k[~tr], S[~tr]
        to_rough = not to_rough
    lost += float(np.sum(S[:, 0])) if k.shape[0] else 0.0
    if not out_side:
        return Exits(np.zeros(0, np.int8), np.zeros((0, 3)), np.zeros(0), n_photons, lost)
    dirs = np.concatenate(out_dirs)
    if model.tilt_deg:
        dirs = dirs @ rot_y(model.tilt_deg).T          # back to the instrument frame
    return Exits(np.concatenate(out_side), dirs, np.concatenate(out_w), n_photons, lost)


def detect(exits: Exits, side: np.ndarray, theta_s_deg: np.ndarray, phi_s_deg: np.ndarray, model: PlateModel,
           rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(BSDF, 1-sigma) of each row from the photons inside its detector cone."""
    from scipy.spatial import cKDTree
    h = np.radians(model.detector_half_angle_deg)
    omega = 2 * np.pi * (1 - np.cos(h))
    val = np.zeros(theta_s_deg.size)
    err = np.zeros(theta_s_deg.size)
    d = exits.dirs
    if model.blur_deg > 0 and d.shape[0]:
        rng = rng or np.random.default_rng(0)
        d = d + np.radians(model.blur_deg) * rng.standard_normal(d.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    for k_side, name in ((0, "R"), (1, "T")):
        sel = np.nonzero(side == name)[0]
        m = exits.side == k_side
        if sel.size == 0 or not m.any():
            continue
        u = d[m] * np.array([1.0, 1.0, 1.0 if k_side == 0 else -1.0])   # theta from +z (R) or -z (T)
        w = exits.weight[m]
        tree = cKDTree(u)
        tr = np.radians(theta_s_deg[sel])
        pr = np.radians(phi_s_deg[sel])
        q = np.column_stack([np.sin(tr) * np.cos(pr), np.sin(tr) * np.sin(pr), np.cos(tr)])
        hits = tree.query_ball_point(q, 2 * np.sin(h / 2))
        norm = exits.n_photons * omega * np.cos(tr)
        for j, idx in enumerate(hits):
            if idx:
                ww = w[idx]
                val[sel[j]] = ww.sum() / norm[j]
                err[sel[j]] = np.sqrt(np.sum(ww**2)) / norm[j]
    return val + model.background_per_sr, err


def simulate_rows_mc(relief: Relief, model: PlateModel, rows: Any, photons: int = 200_000, seed: int = 0,
                     tracer: Any = None, where: str = "recording") -> tuple[np.ndarray, np.ndarray, dict]:
    """Monte-Carlo plate BSDF on every row: (values, sigma, info with lost fractions per incidence).

    Each (wavelength, theta_i, phi_i) uses its own generator `parallel.task_rng(seed, w, i, p)`.
    """
    from relief_bsdf.parallel.tasks import task_rng
    check_rows(model, rows, where)
    if photons < 1:
        raise InputError("photons", f"need at least one photon, got {photons}")
    tracer = tracer or make_tracer(relief, model.rough_face)
    wl, ti, pi, side, ts, ps = row_arrays(rows)
    val = np.zeros(wl.size)
    err = np.zeros(wl.size)
    info = {"lost_fraction": {}}
    keys = np.unique(np.stack([wl, ti, pi], 1), axis=0)
    for w, t, p in keys:
        sel = (wl == w) & (ti == t) & (pi == p)
        rng = task_rng(seed, int(round(w * 1000)), int(round(t * 1000)), int(round(p * 1000)))
        ex = trace_plate(tracer, model, w, t, p, photons, rng)
        v, e = detect(ex, side[sel], ts[sel], ps[sel], model, rng)
        val[sel], err[sel] = v, e
        info["lost_fraction"][f"{w:g},{t:g},{p:g}"] = ex.lost_weight / photons
    return val, err, info


def hemispherical(exits: Exits) -> dict:
    """Total R, T and lost fractions of one incidence (energy check)."""
    n = exits.n_photons
    return {"R": float(exits.weight[exits.side == 0].sum() / n), "T": float(exits.weight[exits.side == 1].sum() / n),
            "lost": exits.lost_weight / n}

