"""Independent recordings: a goniophotometer scan of a plate simulated by the validation's photon Monte Carlo.

`trace_recording` runs the validation's own photon engine (`photon.run_photons`) with the real
relief ray traced on the rough face (`conceal.HeightFieldFace`: the triangulated height field in
Embree, shadowing, masking and inter-reflections included) and detects the exits on each row
with the validation's own detector (`photon.detect`, a uniform cone of the instrument's
half-angle).  Nothing of the forward model it is compared with (plate/, methods/, diagnose/) is
used, so a recording made here is evidence *for or against* that model, never a copy of it.

`instrument_noise` turns a clean recording into what a goniophotometer returns: Poisson shot
noise on the detected counts (gain `counts_per_sr`: counts per unit BSDF), a relative gain noise
per row (`gain_noise`, lamp and amplifier drift), an additive floor (`floor_sr`), plus the
Monte Carlo's own variance; `sigma_sr` is their quadrature sum (what the instrument's error
model would report).  conceal.py's cases use the same function.

Rows are any object with the recording columns as arrays (`io.recording.Recording`, the
plate's Rows): wavelength_nm, theta_i_deg, side, theta_s_deg, phi_s_deg (phi_i = 0 assumed,
in-plane scans).

Detection limit of a clean recording: where a row's cone caught no photon, the Monte-Carlo
sigma is 0; `trace_recording` reports there the one-photon level 1 / (N Omega cos theta_s)
(the value one photon would have given), so a z-score against a clean recording is finite
and an empty row does not dominate a comparison.

Assumptions: geometric optics (relief lateral scales >> wavelength; no coherent specular part),
plate thickness >> relief height, incoherent sum of paths, front face rough, back face flat
(PlatePhysics's back_alpha for a rough one), air outside.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relief_bsdf.parallel import task_rng
from relief_bsdf.surface.relief import Relief
from relief_bsdf.validation.photon import Exits, PlatePhysics, detect, run_photons

__all__ = ["Goniophotometer", "instrument_noise", "trace_recording"]

CHUNK_PHOTONS = 500_000          # photons per run_photons call (memory: ~0.5 GB at most)


@dataclass(frozen=True)
class Goniophotometer:
    """Noise model of the instrument (module doc): counts per unit BSDF, relative gain noise, floor (1/sr)."""

    counts_per_sr: float = 2.0e4
    gain_noise: float = 0.015
    floor_sr: float = 0.0


def _exits_of(face, phys: PlatePhysics, theta_i_deg: float, photons: int, seed: int, stream: int) -> Exits:
    """All exits of `photons` photons at one incidence, traced in chunks (each with its own seeded stream)."""
    d, w, path, launched, lost = [], [], [], 0, 0
    for k, start in enumerate(range(0, int(photons), CHUNK_PHOTONS)):
        n = min(CHUNK_PHOTONS, int(photons) - start)
        ex = run_photons(face, phys, float(theta_i_deg), 0.0, (1.0, 0.0, 0.0, 0.0), n, task_rng(seed, stream, k))
        d.append(ex.d)
        w.append(ex.w)
        path.append(ex.path_mm)
        launched += ex.n_launched
        lost += ex.lost
    return Exits(d=np.concatenate(d), w=np.concatenate(w), path_mm=np.concatenate(path), n_launched=launched,
                 lost=lost)


def trace_recording(relief: Relief, rows, phys: PlatePhysics, half_angle_deg: float, photons: int,
                    seed: int = 0, max_hits: int = 20) -> tuple[np.ndarray, np.ndarray, dict]:
    """Clean recording of the plate `phys` whose front face carries `relief` (periodic tile).

    Returns (bsdf_sr per row, Monte-Carlo 1-sigma per row, floored at the one-photon level,
    info: photons, lost fraction per incidence).  One photon run per (wavelength, theta_i),
    `photons` photons each, seeded by (seed, incidence index).  Only n_glass of `phys` is used
    as given (no dispersion here).
    """
    from relief_bsdf.validation.conceal import HeightFieldFace
    face = HeightFieldFace(relief.heights_m, relief.dx_m, relief.dy_m, max_hits=max_hits)
    wl = np.asarray(rows.wavelength_nm, float)
    ti = np.asarray(rows.theta_i_deg, float)
    side = np.asarray(rows.side).astype(str)
    ts = np.asarray(rows.theta_s_deg, float)
    ps = np.asarray(rows.phi_s_deg, float)
    val = np.zeros(ti.size)
    sig = np.zeros(ti.size)
    lost = {}
    a = np.radians(half_angle_deg)
    omega = 2 * np.pi * (1 - np.cos(a))
    for k, (w, t) in enumerate(sorted(set(zip(wl.tolist(), ti.tolist())))):
        sel = np.nonzero((wl == w) & (ti == t))[0]
        ex = _exits_of(face, phys, t, photons, seed, k)
        v, s = detect(ex, side[sel], ts[sel], ps[sel], half_angle_deg)
        one = 1.0 / (ex.n_launched * omega * np.maximum(np.cos(np.radians(ts[sel])), 1e-3))
        val[sel] = v
        sig[sel] = np.maximum(s, one)
        lost[f"{w:g} nm, {t:g} deg"] = ex.lost / ex.n_launched
    return val, sig, {"photons_per_incidence": int(photons), "lost_fraction": lost, "half_angle_deg": half_angle_deg}


def instrument_noise(clean: np.ndarray, mc_sigma: np.ndarray, noise: Goniophotometer,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(noisy values, sigma_sr) of a clean recording read by the instrument `noise` (module doc).

    Poisson counts at counts_per_sr per unit BSDF, times a per-row gain 1 + gain_noise N(0, 1),
    plus floor_sr N(0, 1), clipped at 0 (recording.csv holds no negative BSDF); sigma is the
    quadrature sum of the shot, gain, floor and Monte-Carlo terms.
    """
    v = np.maximum(np.asarray(clean, float), 0.0)
    counts = rng.poisson(v * noise.counts_per_sr) / noise.counts_per_sr
    gain = 1.0 + noise.gain_noise * rng.normal(size=v.size)
    noisy = np.maximum(counts * gain + noise.floor_sr * rng.normal(size=v.size), 0.0)
    sigma = np.sqrt(v / noise.counts_per_sr + (noise.gain_noise * v) ** 2 + noise.floor_sr**2
                    + np.asarray(mc_sigma, float) ** 2)
    return noisy, sigma

