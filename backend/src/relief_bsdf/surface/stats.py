"""Statistics of a height map: rms height and slope, autocorrelation, PSD, facet normals.

Conventions (all SI; x = columns with pitch dx, y = rows with pitch dy):

- **rms height** sigma: standard deviation of the heights after least-squares plane
  levelling (valid points only), as Gwyddion's mean-plane levelling (ISO 25178 Sq).
  Periodic reliefs are only mean-levelled (a plane is not periodic).
- **rms slope** (per axis): root mean square of forward differences between
  horizontally (vertically) adjacent valid pixels, (z[i, j+1] - z[i, j]) / dx; periodic
  reliefs include the wrap-around pair.  The magnitude is
  rms_slope = sqrt(rms_slope_x^2 + rms_slope_y^2) (= 2 sigma / L for the Gaussian
  autocovariance sigma^2 exp(-r^2/L^2)).  A forward difference at pitch d sees the
  structure function D(d)/d^2 = 2 (C(0) - C(d)) / d^2, which underestimates the true rms
  slope by a relative d^2 / (4 L^2) for a Gaussian ACF (0.25 % at L = 10 d).  On AFM data
  the pixel-scale slope is noise and tip dominated: rms slope depends on the band limit.
- **autocorrelation** C(tx, ty) = <z(x, y) z(x + tx, y + ty)> of the levelled heights:
  circular for periodic reliefs, otherwise zero-padded FFT correlation divided by the
  number of overlapping valid pairs at each lag (unbiased estimator).
- **correlation length**: smallest radius at which the radially averaged C(r) / C(0)
  falls to 1/e (linear interpolation between annuli), searched up to half the smaller
  tile side; NaN if it never falls that low (the tile is too small for the relief).
  For C = s^2 exp(-r^2/L^2) or s^2 exp(-r/L) it returns L.
- **PSD** (2-D, m^4): psd = |FFT(w z)|^2 dx dy / (N sum-normalised window power), so that
  sum(psd) * dfx * dfy = sigma^2 (exact without window; the window-weighted variance
  with one), dfx = 1 / (nx dx).  Frequencies in cycles per metre (numpy FFT order).
- **facets**: the triangles of the piecewise-linear surface that `surface.mesh` builds and
  the ray tracer intersects: two per grid cell, split along the (i, j)-(i+1, j+1) diagonal
  (wrap-around cells too when periodic).  Triangle A = (00, 01, 11) has slopes
  ((z01 - z00) / dx, (z11 - z01) / dy), triangle B = (00, 11, 10) has ((z11 - z10) / dx,
  (z10 - z00) / dy) (zRC: R = row offset, C = column offset).  Every facet covers the
  projected area dx dy / 2.  Triangles with an invalid corner are NaN.

One slope definition: the x (y) components of the facet slopes are exactly the forward
differences along x (y), each edge counted twice, so on a periodic tile the rms facet slope
magnitude equals `rms_slope` (forward differences) to rounding; on a non-periodic map they
differ only by the weight of the border edges.  Every consumer (relief info, the fit's
microfacet alpha, the diagnosis, the facet-normal and microfacet methods) uses these
functions; central differences (np.gradient) are *not* used because they measure the slope
at twice the pitch (relative bias d^2 / L^2 on the rms instead of d^2 / (4 L^2)) and are not
the slope of any facet the tracer sees.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import scipy.fft as sfft

from relief_bsdf.core.microfacet import normals_from_slopes
from relief_bsdf.surface.relief import Relief


@dataclass(frozen=True)
class ReliefStats:
    """Summary statistics of a relief (see the module docstring for each estimator)."""

    shape: tuple[int, int]            # (ny, nx)
    pitch_m: tuple[float, float]      # (dx, dy)
    valid_fraction: float
    rms_height_m: float
    rms_slope_x: float
    rms_slope_y: float
    rms_slope: float
    correlation_length_m: float
    correlation_length_x_m: float
    correlation_length_y_m: float
    skewness: float
    kurtosis: float                   # not excess: 3 for Gaussian heights
    mean_height_m: float              # mean before levelling
    peak_to_valley_m: float           # after levelling

    def as_dict(self) -> dict:
        """JSON-ready dict (formats.md keys; NaN becomes None)."""
        d = asdict(self)
        d["shape"] = list(self.shape)
        d["pitch_m"] = list(self.pitch_m)
        for k, v in d.items():
            if isinstance(v, float) and not np.isfinite(v):
                d[k] = None
        return d


def levelled(relief: Relief) -> Relief:
    """Plane-levelled relief (mean-levelled when periodic), the basis of every statistic."""
    return relief.level(0 if relief.periodic else 1)


def _forward_differences(h: np.ndarray, periodic: bool, axis: int) -> np.ndarray:
    """Differences z[k+1] - z[k] along `axis`, NaN where either point is invalid."""
    if periodic:
        return np.roll(h, -1, axis=axis) - h
    return np.diff(h, axis=axis)


def slopes(relief: Relief) -> tuple[np.ndarray, np.ndarray]:
    """Forward-difference slopes (dz/dx on x-pairs, dz/dy on y-pairs); NaN where invalid."""
    h = relief.heights_m
    return (_forward_differences(h, relief.periodic, 1) / relief.dx_m,
            _forward_differences(h, relief.periodic, 0) / relief.dy_m)


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def rms_height(relief: Relief) -> float:
    """rms height (m) of the levelled relief over its valid points (module doc); NaN if none."""
    lv = levelled(relief)
    return _rms(lv.heights_m)


def rms_slope_xy(relief: Relief) -> tuple[float, float]:
    """(rms slope along x, along y) of the levelled relief: rms forward differences (module doc)."""
    sx, sy = slopes(levelled(relief))
    return _rms(sx), _rms(sy)


def rms_slope(relief: Relief) -> float:
    """rms slope magnitude sqrt(rms_x^2 + rms_y^2) of the levelled relief; what `relief info` prints.

    Equals the rms magnitude of the facet slopes (`facet_slopes`) on a periodic tile, and
    2 s / L for the Gaussian autocovariance s^2 exp(-r^2 / L^2) (up to d^2 / (4 L^2)).
    """
    return float(np.hypot(*rms_slope_xy(relief)))


def rms_height_and_slope(relief: Relief) -> tuple[float, float]:
    """(rms height in m, rms slope magnitude) of the levelled relief: the two figures every model uses."""
    return rms_height(relief), rms_slope(relief)


def relief_stats(relief: Relief) -> ReliefStats:
    """rms height, slopes, correlation lengths and moments of `relief` (valid points only)."""
    relief.require_valid()
    mean = float(np.nanmean(relief.heights_m))
    lv = levelled(relief)
    z = lv.heights_m[lv.valid]
    sigma = float(np.sqrt(np.mean(z * z)))
    if sigma > 0:
        skew = float(np.mean(z**3) / sigma**3)
        kurt = float(np.mean(z**4) / sigma**4)
    else:
        skew = kurt = float("nan")
    rx, ry = rms_slope_xy(relief)
    lags_x, lags_y, acf = acf_2d(lv, level=False)
    return ReliefStats(shape=relief.shape, pitch_m=(relief.dx_m, relief.dy_m),
                       valid_fraction=relief.valid_fraction, rms_height_m=sigma,
                       rms_slope_x=rx, rms_slope_y=ry, rms_slope=float(np.hypot(rx, ry)),
                       correlation_length_m=_radial_one_over_e(lags_x, lags_y, acf, relief),
                       correlation_length_x_m=_axis_one_over_e(lags_x, acf[int(np.argmin(np.abs(lags_y))), :], relief.size_m[0]),
                       correlation_length_y_m=_axis_one_over_e(lags_y, acf[:, int(np.argmin(np.abs(lags_x)))], relief.size_m[1]),
                       skewness=skew, kurtosis=kurt, mean_height_m=mean,
                       peak_to_valley_m=float(np.ptp(z)) if z.size else float("nan"))


# ---------------------------------------------------------------- autocorrelation


def acf_2d(relief: Relief, level: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Autocovariance C(tx, ty) in m^2, centred: returns (lags_x_m, lags_y_m, acf[ny_l, nx_l]).

    Periodic reliefs: circular correlation, lags -n/2 .. n/2-1 (acf shape = relief shape).
    Otherwise: zero-padded FFT correlation of the valid points divided by the number
    of valid pairs at each lag, lags -(n-1) .. n-1; lags with no pair are NaN.
    acf at zero lag (the centre) is the variance of the levelled heights.
    """
    lv = levelled(relief) if level else relief
    h = lv.heights_m
    m = lv.valid
    z = np.where(m, h, 0.0)
    ny, nx = h.shape
    if relief.periodic and m.all():
        F = sfft.rfft2(z, workers=-1)
        acf = sfft.irfft2(np.abs(F) ** 2, s=(ny, nx), workers=-1) / (nx * ny)
        acf = np.fft.fftshift(acf)
        lx = (np.arange(nx) - nx // 2) * relief.dx_m
        ly = (np.arange(ny) - ny // 2) * relief.dy_m
        return lx, ly, acf
    sy, sx = 2 * ny - 1, 2 * nx - 1
    fy, fx = _fast_len(sy), _fast_len(sx)
    Fz = sfft.rfft2(z, s=(fy, fx), workers=-1)
    num = sfft.irfft2(np.abs(Fz) ** 2, s=(fy, fx), workers=-1)
    if m.all():
        # every point valid: the number of pairs at lag (ty, tx) is (ny - |ty|)(nx - |tx|)
        cy = ny - np.abs(np.fft.fftfreq(fy, 1.0 / fy)).astype(int)
        cx = nx - np.abs(np.fft.fftfreq(fx, 1.0 / fx)).astype(int)
        cnt = np.clip(cy, 0, None)[:, None] * np.clip(cx, 0, None)[None, :].astype(float)
    else:
        Fm = sfft.rfft2(m.astype(float), s=(fy, fx), workers=-1)
        cnt = sfft.irfft2(np.abs(Fm) ** 2, s=(fy, fx), workers=-1)
    # rearrange lags -(n-1)..(n-1) to the centre
    idx_y = np.r_[fy - (ny - 1):fy, 0:ny]
    idx_x = np.r_[fx - (nx - 1):fx, 0:nx]
    num = num[np.ix_(idx_y, idx_x)]
    cnt = np.rint(cnt[np.ix_(idx_y, idx_x)])
    with np.errstate(invalid="ignore", divide="ignore"):
        acf = np.where(cnt >= 1, num / np.maximum(cnt, 1), np.nan)
    lx = np.arange(-(nx - 1), nx) * relief.dx_m
    ly = np.arange(-(ny - 1), ny) * relief.dy_m
    return lx, ly, acf


def _fast_len(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (fast FFT size)."""
    best = 1 << (int(n) - 1).bit_length()
    p5 = 1
    while p5 < 2 * n:
        p35 = p5
        while p35 < 2 * n:
            p = p35
            while p < n:
                p *= 2
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


def _first_crossing(r: np.ndarray, c: np.ndarray, level: float) -> float:
    """Linear interpolation of the first r where c drops below `level` (c[0] = 1 expected)."""
    ok = np.isfinite(c)
    r, c = r[ok], c[ok]
    below = np.nonzero(c < level)[0]
    if below.size == 0 or below[0] == 0:
        return float("nan")
    k = below[0]
    r0, r1, c0, c1 = r[k - 1], r[k], c[k - 1], c[k]
    return float(r0 + (c0 - level) * (r1 - r0) / (c0 - c1))


def _axis_one_over_e(lags: np.ndarray, acf_line: np.ndarray, tile_m: float) -> float:
    """1/e point of a 1-D cut through the centred ACF (positive lags up to half the tile)."""
    c0 = int(np.argmin(np.abs(lags)))
    if not acf_line[c0] > 0:                 # a flat map: no variance, no correlation length
        return float("nan")
    pos = lags[c0:]
    keep = pos <= 0.5 * tile_m
    return _first_crossing(pos[keep], acf_line[c0:][keep] / acf_line[c0], np.exp(-1.0))


def _radial_one_over_e(lx: np.ndarray, ly: np.ndarray, acf: np.ndarray, relief: Relief) -> float:
    lxmax, lymax = relief.size_m
    # only lags up to half the tile are used: average over that window, not the whole ACF
    half = 0.5 * min(lxmax, lymax) * (1 + 1e-9)
    kx = np.abs(lx) <= half + abs(lx[1] - lx[0]) if lx.size > 1 else np.ones(lx.size, bool)
    ky = np.abs(ly) <= half + abs(ly[1] - ly[0]) if ly.size > 1 else np.ones(ly.size, bool)
    c0 = acf[np.argmin(np.abs(ly)), np.argmin(np.abs(lx))]
    if not c0 > 0:                           # a flat map: no variance, no correlation length
        return float("nan")
    r_centres, c = radial_average(lx[kx], ly[ky], acf[np.ix_(ky, kx)])
    c = c / c0
    keep = r_centres <= 0.5 * min(lxmax, lymax)
    return _first_crossing(r_centres[keep], c[keep], np.exp(-1.0))


def radial_average(kx: np.ndarray, ky: np.ndarray, values: np.ndarray,
                   bin_width: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Average `values[ny, nx]` on a (ky, kx) grid over annuli of |k|; first bin is k = 0.

    Returns (mean radius of each annulus, mean value); empty annuli are dropped.  The
    default bin width is the coarser grid step, so each annulus holds points on the
    finer axis too.
    """
    KX, KY = np.meshgrid(kx, ky)
    r = np.hypot(KX, KY)
    if bin_width is None:
        steps = [abs(a[1] - a[0]) for a in (kx, ky) if len(a) > 1]
        bin_width = max(steps)
    idx = np.floor(r / bin_width + 0.5).astype(int).ravel()
    v = values.ravel()
    ok = np.isfinite(v)
    n = np.bincount(idx[ok], minlength=idx.max() + 1)
    s = np.bincount(idx[ok], weights=v[ok], minlength=idx.max() + 1)
    sr = np.bincount(idx[ok], weights=r.ravel()[ok], minlength=idx.max() + 1)
    has = n > 0
    return sr[has] / n[has], s[has] / n[has]


# ---------------------------------------------------------------- power spectral density


def psd_2d(relief: Relief, window: str | None = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-sided 2-D PSD of the levelled heights: (fx, fy, psd[ny, nx]) in 1/m and m^4.

    window: "hann" (separable Hann, for measured non-periodic maps, suppresses the
        edge discontinuity), None (no window; right for periodic tiles) or "auto"
        (None when periodic, else "hann").
    Normalisation: sum(psd) * dfx * dfy equals the mean of (w z)^2 over the valid
    points divided by the mean of w^2 there: exactly sigma^2 with no window.  Invalid
    points are set to zero after levelling and the normalisation uses only the valid
    ones (fine for scattered holes; large gaps bias the spectrum).
    fx, fy are in numpy FFT order (np.fft.fftfreq); use np.fft.fftshift to plot.
    """
    if window == "auto":
        window = None if relief.periodic else "hann"
    if window not in (None, "hann"):
        raise ValueError(f"psd_2d: window must be 'hann', None or 'auto', got {window!r}")
    lv = levelled(relief)
    ny, nx = lv.shape
    m = lv.valid
    z = np.where(m, lv.heights_m, 0.0)
    if window == "hann":
        w = np.outer(np.hanning(ny + 2)[1:-1], np.hanning(nx + 2)[1:-1])
    else:
        w = np.ones((ny, nx))
    power = np.mean((w * w)[m])
    n_valid = m.sum()
    F = np.fft.fft2(z * w)
    psd = np.abs(F) ** 2 * lv.dx_m * lv.dy_m / (n_valid * power)
    fx = np.fft.fftfreq(nx, lv.dx_m)
    fy = np.fft.fftfreq(ny, lv.dy_m)
    return fx, fy, psd


def radial_psd(relief: Relief, window: str | None = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Radially averaged 2-D PSD: (f in cycles/m, psd in m^4).

    For an isotropic relief sum over annuli of 2 pi f psd(f) df approximates sigma^2.
    """
    fx, fy, psd = psd_2d(relief, window)
    return radial_average(np.fft.fftshift(fx), np.fft.fftshift(fy), np.fft.fftshift(psd))


# ---------------------------------------------------------------- facets and slope histogram


def facet_slopes(relief: Relief) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (dz/dx, dz/dy) of the mesh triangles, each (2, ny-1, nx-1), or (2, ny, nx) if periodic.

    Index 0 along the first axis is triangle A = (00, 01, 11), index 1 triangle B = (00, 11, 10)
    (module doc); NaN for triangles with an invalid corner.
    """
    h = relief.heights_m
    if relief.periodic:
        h00 = h
        h01 = np.roll(h, -1, axis=1)
        h10 = np.roll(h, -1, axis=0)
        h11 = np.roll(h10, -1, axis=1)
    else:
        h00, h01, h10, h11 = h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:]
    sx = np.stack([h01 - h00, h11 - h10]) / relief.dx_m
    sy = np.stack([h11 - h01, h10 - h00]) / relief.dy_m
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(sx) & np.isfinite(sy))
    sx[bad] = np.nan
    sy[bad] = np.nan
    return sx, sy


def facet_normals(relief: Relief) -> np.ndarray:
    """Unit normals (2, ..., 3) of the mesh triangles, (-sx, -sy, 1) / sqrt(1 + sx^2 + sy^2).

    Each triangle covers the projected area dx * dy / 2; its true area is that times
    sqrt(1 + sx^2 + sy^2) = 1 / n_z.  NaN for triangles with an invalid corner.
    """
    sx, sy = facet_slopes(relief)
    return normals_from_slopes(sx, sy)


def slope_histogram(relief: Relief, bins: Any = 64, max_slope: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2-D histogram of facet slopes: (edges_sx, edges_sy, density[n_sx, n_sy]).

    density is per unit slope-plane area and per unit projected surface area:
    sum(density) * dsx * dsy = fraction of valid facets inside the range (1 if none
    is outside).  Range: +-max_slope on both axes (default: 4 times the larger rms
    facet slope, at least covering the largest slope when it is smaller).
    """
    sx, sy = facet_slopes(relief)
    ok = np.isfinite(sx) & np.isfinite(sy)
    if not ok.any():
        relief.require_valid(1.0)
        raise ValueError("no valid facet")
    a, b = sx[ok], sy[ok]
    if max_slope is None:
        rms = max(np.sqrt(np.mean(a * a)), np.sqrt(np.mean(b * b)))
        max_slope = float(min(4 * rms, max(np.abs(a).max(), np.abs(b).max()))) or 1e-12
        max_slope = max(max_slope, 1e-12)
    rng = [[-max_slope, max_slope], [-max_slope, max_slope]]
    counts, ex, ey = np.histogram2d(a, b, bins=bins, range=rng)
    area = np.outer(np.diff(ex), np.diff(ey))
    return ex, ey, counts / (ok.sum() * area)


# ---------------------------------------------------------------- measured maps as they are


@dataclass(frozen=True)
class BandLimit:
    """A relief low-passed to the spatial frequencies that scatter into propagating directions.

    f_max_per_m: the cut-off |f| (cycles/m); removed_rms_m / removed_rms_slope: rms height and
    rms slope of what was removed (the difference map); kept_rms_m: rms of what remains.
    """

    relief: Relief
    f_max_per_m: float
    removed_rms_m: float
    removed_rms_slope: float
    kept_rms_m: float

    def statement(self) -> str:
        return (f"band-limited to |f| <= {self.f_max_per_m * 1e-6:.3g} /um (propagating scatter): removed "
                f"{self.removed_rms_m * 1e9:.3g} nm rms height, {self.removed_rms_slope:.3g} rms slope; kept "
                f"{self.kept_rms_m * 1e9:.3g} nm rms")


def propagating_f_max(wavelength_nm: float, n_incident: float, n_scatter: float, theta_i_max_deg: float) -> float:
    """|f| (cycles/m) of the finest relief component that scatters into a propagating direction:
    (n1 sin t_i,max + n_s) / lambda (first-order grating equation)."""
    return (n_incident * np.sin(np.radians(theta_i_max_deg)) + n_scatter) / (wavelength_nm * 1e-9)


def band_limited(relief: Relief, f_max_per_m: float) -> BandLimit:
    """Levelled heights with every Fourier component above f_max_per_m removed (sharp disc in f).

    Non-periodic maps are mirrored to twice their size first (no wrap-around edge); invalid
    points are set to the mean plane (0) for the transform and stay invalid in the result.
    """
    lv = levelled(relief)
    m = lv.valid
    z = np.where(m, lv.heights_m, 0.0)
    ny, nx = z.shape
    big = z if relief.periodic else np.block([[z, z[:, ::-1]], [z[::-1, :], z[::-1, ::-1]]])
    fx = np.fft.fftfreq(big.shape[1], relief.dx_m)
    fy = np.fft.fftfreq(big.shape[0], relief.dy_m)
    keep = fx[None, :] ** 2 + fy[:, None] ** 2 <= f_max_per_m ** 2
    zl = np.real(np.fft.ifft2(np.fft.fft2(big) * keep))[:ny, :nx]
    out = lv.with_heights(np.where(m, zl, np.nan), f"band-limited to |f| <= {f_max_per_m:.4g} /m")
    diff = lv.with_heights(np.where(m, z - zl, np.nan), "removed part")
    return BandLimit(relief=out, f_max_per_m=float(f_max_per_m), removed_rms_m=_rms((z - zl)[m]),
                     removed_rms_slope=rms_slope(diff), kept_rms_m=_rms(zl[m]))


@dataclass(frozen=True)
class NoiseFloor:
    """White-noise floor of a measured map from its PSD (see `noise_floor`)."""

    psd_m4: float                 # 2-D PSD level of the floor
    rms_m: float                  # rms height of white noise at that level over the map's band
    fraction_of_rms: float        # rms_m / rms height of the map
    slope_rms: float              # rms slope such noise adds (forward differences)

    def statement(self) -> str:
        share = (f"{self.fraction_of_rms:.1%} of the heights" if np.isfinite(self.fraction_of_rms)
                 else "the map is flat")
        return (f"PSD noise floor {self.psd_m4:.3g} m^4: white noise of {self.rms_m * 1e9:.3g} nm rms "
                f"({share}) adding {self.slope_rms:.3g} rms slope")


def noise_floor(relief: Relief) -> NoiseFloor:
    """Noise floor = median of the 2-D PSD over the outer annulus (0.8-1 of the Nyquist radius of
    the coarser axis), where a measured surface's PSD has usually fallen to the instrument's white
    noise.  White noise of PSD level P over the band [-1/(2dx), 1/(2dx)] x [-1/(2dy), 1/(2dy)] has
    variance P / (dx dy), and forward-difference slope variance 2 P / (dx dy) (1/dx^2 + 1/dy^2)
    (uncorrelated pixels).  An upper estimate when the surface itself still has power there."""
    fx, fy, psd = psd_2d(relief)
    fr = np.hypot(fx[None, :] * (2 * relief.dx_m), fy[:, None] * (2 * relief.dy_m))  # 1 at each axis's Nyquist
    ring = (fr >= 0.8) & (fr <= 1.0)
    P = float(np.median(psd[ring])) if ring.any() else 0.0
    var = P / (relief.dx_m * relief.dy_m)
    sigma = rms_height(relief)
    return NoiseFloor(psd_m4=P, rms_m=float(np.sqrt(var)), fraction_of_rms=float(np.sqrt(var) / sigma) if sigma > 0
                      else float("nan"), slope_rms=float(np.sqrt(2 * var * (relief.dx_m ** -2 + relief.dy_m ** -2))))


def slope_tensor(relief: Relief) -> np.ndarray:
    """2 x 2 rms slope tensor <g g^T> of the levelled relief, g = (dz/dx, dz/dy) per grid cell.

    g of a cell is the mean of its two triangles' facet slopes (`facet_slopes`: the two forward
    differences along each axis), the gradient at the centre of the bilinear cell, so both
    components belong to the same place.  (Pairing one triangle's x and y slopes instead correlates
    them through the shared corner: uncorrelated pixel noise would look anisotropic, ratio sqrt(3).)
    In geometric optics the lobe's covariance follows this tensor (anisotropic Beckmann: Walter et
    al. 2007 / Heitz 2014, slope covariance), so its eigenvalues are the rms slopes along and across
    the lay whatever the map's orientation; trace = rms_slope^2 up to the cell averaging.
    """
    sx, sy = facet_slopes(levelled(relief))
    gx, gy = sx.mean(axis=0), sy.mean(axis=0)
    ok = np.isfinite(gx) & np.isfinite(gy)
    gx, gy = gx[ok], gy[ok]
    if gx.size == 0:
        return np.full((2, 2), np.nan)
    return np.array([[np.mean(gx * gx), np.mean(gx * gy)], [np.mean(gx * gy), np.mean(gy * gy)]])


@dataclass(frozen=True)
class MapFlags:
    """Flags of a measured map that change its BSDF (`map_flags`)."""

    kurtosis: float
    spiky: bool                   # kurtosis > 5: spikes / outliers dominate the high moments
    anisotropy: float             # ratio of the largest to the smallest rms slope over all directions
    anisotropic: bool             # anisotropy > 1.5
    lay_angle_deg: float = float("nan")   # direction of the smallest rms slope (the lay), deg from +x, [0, 180)

    def statements(self) -> list[str]:
        out = []
        if self.spiky:
            out.append(f"spiky: kurtosis {self.kurtosis:.3g} >> 3 (Gaussian): spikes or outliers raise the wide-angle "
                       "scatter and lower the coherent specular part beyond what the rms height says; remove "
                       "outliers before reconstructing if they are measurement artefacts")
        if self.anisotropic:
            out.append(f"anisotropic: rms slopes differ {self.anisotropy:.3g}x between along the lay "
                       f"({self.lay_angle_deg:.0f} deg from x) and across it: the BSDF is not rotationally symmetric "
                       "(lobes stretched across the lay); keep phi_i and the azimuth cells")
        return out


def map_flags(relief: Relief) -> MapFlags:
    """Spike flag from the height kurtosis; anisotropy from the eigenvalues of `slope_tensor`
    (rotation invariant: a lay at 45 deg to the pixel axes is found as one along x)."""
    st = relief_stats(relief)
    t = slope_tensor(relief)
    if not np.all(np.isfinite(t)):
        return MapFlags(kurtosis=st.kurtosis, spiky=bool(st.kurtosis > 5.0), anisotropy=float("nan"),
                        anisotropic=False)
    ev, vec = np.linalg.eigh(t)                                   # ascending: ev[0] along the lay
    a = float(np.sqrt(max(ev[1], 0.0) / max(ev[0], 1e-300)))
    lay = float(np.degrees(np.arctan2(vec[1, 0], vec[0, 0])) % 180.0)
    return MapFlags(kurtosis=st.kurtosis, spiky=bool(st.kurtosis > 5.0), anisotropy=a, anisotropic=bool(a > 1.5),
                    lay_angle_deg=lay)
