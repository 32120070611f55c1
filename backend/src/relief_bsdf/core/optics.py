"""Refractive index models and the optics of one flat interface.

Conventions (pbrt style, see ../shared/formats.md): directions are unit vectors
pointing *away* from the surface point; the interface normal points into the
medium the light arrives from.  Indices may be complex (n + i k, k >= 0) for
absorbing media; metals then reflect by the same Fresnel formulas.

Physics: Fresnel amplitude coefficients for s (TE) and p (TM) polarisation,
Born & Wolf, *Principles of Optics*, sec. 1.5.2 eqs. (20)-(21); Snell's law;
total internal reflection when (n1/n2) sin(theta_i) > 1 for real indices.
All functions are numpy-vectorised over angles.
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


# ---------------------------------------------------------------- interface optics


def cos_transmitted(cos_i: Any, n1: Any, n2: Any) -> np.ndarray:
    """Complex cosine of the refraction angle (Snell's law), branch with Im >= 0.

    Past the critical angle (real indices) the result is purely imaginary (evanescent).
    """
    cos_i = np.asarray(cos_i, dtype=float)
    eta = np.asarray(n1, dtype=complex) / np.asarray(n2, dtype=complex)
    ct = np.sqrt(1.0 - eta**2 * (1.0 - cos_i**2) + 0j)
    return np.where(np.imag(ct) < 0, -ct, ct)


def fresnel_amplitudes(cos_i: Any, n1: Any, n2: Any):
    """Fresnel amplitude coefficients (r_s, r_p, t_s, t_p) for light in medium n1 hitting n2.

    `cos_i` is the cosine of the incidence angle (>= 0).  Born & Wolf (1.5.20-21):
    r_s = (n1 c_i - n2 c_t)/(n1 c_i + n2 c_t),  r_p = (n2 c_i - n1 c_t)/(n2 c_i + n1 c_t),
    t_s = 2 n1 c_i/(n1 c_i + n2 c_t),           t_p = 2 n1 c_i/(n2 c_i + n1 c_t).
    """
    ci = np.abs(np.asarray(cos_i, dtype=float))
    n1 = np.asarray(n1, dtype=complex)
    n2 = np.asarray(n2, dtype=complex)
    ct = cos_transmitted(ci, n1, n2)
    a = n1 * ci
    b = n2 * ct
    c = n2 * ci
    d = n1 * ct
    rs = (a - b) / (a + b)
    rp = (c - d) / (c + d)
    ts = 2 * a / (a + b)
    tp = 2 * a / (c + d)
    return rs, rp, ts, tp


def fresnel_power(cos_i: Any, n1: Any, n2: Any):
    """Power reflectances and transmittances (R_s, R_p, T_s, T_p) of a flat interface.

    For a real n2 the transmittances are 1 - R (energy conservation); past the
    critical angle they are 0.  For an absorbing n2 (metal) the transmitted power
    is absorbed in the medium and T is reported as 1 - R (the power entering it).
    """
    rs, rp, _, _ = fresnel_amplitudes(cos_i, n1, n2)
    Rs = np.abs(rs) ** 2
    Rp = np.abs(rp) ** 2
    Rs = np.clip(Rs, 0.0, 1.0)
    Rp = np.clip(Rp, 0.0, 1.0)
    return Rs, Rp, 1.0 - Rs, 1.0 - Rp


def fresnel_unpolarized(cos_i: Any, n1: Any, n2: Any) -> np.ndarray:
    """Unpolarised power reflectance (R_s + R_p) / 2."""
    Rs, Rp, _, _ = fresnel_power(cos_i, n1, n2)
    return 0.5 * (Rs + Rp)


def critical_angle_deg(n1: float, n2: float) -> float:
    """Critical angle for light in n1 hitting n2 < n1; 90 when there is none."""
    if np.real(n2) >= np.real(n1):
        return 90.0
    return float(np.degrees(np.arcsin(np.real(n2) / np.real(n1))))


def reflect(w: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror direction of w (pointing away) about normal n: 2 (w.n) n - w.  Shapes (..., 3)."""
    d = np.sum(w * n, axis=-1, keepdims=True)
    return 2.0 * d * n - w


def refract(w: np.ndarray, n: np.ndarray, eta: Any):
    """Refract w (pointing away, on the side of n) through the interface.

    eta = n_incident / n_transmitted (real).  Returns (w_t, ok) where w_t points away on the
    other side and ok is False where total internal reflection occurs (w_t undefined there).
    pbrt-v4 sec. 9.3 convention.
    """
    eta = np.asarray(eta, dtype=float)
    cos_i = np.sum(w * n, axis=-1)
    sin2_t = eta**2 * np.maximum(0.0, 1.0 - cos_i**2)
    ok = sin2_t < 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin2_t))
    wt = -eta[..., None] * w + (eta * cos_i - cos_t)[..., None] * n if eta.ndim else \
        -eta * w + (eta * cos_i - cos_t)[..., None] * n
    return wt, ok


def mueller_interface(cos_i: Any, n1: Any, n2: Any, kind: str) -> np.ndarray:
    """Mueller matrix (..., 4, 4) of reflection ('R') or transmission ('T') at a flat interface.

    Stokes vectors in the s/p basis of the plane of incidence (S0, S1 = I_s - I_p, S2, S3).
    Reflection: amplitudes r_s, r_p; transmission: t_s, t_p with the power factor
    Re(n2 c_t)/(n1 c_i) so that M00 is the power transmittance (Born & Wolf 1.5.27).
    """
    rs, rp, ts, tp = fresnel_amplitudes(cos_i, n1, n2)
    if kind == "R":
        a, b = rs, rp
        scale = 1.0
    elif kind == "T":
        ci = np.abs(np.asarray(cos_i, dtype=float))
        ct = cos_transmitted(ci, n1, n2)
        a, b = ts, tp
        scale = np.real(np.asarray(n2, dtype=complex) * ct) / np.real(np.asarray(n1, dtype=complex) * ci)
    else:
        raise ValueError("kind must be 'R' or 'T'")
    A = np.abs(a) ** 2
    B = np.abs(b) ** 2
    C = a * np.conj(b)
    M = np.zeros(np.broadcast(A, B).shape + (4, 4))
    M[..., 0, 0] = 0.5 * (A + B)
    M[..., 0, 1] = 0.5 * (A - B)
    M[..., 1, 0] = 0.5 * (A - B)
    M[..., 1, 1] = 0.5 * (A + B)
    M[..., 2, 2] = np.real(C)
    M[..., 2, 3] = np.imag(C)
    M[..., 3, 2] = -np.imag(C)
    M[..., 3, 3] = np.real(C)
    return M * np.asarray(scale)[..., None, None]
