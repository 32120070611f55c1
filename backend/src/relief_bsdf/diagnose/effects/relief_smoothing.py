"""relief_smoothing: the real surface is smoother than measured (noise, tip artefacts).

Physics: h -> G_sigma * h, a Gaussian low-pass of 1-sigma sigma, by the surface's one
scale-and-filter operation (the same the fit optimises); the front face's tables are
re-derived with the baseline's method.
Validity: that of the baseline boundary method; sigma well below the tile size.

Search coordinate: the rms slope the filter leaves, as a fraction of the relief's own (`_coordinate`):
in geometric optics the lobes follow the slopes, which fall steeply over a narrow range of sigma
(seed-5 concealed case06, sigma 2.36 um on a 5-um correlation length: chi^2 262 at the truth,
2560 at 2.0 um and 2170 at 2.7 um), so a grid over sigma misses the valley; over the slope
fraction it is as wide as relief_scale's (which scales the slopes linearly).
"""
import numpy as np

from relief_bsdf.diagnose.effects._base import Effect, Param

COORDINATE_POINTS = 65


def _coordinate(context):
    """{filter_sigma_um: (to_u, from_u)}: u = rms slope after the filter / rms slope of the relief, from
    the surface's one scale-and-filter operation and surface.stats' one rms slope, tabulated on
    sigma in [0, 8] um (monotone decreasing) and interpolated both ways."""
    from relief_bsdf.surface.stats import rms_height_and_slope
    sig = np.linspace(0.0, PARAM.upper, COORDINATE_POINTS)
    m0 = float(rms_height_and_slope(context.relief)[1])
    u = np.array([1.0] + [float(rms_height_and_slope(context.scale_and_filter(context.relief, 1.0, g * 1e-6))[1]) / m0
                          for g in sig[1:]])
    u = np.minimum.accumulate(u)                      # monotone (round-off on a nearly flat tail)
    return {"filter_sigma_um": (lambda x: float(np.interp(x, sig, u)),
                                lambda v: float(np.interp(-v, -u, sig)))}


def _apply(experiment, context, values):
    g_m = float(values["filter_sigma_um"]) * 1e-6
    if g_m <= 0.0:
        return experiment
    return context.with_relief_face(experiment, context.processed_relief(1.0, g_m), context.method)


PARAM = Param("filter_sigma_um", 0.0, 8.0, 0.0, "um")

EFFECT = Effect(
    name="relief_smoothing",
    params=(PARAM,),
    physics="the real surface is smoother than measured (measurement noise / tip artefacts)",
    validity="that of the baseline boundary method; filter much smaller than the tile",
    apply=_apply,
    explain=lambda v: f"the relief smoothed by a Gaussian of {v['filter_sigma_um']:.2f} um",
    face="relief",
    coordinate=_coordinate,
)
