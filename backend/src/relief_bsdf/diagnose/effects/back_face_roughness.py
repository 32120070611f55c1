"""back_face_roughness: the back face is not optically flat.

Physics: the back face (z = -t) becomes a Beckmann microfacet surface of roughness alpha
(Walter et al. 2007, rough dielectric BSDF with Smith shadowing), light from inside only;
alpha = 0 is the flat (Fresnel) face of the baseline.  In the plate description: the back
face is swapped for `MicrofacetFace(alpha)`.
Validity: geometric optics of one scattering event on the back face, alpha <~ 0.5.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param
from relief_bsdf.plate import MicrofacetFace


def _apply(experiment, context, values):
    alpha = float(values["back_alpha"])
    if alpha <= 0.0:
        return experiment
    return experiment.with_plate(back=MicrofacetFace(alpha))


EFFECT = Effect(
    name="back_face_roughness",
    params=(Param("back_alpha", 0.0, 0.5, 0.0, ""),),
    physics="the back face is not optically flat (Beckmann microfacet surface)",
    validity="geometric optics, one scattering event per crossing of the back face",
    apply=_apply,
    explain=lambda v: f"a Beckmann roughness alpha = {v['back_alpha']:.3g} on the back face",
)
