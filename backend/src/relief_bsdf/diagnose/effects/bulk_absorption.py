"""bulk_absorption: the glass absorbs (Beer-Lambert), more on longer paths.

Physics: a path of length L in the glass keeps exp(-a L) of its power (Beer-Lambert law);
the fitted a adds to the absorption sample.toml states (0 when not known).  In the plate
description it is `Bulk.absorption_per_m`; the boundary tables do not change (cheap).
Validity: homogeneous, weakly absorbing glass (k << n, a lambda << 1), intensities add.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    a_per_m = float(values["absorption_per_mm"]) * 1e3
    return experiment.with_bulk(absorption_per_m=experiment.plate.bulk.absorption_per_m + a_per_m)


EFFECT = Effect(
    name="bulk_absorption",
    params=(Param("absorption_per_mm", 0.0, 3.0, 0.0, "1/mm"),),
    physics="light is absorbed in the glass (Beer-Lambert), more on longer paths",
    validity="homogeneous weakly absorbing bulk, geometric optics between the faces",
    apply=_apply,
    explain=lambda v: f"an absorption coefficient of {v['absorption_per_mm']:.3g} per mm",
    cheap=True,
)
