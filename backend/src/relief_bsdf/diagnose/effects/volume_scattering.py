"""volume_scattering: the glass bulk scatters light (Henyey-Greenstein volume scattering).

Physics: free paths between volume events ~ Exp(mu_s); at an event the direction changes
by the Henyey-Greenstein phase function of asymmetry g (Henyey & Greenstein 1941),
polarisation carried unchanged (scalar approximation).  In the plate description:
`Bulk.scatter_per_m`, `Bulk.hg_g` (the deterministic engine's slab operators); the boundary
tables do not change (cheap).
Validity: dilute scatterers, independent scattering, radiative transfer in the bulk.
"""
from relief_bsdf.diagnose.effects._base import Effect, Param


def _apply(experiment, context, values):
    if float(values["scatter_per_mm"]) <= 0.0:
        return experiment                 # no scatterers: g means nothing
    return experiment.with_bulk(scatter_per_m=float(values["scatter_per_mm"]) * 1e3, hg_g=float(values["hg_g"]))


EFFECT = Effect(
    name="volume_scattering",
    params=(Param("scatter_per_mm", 0.0, 3.0, 0.0, "1/mm"), Param("hg_g", 0.0, 0.95, 0.7, "")),
    physics="the glass bulk scatters light (Henyey-Greenstein volume scattering)",
    validity="dilute independent scatterers; polarisation carried unchanged through a volume event",
    apply=_apply,
    explain=lambda v: (f"a scattering coefficient of {v['scatter_per_mm']:.3g} per mm with Henyey-Greenstein "
                       f"asymmetry g = {v['hg_g']:.2f}"),
    cheap=True,
    slow=True,
)
