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

from dataclasses import dataclass

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.seeds import task_rng
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


@dataclass(frozen=True)
class RandomFieldSpec:
    """What a random relief is: grid, statistics and shape of the autocovariance (module doc).

    nx, ny: pixels; pitch_m: x pitch (pitch_y_m: y pitch, default the same); rms_height_m: s;
    corr_length_m: L; kind: "gaussian" (s^2 exp(-r^2/L^2)) or "exponential" (s^2 exp(-r/L));
    anisotropy: L is stretched to anisotropy * L along `angle_deg` from +x; exact_rms: scale each
    realisation to exactly s.
    """

    nx: int
    ny: int
    pitch_m: float
    rms_height_m: float
    corr_length_m: float
    kind: str = "gaussian"
    anisotropy: float = 1.0
    angle_deg: float = 0.0
    exact_rms: bool = True
    pitch_y_m: float | None = None

    @property
    def dy_m(self) -> float:
        return self.pitch_m if self.pitch_y_m is None else float(self.pitch_y_m)

    def check(self) -> None:
        """InputError for a grid or statistics the generator cannot honour (aliased, too small a tile)."""
        for name, v in (("size", self.nx), ("ny", self.ny)):
            if v < 4:
                raise InputError(name, f"grid size must be at least 4 pixels, got {v}")
        for name, v in (("pitch", self.pitch_m), ("pitch y", self.dy_m), ("rms height", self.rms_height_m),
                        ("correlation length", self.corr_length_m), ("anisotropy", self.anisotropy)):
            if not (np.isfinite(v) and v > 0):
                raise InputError(name, f"must be a positive number, got {v!r}")
        if self.kind not in KINDS:
            raise InputError("kind", f"unknown relief kind {self.kind!r}; expected 'gaussian' or 'exponential'")
        lu, lv = self.corr_length_m * self.anisotropy, self.corr_length_m
        pitch = max(self.pitch_m, self.dy_m)
        if min(lu, lv) < 2 * pitch:
            raise InputError("correlation length", f"{min(lu, lv) * 1e6:.4g} um is under 2 pixels "
                                                   f"({pitch * 1e6:.4g} um): the relief would be aliased")
        if max(lu, lv) > 0.5 * min(self.nx * self.pitch_m, self.ny * self.dy_m):
            raise InputError("size", f"tile {min(self.nx, self.ny)} px x {self.pitch_m * 1e6:.4g} um is shorter "
                                     f"than 2 correlation lengths ({max(lu, lv) * 1e6:.4g} um): the statistics "
                                     "would be meaningless")


KINDS = ("gaussian", "exponential")


def gaussian_field(spec: RandomFieldSpec, rng: np.random.Generator) -> np.ndarray:
    """Heights (ny, nx) in m of one periodic realisation of `spec`: FFT filtering of white noise.

    z = IFFT(FFT(e) sqrt(W / (dx dy))) with e standard normal white noise and W the 2-D PSD of the
    autocovariance (module doc); the mean (f = 0) is removed, and with spec.exact_rms the
    realisation is scaled to rms exactly s.  No validation: see `RandomFieldSpec.check`.
    """
    noise = rng.standard_normal((spec.ny, spec.nx))
    fu, fv = _grid_freqs(spec.nx, spec.ny, spec.pitch_m, spec.dy_m, spec.angle_deg)
    W = psd_model(spec.kind, fu, fv, spec.rms_height_m, spec.corr_length_m * spec.anisotropy, spec.corr_length_m)
    W[0, 0] = 0.0                                   # zero mean
    z = np.fft.ifft2(np.fft.fft2(noise) * np.sqrt(W / (spec.pitch_m * spec.dy_m))).real
    if spec.exact_rms:
        z *= spec.rms_height_m / np.sqrt(np.mean(z * z))
    return z


def random_heights(spec: RandomFieldSpec, seed: int = 0, stream: int = 0) -> np.ndarray:
    """Validated heights (ny, nx) of `spec`, seeded through `seeds.task_rng(seed, stream)`."""
    spec.check()
    return gaussian_field(spec, task_rng(int(seed), int(stream)))


