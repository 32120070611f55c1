"""interreflection: light bounces more than once on the relief and is shadowed by it.

Physics: the front face's tables come from geometric-optics ray tracing of the triangulated
relief (method "ray": shadowing, masking, multiple bounces, Fresnel Mueller matrices)
instead of the baseline's single-scatter model.  No fitted parameter (k = 0): the effect is
the ray-traced relief itself.  Not a candidate when the baseline already traces the relief.
Validity: geometric optics, facets >= 10 wavelengths; matters for steep reliefs (rms slope
>~ 0.3) at grazing angles.
"""
from relief_bsdf.diagnose.effects._base import Effect


def _apply(experiment, context, values):
    return context.with_relief_face(experiment, context.relief, "ray")


def _skip(context):
    if context.method == "ray":
        return "the baseline already traces the relief (method ray)"
    return None


EFFECT = Effect(
    name="interreflection",
    params=(),
    physics="light bounces more than once on the relief and is shadowed by it (ray-traced real relief)",
    validity="geometric optics, facets much larger than the wavelength",
    apply=_apply,
    explain=lambda v: "the relief ray traced (shadowing, masking and multiple bounces) instead of single scattering",
    skip_reason=_skip,
    face="swap",
)
