"""Figures of a transmitted top-hat lobe, the same for a measurement and a prediction (issue targets).

For the T rows of one incidence on a full (theta_s, phi_s) grid, with values f (1/sr):
- transmittance: sum f cos(theta_s) dOmega over the rows (cells between mid-points of the polar grid,
  360 / n_phi in azimuth: `direction_cosine_cell`; the rows must form a full grid,
  `full_grid`);
- centroid offset (deg): the power-weighted mean direction of the readings at or above half the lobe's
  peak (99.5th percentile, as io.measured.lobe_summary), its angle to the undeviated ray
  (T, theta_i, phi_i + 180);
- half-maximum edges (direction cosine): along the two axes of the direction-cosine plane through
  the undeviated ray's u0 = -sin(theta_i) (cos phi_i, sin phi_i), f sampled (bilinear in theta, phi)
  every 0.0005 and the outermost crossing of half the plateau on each side: (-x, +x, -y, +y) as
  positions u, relative to u0;
- plateau (1/sr): the median of f over the readings within `PLATEAU_RADIUS` of u0 (the lobe's flat
  top, well inside its edges at ~0.095).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

PLATEAU_RADIUS = 0.05
_STEP = 0.0005


def full_grid(rows: Any) -> bool:
    """The rows form a full (theta_s, phi_s) grid (as measured plate files do), with at least 2 x 4 points."""
    th, ph = np.unique(rows.theta_s_deg), np.unique(rows.phi_s_deg)
    return th.size >= 2 and ph.size >= 4 and th.size * ph.size == len(rows)


def direction_cosine_cell(rows: Any) -> np.ndarray:
    """Projected solid angle cos(theta_s) dOmega of each row's cell on a full (theta, phi) grid (theta cells
    between mid-points, clipped to the grid's range; azimuth cells 360 / n_phi); NaN-free."""
    th = np.unique(rows.theta_s_deg)
    ph = np.unique(rows.phi_s_deg)
    mids = np.concatenate([[th[0]], 0.5 * (th[1:] + th[:-1]), [th[-1]]])
    lo = np.radians(mids[np.searchsorted(th, rows.theta_s_deg)])
    hi = np.radians(mids[np.searchsorted(th, rows.theta_s_deg) + 1])
    return 0.5 * (np.sin(hi) ** 2 - np.sin(lo) ** 2) * (2 * math.pi / ph.size)


def lobe_figures(rows: Any, values: np.ndarray) -> dict:
    """The figures of the module doc for the T rows of ONE incidence (`rows` a Recording subset)."""
    from relief_bsdf.infer.slopes import _lobe_interpolator
    f = np.asarray(values, float)
    ti, pi = float(rows.theta_i_deg[0]), float(rows.phi_i_deg[0])
    t, p = np.radians(rows.theta_s_deg), np.radians(rows.phi_s_deg)
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    u0 = -np.sin(np.radians(ti)) * np.array([np.cos(np.radians(pi)), np.sin(np.radians(pi))])
    nominal = np.array([u0[0], u0[1], np.sqrt(1 - u0 @ u0)])
    w = direction_cosine_cell(rows)
    peak = float(np.percentile(f, 99.5))
    core = f >= 0.5 * peak
    c = ((f * w)[core, None] * d[core]).sum(axis=0)
    c /= np.linalg.norm(c)
    offset = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(c, nominal)), c @ nominal)))
    plateau = float(np.median(f[np.hypot(d[:, 0] - u0[0], d[:, 1] - u0[1]) <= PLATEAU_RADIUS]))
    interp = _lobe_interpolator(np.asarray(rows.theta_s_deg), np.asarray(rows.phi_s_deg), f)
    r = np.arange(0.0, 0.4, _STEP)
    edges = []
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            q = np.tile(u0, (r.size, 1))
            q[:, axis] += sign * r
            v = interp(q)
            above = np.nonzero(v >= 0.5 * plateau)[0]
            k = int(above[-1]) if above.size else 0
            if k + 1 < r.size:        # linear crossing between the last sample above and the next
                a, b = v[k], v[k + 1]
                frac = (a - 0.5 * plateau) / (a - b) if a != b else 0.0
                edges.append(sign * (r[k] + frac * _STEP))
            else:
                edges.append(sign * r[k])
    return {"theta_i_deg": ti, "phi_i_deg": pi, "transmittance": float(np.sum(f * w)),
            "centroid_offset_deg": offset, "plateau_sr": plateau,
            "edges_u": [float(e) for e in edges]}        # (-x, +x, -y, +y) relative to the undeviated ray
