"""sample_tilt: the sample was mounted tilted in the plane of incidence.

Physics: the sample normal is rotated by tilt about the instrument's y axis; incidence and
exit directions are seen in the tilted sample frame and a reading converted back with the
instrument's own cos theta_s (`Instrument.tilt_deg`, one definition in the plate engine).
Only the outside tables at the tilted incidences are new; the inside tables are re-used.
Not `cheap` (an evaluation derives those outside tables: a ray table traces rays), so budgeted:
screened by two probes and fitted on the short grid (`stepwise`, `fitting`).
Validity: a rigid rotation of a laterally infinite plate; tilts of a few degrees.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    return experiment.with_instrument(tilt_deg=experiment.instrument.tilt_deg + float(values["tilt_deg"]))


EFFECT = Effect(
    name="sample_tilt",
    params=(Param("tilt_deg", -8.0, 8.0, 0.0, "deg"),),
    physics="the sample was mounted tilted in the plane of incidence",
    validity="rigid rotation about the y axis of a laterally infinite plate",
    apply=_apply,
    explain=lambda v: f"a tilt of {v['tilt_deg']:+.2f} deg in the plane of incidence",
    cheap=False,
)
