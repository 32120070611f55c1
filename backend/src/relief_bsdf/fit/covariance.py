"""Covariance of fitted parameters from the Jacobian of the normalised residuals: curvature and HAC.

One definition shared by `relief fit` (fit.optimise) and `relief diagnose` (diagnose.fitting).

With r = (y - m) / s the normalised residuals at the best point (s^2 = sigma_recording^2 +
sigma_model^2) and J = dr/dx, the *curvature* covariance is (J^T J)^-1, the covariance for
Delta chi^2 = 1 (Numerical Recipes 15.6), inflated by the reduced chi^2 when it exceeds one
(the Birge ratio).  It assumes the residuals independent between rows.  A forward model's
error is not: a slightly wrong lobe width, the grid's interpolation or a table's noise
seen through a detector cone leave residuals that run with the scatter angle across a scan,
so the rows carry fewer independent pieces of information than their number, and the
curvature interval is too narrow (measured on the concealed-effect benchmark: truth inside
the curvature-only 68 % interval 5 times in 13).

The *HAC* covariance (heteroscedasticity and autocorrelation consistent; Newey & West 1987)
estimates the variance of the score sum_i J_i r_i from the residuals themselves, counting
the products of neighbouring rows of a scan with Bartlett weights w_l = 1 - l / (L + 1):

    cov_HAC = A^-1 M A^-1,  A = J^T J,
    M = n / (n - k) sum_scans [ sum_i g_i g_i^T + sum_{l=1..L} w_l sum_i (g_i g_{i+l}^T + g_{i+l} g_i^T) ],
    g_i = J_i^T r_i.

A scan is the rows of one wavelength, incidence (theta_i, phi_i), side and scatter azimuth,
in order of theta_s.  The bandwidth L is Andrews' (1991) plug-in for the Bartlett kernel with
an AR(1) model of the residuals along the scans: rho the pooled lag-1 correlation,
alpha = (2 rho / (1 - rho^2))^2, L = 1.1447 (alpha T)^(1/3) with T the median scan length.

Each parameter's variance is the larger of the two (`parameter_covariance`): the curvature
one when the model is right (the HAC estimate is then noisy around it), the HAC one when
the residuals are correlated or larger than the noise somewhere the parameter acts; their
correlations are the curvature's.

*Stated model accuracy* (`nuisance`).  A model error that shifts every scan alike, a wrong
overall level of one side, is neither in the noise nor in the HAC estimate (its residuals are
correlated across scans, not only within one); where the forward model's accuracy has been
measured independently, it is a nuisance parameter u with a Gaussian prior: the columns
N = d r / d u (u in units of its prior 1-sigma), marginalised analytically (the residuals'
covariance becomes I + N N^T; Woodbury):

    A_marg = J^T J - J^T N (I + N^T N)^-1 N^T J,    Delta = A_marg^-1 - (J^T J)^-1  (>= 0),

and Delta is added to the covariance above: a parameter that moves the rows as a level does
(bulk absorption in T, the index or the source polarisation in R) gets the level's uncertainty,
one that changes shapes (blur, tilt, a lobe width) hardly any.  `level_nuisance` makes the
columns of the plate's stated per-side level accuracy (plate.uncertainty.FORWARD_LEVEL_SD).

*Model noise shared by rows* (`shared`).  The simulation's own noise (its boundary tables' Monte-Carlo
noise, plate.uncertainty) is in s as an independent per-row sigma, but it is one realisation: a
noisy cell moves every row that reads it, in every scan, and the fit is pulled by that one draw.
With K perturbed-table draws of the simulation at the fitted point, d_k (n), normalised
(`shared_columns`: D = d / (s sqrt(K - 1)), so D D^T estimates the noise's covariance in units of
s^2), the estimator x = argmin |r|^2 has the sandwich covariance A^-1 J^T Sigma J A^-1 (Huber 1967),
Sigma = I - diag(f) + D D^T with f the model's part of each row's s^2, whose part beyond A^-1 is

    E = A^-1 [ (J^T D)(J^T D)^T - J^T diag(f) J ] A^-1,

(f: `model_fraction`, default diag(D D^T)).  Each parameter's variance is then the largest of the
HAC one and the curvature one plus E (correlations the curvature's).  With K = 16 draws
(plate.uncertainty.INTERVAL_DRAWS), E is known to about +-37 %.

Regime: residuals whose correlation falls off within a scan, besides the stated levels and the
shared model noise; a score that is roughly linear within the interval.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Covariance", "level_nuisance", "parameter_covariance", "scans_of", "shared_columns"]

SINGULAR_COND = 1e12


@dataclass(frozen=True)
class Covariance:
    """cov (k x k; NaN where not determined), and how it was widened."""

    cov: np.ndarray
    birge: float                 # reduced chi^2 used as inflation (>= 1)
    hac_widening: np.ndarray     # per parameter: sd_final / sd_curvature (>= 1)
    bandwidth: int               # Bartlett lags L
    lag1: float                  # pooled lag-1 correlation of the residuals along the scans
    nuisance_widening: np.ndarray | None = None   # per parameter: sd with / without the stated levels (>= 1)
    nuisance_text: str = ""      # what the nuisance levels are (for the notes)
    shared_widening: np.ndarray | None = None     # per parameter: sd with the shared model noise / curvature's
    shared_draws: int = 0        # the draws the shared model noise was estimated from

    def shared_reason(self) -> str:
        return (f"the simulation's own table noise, one draw shared by every row that reads it "
                f"({self.shared_draws} draws)")

    def hac_reason(self) -> str:
        """What the HAC rule widened for: correlation along the scans when it found lags, else residuals
        larger than the noise (White's estimate, lag 0)."""
        if self.bandwidth > 0:
            return (f"residuals correlated along the scans (lag-1 {self.lag1:.2f}, {self.bandwidth} lags; "
                    "Newey-West)")
        return ("residuals larger than the noise where the parameters act (White's estimate: no correlation "
                "along the scans)")

    def note(self, j: int) -> str | None:
        """Why parameter j's interval is wider than the curvature's, or None."""
        parts = []
        if self.birge > 1.0:
            parts.append(f"the reduced chi^2 {self.birge:.2f} (the model misses the noise)")
        shared = 1.0 if self.shared_widening is None else float(self.shared_widening[j])
        if self.hac_widening[j] > 1.0 + 1e-9 and self.hac_widening[j] >= shared:
            parts.append(f"x{self.hac_widening[j]:.2f} for {self.hac_reason()}")
        elif shared > 1.0 + 1e-9:
            parts.append(f"x{shared:.2f} for {self.shared_reason()}")
        if self.nuisance_widening is not None and self.nuisance_widening[j] > 1.005:
            why = self.nuisance_text or "the stated model accuracy"
            parts.append(f"x{self.nuisance_widening[j]:.2f} for {why}")
        return ("widened by " + " and ".join(parts)) if parts else None


def scans_of(rows: Any) -> list[np.ndarray]:
    """Row indices of each scan (same wavelength, theta_i, phi_i, side, phi_s), ordered by theta_s."""
    keys = np.stack([np.round(np.asarray(rows.wavelength_nm, float), 6), np.round(np.asarray(rows.theta_i_deg, float), 6),
                     np.round(np.asarray(rows.phi_i_deg, float), 6),
                     (np.asarray(rows.side) == "T").astype(float),
                     np.round(np.mod(np.asarray(rows.phi_s_deg, float), 360.0), 6)], axis=1)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = np.asarray(group).reshape(-1)
    order = np.lexsort((np.asarray(rows.theta_s_deg, float), group))
    bounds = np.flatnonzero(np.diff(group[order])) + 1
    return [s for s in np.split(order, bounds) if s.size]


def _bandwidth(r: np.ndarray, scans: list[np.ndarray]) -> tuple[int, float]:
    """Andrews' AR(1) plug-in Bartlett bandwidth and the pooled lag-1 correlation (module doc)."""
    num = sum(float(r[s[1:]] @ r[s[:-1]]) for s in scans if s.size > 1)
    den = sum(float(r[s] @ r[s]) for s in scans if s.size > 1)
    rho = float(np.clip(num / den, 0.0, 0.97)) if den > 0 else 0.0
    lengths = [s.size for s in scans]
    t = float(np.median(lengths)) if lengths else 0.0
    alpha = (2.0 * rho / (1.0 - rho * rho)) ** 2
    lag = int(np.floor(1.1447 * (alpha * t) ** (1.0 / 3.0)))
    return max(0, min(lag, max(lengths, default=1) - 1)), rho


def _meat(g: np.ndarray, scans: list[np.ndarray], lag: int) -> np.ndarray:
    k = g.shape[1]
    m = np.zeros((k, k))
    for s in scans:
        gs = g[s]
        m += gs.T @ gs
        for lag_l in range(1, min(lag, s.size - 1) + 1):
            w = 1.0 - lag_l / (lag + 1.0)
            c = gs[lag_l:].T @ gs[:-lag_l]
            m += w * (c + c.T)
    return m


def level_nuisance(rows: Any, model: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, str]:
    """(N, text): the columns d r / d u of the plate's stated per-side level accuracy (module doc), one
    per side present, r = (y - m) / s and m -> m (1 + sd_side u) with u ~ N(0, 1), so N = -sd m / s on
    that side's rows; text says the levels (plate.uncertainty.FORWARD_LEVEL_SD)."""
    from relief_bsdf.plate.uncertainty import FORWARD_LEVEL_SD
    side = np.asarray(rows.side).astype(str)
    m = np.asarray(model, float)
    s = np.asarray(s, float)
    cols, said = [], []
    for name, sd in FORWARD_LEVEL_SD.items():
        on = side == name
        if on.any() and sd > 0:
            cols.append(np.where(on, -sd * m / np.where(s > 0, s, np.inf), 0.0))
            said.append(f"{name} +-{100 * sd:.1f} %")
    N = np.stack(cols, axis=1) if cols else np.zeros((m.size, 0))
    return N, "the forward model's stated level accuracy (" + ", ".join(said) + ")"


def shared_columns(deviations: np.ndarray, s: np.ndarray) -> np.ndarray:
    """D (n x K) of the module doc: the simulation's K table draws as deviations per row (K x n, 1/sr,
    `plate.uncertainty.deviations`) over s sqrt(K - 1); (n, 0) with fewer than two draws."""
    dev = np.asarray(deviations, float)
    K = dev.shape[0]
    s = np.asarray(s, float)
    if K < 2:
        return np.zeros((s.size, 0))
    return np.divide(dev.T, s[:, None] * np.sqrt(K - 1.0), out=np.zeros((s.size, K)), where=s[:, None] > 0)


def _shared_extra(Js: np.ndarray, ainv: np.ndarray, D: np.ndarray, f: np.ndarray) -> np.ndarray:
    """E of the module doc (k x k): the shared model noise's covariance beyond the independent rows."""
    G = Js.T @ D
    return ainv @ (G @ G.T - Js.T @ (f[:, None] * Js)) @ ainv


def _marginal_extra(Js: np.ndarray, N: np.ndarray) -> np.ndarray | None:
    """Delta = A_marg^-1 - A^-1 of the module doc (k x k), or None when A_marg is singular."""
    A = Js.T @ Js
    B = Js.T @ N
    A_marg = A - B @ np.linalg.solve(np.eye(N.shape[1]) + N.T @ N, B.T)
    if not np.all(np.isfinite(A_marg)) or np.linalg.cond(A_marg) >= SINGULAR_COND:
        return None
    return np.linalg.inv(A_marg) - np.linalg.inv(A)


def parameter_covariance(J: np.ndarray, r: np.ndarray, scans: list[np.ndarray] | None = None,
                         live: np.ndarray | None = None, nuisance: np.ndarray | None = None,
                         nuisance_text: str = "", shared: np.ndarray | None = None,
                         model_fraction: np.ndarray | None = None) -> Covariance:
    """Covariance of the parameters (module doc).  `J` (n x k) = d r / d x, `r` (n) the normalised
    residuals at the best point, `scans` from `scans_of` (None: every row its own scan, White's
    estimator), `live` (k bools, default all): the parameters the rows respond to; the others, and
    all when J^T J of the live ones is singular, are NaN.  `nuisance` (n x q): d r / d u of
    nuisance parameters with unit Gaussian priors (`level_nuisance`), marginalised (module doc).
    `shared` (n x K): the simulation's noise draws (`shared_columns`), its covariance across rows;
    `model_fraction` (n): the part of each row's s^2 that is the model's own sigma (default: the draws')."""
    J = np.asarray(J, float)
    r = np.asarray(r, float)
    n, k = J.shape
    live = np.ones(k, bool) if live is None else np.asarray(live, bool)
    scans = [np.array([i]) for i in range(n)] if scans is None else scans
    birge = max(1.0, float(r @ r) / max(n - k, 1))
    lag, rho = _bandwidth(r, scans)
    cov = np.full((k, k), np.nan)
    widen = np.ones(k)
    nw = np.ones(k)
    sw = np.ones(k)
    D = None if shared is None or np.shape(shared)[-1] < 2 else np.asarray(shared, float).reshape(n, -1)
    f_model = (None if D is None else np.sum(D * D, axis=1) if model_fraction is None
               else np.asarray(model_fraction, float))
    N = None if nuisance is None else np.asarray(nuisance, float).reshape(n, -1)
    idx = np.flatnonzero(live)
    if idx.size:
        Js = J[:, idx]
        A = Js.T @ Js
        if np.all(np.isfinite(A)) and np.linalg.cond(A) < SINGULAR_COND:
            ainv = np.linalg.inv(A)
            curv = ainv * birge
            hac = ainv @ _meat(Js * r[:, None], scans, lag) @ ainv * (n / max(n - idx.size, 1))
            sd_c = np.sqrt(np.diag(curv))
            f = np.maximum(1.0, np.sqrt(np.maximum(np.diag(hac), 0.0)) / np.where(sd_c > 0, sd_c, np.inf))
            if D is not None:
                var = np.diag(curv) + np.diag(_shared_extra(Js, ainv, D, f_model))
                sw[idx] = np.maximum(1.0, np.sqrt(np.maximum(var, 0.0)) / np.where(sd_c > 0, sd_c, np.inf))
            final = curv * np.outer(np.maximum(f, sw[idx]), np.maximum(f, sw[idx]))
            if N is not None and N.shape[1]:
                extra = _marginal_extra(Js, N)
                if extra is None:
                    final = np.full_like(final, np.nan)      # a parameter that only a level moves
                else:
                    before = np.sqrt(np.diag(final))
                    final = final + extra
                    nw[idx] = np.sqrt(np.maximum(np.diag(final), 0.0)) / np.where(before > 0, before, np.inf)
            cov[np.ix_(idx, idx)] = final
            widen[idx] = f
    return Covariance(cov=cov, birge=birge, hac_widening=widen, bandwidth=lag, lag1=rho,
                      nuisance_widening=None if N is None else np.maximum(nw, 1.0), nuisance_text=nuisance_text,
                      shared_widening=None if D is None else sw, shared_draws=0 if D is None else D.shape[1])
