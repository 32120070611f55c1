"""refractive_index: the stated index is off (a common data-sheet error of 0.005 - 0.05).

Physics: n(l) = n_stated(l) + dn at every wavelength; Fresnel coefficients, refraction
angles and the boundary tables change (re-derived with the new index).
Validity: a constant offset; a wavelength-dependent error is `dispersion`.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param
from relief_bsdf.diagnose.effects._index import perturbed


def _apply(experiment, context, values):
    dn = float(values["index_offset"])
    if dn == 0.0:
        return experiment
    wls = sorted(set(context.wavelengths_nm))
    return experiment.with_plate(index=perturbed(experiment.plate.index, wls[len(wls) // 2], offset=dn))


EFFECT = Effect(
    name="refractive_index",
    params=(Param("index_offset", -0.06, 0.06, 0.0, ""),),
    physics="the glass's refractive index is off from the stated one by a constant",
    validity="a wavelength-independent offset of the stated index model",
    apply=_apply,
    explain=lambda v: f"the stated index changed by {v['index_offset']:+.4f}",
)
