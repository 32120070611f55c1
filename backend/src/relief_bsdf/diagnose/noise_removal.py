"""Relief smoothing as removal of the map's own measurement noise (a Wiener filter at its PSD floor).

A measured height map is the true relief plus the instrument's noise, h_map = h + e.  Where that
noise is white (uncorrelated pixels: a profilometer's detector noise, the independent engine's
"relief smoothing"), its 2-D PSD is a constant N over the whole band, and the map's own spectrum
shows it as the floor its PSD falls to near the Nyquist frequency (`surface.stats.noise_floor`, the
estimator `relief info` prints: the median PSD over the outer annulus, 0.8-1 of the Nyquist
radius).  The least-squares estimate of h from h_map is then the Wiener filter (Wiener 1949;
Press et al., Numerical Recipes 13.3):

    H(f) = S(f) / (S(f) + N) = max(0, 1 - N / P(f)),     h_est = IFFT(H FFT(h_map))

with P = S + N the map's PSD, estimated from its periodogram smoothed over a box of
SMOOTH_BINS x SMOOTH_BINS frequency samples (wrapped), so one sample's scatter (the periodogram of
a Gaussian field is exponential about its mean) does not switch H on and off.  Where the surface
dominates (P >> N) the heights are kept; where the floor dominates (the band the noise fills) they
are removed; in between they are weighed.  A Gaussian filter (`surface.operations.scale_and_filter`,
the paper's) instead lowers every frequency by exp(-2 pi^2 sigma^2 f^2): it removes noise and
surface alike at high f, and blunts a feature whose own spectrum reaches high f (a dot's edge).
When the noise is white, the Wiener filter holds; when the map's excess is a smooth blur of the
surface (a tip or an optical transfer function: no flat floor), the Gaussian is the model.  The
diagnosis offers both as the one effect relief_smoothing and keeps the one with the lower
information criterion (`effects.relief_smoothing`).

The filter is derived on the levelled map (`surface.stats.levelled`, as every figure of the relief)
and what it removes is subtracted from the map as it is (its plane and periodicity kept); a non-periodic
map is mirrored to twice its size (as `surface.stats.band_limited`), invalid points are set to the
mean plane for the transform and stay invalid.
"""
from __future__ import annotations

import numpy as np

from relief_bsdf.surface.relief import Relief

SMOOTH_BINS = 5


def wiener_gain(relief: Relief) -> tuple[np.ndarray, float]:
    """(H on the FFT grid of the (mirrored) levelled map, N the floor's PSD level in m^4)."""
    from scipy.ndimage import uniform_filter

    from relief_bsdf.surface.stats import levelled, noise_floor
    lv = levelled(relief)
    z = np.where(lv.valid, lv.heights_m, 0.0)
    big = z if relief.periodic else np.block([[z, z[:, ::-1]], [z[::-1, :], z[::-1, ::-1]]])
    ny, nx = big.shape
    F = np.fft.fft2(big)
    psd = np.abs(F) ** 2 * relief.dx_m * relief.dy_m / (nx * ny)     # psd_2d's normalisation, no window
    smooth = uniform_filter(psd, size=SMOOTH_BINS, mode="wrap")
    N = float(noise_floor(relief).psd_m4)
    H = np.clip(1.0 - N / np.maximum(smooth, 1e-300), 0.0, 1.0)
    H[0, 0] = 1.0
    return H, N


def remove_noise(relief: Relief) -> Relief:
    """The map with its white-noise floor removed by the Wiener filter (module docstring)."""
    from relief_bsdf.surface.stats import levelled
    lv = levelled(relief)
    ny, nx = lv.shape
    z = np.where(lv.valid, lv.heights_m, 0.0)
    big = z if relief.periodic else np.block([[z, z[:, ::-1]], [z[::-1, :], z[::-1, ::-1]]])
    H, N = wiener_gain(relief)
    removed = np.real(np.fft.ifft2(np.fft.fft2(big) * (1.0 - H)))[:ny, :nx]
    return relief.with_heights(np.where(lv.valid, relief.heights_m - removed, np.nan),
                               f"measurement noise removed: Wiener filter at the map's PSD floor {N:.3g} m^4")
