"""The one information criterion of the project: which of two nested models the data ask for.

BIC = chi^2 + k ln n (Schwarz 1978) for n rows and k fitted parameters, chi^2 the noise-weighted
misfit.  A model with more parameters is preferred only when it lowers the BIC by more than
`BIC_MARGIN` = 10, "very strong" evidence on the scale of Kass & Raftery (1995, sec. 3.2).
Used by the fit (is a Gaussian filter of the relief needed besides its height scale?) and by
the diagnosis (is a candidate effect needed besides the baseline?), so both answer "does the
recording ask for this?" the same way.
"""
from __future__ import annotations

import math

BIC_MARGIN = 10.0


def bic(chi2: float, k: int, n: int) -> float:
    """Bayesian information criterion chi^2 + k ln n."""
    return float(chi2) + int(k) * math.log(max(int(n), 1))


def bic_gain(chi2_simple: float, k_simple: int, chi2_complex: float, k_complex: int, n: int) -> float:
    """BIC(simple) - BIC(complex): > BIC_MARGIN means the data ask for the complex model."""
    return bic(chi2_simple, k_simple, n) - bic(chi2_complex, k_complex, n)


def asks_for(chi2_simple: float, k_simple: int, chi2_complex: float, k_complex: int, n: int) -> bool:
    """True when the complex model beats the simple one by more than BIC_MARGIN."""
    return bic_gain(chi2_simple, k_simple, chi2_complex, k_complex, n) > BIC_MARGIN
