"""Recording rows as the plate engines read them: `Rows`, in-plane scans, their checks, the sample tilt's frame
and the far half of incidence azimuths."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from relief_bsdf.core.frames import rot_y
from relief_bsdf.errors import InputError


@dataclass
class Rows:
    """The geometry of recording rows (any object with these arrays works)."""

    wavelength_nm: np.ndarray
    theta_i_deg: np.ndarray
    phi_i_deg: np.ndarray
    side: np.ndarray
    theta_s_deg: np.ndarray
    phi_s_deg: np.ndarray

    def __post_init__(self) -> None:
        for k in ("wavelength_nm", "theta_i_deg", "phi_i_deg", "theta_s_deg", "phi_s_deg"):
            setattr(self, k, np.atleast_1d(np.asarray(getattr(self, k), float)))
        self.side = np.atleast_1d(np.asarray(self.side, dtype="<U1"))

    def __len__(self) -> int:
        return self.wavelength_nm.size


def in_plane_rows(wavelength_nm: float, theta_i_deg: Sequence[float], theta_s_deg: Sequence[float],
                  sides: Sequence[str] = ("R", "T"), phi_s_deg: Sequence[float] = (0.0, 180.0)) -> Rows:
    """Rows of a typical in-plane scan (phi_i = 0, phi_s in {0, 180})."""
    g = np.array([(wavelength_nm, ti, 0.0, sd, ts, ps) for ti in theta_i_deg for sd in sides
                  for ps in phi_s_deg for ts in theta_s_deg], dtype=object)
    return Rows(g[:, 0].astype(float), g[:, 1].astype(float), g[:, 2].astype(float), g[:, 3].astype(str),
                g[:, 4].astype(float), g[:, 5].astype(float))


def check_rows(experiment: Any, rows: Any, where: str = "recording") -> None:
    """InputError (naming `where` and the column) for rows the Experiment's plate cannot produce."""
    experiment.plate.index.check_range(rows.wavelength_nm, f"{where}: wavelength_nm")
    experiment.plate.outside_index.check_range(rows.wavelength_nm, f"{where}: wavelength_nm")
    for key in ("theta_i_deg", "theta_s_deg"):
        v = np.asarray(getattr(rows, key), float)
        bad = ~np.isfinite(v) | (v < 0) | (v >= 90)
        if bad.any():
            raise InputError(f"{where}: {key}", f"value {v[bad][0]:g} is outside [0, 90) degrees "
                             "(a plate cannot be lit or seen at or past grazing)")
    s = np.asarray(rows.side).astype(str)
    if np.any((s != "R") & (s != "T")):
        raise InputError(f"{where}: side", "side must be R or T")


def row_arrays(rows):
    """(wavelength_nm, theta_i_deg, phi_i_deg, side, theta_s_deg, phi_s_deg) of any row set as arrays."""
    return (np.asarray(rows.wavelength_nm, float), np.asarray(rows.theta_i_deg, float),
            np.asarray(rows.phi_i_deg, float), np.asarray(rows.side).astype(str),
            np.asarray(rows.theta_s_deg, float), np.asarray(rows.phi_s_deg, float))


def to_sample_frame(theta_deg: Any, phi_deg: Any, side: Any, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of instrument-frame directions (R: above, T: below) seen in the tilted sample's frame."""
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    sgn = np.where(np.asarray(side) == "T", -1.0, 1.0)
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), sgn * np.cos(t)], -1)
    w2 = w @ rot_y(tilt_deg)            # R^T w for each row
    th = np.degrees(np.arccos(np.clip(np.abs(w2[..., 2]), 0.0, 1.0)))
    ph = np.mod(np.degrees(np.arctan2(w2[..., 1], w2[..., 0])), 360.0)
    return th, ph


def azimuth_key(phi_deg: Any) -> np.ndarray:
    """Incidence azimuths as the keys of the turned outside tables: in [0, 360), rounded to 1e-6 deg."""
    a = np.round(np.mod(np.asarray(phi_deg, float), 360.0), 6)
    return np.where(a >= 360.0, 0.0, a)


def far_side(theta_deg: Any, phi_deg: Any) -> np.ndarray:
    """Whether each incidence (sample frame) is lit from the far half of azimuths, 90 < phi < 270 deg,
    where the engine reads the half-turned relief's outside table (`PlateSolver.half_turn`); normal
    incidence has no azimuth and is read from the table at 0."""
    t = np.asarray(theta_deg, float)
    return (t > 1e-9) & (np.cos(np.radians(np.asarray(phi_deg, float) + 0 * t)) < -1e-9)
