"""relief_smoothing: the real surface is smoother than measured (noise, tip artefacts).

Physics: h -> G_sigma * h, a Gaussian low-pass of 1-sigma sigma, by the surface's one
scale-and-filter operation (the same the fit optimises); the front face's tables are
re-derived with the baseline's method.
Validity: that of the baseline boundary method; sigma well below the tile size.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    g_m = float(values["filter_sigma_um"]) * 1e-6
    if g_m <= 0.0:
        return experiment
    return context.with_relief_face(experiment, context.processed_relief(1.0, g_m), context.method)


EFFECT = Effect(
    name="relief_smoothing",
    params=(Param("filter_sigma_um", 0.0, 8.0, 0.0, "um"),),
    physics="the real surface is smoother than measured (measurement noise / tip artefacts)",
    validity="that of the baseline boundary method; filter much smaller than the tile",
    apply=_apply,
    explain=lambda v: f"the relief smoothed by a Gaussian of {v['filter_sigma_um']:.2f} um",
    face="relief",
)
