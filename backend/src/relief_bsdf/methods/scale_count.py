"""Does a relief have a second scale?  A test of a two-scale spectrum against a one-scale one.

`auto` may choose the two-scale composite only where the height spectrum holds two scales; the
split of `surface.bands` finds *a* cut in any spectrum (the tail of one scale above the cut is
a "fine scale" by construction), so the split alone cannot tell.  Here the relief's own 2-D
periodogram decides, by the project's one information criterion (`criteria`).

Models (2-D PSD, f = (f_x, f_y) rotated by the lay angle phi into (u, v)):

    one scale:   S_1(f) = A C(q^2; nu) + N
    two scales:  S_2(f) = A_L C(q_L^2; nu_L) + A_F C(q_F^2; nu_F) + N
    C(q^2; nu) = (1 + q^2 / (nu + 1))^-(nu + 1),   q^2 = pi^2 (l_u^2 u^2 + l_v^2 v^2)

C is the von Karman (Matern) spectrum: nu = 1/2 is the exponential autocovariance, nu -> infinity
the Gaussian exp(-q^2) (autocovariance s^2 exp(-r^2 / l^2)); each scale has its own lengths along
and across its lay (an anisotropic relief is ONE scale with two lengths), N is the white floor of
the instrument's noise (not a scale).  Parameters: one scale k_1 = 6 (ln A, ln l_u, ln l_v, phi,
ln nu, ln N), two scales k_2 = 11.

Data: the periodogram of the levelled heights (`surface.bands.BandSpectrum`'s extension: the map
itself when periodic, else mirrored), the half plane f_y > 0 or (f_y = 0, f_x > 0) (the other half
is its mirror), averaged in polar bins (BINS_RADIAL log-spaced radii from the tile's fundamental to
the Nyquist radius of the coarser axis, BINS_ANGULAR sectors of the half turn).  The mean of m
periodogram samples of one PSD level S is Gamma(m, S / m) (each sample exponential, Whittle's
approximation), so ln P_bin has mean ln S_bin + psi(m) - ln m and variance psi'(m) (digamma,
trigamma): the misfit is chi^2 = sum over bins of (ln P_bin - ln S_bin - psi(m) + ln m)^2 / psi'(m),
S_bin the model averaged over the bin's own samples.

Decision: the QBIC gain (`criteria.bic_gain` with the two-scale model's overdispersion
c = chi^2_2 / (n - k_2), Burnham & Anderson 2002): a spectrum neither model follows (dots, a
measured scan) has c >> 1 and its chi^2 differences are discounted by c, so only a second scale
that the spectrum shows well beyond the one-scale family's shape errors passes.  Two scales exist
when the gain exceeds BIC_MARGIN = 10 ("very strong", Kass & Raftery 1995) AND the two fitted
components are separated, l_L / l_F >= 2 (geometric means over the axes), and the fine one is
seen: it carries most of the model's power in at least one bin (an optically smooth haze has a
tiny share of the height variance, so no share of the variance is asked).  Fits: scipy least_squares (trust region, bounded) from a few starts each
(the one-scale fit from the relief's correlation length and slope tensor; the two-scale fit from
the one-scale fit plus a component at a tenth and at a third of its length, and from the band
split's two lengths when given); the best of each kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, special

from relief_bsdf.criteria import BIC_MARGIN, bic_gain, overdispersion

BINS_RADIAL = 24
BINS_ANGULAR = 12
MIN_SEPARATION = 2.0          # l_L / l_F (geometric mean of the axes) of two distinct scales
NU_BOUNDS = (0.3, 1e5)        # exponential (0.5) to Gaussian (infinity)
MODEL_SAMPLES = 64            # samples per bin the model's bin mean is taken over
DYNAMIC_RANGE = 1e-12         # bins whose mean power is below this share of the largest bin's are left out


@dataclass(frozen=True)
class ScaleTest:
    """The test's numbers: chi^2 and parameter counts of both models on n bins, the QBIC gain, the
    two-scale fit's lengths (geometric mean over the axes, m) and variance shares, and the verdict."""

    n_bins: int
    chi2_one: float
    chi2_two: float
    k_one: int
    k_two: int
    qbic_gain: float
    large_length_m: float
    fine_length_m: float
    fine_share: float
    two_scales: bool

    def statement(self) -> str:
        if self.two_scales:
            return (f"two scales in the spectrum: QBIC gain {self.qbic_gain:.3g} > {BIC_MARGIN:g} over one scale "
                    f"(chi2 {self.chi2_one:.4g} -> {self.chi2_two:.4g} on {self.n_bins} bins), lengths "
                    f"{self.large_length_m * 1e6:.3g} / {self.fine_length_m * 1e6:.3g} um, fine share "
                    f"{self.fine_share:.1%}")
        return (f"one scale: a second scale in the spectrum gains QBIC {self.qbic_gain:.3g} (bar {BIC_MARGIN:g}; chi2 "
                f"{self.chi2_one:.4g} -> {self.chi2_two:.4g} on {self.n_bins} bins; lengths "
                f"{self.large_length_m * 1e6:.3g} / {self.fine_length_m * 1e6:.3g} um, fine share {self.fine_share:.1%})")


