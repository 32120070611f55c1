"""Comparison of a simulated plate BSDF with a goniophotometer recording.

THE metric (`rms_z`, the one number `relief simulate`, `relief fit`, `relief diagnose` and their
reports call "metric", in fit.json and diagnosis.json as rms_before / rms_after):

    rms z = sqrt(chi^2 / n),  chi^2 = sum_k z_k^2 over all n recording rows,
    z_k = (measured_k - simulated_k) / s_k,  s_k^2 = sigma_k^2 + sigma_model_k^2

the noise-normalised residual of the likelihood (`chi2`: a reading clipped at zero is censored,
Tobit; an unknown sigma_k takes io.recording's documented fallback; sigma_model_k is the
simulation's own 1-sigma, its tables' Monte-Carlo noise through the plate).  1 = agreement to the
noise; the forward model is required to reach 1.2 on clean independent recordings.

The fit's search device ("log-chi", `LogChiMetric`, not the metric: the fit reports it as each
evaluation's `search` value): a BSDF spans many decades (a specular peak 1e3-1e5 times the wings), so
differences are taken on logarithms, each normalised by its uncertainty:

    r_k = [ln(sim_k + b) - ln(meas_k + b)] / s_k
    s_k = sqrt( (sigma_k^2 + sigma_model_k^2) / (meas_k + b)^2 + q^2 )
    metric = sqrt(mean_k r_k^2)

- b (floor, 1/sr) = max(`floor_rel` x median(meas), the recording's noise floor = the
  `noise_quantile` quantile of its known sigma): values far below the floor (dark noise, the
  detector's stray light) count as "about zero", so the metric does not chase noise in the
  deep wings.  With b at least the noise floor, ln(x + b) is close to linear over a row's
  noise, so a simulation that agrees with the recording scores ~1; with b below it (a
  recording whose wings sit at the detector's floor, readings clipped at 0) the log stretches
  noise around zero and a perfect simulation scored ~1.4.
- sigma_k / (meas_k + b) is the row's 1-sigma uncertainty propagated to ln (first order);
  where sigma is unknown (NaN) `default_rel_sigma` of the value is assumed.
- sigma_model_k is the simulation's own 1-sigma (its boundary tables' Monte-Carlo noise and
  tile realisation carried through the plate, plate.uncertainty), when known.
- q = `model_rel` is a relative model/calibration floor added in quadrature (default 1 %).

A recording that agrees with the simulation within its noise gives metric ~ 1 (chi-like);
below 1 is "within the noise".  `describe()` is the text written to fit.json's "metric".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class LogChiMetric:
    floor_rel: float = 1e-2
    default_rel_sigma: float = 0.05
    model_rel: float = 0.01
    noise_quantile: float | None = 0.1          # None: no noise-floor term

    def floor(self, meas: np.ndarray, sigma: np.ndarray | None = None) -> float:
        m = np.asarray(meas, float)
        pos = m[np.isfinite(m) & (m > 0)]
        b = float(self.floor_rel * np.median(pos)) if pos.size else 1e-12
        if sigma is not None and self.noise_quantile is not None:
            s = np.asarray(sigma, float)
            s = s[np.isfinite(s) & (s > 0)]
            if s.size:
                b = max(b, float(np.quantile(s, self.noise_quantile)))
        return b

    def sigma_log(self, meas: np.ndarray, sigma: np.ndarray | None, model_sigma: np.ndarray | None = None
                  ) -> np.ndarray:
        m = np.asarray(meas, float)
        b = self.floor(m, sigma)
        s = np.full(m.shape, np.nan) if sigma is None else np.asarray(sigma, float)
        s = np.where(np.isfinite(s), s, self.default_rel_sigma * np.abs(m))
        if model_sigma is not None:
            s = np.sqrt(s**2 + np.nan_to_num(np.asarray(model_sigma, float)) ** 2)
        return np.sqrt((s / (np.abs(m) + b)) ** 2 + self.model_rel**2)

    def residuals(self, sim: Any, meas: Any, sigma: Any = None, model_sigma: Any = None) -> np.ndarray:
        """Normalised residuals r_k (sim above the measurement: positive)."""
        sim = np.asarray(sim, float)
        meas = np.asarray(meas, float)
        b = self.floor(meas, sigma)
        d = np.log(np.maximum(sim, 0.0) + b) - np.log(np.maximum(meas, 0.0) + b)
        return d / self.sigma_log(meas, sigma, model_sigma)

    def value(self, sim: Any, meas: Any, sigma: Any = None, model_sigma: Any = None) -> float:
        r = self.residuals(sim, meas, sigma, model_sigma)
        return float(np.sqrt(np.mean(r**2))) if r.size else 0.0

    def describe(self) -> str:
        return ("log-chi: sqrt(mean(r^2)), r = [ln(sim + b) - ln(meas + b)] / s, b = max("
                f"{self.floor_rel:g} x median(measured), the {self.noise_quantile:g} quantile of the recording's "
                "sigma) (floor, 1/sr), s = sqrt((sigma/(meas + b))^2 + "
                f"{self.model_rel:g}^2), sigma^2 = recording sigma^2 + the simulation's own sigma^2 (sigma "
                f"unknown: {self.default_rel_sigma:g} x meas); "
                "1 = agreement within the recording's noise")


DEFAULT_METRIC = LogChiMetric()      # the fit's search objective (module doc), not the reported metric

METRIC = ("rms z = sqrt(chi2 / n) over all n recording rows, z = (measured - simulated) / s, s^2 = recording "
          "sigma^2 + the simulation's own sigma^2 (unknown recording sigma: the documented fallback), a reading "
          "clipped at zero censored (Tobit); 1 = agreement to the noise")


def rms_z(measured: Any, sigma: Any, simulated: Any, model_sigma: Any = None) -> float:
    """The metric (module doc): sqrt(chi^2 / n) of `simulated` against the recording's `measured`
    values and 1-sigma `sigma` (None or NaN: io.recording's fallback), `model_sigma` the simulation's
    own 1-sigma per row (None: 0)."""
    r = z_residuals(measured, sigma, simulated, model_sigma)
    return metric_of_chi2(float(r @ r), r.size)


def metric_of_chi2(chi2_value: float, n: int) -> float:
    """The metric from a chi^2 of `chi2` over n rows: sqrt(chi^2 / n) (0 without rows)."""
    return float(np.sqrt(chi2_value / n)) if n else 0.0


def z_residuals(measured: Any, sigma: Any, simulated: Any, model_sigma: Any = None) -> np.ndarray:
    """The z_k whose rms is `rms_z` (for residual maps): + where the recording is above the simulation."""
    from relief_bsdf.io.recording import sigma_with_fallback
    y = np.asarray(measured, float)
    s = sigma_with_fallback(y, sigma)
    if model_sigma is not None:
        s = np.sqrt(s**2 + np.nan_to_num(np.asarray(model_sigma, float)) ** 2)
    return signed_residuals(y, np.asarray(simulated, float), s)


def residual_map(rec: Any, sim: Any, metric: LogChiMetric = DEFAULT_METRIC) -> dict:
    """Residuals grouped for plotting: {(side, phi_rel): (theta_i list, signed theta_s list, r)}.

    Signed scatter angle: negative on the phi_s = phi_i + 180 half-plane (specular /
    undeviated side), positive on phi_s = phi_i (paper figs. 4 and 9).
    """
    r = metric.residuals(sim, rec.bsdf_sr, rec.sigma_sr)
    rel = np.mod(np.asarray(rec.phi_s_deg) - np.asarray(rec.phi_i_deg), 360.0)
    signed = np.where(np.abs(rel - 180.0) < 90.0, -1.0, 1.0) * np.asarray(rec.theta_s_deg)
    out = {}
    for sd in ("R", "T"):
        m = np.asarray(rec.side) == sd
        if m.any():
            out[sd] = (np.asarray(rec.theta_i_deg)[m], signed[m], r[m])
    return out


def mismatch_share(rec: Any, sim: Any, metric: LogChiMetric = DEFAULT_METRIC) -> list[dict]:
    """Where the squared residual lives: share per (side, theta_i), largest first."""
    r2 = metric.residuals(sim, rec.bsdf_sr, rec.sigma_sr) ** 2
    tot = float(r2.sum()) or 1.0
    out = []
    for sd in ("R", "T"):
        for ti in np.unique(rec.theta_i_deg):
            m = (np.asarray(rec.side) == sd) & (np.asarray(rec.theta_i_deg) == ti)
            if m.any():
                out.append({"side": sd, "theta_i_deg": float(ti), "share": float(r2[m].sum() / tot)})
    return sorted(out, key=lambda d: -d["share"])


def chi2(rows: Any, model: np.ndarray, model_sigma: np.ndarray | None = None) -> float:
    """Noise-weighted misfit of a simulation on recording rows (censored Gaussian, Tobit likelihood).

    s^2 = sigma_recording^2 + sigma_model^2 (rows.sigma_sr finite: Recording.with_sigma_fallback).
    Rows with a measured value > 0 contribute ((y - m) / s)^2.  recording.csv holds no negative
    BSDF values, so a reading at exactly 0 is a reading clipped at zero (Tobin 1958): it
    contributes -2 ln(2 Phi(-m / s)), the log-probability of reading <= 0, shifted so that m = 0
    costs nothing (as z^2 would).  Without this, clipped noise reads as a positive background.
    Used by the diagnosis (selection by BIC = chi2 + k ln n).
    """
    model = np.asarray(model, float)
    r = signed_residuals(np.asarray(rows.bsdf_sr, float), model, misfit_sigma(rows, model_sigma))
    return float(r @ r)


def misfit_sigma(rows: Any, model_sigma: np.ndarray | None = None) -> np.ndarray:
    """s of `chi2` per row: sqrt(sigma_recording^2 + sigma_model^2) (no model sigma: the recording's)."""
    var = np.asarray(rows.sigma_sr, float) ** 2
    return np.sqrt(var if model_sigma is None else var + np.asarray(model_sigma, float) ** 2)


def signed_residuals(measured: np.ndarray, model: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The residuals r of `chi2` (r @ r = chi^2): (y - m) / s, and for a reading clipped at zero minus
    the square root of its censored term -2 ln(2 Phi(-m / s)) (the model above the reading)."""
    from scipy.special import log_ndtr
    y = np.asarray(measured, float)
    model = np.asarray(model, float)
    r = (y - model) / s
    cens = y <= 0
    if cens.any():
        r[cens] = -np.sqrt(np.maximum(-2.0 * (log_ndtr(-model[cens] / s[cens]) + np.log(2.0)), 0.0))
    return r
