"""stray_light: stray light adds a constant background to every reading.

Physics: f_read = f + b, b >= 0 the same for every row (`Instrument.background_per_sr`).
Tables unchanged (cheap).  The search starts from the weighted-mean residual of the
baseline (the linear least-squares value), then minimises the censored chi^2.
Validity: a background independent of the geometry (room light, detector offset).
"""
import numpy as np

from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    b = experiment.instrument.background_per_sr + float(values["background_per_sr"])
    return experiment.with_instrument(background_per_sr=b)


def _bracket(context, forward):
    v0, s0 = forward.baseline()
    rows = forward.rows
    w = 1.0 / (rows.sigma_sr**2 + s0**2)
    b0 = max(0.0, float(np.sum(w * (rows.bsdf_sr - v0)) / np.sum(w)))
    return {"background_per_sr": (0.0, min(2.0, max(3.0 * b0, 1e-3)))}


EFFECT = Effect(
    name="stray_light",
    params=(Param("background_per_sr", 0.0, 2.0, 0.0, "1/sr"),),
    physics="stray light adds a constant background to every reading",
    validity="a background independent of the measurement geometry",
    apply=_apply,
    explain=lambda v: f"a background of {v['background_per_sr']:.3g} 1/sr",
    cheap=True,
    bracket=_bracket,
)
