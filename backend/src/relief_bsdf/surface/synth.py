"""Synthetic periodic reliefs: Gaussian / exponential random surfaces and light-guide dots.

Random surfaces (`random_relief`) are made by FFT filtering of white noise: a real
Gaussian white-noise field e on the (ny, nx) grid is transformed, multiplied by
sqrt(W(f) / (dx dy)) and transformed back, where W is the 2-D PSD (cycles/m
convention, integral of W over the plane = s^2) of the requested autocovariance:

- gaussian:     C(r) = s^2 exp(-r^2 / L^2)   W(f) = pi s^2 L^2 exp(-pi^2 L^2 f^2)
                rms slope magnitude 2 s / L (per axis sqrt(2) s / L), as the Gaussian
                PSD of NIST SCATMECH.
- exponential:  C(r) = s^2 exp(-r / L)       W(f) = 2 pi s^2 L^2 / (1 + 4 pi^2 L^2 f^2)^(3/2)
                (its rms slope diverges in the continuum: on a grid it depends on the pitch).

Anisotropy a stretches the correlation length to a L along the direction at
`angle_deg` from +x (L across it): r^2 / L^2 -> u^2 / (a L)^2 + v^2 / L^2.  The result is
periodic (the FFT grid wraps) and has zero mean.

Statistical tolerance: a finite tile of side T holds about (T / L)^2 independent
correlation areas, so a realisation's rms height scatters by roughly L / T relative
(e.g. 2 % for T = 50 L) and its correlation length by a few times that.  With
``exact_rms=True`` (the default) each realisation is scaled so its rms height is
exactly the requested s (what a user asking for "s = 50 nm" expects); the slope and
correlation length then scatter by ~ L / T.  The spectrum is cut at the Nyquist
frequency 1 / (2 d): keep L >= 5 d (Gaussian) so nothing important is lost; for an
exponential ACF a fraction ~ d / (pi L) of the variance lies beyond Nyquist.
"""
from __future__ import annotations

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.parallel.tasks import task_rng
from relief_bsdf.surface.relief import Relief


def _grid_freqs(nx: int, ny: int, dx: float, dy: float, angle_deg: float):
    fx = np.fft.fftfreq(nx, dx)
    fy = np.fft.fftfreq(ny, dy)
    FX, FY = np.meshgrid(fx, fy)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    fu = c * FX + s * FY          # frequency along the stretched direction
    fv = -s * FX + c * FY
    return fu, fv


def psd_model(kind: str, fu: np.ndarray, fv: np.ndarray, rms_height_m: float, lu_m: float, lv_m: float) -> np.ndarray:
    """2-D PSD (m^4) of the anisotropic Gaussian or exponential autocovariance (see module doc)."""
    q2 = (lu_m * fu) ** 2 + (lv_m * fv) ** 2
    s2 = rms_height_m**2
    if kind == "gaussian":
        return np.pi * s2 * lu_m * lv_m * np.exp(-np.pi**2 * q2)
    if kind == "exponential":
        return 2 * np.pi * s2 * lu_m * lv_m / (1 + 4 * np.pi**2 * q2) ** 1.5
    raise InputError("kind", f"unknown relief kind {kind!r}; expected 'gaussian' or 'exponential'")


