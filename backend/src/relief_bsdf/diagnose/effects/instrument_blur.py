"""instrument_blur: beam divergence / detector aperture wider than stated.

Physics: the instrument's angular response is the detector cone convolved with a 2-D
Gaussian of 1-sigma b (`Instrument.blur_deg`, the plate engine's one blur definition);
Gaussians convolve by adding variances, so the fitted extra blur adds in quadrature to the
stated one.  Tables unchanged (cheap).
Validity: small angles (b of a few degrees), blur independent of the direction.  The search
stops at b = 5 deg: the detector's tangent-plane offsets hold while h + 5 b stays well below
45 deg (plate.detector, Regime), and a 5-deg 1-sigma (12 deg FWHM) is already far beyond a
goniophotometer's divergence.
"""
import math

from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    b = math.hypot(experiment.instrument.blur_deg, float(values["blur_deg"]))
    return experiment.with_instrument(blur_deg=b)


EFFECT = Effect(
    name="instrument_blur",
    params=(Param("blur_deg", 0.0, 5.0, 0.0, "deg"),),
    physics="beam divergence / detector aperture wider than stated (angular blur)",
    validity="Gaussian angular response of a few degrees, the same in every direction",
    apply=_apply,
    explain=lambda v: f"an extra angular blur of {v['blur_deg']:.2f} deg (1-sigma)",
    cheap=True,
    slow=True,
)
