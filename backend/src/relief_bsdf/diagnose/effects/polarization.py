"""polarization: the source is polarised, unlike stated.

Physics: source Stokes vector (1, q, 0, 0) in the s/p basis of the plane of incidence,
q = +1 s, -1 p; by linearity the reading is ((1 + q) I_s + (1 - q) I_p) / 2
(`Instrument.polarization_q`).  The fitted q replaces the stated one (neutral 0 =
unpolarised, formats.md's default).  Tables unchanged (cheap).
Validity: a fully or partly linearly polarised source along s or p (no S2, S3 component).
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    return experiment.with_instrument(polarization_q=float(values["polarization_q"]))


def _explain(v):
    q = v["polarization_q"]
    return f"a source Stokes S1/S0 = {q:+.2f} ({'s' if q > 0 else 'p'}-polarised)"


EFFECT = Effect(
    name="polarization",
    params=(Param("polarization_q", -1.0, 1.0, 0.0, ""),),
    physics="the source is polarised (q = +1 s, -1 p) unlike stated",
    validity="linear polarisation along s or p of the plane of incidence",
    apply=_apply,
    explain=_explain,
    cheap=True,
    stokes=True,
)
