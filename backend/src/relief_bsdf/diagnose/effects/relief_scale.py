"""relief_scale: the relief's heights are off by a factor (profilometer calibration).

Physics: h -> s h, by the surface's one scale-and-filter operation (the same the fit
optimises); the front face's tables are re-derived from the scaled relief with the
baseline's method.
Validity: that of the baseline method; a pure geometric-optics method sees slopes only, so
on Gaussian reliefs a scale below 1 resembles smoothing.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    s = float(values["height_scale"])
    if s == 1.0:
        return experiment
    return context.with_relief_face(experiment, context.processed_relief(s, 0.0), context.method)


EFFECT = Effect(
    name="relief_scale",
    params=(Param("height_scale", 0.3, 2.5, 1.0, ""),),
    physics="the relief's heights are off by a factor (instrument calibration)",
    validity="that of the baseline boundary method",
    apply=_apply,
    explain=lambda v: f"heights scaled by {v['height_scale']:.3f}",
    face="relief",
)
