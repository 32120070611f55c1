"""partial_coherence: wave scattering lit by a partially coherent source.

Physics: the Kirchhoff face (method "kirchhoff") lit by a Gaussian Schell-model source of
coherence length l_c (the method's coherence-length option: random phase screens, mutual
coherence ~ exp(-r^2 / l_c^2)); the coherent specular beam becomes a lobe of angular width
~ lambda / (pi l_c).  l_c = 0 (neutral) is the baseline.  Fitted on a log scale between
two relief pixels and lambda / (pi h) (h the detector half-angle): a longer coherence
length is not resolved by the instrument and the case is `diffraction`.
Validity: that of the Kirchhoff method; l_c between 2 pixels and a quarter of the tile.
"""
import math

from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    lc_m = float(values["coherence_length_um"]) * 1e-6
    if lc_m <= 0.0:
        return experiment
    return context.with_relief_face(experiment, context.relief, "kirchhoff", band_limited=True,
                                    coherence_length_m=lc_m)


def _bracket(context, forward):
    pitch_um = max(context.relief.dx_m, context.relief.dy_m) * 1e6
    wl_um = sorted(context.wavelengths_nm)[len(context.wavelengths_nm) // 2] * 1e-3
    lo = max(0.3, 2.0 * pitch_um)
    hi = min(30.0, wl_um / (math.pi * math.radians(context.detector_half_angle_deg)))
    return {"coherence_length_um": (lo, max(hi, 1.01 * lo))}


EFFECT = Effect(
    name="partial_coherence",
    params=(Param("coherence_length_um", 0.3, 30.0, 0.0, "um", log_scale=True),),
    physics="wave scattering lit by a partially coherent source: the specular peak is broadened",
    validity="Kirchhoff method; coherence length between 2 pixels and a quarter of the tile",
    apply=_apply,
    explain=lambda v: (f"Kirchhoff scattering lit by a source of coherence length {v['coherence_length_um']:.3g} um "
                       f"(the coherent beam spread over lambda / (pi l_c))"),
    bracket=_bracket,
    face="swap",
)
