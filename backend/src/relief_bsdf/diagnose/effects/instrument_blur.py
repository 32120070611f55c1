"""instrument_blur: the source beam diverges more than stated (angular blur of the incidence).

Physics: the incident beam's rays deviate from the nominal incidence by a 2-D Gaussian angle of
1-sigma b per axis (`Instrument.beam_divergence_deg`, one definition in the plate engine: the
deterministic engine traces it into a ray-traced relief's outside table or solves the plate at a
quadrature of incidences, the photon engine draws each photon's); Gaussians compose by adding variances, so the fitted divergence adds in quadrature to
a stated one.  Not the same as blurring the reading: off normal incidence a lobe does not move
rigidly with the incidence (the grazing flank of a reflected lobe and the transmitted lobe's
shape at 55 deg differ by up to 8-20 % between the two against the independent photon
Monte Carlo); a too-wide detector aperture is the other blur (`Instrument.blur_deg`).
Tables: the outside tables are new (traced with the beam, or at the quadrature's incidences;
budgeted: slow).
Validity: small angles (b of a few degrees, tangent-plane offsets); the search stops at b = 5 deg,
already far beyond a goniophotometer's divergence.
"""
import math

from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    b = math.hypot(experiment.instrument.beam_divergence_deg, float(values["blur_deg"]))
    return experiment.with_instrument(beam_divergence_deg=b)


EFFECT = Effect(
    name="instrument_blur",
    params=(Param("blur_deg", 0.0, 5.0, 0.0, "deg"),),
    physics="the source beam diverges more than stated (a Gaussian spread of the incidence)",
    validity="Gaussian divergence of a few degrees, the same in every direction",
    apply=_apply,
    explain=lambda v: f"a beam divergence of {v['blur_deg']:.2f} deg (1-sigma per axis)",
    cheap=False,
)
