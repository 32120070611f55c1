"""diffraction: the relief scatters as a wave (Kirchhoff): part of the light stays coherent.

Physics: the front face's tables come from the scalar Kirchhoff (tangent-plane) integral of
the measured height map (method "kirchhoff": coherent specular part from the relief's own
phase, diffuse part by FFT) instead of the baseline's ray-optics lobe.  No fitted parameter
(k = 0): the effect is the wave-optics face itself.  Not a candidate when the baseline is
already Kirchhoff.  The relief is taken as band-limited (directions beyond what its pitch
resolves get no scattered power: a measured map holds no finer structure); the method
still refuses reliefs whose tile or phase it cannot sample, and the candidate is then
skipped with the method's reason.
Validity: radius of curvature >> wavelength, slopes < ~0.5, single scattering at the face.
"""
from relief_bsdf.diagnose.effects._base import Effect


def _apply(experiment, context, values):
    return context.with_relief_face(experiment, context.relief, "kirchhoff", band_limited=True)


def _skip(context):
    if context.method.startswith("kirchhoff"):
        return "the baseline already is wave optics (method kirchhoff)"
    return None


EFFECT = Effect(
    name="diffraction",
    params=(),
    physics="the relief scatters as a wave (Kirchhoff): part of the light stays coherent and specular",
    validity="tangent-plane approximation: curvature radius >> wavelength, moderate slopes",
    apply=_apply,
    explain=lambda v: "scalar Kirchhoff (wave-optics) scattering at the relief instead of ray optics",
    skip_reason=_skip,
    face="swap",
)
