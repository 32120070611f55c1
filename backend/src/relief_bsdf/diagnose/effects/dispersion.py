"""dispersion: the glass index depends on the wavelength, unlike stated.

Physics: n(l) = n_stated(l) + B (1 / l^2 - 1 / l_ref^2) (Cauchy term, l_ref the middle
recorded wavelength, so the index there is unchanged); the boundary tables are re-derived
per wavelength with the new index.  Only for spectral recordings.
Validity: transparent range of the glass (Cauchy).
"""
from relief_bsdf.diagnose.effects._base import Effect, Param
from relief_bsdf.diagnose.effects._index import perturbed


def _apply(experiment, context, values):
    b = float(values["cauchy_B_nm2"])
    if b == 0.0:
        return experiment
    wls = sorted(set(context.wavelengths_nm))
    return experiment.with_plate(index=perturbed(experiment.plate.index, wls[len(wls) // 2], cauchy_B_nm2=b))


def _skip(context):
    return None if context.spectral else "needs a spectral recording (one wavelength recorded)"


EFFECT = Effect(
    name="dispersion",
    params=(Param("cauchy_B_nm2", -40000.0, 80000.0, 0.0, "nm^2"),),
    physics="the glass index depends on wavelength (Cauchy B) unlike stated",
    validity="transparent range of the glass",
    apply=_apply,
    explain=lambda v: f"a Cauchy B of {v['cauchy_B_nm2']:.4g} nm^2 added to the stated index",
    skip_reason=_skip,
)
