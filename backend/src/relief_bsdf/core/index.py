"""Refractive index models of the media and the `Material` pair on either side of a boundary.

Physics: the complex refractive index n + i k of a medium as a function of the vacuum
wavelength (nm): constant, Cauchy (n = A + B / l^2 + C / l^4, transparent range only) or
Sellmeier (n^2 = 1 + sum B_j l^2 / (l^2 - C_j), l in um; Schott N-BK7 by default).  k >= 0
means absorption (metals).  Each model carries the wavelength range where it is valid and
refuses wavelengths outside it (`check_range`).  Serialised by `describe()` /
`index_from_dict()` (the `material` block of ../shared/formats.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relief_bsdf.errors import InputError

# ---------------------------------------------------------------- index models


@dataclass(frozen=True)
class IndexModel:
    """Base class: complex refractive index as a function of vacuum wavelength (nm)."""

    min_nm: float = field(default=200.0, kw_only=True)
    max_nm: float = field(default=20000.0, kw_only=True)

    def n(self, wavelength_nm: Any) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def check_range(self, wavelength_nm: Any, where: str = "refractive index") -> None:
        w = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
        bad = w[(w < self.min_nm) | (w > self.max_nm) | ~np.isfinite(w)]
        if bad.size:
            raise InputError(
                where,
                f"wavelength {bad[0]:g} nm is outside the index model's range "
                f"[{self.min_nm:g}, {self.max_nm:g}] nm",
            )

    def is_absorbing(self, wavelength_nm: Any) -> bool:
        return bool(np.any(np.imag(self.n(wavelength_nm)) > 0))

    def describe(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass(frozen=True)
class ConstantIndex(IndexModel):
    """Wavelength-independent index n + i k."""

    real: float = 1.5
    imag: float = 0.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.real) or self.real <= 0 or self.imag < 0:
            raise InputError("refractive index", f"unphysical index {self.real}+{self.imag}i "
                             "(need real part > 0 and extinction k >= 0)")

    def n(self, wavelength_nm: Any) -> np.ndarray:
        w = np.asarray(wavelength_nm, dtype=float)
        val = complex(self.real, self.imag) if self.imag else self.real
        return np.full(w.shape, val)

    def describe(self) -> dict:
        return {"model": "constant", "n": self.real, "k": self.imag}


@dataclass(frozen=True)
class CauchyIndex(IndexModel):
    """Cauchy dispersion n = A + B / l^2 + C / l^4, l in nm (B in nm^2, C in nm^4).

    Valid in the transparent range of the material; by default 350-1000 nm.
    """

    A: float = 1.5
    B_nm2: float = 0.0
    C_nm4: float = 0.0
    min_nm: float = field(default=350.0, kw_only=True)
    max_nm: float = field(default=1000.0, kw_only=True)

    def __post_init__(self) -> None:
        n_mid = self.A + self.B_nm2 / 550.0**2 + self.C_nm4 / 550.0**4
        if not (np.isfinite(n_mid) and n_mid > 0):
            raise InputError("cauchy", f"unphysical Cauchy coefficients A={self.A}, B={self.B_nm2}, C={self.C_nm4}")

    def n(self, wavelength_nm: Any) -> np.ndarray:
        w = np.asarray(wavelength_nm, dtype=float)
        return self.A + self.B_nm2 / w**2 + self.C_nm4 / w**4

    def describe(self) -> dict:
        return {"model": "cauchy", "A": self.A, "B_nm2": self.B_nm2, "C_nm4": self.C_nm4,
                "min_nm": self.min_nm, "max_nm": self.max_nm}


@dataclass(frozen=True)
class SellmeierIndex(IndexModel):
    """Sellmeier n^2 = 1 + sum_j B_j l^2 / (l^2 - C_j), l in micrometres, C_j in um^2."""

    B: tuple = (1.03961212, 0.231792344, 1.01046945)        # Schott N-BK7 by default
    C_um2: tuple = (0.00600069867, 0.0200179144, 103.560653)
    min_nm: float = field(default=300.0, kw_only=True)
    max_nm: float = field(default=2500.0, kw_only=True)

    def n(self, wavelength_nm: Any) -> np.ndarray:
        l2 = (np.asarray(wavelength_nm, dtype=float) * 1e-3) ** 2
        n2 = 1.0 + sum(b * l2 / (l2 - c) for b, c in zip(self.B, self.C_um2))
        return np.sqrt(n2)

    def describe(self) -> dict:
        return {"model": "sellmeier", "B": list(self.B), "C_um2": list(self.C_um2),
                "min_nm": self.min_nm, "max_nm": self.max_nm}


def index_from_dict(d: dict) -> IndexModel:
    """Inverse of `IndexModel.describe()`."""
    kind = d.get("model")
    if kind == "constant":
        return ConstantIndex(real=float(d["n"]), imag=float(d.get("k", 0.0)))
    if kind == "cauchy":
        return CauchyIndex(A=float(d["A"]), B_nm2=float(d["B_nm2"]), C_nm4=float(d.get("C_nm4", 0.0)),
                           min_nm=float(d.get("min_nm", 350.0)), max_nm=float(d.get("max_nm", 1000.0)))
    if kind == "sellmeier":
        return SellmeierIndex(B=tuple(d["B"]), C_um2=tuple(d["C_um2"]),
                              min_nm=float(d.get("min_nm", 300.0)), max_nm=float(d.get("max_nm", 2500.0)))
    raise InputError("refractive index", f"unknown index model {kind!r}")


@dataclass(frozen=True)
class Material:
    """The two media on either side of the rough boundary.

    `outside` is the medium of the lit half-space z > 0 (air by default); `inside`
    is the dielectric (or metal) below the relief.
    """

    inside: IndexModel
    outside: IndexModel = ConstantIndex(1.0)

    def n_pair(self, wavelength_nm: float, incident_from: str) -> tuple[complex, complex]:
        """(n of the medium the light comes from, n of the other medium)."""
        n_out = self.outside.n(wavelength_nm)[()]
        n_in = self.inside.n(wavelength_nm)[()]
        return (n_out, n_in) if incident_from == "outside" else (n_in, n_out)

    def check(self, wavelengths_nm: Any, where: str = "material") -> None:
        self.inside.check_range(wavelengths_nm, where)
        self.outside.check_range(wavelengths_nm, where)
        if np.any(np.imag(self.outside.n(wavelengths_nm)) > 0):
            raise InputError(where, "the outside medium must be transparent (real index)")

    def check_incidence(self, wavelengths_nm: Any, incident_from: Any, method: str = "") -> None:
        """RequestError for an unphysical index at a requested wavelength, or light from inside a metal.

        Every method calls this before work starts: indices need a positive real part and
        k >= 0, and light cannot arrive from inside an absorbing (k > 0) medium.
        """
        from relief_bsdf.errors import RequestError

        prefix = f"{method}: " if method else ""
        for wl in np.atleast_1d(np.asarray(wavelengths_nm, float)):
            for side in incident_from:
                n1, n2 = self.n_pair(float(wl), side)
                for v in (n1, n2):
                    if not (np.isfinite(v) and np.real(v) > 0 and np.imag(v) >= 0):
                        raise RequestError(f"{prefix}unphysical refractive index {v} at {wl:g} nm", "--n/--cauchy")
                if np.imag(n1) > 0:
                    raise RequestError(f"{prefix}light cannot arrive from inside an absorbing medium "
                                       "(complex index); use --from outside", "--from")

    def describe(self) -> dict:
        return {"inside": self.inside.describe(), "outside": self.outside.describe()}

    @staticmethod
    def from_dict(d: dict) -> "Material":
        return Material(inside=index_from_dict(d["inside"]), outside=index_from_dict(d["outside"]))