def relief_from_spec(spec: RandomFieldSpec, seed: int = 0) -> Relief:
    """Periodic `Relief` of one realisation of `spec` (history and metadata say how it was made)."""
    z = random_heights(spec, seed)
    step = (f"synthetic {spec.kind} relief: s = {spec.rms_height_m * 1e9:.4g} nm, L = {spec.corr_length_m * 1e6:.4g} um"
            + (f", anisotropy {spec.anisotropy:g} at {spec.angle_deg:g} deg" if spec.anisotropy != 1 else "")
            + f", seed {seed}" + (", rms normalised exactly" if spec.exact_rms else ""))
    meta = {"generator": "relief_bsdf.surface.synth.random_relief", "kind": spec.kind,
            "rms_height_m": spec.rms_height_m, "corr_length_m": spec.corr_length_m, "anisotropy": spec.anisotropy,
            "angle_deg": spec.angle_deg, "seed": int(seed), "exact_rms": spec.exact_rms}
    return Relief(z, spec.pitch_m, spec.dy_m, periodic=True, source=step, metadata=meta, history=(step,))


def random_relief(n: int, pitch_m: float, rms_height_m: float, corr_length_m: float,
                  kind: str = "gaussian", seed: int = 0, ny: int | None = None) -> Relief:
    """Isotropic periodic random relief of n x n (or ny x n) pixels at square pitch `pitch_m`.

    The autocovariance is s^2 exp(-r^2/L^2) ("gaussian") or s^2 exp(-r/L) ("exponential")
    with s = rms_height_m (exactly, per realisation), L = corr_length_m.  Seeded through
    `seeds.task_rng(seed, 0)`: the same arguments give the same relief.  The short form of
    `relief_from_spec(RandomFieldSpec(...), seed)`, which also takes anisotropy and exact_rms.
    """
    nx = int(n)
    spec = RandomFieldSpec(nx=nx, ny=nx if ny is None else int(ny), pitch_m=pitch_m, rms_height_m=rms_height_m,
                           corr_length_m=corr_length_m, kind=kind)
    return relief_from_spec(spec, seed)


@dataclass(frozen=True)
class DotPattern:
    """A light-guide-plate dot pattern (see `lgp_dots`): dot spacing, radius and height in metres.

    shape "cap" or "gaussian"; jitter: fraction of the spacing the dots wander; micro_rms_m /
    micro_corr_m: Gaussian micro-roughness inside the dots (0 = none; default L = 4 pixels).
    """

    dot_pitch_m: float
    dot_radius_m: float
    dot_height_m: float
    shape: str = "cap"
    jitter: float = 0.2
    micro_rms_m: float = 0.0
    micro_corr_m: float | None = None


def lgp_dots(n: int, pitch_m: float, dots: DotPattern, seed: int = 0, ny: int | None = None) -> Relief:
    """Light-guide-plate dot pattern `dots` on a jittered square grid, periodic n x n (ny x n) tile.

    Each grid cell (spacing = tile / round(tile / dot_pitch), so the tile stays periodic)
    holds one dot displaced uniformly by up to +-jitter * spacing / 2 along x and y.
    shape "cap": spherical cap of base radius a and height h (sphere radius
    R = (a^2 + h^2) / (2 h)); "gaussian": h exp(-2 r^2 / a^2) (1/e^2 radius a), cut at 2a.
    A negative dot_height_m makes pits instead of bumps (etched or laser-marked plates).
    micro_rms_m > 0 adds Gaussian micro-roughness (correlation length micro_corr_m,
    default 4 pixels) inside the dots only, as on printed / moulded dots.
    Dots must not overlap: dot_radius (x2 for gaussian) + jitter * spacing / 2 < spacing / 2.
    """
    dot_pitch_m, dot_radius_m, dot_height_m = dots.dot_pitch_m, dots.dot_radius_m, dots.dot_height_m
    shape, jitter, micro_rms_m, micro_corr_m = dots.shape, dots.jitter, dots.micro_rms_m, dots.micro_corr_m
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
