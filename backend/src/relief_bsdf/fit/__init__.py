"""Fit: optimise the relief's height scale and smoothing so the plate matches a recording.

    fwd = Forward(relief, experiment, recording_rows, grid)     # the one forward model (plate.simulate)
    result = fit_relief(fwd, measured, sigma)                    # least squares on (scale, filter^2)
    run_fit_job(sample.toml, out_dir)                           # `relief fit`

`fit.residual` holds the comparison (log-chi metric, residual maps, the diagnosis's chi2).
The relief operation is surface.operations.scale_and_filter (the one definition).
"""
from relief_bsdf.fit.optimise import (FIT_FORMAT, FitJob, FitResult, FitSettings, Forward, fit_relief, process_relief,
                                      relief_rms, run_fit_job)
from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric, mismatch_share, residual_map

__all__ = ["FIT_FORMAT", "FitJob", "FitResult", "FitSettings", "Forward", "fit_relief", "process_relief", "relief_rms",
           "run_fit_job", "DEFAULT_METRIC", "LogChiMetric", "mismatch_share", "residual_map"]
