"""The one information criterion of the project: which of two nested models the data ask for.

BIC = chi^2 + k ln n (Schwarz 1978) for n rows and k fitted parameters, chi^2 the noise-weighted
misfit.  A model with more parameters is preferred only when it lowers the BIC by more than
`BIC_MARGIN` = 10, "very strong" evidence on the scale of Kass & Raftery (1995, sec. 3.2).
Used by the fit (is a Gaussian filter of the relief needed besides its height scale?) and by
the diagnosis (is a candidate effect needed besides the baseline?), so both answer "does the
recording ask for this?" the same way.

Overdispersion.  When even the complex model misses the noise (reduced chi^2 c = chi^2 / (n - k)
> 1: a systematic error of the forward model, not noise), chi^2 differences are inflated by c
and a parameter that only bends the model towards its own systematic error would pass the bar.
The quasi-likelihood form (QBIC; Burnham & Anderson 2002, sec. 2.5 for QAIC) divides the chi^2
by c of the complex model: gain = (chi^2_s - chi^2_c) / c - (k_c - k_s) ln n.  `overdispersion`
= c (1 when the model reaches the noise).
"""
from __future__ import annotations

import math

BIC_MARGIN = 10.0


def bic(chi2: float, k: int, n: int) -> float:
    """Bayesian information criterion chi^2 + k ln n."""
    return float(chi2) + int(k) * math.log(max(int(n), 1))


def overdispersion(chi2: float, k: int, n: int) -> float:
    """c = max(1, chi^2 / (n - k)): how far a model's misfit exceeds the noise (module doc)."""
    return max(1.0, float(chi2) / max(int(n) - int(k), 1))


def bic_gain(chi2_simple: float, k_simple: int, chi2_complex: float, k_complex: int, n: int,
             overdispersion: float = 1.0) -> float:
    """BIC(simple) - BIC(complex), the chi^2 divided by `overdispersion` (QBIC, module doc): >
    BIC_MARGIN means the data ask for the complex model."""
    c = max(float(overdispersion), 1.0)
    return bic(chi2_simple / c, k_simple, n) - bic(chi2_complex / c, k_complex, n)


def asks_for(chi2_simple: float, k_simple: int, chi2_complex: float, k_complex: int, n: int) -> bool:
    """True when the complex model beats the simple one by more than BIC_MARGIN."""
    return bic_gain(chi2_simple, k_simple, chi2_complex, k_complex, n) > BIC_MARGIN
