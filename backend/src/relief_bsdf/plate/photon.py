"""The ONE photon Monte Carlo of the plate: an Experiment traced photon by photon (vectorised).

Independent of the deterministic engine (no round-trip operators, no angular grid of the
plate): it checks it.  What it shares is the description, the faces' photon interactions
(`plate.faces`: Fresnel, the ray-traced relief, table sampling, Beckmann facets), the physics
core (Fresnel Mueller matrices, Henyey-Greenstein sampling) and the one detector.

Transport (geometry as formats.md: plate -t < z < 0, light from z > 0, laterally infinite):

1. source: propagation direction of the beam in the (tilted) sample frame, each photon's
   deviated by the beam divergence (`beam_directions`), Stokes (1, q, 0, 0) in the frame
   s = z x k (the plane of incidence);
2. the front face scatters it (face-local frame = plate frame); what goes up leaves as R;
3. in the glass a photon at depth z draws a free path l ~ Exp(mu_s) (mu_s = scatter_per_m);
   if l is shorter than the distance to the next face along k it scatters there into a
   Henyey-Greenstein direction (core.bulk.scatter_directions; Stokes vector carried unchanged:
   the scalar approximation stated in plate.description), else it reaches the face.  Absorption
   multiplies the weight by exp(-a L) over every path length L (Beer-Lambert);
4. a face hit from inside: the front face is in its local frame, the back face through the
   mirror z -> -z (directions mirrored, Stokes S2, S3 change sign).  A photon that crosses
   leaves (front: R, back: T); the others continue in the glass;
5. photons still inside after `max_events` events are counted as lost (reported).

Detection: `plate.detector.photon_reading` in the instrument frame (exit directions rotated
back by the tilt): each exit adds w response(psi) / (N Omega cos theta_s), 1-sigma from
sum (w response)^2.  Each (wavelength, theta_i, phi_i) uses `parallel.task_rng(seed, ...)`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.core.bulk import scatter_directions
from relief_bsdf.core.frames import beam_directions, rot_y
from relief_bsdf.errors import InputError
from relief_bsdf.parallel import task_rng
from relief_bsdf.plate.detector import photon_reading
from relief_bsdf.plate.faces import PhotonContext
from relief_bsdf.plate.grid import TableGrid
from relief_bsdf.plate.rows import check_rows, row_arrays

_MIRROR_S = np.array([1.0, 1.0, -1.0, -1.0])


@dataclass
class Exits:
    """Photons that left the plate: side 0 = R (z > 0), 1 = T; propagation dirs (instrument frame); weights."""

    side: np.ndarray
    dirs: np.ndarray
    weight: np.ndarray
    n_photons: int
    lost_weight: float


@dataclass
class _Photons:
    """Photons inside the glass: propagation direction, Stokes vector (S0 = weight), depth z."""

    d: np.ndarray
    S: np.ndarray
    z: np.ndarray

    def take(self, m: np.ndarray) -> "_Photons":
        return _Photons(self.d[m], self.S[m], self.z[m])

    @staticmethod
    def join(parts: list) -> "_Photons":
        parts = [p for p in parts if p.d.shape[0]]
        if not parts:
            return _Photons(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0))
        return _Photons(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("d", "S", "z")))


class _Tally:
    def __init__(self) -> None:
        self.side, self.dirs, self.w = [], [], []
        self.lost = 0.0

    def leave(self, side: int, d: np.ndarray, S: np.ndarray) -> None:
        if d.shape[0]:
            self.side.append(np.full(d.shape[0], side, np.int8))
            self.dirs.append(d)
            self.w.append(S[:, 0].copy())


def _face_hit(face: Any, back: bool, ph: _Photons, ctx: PhotonContext, rng: np.random.Generator):
    """(left: photons that crossed, stay: photons back in the glass, lost weight) at one face."""
    d, S = ph.d, ph.S
    if back:
        d, S = d * np.array([1.0, 1.0, -1.0]), S * _MIRROR_S
    ev = face.interact(d, S, True, ctx, rng)
    nd, nS = ev.d, ev.S
    if back:
        nd, nS = nd * np.array([1.0, 1.0, -1.0]), nS * _MIRROR_S
    lost = float(np.sum(ph.S[ev.lost, 0]))
    ok = ~ev.lost
    left, stay = ok & ev.outside, ok & ~ev.outside
    return (nd[left], nS[left]), _Photons(nd[stay], nS[stay], ph.z[stay]), lost


def _bulk_step(ph: _Photons, t: float, bulk: Any, rng: np.random.Generator):
    """Move photons to the next event: (scattered photons, photons at the front, photons at the back)."""
    kz = ph.d[:, 2]
    dist = np.where(kz < 0, (ph.z + t) / np.maximum(-kz, 1e-12), -ph.z / np.maximum(kz, 1e-12))
    free = (rng.exponential(1.0 / bulk.scatter_per_m, kz.size) if bulk.scatter_per_m > 0
            else np.full(kz.size, np.inf))
    path = np.minimum(free, dist)
    S = ph.S * np.exp(-bulk.absorption_per_m * path)[:, None] if bulk.absorption_per_m > 0 else ph.S
    scat = free < dist
    z = np.where(scat, ph.z + path * kz, np.where(kz < 0, -t, 0.0))
    moved = _Photons(ph.d, S, z)
    s = moved.take(scat)
    if s.d.shape[0]:
        s.d = scatter_directions(s.d, bulk.hg_g, rng)
    return s, moved.take(~scat & (kz > 0)), moved.take(~scat & (kz <= 0))


def trace(experiment: Any, wavelength_nm: float, theta_i_deg: float, phi_i_deg: float, n_photons: int,
          rng: np.random.Generator, grid: TableGrid | None = None, max_events: int = 2000) -> Exits:
    """Trace `n_photons` of one incidence through the plate; return what left it (instrument frame)."""
    p, ins = experiment.plate, experiment.instrument
    ctx = PhotonContext(p.material, float(wavelength_nm), grid or TableGrid(), (float(abs(theta_i_deg)),))
    t, ph_ = np.radians(theta_i_deg), np.radians(phi_i_deg)
    k_ins = np.array([-np.sin(t) * np.cos(ph_), -np.sin(t) * np.sin(ph_), -np.cos(t)])
    tally = _Tally()
    d = beam_directions(k_ins, ins.beam_divergence_deg, n_photons, rng) @ rot_y(ins.tilt_deg)
    S = np.tile([1.0, float(ins.polarization_q), 0.0, 0.0], (n_photons, 1))
    ev = p.front.interact(d, S, False, ctx, rng)
    tally.lost += float(np.sum(S[ev.lost, 0]))
    up = ~ev.lost & ev.outside
    tally.leave(0, ev.d[up], ev.S[up])
    into = ~ev.lost & ~ev.outside
    glass = _Photons(ev.d[into], ev.S[into], np.zeros(int(into.sum())))
    for _ in range(max_events):
        if glass.d.shape[0] == 0:
            break
        scattered, at_front, at_back = _bulk_step(glass, p.thickness_m, p.bulk, rng)
        (fd, fS), f_stay, lf = _face_hit(p.front, False, at_front, ctx, rng)
        (bd, bS), b_stay, lb = _face_hit(p.back, True, at_back, ctx, rng)
        tally.leave(0, fd, fS)
        tally.leave(1, bd, bS)
        tally.lost += lf + lb
        glass = _Photons.join([scattered, f_stay, b_stay])
    tally.lost += float(np.sum(glass.S[:, 0]))
    if not tally.side:
        return Exits(np.zeros(0, np.int8), np.zeros((0, 3)), np.zeros(0), n_photons, tally.lost)
    dirs = np.concatenate(tally.dirs)
    if ins.tilt_deg:
        dirs = dirs @ rot_y(ins.tilt_deg).T          # back to the instrument frame
    return Exits(np.concatenate(tally.side), dirs, np.concatenate(tally.w), n_photons, tally.lost)


def detect(exits: Exits, side: np.ndarray, theta_s_deg: np.ndarray, phi_s_deg: np.ndarray,
           instrument: Any) -> tuple[np.ndarray, np.ndarray]:
    """(BSDF, 1-sigma) of each row from the exit photons (the one detector, plate.detector)."""
    val = np.zeros(theta_s_deg.size)
    err = np.zeros(theta_s_deg.size)
    for k_side, name in ((0, "R"), (1, "T")):
        sel = np.nonzero(side == name)[0]
        m = exits.side == k_side
        if sel.size == 0 or not m.any():
            continue
        u = exits.dirs[m] * np.array([1.0, 1.0, 1.0 if k_side == 0 else -1.0])   # theta from +z (R) or -z (T)
        val[sel], err[sel] = photon_reading(u, exits.weight[m], exits.n_photons, theta_s_deg[sel], phi_s_deg[sel],
                                            instrument.detector_half_angle_deg, instrument.blur_deg)
    return val + instrument.background_per_sr, err


def run(experiment: Any, rows: Any, photons: int = 200_000, seed: int = 0, grid: TableGrid | None = None,
        where: str = "recording") -> tuple[np.ndarray, np.ndarray, dict]:
    """Monte-Carlo plate BSDF on every row: (values, sigma, info with lost fractions per incidence)."""
    check_rows(experiment, rows, where)
    if photons < 1:
        raise InputError("photons", f"need at least one photon, got {photons}")
    wl, ti, pi, side, ts, ps = row_arrays(rows)
    val = np.zeros(wl.size)
    err = np.zeros(wl.size)
    info: dict = {"engine": "photon", "photons_per_incidence": int(photons), "seed": int(seed), "lost_fraction": {}}
    for w, t, p in np.unique(np.stack([wl, ti, pi], 1), axis=0):
        sel = (wl == w) & (ti == t) & (pi == p)
        rng = task_rng(seed, int(round(w * 1000)), int(round(t * 1000)), int(round(p * 1000)))
        ex = trace(experiment, w, t, p, photons, rng, grid)
        val[sel], err[sel] = detect(ex, side[sel], ts[sel], ps[sel], experiment.instrument)
        info["lost_fraction"][f"{w:g},{t:g},{p:g}"] = ex.lost_weight / photons
    return val, err, info


def hemispherical(exits: Exits) -> dict:
    """Total R, T and lost fractions of one incidence (energy check)."""
    n = exits.n_photons
    return {"R": float(exits.weight[exits.side == 0].sum() / n), "T": float(exits.weight[exits.side == 1].sum() / n),
            "lost": exits.lost_weight / n}