def random_relief(n: int, pitch_m: float, rms_height_m: float, corr_length_m: float,
                  kind: str = "gaussian", seed: int = 0, anisotropy: float = 1.0, angle_deg: float = 0.0,
                  ny: int | None = None, exact_rms: bool = True) -> Relief:
    """Periodic random relief of n x n (or ny x n) pixels at square pitch `pitch_m`.

    The autocovariance is s^2 exp(-r^2/L^2) ("gaussian") or s^2 exp(-r/L) ("exponential")
    with s = rms_height_m, L = corr_length_m (times `anisotropy` along `angle_deg`).
    Seeded through `parallel.task_rng(seed, 0)`: the same arguments give the same relief.
    """
    nx = int(n)
    ny = nx if ny is None else int(ny)
    for name, v in (("size", nx), ("ny", ny)):
        if v < 4:
            raise InputError(name, f"grid size must be at least 4 pixels, got {v}")
    for name, v in (("pitch", pitch_m), ("rms height", rms_height_m), ("correlation length", corr_length_m),
                    ("anisotropy", anisotropy)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(name, f"must be a positive number, got {v!r}")
    if kind not in ("gaussian", "exponential"):
        raise InputError("kind", f"unknown relief kind {kind!r}; expected 'gaussian' or 'exponential'")
    lu, lv = corr_length_m * anisotropy, corr_length_m
    if min(lu, lv) < 2 * pitch_m:
        raise InputError("correlation length", f"{min(lu, lv) * 1e6:.4g} um is under 2 pixels "
                                               f"({pitch_m * 1e6:.4g} um): the relief would be aliased")
    if max(lu, lv) > 0.5 * min(nx, ny) * pitch_m:
        raise InputError("size", f"tile {min(nx, ny)} px x {pitch_m * 1e6:.4g} um is shorter than 2 correlation "
                                 f"lengths ({max(lu, lv) * 1e6:.4g} um): the statistics would be meaningless")
    rng = task_rng(int(seed), 0)
    noise = rng.standard_normal((ny, nx))
    fu, fv = _grid_freqs(nx, ny, pitch_m, pitch_m, angle_deg)
    W = psd_model(kind, fu, fv, rms_height_m, lu, lv)
    W[0, 0] = 0.0                                   # zero mean
    z = np.fft.ifft2(np.fft.fft2(noise) * np.sqrt(W / (pitch_m * pitch_m))).real
    step = (f"synthetic {kind} relief: s = {rms_height_m * 1e9:.4g} nm, L = {corr_length_m * 1e6:.4g} um"
            + (f", anisotropy {anisotropy:g} at {angle_deg:g} deg" if anisotropy != 1 else "")
            + f", seed {seed}")
    if exact_rms:
        z *= rms_height_m / np.sqrt(np.mean(z * z))
        step += ", rms normalised exactly"
    meta = {"generator": "relief_bsdf.surface.synth.random_relief", "kind": kind, "rms_height_m": rms_height_m,
            "corr_length_m": corr_length_m, "anisotropy": anisotropy, "angle_deg": angle_deg, "seed": int(seed),
            "exact_rms": exact_rms}
    return Relief(z, pitch_m, pitch_m, periodic=True, source=step, metadata=meta, history=(step,))


def lgp_dots(n: int, pitch_m: float, dot_pitch_m: float, dot_radius_m: float, dot_height_m: float,
             shape: str = "cap", jitter: float = 0.2, seed: int = 0, micro_rms_m: float = 0.0,
             micro_corr_m: float | None = None, ny: int | None = None) -> Relief:
    """Light-guide-plate dot pattern: dots on a jittered square grid, periodic tile.

    Each grid cell (spacing = tile / round(tile / dot_pitch), so the tile stays periodic)
    holds one dot displaced uniformly by up to +-jitter * spacing / 2 along x and y.
    shape "cap": spherical cap of base radius a and height h (sphere radius
    R = (a^2 + h^2) / (2 h)); "gaussian": h exp(-2 r^2 / a^2) (1/e^2 radius a), cut at 2a.
    A negative dot_height_m makes pits instead of bumps (etched or laser-marked plates).
    micro_rms_m > 0 adds Gaussian micro-roughness (correlation length micro_corr_m,
    default 4 pixels) inside the dots only, as on printed / moulded dots.
    Dots must not overlap: dot_radius (x2 for gaussian) + jitter * spacing / 2 < spacing / 2.
    """
    nx = int(n)
    ny = nx if ny is None else int(ny)
    if shape not in ("cap", "gaussian"):
        raise InputError("shape", f"dot shape must be 'cap' or 'gaussian', got {shape!r}")
    for name, v in (("pitch", pitch_m), ("dot pitch", dot_pitch_m), ("dot radius", dot_radius_m)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(name, f"must be a positive number, got {v!r}")
    if not np.isfinite(dot_height_m) or dot_height_m == 0:
        raise InputError("dot height", f"must be a non-zero number, got {dot_height_m!r}")
    if not 0 <= jitter < 1:
        raise InputError("jitter", f"must be in [0, 1), got {jitter}")
    Lx, Ly = nx * pitch_m, ny * pitch_m
    cx, cy = max(1, round(Lx / dot_pitch_m)), max(1, round(Ly / dot_pitch_m))
    sx, sy = Lx / cx, Ly / cy
    reach = dot_radius_m * (2.0 if shape == "gaussian" else 1.0)
    if reach + jitter * min(sx, sy) / 2 >= min(sx, sy) / 2:
        raise InputError("dot radius", f"dots of radius {dot_radius_m * 1e6:.4g} um overlap at spacing "
                                       f"{min(sx, sy) * 1e6:.4g} um with jitter {jitter}")
    if dot_radius_m < 2 * pitch_m:
        raise InputError("dot radius", f"{dot_radius_m * 1e6:.4g} um is under 2 pixels: dots would not be resolved")
    rng = task_rng(int(seed), 1)
    jx = (rng.random((cy, cx)) - 0.5) * jitter * sx
    jy = (rng.random((cy, cx)) - 0.5) * jitter * sy
    # every pixel belongs to one cell; its dot is the only one that can reach it
    x = (np.arange(nx) + 0.5) * pitch_m
    y = (np.arange(ny) + 0.5) * pitch_m
    X, Y = np.meshgrid(x, y)
    ix = np.minimum((X / sx).astype(int), cx - 1)
    iy = np.minimum((Y / sy).astype(int), cy - 1)
    dxc = X - ((ix + 0.5) * sx + jx[iy, ix])
    dyc = Y - ((iy + 0.5) * sy + jy[iy, ix])
    r2 = dxc**2 + dyc**2
    a, h = dot_radius_m, abs(dot_height_m)
    if shape == "cap":
        R = (a * a + h * h) / (2 * h)
        z = np.where(r2 < a * a, np.sqrt(np.maximum(R * R - r2, 0.0)) - (R - h), 0.0)
    else:
        z = np.where(r2 < 4 * a * a, h * np.exp(-2 * r2 / (a * a)), 0.0)
    inside = z > 0
    z = np.sign(dot_height_m) * z
    step = (f"light-guide dots ({shape}): radius {a * 1e6:.4g} um, height {dot_height_m * 1e6:.4g} um, "
            f"{cx} x {cy} dots at {sx * 1e6:.4g} x {sy * 1e6:.4g} um, jitter {jitter:g}, seed {seed}")
    if micro_rms_m > 0:
        mc = micro_corr_m if micro_corr_m is not None else 4 * pitch_m
        micro = random_relief(nx, pitch_m, micro_rms_m, mc, seed=int(seed) + 1, ny=ny).heights_m
        z = z + np.where(inside, micro, 0.0)
        step += f", micro-roughness {micro_rms_m * 1e9:.3g} nm rms (L = {mc * 1e6:.3g} um) inside dots"
    meta = {"generator": "relief_bsdf.surface.synth.lgp_dots", "shape": shape, "dot_pitch_m": [sx, sy],
            "dot_radius_m": a, "dot_height_m": dot_height_m, "jitter": jitter, "seed": int(seed),
            "dot_count": cx * cy, "fill_fraction": float(inside.mean())}
    return Relief(z, pitch_m, pitch_m, periodic=True, source=step, metadata=meta, history=(step,))