def _periodogram(relief):
    """(f_x, f_y, P) of the half plane, P in m^2 per sample (summing to the mean square height)."""
    from relief_bsdf.surface.stats import levelled
    lv = levelled(relief)
    z = np.where(lv.valid, lv.heights_m, 0.0)
    big = z if relief.periodic else np.block([[z, z[:, ::-1]], [z[::-1, :], z[::-1, ::-1]]])
    ny, nx = big.shape
    P = np.abs(np.fft.fft2(big)) ** 2 / (nx * ny) ** 2
    fx = np.fft.fftfreq(nx, relief.dx_m)[None, :] * np.ones((ny, 1))
    fy = np.fft.fftfreq(ny, relief.dy_m)[:, None] * np.ones((1, nx))
    half = (fy > 0) | ((fy == 0) & (fx > 0))
    return fx[half], fy[half], P[half], (nx * relief.dx_m, ny * relief.dy_m)


def _bins(fx, fy, tile):
    f = np.hypot(fx, fy)
    f_lo = 1.0 / max(tile)
    f_hi = min(np.max(np.abs(fx)), np.max(np.abs(fy)))
    keep = (f >= f_lo * 0.999) & (f <= f_hi)
    edges = np.geomspace(f_lo * 0.999, f_hi * 1.0001, BINS_RADIAL + 1)
    ir = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, BINS_RADIAL - 1)
    ang = np.mod(np.arctan2(fy, fx), np.pi)
    ia = np.clip((ang / np.pi * BINS_ANGULAR).astype(int), 0, BINS_ANGULAR - 1)
    label = np.where(keep, ir * BINS_ANGULAR + ia, -1)
    return label


def _component(fx, fy, ln_a, ln_lu, ln_lv, phi, ln_nu):
    c, s = math.cos(phi), math.sin(phi)
    u, v = c * fx + s * fy, -s * fx + c * fy
    q2 = np.pi**2 * (math.exp(2 * ln_lu) * u * u + math.exp(2 * ln_lv) * v * v)
    nu = math.exp(ln_nu)
    return math.exp(ln_a) * np.exp(-(nu + 1.0) * np.log1p(q2 / (nu + 1.0)))


