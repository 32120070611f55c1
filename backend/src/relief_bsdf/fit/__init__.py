"""Fit: optimise the relief's height scale and smoothing so the plate matches a recording.

    b = baseline(sample, method=..., grid=...)                   # the sample's plate (fit.baseline)
    fwd = Forward.of(b)                                          # the one forward model (fit.forward)
    result = fit_relief(fwd, measured, sigma)                    # least squares on (scale, filter^2)

The whole `relief fit` job (reading the sample, writing fit.json, tables, plots and the report) is
`relief_bsdf.jobs.run_fit`.  `fit.residual` holds the comparison (log-chi metric, residual maps, the
diagnosis's chi2).  The relief operation is surface.operations.scale_and_filter (the one definition).
"""
from relief_bsdf.fit.baseline import Baseline, baseline, resolved, sample_relief
from relief_bsdf.fit.forward import Forward, PlateForward, process_relief
from relief_bsdf.fit.optimise import FIT_FORMAT, FitResult, FitSettings, fit_relief, relief_rms
from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric, mismatch_share, residual_map

__all__ = ["FIT_FORMAT", "Baseline", "FitResult", "FitSettings", "Forward", "PlateForward", "baseline", "fit_relief",
           "process_relief", "relief_rms", "resolved", "sample_relief", "DEFAULT_METRIC", "LogChiMetric",
           "mismatch_share", "residual_map"]
