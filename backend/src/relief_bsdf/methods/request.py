"""What a reconstruction is asked to compute: the table's axes, the sampling effort and the options.

`options` is the contract's plain mapping (formats.md, ``--option KEY=VALUE``); methods read it
only as their typed options object, `request.options_for(method)` (methods.options).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from relief_bsdf.errors import RequestError

DEFAULT_THETA_S_EDGES_DEG = tuple(np.linspace(0.0, 90.0, 91))          # 1 degree rings
DEFAULT_PHI_S_EDGES_DEG = tuple(np.arange(-2.5, 360.0, 5.0))             # centres 0, 5, ..., 355


@dataclass(frozen=True)
class Request:
    """Axes and effort of a reconstruction.

    theta_s / phi_s are given as cell *edges*; tables store cell centres and the
    values are averages over each cell in projected solid angle (cos theta d omega),
    so hemispherical integrals are exact sums.  phi edges may start below 0 so that
    cells are centred on the plane of incidence (phi_s = 0 and 180).
    """

    wavelengths_nm: tuple = (550.0,)
    theta_i_deg: tuple = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)
    phi_i_deg: tuple = (0.0,)
    incident_from: tuple = ("outside",)
    theta_s_edges_deg: tuple = DEFAULT_THETA_S_EDGES_DEG
    phi_s_edges_deg: tuple = DEFAULT_PHI_S_EDGES_DEG
    samples: int = 1_000_000
    seed: int = 0
    polarization: str = "unpolarized"
    coherence_length_m: float | None = None
    options: dict = field(default_factory=dict)      # KEY -> value; read through options_for(method)

    def options_for(self, method: str):
        """The typed options of `method` (methods.options) from `options`; RequestError naming a bad one."""
        from relief_bsdf.methods.registry import options_for
        return options_for(method, self.options)

    def validate(self) -> "Request":
        """Raise RequestError (naming the offending value) before any work starts."""
        w = np.asarray(self.wavelengths_nm, float)
        if w.size == 0 or np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise RequestError(f"wavelengths must be positive numbers of nm, got {list(self.wavelengths_nm)}",
                               "--wavelengths-nm")
        t = np.asarray(self.theta_i_deg, float)
        if t.size == 0 or np.any(~np.isfinite(t)) or np.any(t < 0) or np.any(t >= 90):
            raise RequestError(f"incidence angles must lie in [0, 90) degrees, got {list(self.theta_i_deg)}",
                               "--theta-i-deg")
        p = np.asarray(self.phi_i_deg, float)
        if p.size == 0 or np.any(~np.isfinite(p)):
            raise RequestError(f"bad incidence azimuths {list(self.phi_i_deg)}", "--phi-i-deg")
        for s in self.incident_from:
            if s not in ("outside", "inside"):
                raise RequestError(f"light arrives from 'outside' or 'inside', got {s!r}", "--from")
        if not self.incident_from:
            raise RequestError("no side of incidence requested", "--from")
        te = np.asarray(self.theta_s_edges_deg, float)
        if te.size < 2 or np.any(np.diff(te) <= 0) or te[0] < 0 or te[-1] > 90:
            raise RequestError("theta_s edges must increase within [0, 90] degrees", "theta_s_edges_deg")
        pe = np.asarray(self.phi_s_edges_deg, float)
        if pe.size < 2 or np.any(np.diff(pe) <= 0) or pe[-1] - pe[0] > 360 + 1e-9:
            raise RequestError("phi_s edges must increase and span at most 360 degrees", "phi_s_edges_deg")
        if int(self.samples) < 1:
            raise RequestError(f"samples must be >= 1, got {self.samples}", "--samples")
        if self.polarization not in ("unpolarized", "s", "p"):
            raise RequestError(f"polarization must be unpolarized, s or p, got {self.polarization!r}")
        if self.coherence_length_m is not None and not (self.coherence_length_m > 0):
            raise RequestError("coherence length must be > 0", "--coherence-length-um")
        return self

    @property
    def theta_s_deg(self) -> np.ndarray:
        e = np.asarray(self.theta_s_edges_deg, float)
        return 0.5 * (e[1:] + e[:-1])

    @property
    def phi_s_deg(self) -> np.ndarray:
        e = np.asarray(self.phi_s_edges_deg, float)
        return 0.5 * (e[1:] + e[:-1])
