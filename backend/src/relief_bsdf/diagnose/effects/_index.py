"""A perturbed index model, n(l) = n_stated(l) + dn + B (1 / l^2 - 1 / l_ref^2).

Used by `refractive_index` (dn: the stated index is off) and `dispersion` (B: a Cauchy term
the statement lacks, zero at the reference wavelength).  Physics of the Cauchy term: Cauchy
(1836), n = A + B / l^2, valid in the transparent range.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.core.index import IndexModel


@dataclass(frozen=True)
class PerturbedIndex(IndexModel):
    base: Any = None
    offset: float = 0.0
    cauchy_B_nm2: float = 0.0
    reference_nm: float = 550.0

    def n(self, wavelength_nm: Any) -> np.ndarray:
        w = np.asarray(wavelength_nm, float)
        return (self.base.n(w) + self.offset
                + self.cauchy_B_nm2 * (1.0 / w**2 - 1.0 / self.reference_nm**2))

    def describe(self) -> dict:
        return {"model": "perturbed", "base": self.base.describe(), "offset": self.offset,
                "cauchy_B_nm2": self.cauchy_B_nm2, "reference_nm": self.reference_nm}


def perturbed(index: IndexModel, reference_nm: float, offset: float = 0.0, cauchy_B_nm2: float = 0.0) -> IndexModel:
    """`index` with the perturbation added (composing with an earlier perturbation)."""
    if isinstance(index, PerturbedIndex):
        return PerturbedIndex(base=index.base, offset=index.offset + offset,
                              cauchy_B_nm2=index.cauchy_B_nm2 + cauchy_B_nm2, reference_nm=index.reference_nm,
                              min_nm=index.min_nm, max_nm=index.max_nm)
    return PerturbedIndex(base=index, offset=offset, cauchy_B_nm2=cauchy_B_nm2, reference_nm=reference_nm,
                          min_nm=index.min_nm, max_nm=index.max_nm)
