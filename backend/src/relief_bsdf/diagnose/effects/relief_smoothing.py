"""relief_smoothing: the real surface is smoother than measured (noise, tip artefacts).

Physics: two forms of the one effect (`Effect.forms`, the one with the lower chi^2 kept: both have
the one parameter filter_sigma_um, so the information criterion compares their chi^2):
- the paper's: h -> G_sigma * h, a Gaussian low-pass of 1-sigma sigma, by the surface's one
  scale-and-filter operation (the same the fit optimises): the map's excess is a smooth blur;
- noise removal (`noise_removed` = 1): the map is the true relief plus white measurement noise;
  the noise is removed by the Wiener filter at the map's own PSD floor (`diagnose.noise_removal`,
  the floor `relief info` estimates), then the Gaussian of sigma (0 when the floor is all there
  is).  It keeps the features whose spectrum stands above the floor (a dot's edge) where the
  Gaussian blunts them.
The front face's tables are re-derived with the baseline's method.
Validity: that of the baseline boundary method; sigma well below the tile size; the noise form
where the map's PSD flattens to a white floor near its Nyquist frequency.

Search coordinate: the rms slope the filter leaves, as a fraction of the relief's own (`_coordinate`):
in geometric optics the lobes follow the slopes, which fall steeply over a narrow range of sigma
(seed-5 concealed case06, sigma 2.36 um on a 5-um correlation length: chi^2 262 at the truth,
2560 at 2.0 um and 2170 at 2.7 um), so a grid over sigma misses the valley; over the slope
fraction it is as wide as relief_scale's (which scales the slopes linearly).
"""
import numpy as np

from relief_bsdf.diagnose.effects._base import NOISE_FORM, Effect, Param

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
    g_m = max(float(values["filter_sigma_um"]), 0.0) * 1e-6
    noise = float(values.get(NOISE_FORM, 0.0)) > 0.5
    if g_m <= 0.0 and not noise:
        return experiment
    return context.with_relief_face(experiment, context.processed_relief(1.0, g_m, noise), context.method)


def _explain(v):
    g = float(v["filter_sigma_um"])
    if float(v.get(NOISE_FORM, 0.0)) > 0.5:
        return ("the map's measurement noise removed (Wiener filter at its PSD floor)"
                + (f", then smoothed by a Gaussian of {g:.2f} um" if g > 0 else ""))
    return f"the relief smoothed by a Gaussian of {g:.2f} um"


def slope_ratio(context, filter_sigma_um: float, noise_removed: bool = False) -> float:
    """The map's rms slope over that of the relief the fitted smoothing leaves (the true relief in this
    effect's model): >= 1, 1 for no smoothing.  In geometric optics the lobes follow the slopes, so this
    is the figure a user compares with an instrument's noise: a map whose slopes read 1.5x the true ones."""
    from relief_bsdf.surface.stats import rms_height_and_slope
    true = context.processed_relief(1.0, max(float(filter_sigma_um), 0.0) * 1e-6, bool(noise_removed))
    return float(rms_height_and_slope(context.relief)[1]) / float(rms_height_and_slope(true)[1])


def derived(context, values: dict, intervals: dict) -> tuple[dict, dict]:
    """({"slope_ratio_file_over_true": r}, {the same: [r at the filter's interval ends]}): the rms-slope
    ratio the fitted smoothing implies, with the interval its filter's interval maps onto (the ratio
    grows with the filter, so the ends map to the ends)."""
    noise = float(values.get(NOISE_FORM, 0.0)) > 0.5
    r = slope_ratio(context, values["filter_sigma_um"], noise)
    iv = intervals.get("filter_sigma_um")
    ends = None if iv is None else sorted(slope_ratio(context, g, noise) for g in iv)
    return {"slope_ratio_file_over_true": r}, ({"slope_ratio_file_over_true": ends} if ends else {})


PARAM = Param("filter_sigma_um", 0.0, 8.0, 0.0, "um")

EFFECT = Effect(
    name="relief_smoothing",
    params=(PARAM,),
    physics="the real surface is smoother than measured (measurement noise / tip artefacts)",
    validity="that of the baseline boundary method; filter much smaller than the tile",
    apply=_apply,
    explain=_explain,
    face="relief",
    coordinate=_coordinate,
    forms=({NOISE_FORM: 0.0}, {NOISE_FORM: 1.0}),
)
