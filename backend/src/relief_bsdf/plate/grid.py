"""The angular grid of the boundary tables, which is also the deterministic plate's discretisation.

The deterministic engine works on the internal direction cells of the inside table (its theta
cells x a uniform azimuth grid of `360 / phi_step_deg` cells), so the table grid *is* the
plate's discretisation: a finer plate grid than the tables would only interpolate.  Regime:
the discretisation error is of the order of a cell (1 deg x 5 deg by default); lobes narrower
than a few cells need a finer grid (issue 18).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from relief_bsdf.methods.request import Request


@dataclass(frozen=True)
class TableGrid:
    """Axes of the boundary tables the plate derives from its faces.

    theta_step_deg: scatter polar cell size (edges 0..90).
    phi_step_deg: scatter azimuth cell size (cells centred on multiples of it; also the plate's
        azimuth grid).
    inside_theta_i_step_deg: step between the incidences of the inside tables (0..85 + 89).
    """

    theta_step_deg: float = 1.0
    phi_step_deg: float = 5.0
    inside_theta_i_step_deg: float = 5.0

    @property
    def azimuth_cells(self) -> int:
        return int(round(360.0 / self.phi_step_deg))

    def theta_edges_deg(self) -> tuple:
        return tuple(np.linspace(0.0, 90.0, int(round(90 / self.theta_step_deg)) + 1))

    def phi_edges_deg(self) -> tuple:
        h = self.phi_step_deg / 2
        return tuple(np.arange(-h, 360.0 - h + 1e-9, self.phi_step_deg))

    def inside_incidences_deg(self) -> np.ndarray:
        """Incidences of the inside tables: every step from 0, plus 89 deg (near-grazing light)."""
        th = np.arange(0.0, 90.0 - 1e-9, self.inside_theta_i_step_deg)
        return np.unique(np.concatenate([th, [89.0]]))

    def request(self, wavelengths: Any, theta_i: Any, incident_from: str, method: str, samples: int, seed: int,
                options: dict | None = None) -> Request:
        """The methods' Request for one side of incidence on this grid (`method` is informational)."""
        return Request(wavelengths_nm=tuple(float(w) for w in wavelengths),
                       theta_i_deg=tuple(float(t) for t in theta_i), incident_from=(incident_from,),
                       theta_s_edges_deg=self.theta_edges_deg(), phi_s_edges_deg=self.phi_edges_deg(),
                       samples=int(samples), seed=int(seed), options=dict(options or {}))
