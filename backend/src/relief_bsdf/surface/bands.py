"""A relief split at one spatial frequency into a large scale and a fine scale (two-scale models).

The composite ("two-scale") scattering model (Bass & Fuks, *Wave Scattering from Statistically
Rough Surfaces*, 1979, ch. 5; Valenzuela, Boundary-Layer Meteorology 13 (1978) 61; Brown, IEEE
Trans. Antennas Propag. 26 (1978) 472) treats the height spectrum above a cut-off |f| > f_c as a
small perturbation riding on the facets of the spectrum below it.  Here

    h = h_L + h_F,   h_L = the relief low-passed to |f| <= f_c (`stats.band_limited`: a sharp disc
                     in f, mirrored to twice its size first for a non-periodic map),
                     h_F = h - h_L (valid points; levelled).

Spectral figures (`BandSpectrum`): the periodogram of the levelled heights (the same mirror
extension as the split, so the spectrum and the split agree), sorted by |f|, gives for every
candidate cut in one pass the fine scale's variance sigma_F^2(f_c) = sum_{|f| > f_c} P (and its
part inside the propagating band) and the large scale's rms mean curvature from *second
differences* (the transfer function of (h_xx + h_yy) / 2 on the grid, so it is the figure
`methods.auto.rms_curvature` computes on the split map).

The cut (`two_scale_cut`): the LOWEST f_c at which the fine scale is optically smooth,
g_F = (4 pi n sigma_F,prop / lambda)^2 <= g_cut (sigma_F,prop: the fine scale inside the
propagating band; n the largest incident index, lambda the shortest wavelength).  Lowest,
because every component left in the large scale is treated by geometric optics, which needs it
rough on the wavelength scale (phase variance >> 1); the perturbation (Rayleigh-Rice) treatment
of the fine scale holds for any lateral scale as long as g_F is small.  Whether the large scale
is then a valid geometric-optics surface (facets >> lambda: k R_c, correlation length, no
coherent part) is for the caller to judge on `BandSplit.large` (methods.auto).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import band_limited, levelled, rms_height


@dataclass(frozen=True)
class BandSpectrum:
    """Periodogram samples of the levelled relief sorted by |f|: radii f_per_m (1/m), power (m^2 per
    sample, summing to the mean square height) and the second-difference mean-curvature transfer
    |T(f)|^2 (1/m^4) of each sample."""

    f_per_m: np.ndarray
    power_m2: np.ndarray
    curv2_per_m4: np.ndarray

    @classmethod
    def of(cls, relief: Relief) -> "BandSpectrum":
        lv = levelled(relief)
        z = np.where(lv.valid, lv.heights_m, 0.0)
        big = z if relief.periodic else np.block([[z, z[:, ::-1]], [z[::-1, :], z[::-1, ::-1]]])
        ny, nx = big.shape
        P = np.abs(np.fft.fft2(big)) ** 2 / (nx * ny) ** 2
        fx = np.fft.fftfreq(nx, relief.dx_m)
        fy = np.fft.fftfreq(ny, relief.dy_m)
        tx = (2.0 - 2.0 * np.cos(2 * np.pi * fx * relief.dx_m)) / relief.dx_m ** 2
        ty = (2.0 - 2.0 * np.cos(2 * np.pi * fy * relief.dy_m)) / relief.dy_m ** 2
        T2 = (0.5 * (tx[None, :] + ty[:, None])) ** 2
        fr = np.hypot(fx[None, :], fy[:, None]).ravel()
        o = np.argsort(fr, kind="stable")
        return cls(fr[o], P.ravel()[o], T2.ravel()[o])

    def fine_variance(self, f_cut_per_m, f_prop_per_m: float = np.inf) -> np.ndarray:
        """sigma_F^2 (m^2) of the components f_cut < |f| <= f_prop, for each f_cut (array)."""
        c = np.concatenate([[0.0], np.cumsum(self.power_m2)])
        lo = np.searchsorted(self.f_per_m, np.asarray(f_cut_per_m, float), side="right")
        hi = np.searchsorted(self.f_per_m, f_prop_per_m, side="right")
        return np.maximum(c[hi] - c[np.minimum(lo, hi)], 0.0)

    def fine_slope(self, f_cut_per_m: float, f_prop_per_m: float = np.inf) -> float:
        """rms slope magnitude of the components f_cut < |f| <= f_prop (continuous derivative, 2 pi f)."""
        m = (self.f_per_m > f_cut_per_m) & (self.f_per_m <= f_prop_per_m)
        return float(np.sqrt(np.sum((2 * np.pi * self.f_per_m[m]) ** 2 * self.power_m2[m])))

    def large_curvature(self, f_cut_per_m) -> np.ndarray:
        """rms mean curvature (1/m, second differences) of the components |f| <= f_cut."""
        c = np.concatenate([[0.0], np.cumsum(self.power_m2 * self.curv2_per_m4)])
        return np.sqrt(np.maximum(c[np.searchsorted(self.f_per_m, np.asarray(f_cut_per_m, float), side="right")],
                                  0.0))


@dataclass(frozen=True)
class BandSplit:
    """h = large + fine at f_cut_per_m (module doc): both as Reliefs on the original grid, and the
    fine scale's rms height in all and inside the propagating band."""

    large: Relief
    fine: Relief
    f_cut_per_m: float
    fine_rms_m: float
    fine_rms_prop_m: float
    large_rms_m: float

    def statement(self) -> str:
        return (f"split at |f| = {self.f_cut_per_m * 1e-6:.3g} /um (period {1e6 / max(self.f_cut_per_m, 1e-300):.3g} um): "
                f"large scale {self.large_rms_m * 1e9:.4g} nm rms, fine scale {self.fine_rms_m * 1e9:.3g} nm rms "
                f"({self.fine_rms_prop_m * 1e9:.3g} nm inside the propagating band)")


def band_split(relief: Relief, f_cut_per_m: float, f_prop_per_m: float = np.inf,
               spectrum: BandSpectrum | None = None) -> BandSplit:
    """The relief split at f_cut_per_m (module doc); f_prop_per_m: the propagating band's edge for the
    fine scale's in-band rms; spectrum: the relief's BandSpectrum if already computed."""
    bl = band_limited(relief, f_cut_per_m)
    lv = levelled(relief)
    fine = lv.with_heights(lv.heights_m - bl.relief.heights_m, f"fine scale: |f| > {f_cut_per_m:.4g} /m")
    spec = spectrum if spectrum is not None else BandSpectrum.of(relief)
    prop = float(np.sqrt(spec.fine_variance(f_cut_per_m, f_prop_per_m)))
    return BandSplit(large=bl.relief, fine=fine, f_cut_per_m=float(f_cut_per_m), fine_rms_m=rms_height(fine),
                     fine_rms_prop_m=prop, large_rms_m=rms_height(bl.relief))


def two_scale_cut(spectrum: BandSpectrum, wavelength_m: float, n_incident: float, f_prop_per_m: float,
                  g_cut: float) -> float:
    """The lowest cut-off |f| (1/m) at which the fine scale's Rayleigh parameter
    (4 pi n sigma_F,prop / lambda)^2 is at most g_cut (module doc); 0 when the whole relief is
    optically smooth (no large scale)."""
    sig_max = np.sqrt(g_cut) * wavelength_m / (4 * np.pi * n_incident)
    radii = np.unique(spectrum.f_per_m)
    var = spectrum.fine_variance(radii, f_prop_per_m)
    ok = np.nonzero(var <= sig_max ** 2)[0]
    return float(radii[ok[0]]) if ok.size else float(radii[-1])