def scale_test(relief, lengths_m: tuple | None = None) -> ScaleTest:
    """The one-scale / two-scale test of the module docstring; `lengths_m` = (l_L, l_F) of the band
    split (`surface.bands`), a further start of the two-scale fit."""
    from relief_bsdf.surface.stats import relief_stats
    fx, fy, P, tile = _periodogram(relief)
    label = _bins(fx, fy, tile)
    sel = label >= 0
    fx, fy, P, label = fx[sel], fy[sel], P[sel], label[sel]
    ids, inv, m = np.unique(label, return_inverse=True, return_counts=True)
    pbin = np.bincount(inv, weights=P) / m
    ok = pbin > DYNAMIC_RANGE * pbin.max()     # below: round-off, no scale of the surface (module doc)
    n = int(ok.sum())
    bias = special.digamma(m) - np.log(m)
    sd = np.sqrt(special.polygamma(1, m))
    y = np.log(np.where(ok, pbin, 1.0))
    outer = np.hypot(fx, fy) > 0.8 * min(np.max(np.abs(fx)), np.max(np.abs(fy)))
    nf = max(float(np.median(P[outer])) if outer.any() else 1e-300, 1e-300)   # the white floor's level, a start
    # the model's bin means from at most MODEL_SAMPLES samples of each bin, evenly spread in |f|
    order = np.lexsort((np.hypot(fx, fy), inv))
    start = np.concatenate([[0], np.cumsum(m)[:-1]])
    take = np.concatenate([order[start[b] + np.unique(np.linspace(0, m[b] - 1, min(m[b], MODEL_SAMPLES)).astype(int))]
                           for b in range(len(m))])
    fx, fy, inv_s = fx[take], fy[take], inv[take]
    m_s = np.bincount(inv_s, minlength=len(m))

    def residuals(model_samples):
        sb = np.bincount(inv_s, weights=model_samples, minlength=len(m)) / m_s
        return ((y - np.log(np.maximum(sb, 1e-300)) - bias) / sd)[ok]

    def one(x):
        return _component(fx, fy, *x[:5]) + math.exp(x[5])

    def two(x):
        return _component(fx, fy, *x[:5]) + _component(fx, fy, *x[5:10]) + math.exp(x[10])

    st = relief_stats(relief)
    l0 = max(float(st.correlation_length_m), 2 * max(relief.dx_m, relief.dy_m))
    var = max(float(st.rms_height_m) ** 2, 1e-30)
    # A C(q^2) summed over the samples of the plane ~ A (nu-dependent) / (pi l_u l_v df^2): start A from the variance
    df2 = 1.0 / (tile[0] * tile[1])

    def amp(var_share, lu, lv):
        return math.log(max(var_share * var * math.pi * lu * lv * df2, 1e-300))
    ln_n0 = math.log(nf * 0.5)
    lo1 = [-800.0, math.log(0.5 * min(relief.dx_m, relief.dy_m)), math.log(0.5 * min(relief.dx_m, relief.dy_m)),
           -math.pi, math.log(NU_BOUNDS[0]), -800.0]
    hi1 = [100.0, math.log(max(tile)), math.log(max(tile)), 2 * math.pi, math.log(NU_BOUNDS[1]), 100.0]

    def fit(fun, starts, lo, hi):
        best = None
        for x0 in starts:
            x0 = np.clip(np.asarray(x0, float), np.asarray(lo) + 1e-9, np.asarray(hi) - 1e-9)
            try:
                r = optimize.least_squares(lambda x: residuals(fun(x)), x0, bounds=(lo, hi), method="trf",
                                           x_scale="jac", max_nfev=200)
            except (ValueError, FloatingPointError):
                continue
            c = float(r.fun @ r.fun)
            if best is None or c < best[0]:
                best = (c, r.x)
        return best
    from relief_bsdf.surface.stats import slope_tensor
    t = slope_tensor(relief)
    ratio, phi0 = 1.0, 0.0
    if np.all(np.isfinite(t)):
        ev, vec = np.linalg.eigh(t)                 # ev[0] along the lay: the longer length there
        ratio = float(np.sqrt(max(ev[1], 1e-30) / max(ev[0], 1e-30)))
        phi0 = float(math.atan2(vec[1, 0], vec[0, 0]))
    lu, lv = l0 * math.sqrt(ratio), l0 / math.sqrt(ratio)
    starts1 = [[amp(1.0, lu, lv), math.log(lu), math.log(lv), phi0, math.log(nu), ln_n0] for nu in (0.5, 30.0, 3000.0)]
    chi1, x1 = fit(one, starts1, lo1, hi1)
    lo2, hi2 = lo1[:5] + lo1[:5] + lo1[5:], hi1[:5] + hi1[:5] + hi1[5:]
    starts2 = []
    for frac in (0.1, 0.3, 3.0, 10.0):
        lu, lv = math.exp(x1[1]) * frac, math.exp(x1[2]) * frac
        starts2.append(list(x1[:5]) + [amp(0.05 if frac < 1 else 0.5, lu, lv), math.log(lu), math.log(lv), x1[3], math.log(2.0)] + [x1[5]])
    if lengths_m is not None and all(np.isfinite(lengths_m)) and min(lengths_m) > 0:
        lL, lF = lengths_m
        starts2.append([amp(0.9, lL, lL), math.log(lL), math.log(lL), 0.0, math.log(30.0),
                        amp(0.1, lF, lF), math.log(lF), math.log(lF), 0.0, math.log(30.0), ln_n0])
    chi2_, x2 = fit(two, starts2, lo2, hi2)
    if chi2_ > chi1:                 # the nested model can always do as well as the one-scale fit
        chi2_, x2 = chi1, np.concatenate([x1[:5], [-800.0], x1[1:5], [x1[5]]])
    k1, k2 = 6, 11
    gain = bic_gain(chi1, k1, chi2_, k2, n, overdispersion(chi2_, k2, n))
    # the two components' lengths (geometric mean of the axes) and variance shares (their sums over the samples)
    comp_a, comp_b = _component(fx, fy, *x2[:5]), _component(fx, fy, *x2[5:10])
    la, lb = math.exp(0.5 * (x2[1] + x2[2])), math.exp(0.5 * (x2[6] + x2[7]))
    (lL, cL), (lF, cF) = sorted([(la, comp_a), (lb, comp_b)], key=lambda t: -t[0])
    tot = max(float(cL.sum() + cF.sum()), 1e-300)
    # the fine scale is seen: it carries most of the model's power in at least one bin
    fine_bins = np.bincount(inv_s, weights=cF, minlength=len(m)) > np.bincount(inv_s, weights=cL, minlength=len(m))
    seen = bool(np.any(fine_bins & ok))
    two_scales = bool(gain > BIC_MARGIN and lL >= MIN_SEPARATION * lF and seen)
    return ScaleTest(n, float(chi1), float(chi2_), k1, k2, float(gain), float(lL), float(lF), float(cF.sum() / tot),
                     two_scales)
