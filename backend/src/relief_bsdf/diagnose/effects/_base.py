"""What a candidate effect is: parameters, physics, and a change of the plate description.

Every module of `relief_bsdf.diagnose.effects` defines one `EFFECT = Effect(...)`:

- `params`: the fitted parameters (`Param`: name with its unit in it, bounds, neutral value);
  at the neutral values the effect is absent and `apply` returns the baseline unchanged;
- `physics` / `validity`: one line each (the docstring of the module says more);
- `apply(experiment, context, values) -> Experiment`: the effect as a change of the plate
  description (`relief_bsdf.plate.description`), nothing else: a bulk field, an instrument
  field, a face swap, an index change.  The forward model is always the one plate model;
- `explain(values) -> str`: the fitted values in words, for diagnosis.json's explanation;
- `skip_reason(context) -> str | None`: why the effect is not a candidate for this sample
  (e.g. `interreflection` when the baseline already traces the relief, `dispersion` on a
  one-wavelength recording, a physics the deterministic engine cannot express yet); a
  skipped effect is listed in `candidates` with its reason and never fitted (no fake);
- `cheap`: True when the effect leaves every boundary table as it is (bulk, instrument),
  so an evaluation re-uses the baseline's tables (the fit grid can then be finer);
- `slow`: True for a cheap effect whose evaluation still takes seconds (the adding-doubling
  slab of a scattering bulk); `budgeted` (not cheap, or slow) effects get the short fit grid
  (`fitting`; every candidate is screened before it is fitted, `stepwise`);
- `stokes`: True for an effect that acts through the light's polarisation (the source's Stokes
  vector): its screen evaluates on the Stokes loop (`forward.DiagnosisForward.screening`);
- `bracket(context, forward) -> {param: (lo, hi)}`: optional narrower search interval
  derived from the data (e.g. the weighted-mean background for stray light);
- `coordinate(context) -> {param: (to_u, from_u)}`: optional monotone search coordinate u of a
  parameter on which the rows depend very unevenly (the relief filter: the rows follow the
  slopes it leaves, which fall steeply over a small range of the filter width, so a grid on the
  width misses the optimum); the fits search on u (`diagnose.fitting`);
- `face`: "" for an effect that leaves the relief face alone, "relief" for an operation on the
  measured relief (relief_scale, relief_smoothing: they compose into the one
  scale-and-filter operation, `apply_all`), "swap" for a different face physics
  (diffraction, partial_coherence, interreflection: at most one face swap in a combination,
  and never together with a relief operation, whose tables belong to the baseline's method).

Several effects act together by applying them one after the other (`apply_all`): each is a
change of a different part of the description (bulk, instrument, index, back face), except
the relief operations, which are merged into one scale-and-filter of the measured relief.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from relief_bsdf.surface.relief import Relief


@dataclass(frozen=True)
class Param:
    """One fitted parameter: name (unit in the name), bounds, the value meaning "no effect"."""

    name: str
    lower: float
    upper: float
    neutral: float
    units: str
    log_scale: bool = False       # search on log10 (a width ~ 1 / value); the neutral value is tried too

    def __post_init__(self) -> None:
        if not (self.lower < self.upper):
            raise ValueError(f"parameter {self.name}: lower bound must be below the upper bound")
        if self.log_scale and self.lower <= 0:
            raise ValueError(f"parameter {self.name}: a log-scale search needs lower > 0")


@dataclass(frozen=True)
class ReliefContext:
    """What the effects need to know about the sample besides the Experiment.

    relief: the measured relief (plane-levelled), the baseline front face's relief.
    method: the boundary method of the baseline's relief face (`relief diagnose --method`).
    face: `face(relief, method, **options)` builds a front face (the plate's ReliefFace).
    scale_and_filter: the ONE relief operation the fit optimises, (relief, s, sigma_m) -> Relief.
    wavelengths_nm: the recording's wavelengths; detector_half_angle_deg: the stated cone.
    method_reason: why the baseline uses `method` (auto's one line; "" when it was named).
    known: effects whose value sample.toml states (e.g. plate.absorption_per_mm for
    bulk_absorption), with the reason; they are held fixed at the stated value, never fitted.
    """

    relief: Relief
    method: str
    face: Callable[..., Any]
    scale_and_filter: Callable[[Relief, float, float], Relief]
    wavelengths_nm: tuple
    detector_half_angle_deg: float
    samples: int = 200_000
    seed: int = 0
    method_reason: str = ""
    known: tuple = ()                 # ((effect name, reason it is held fixed), ...) from sample.toml
    _reliefs: dict = field(default_factory=dict, compare=False, repr=False)

    def with_relief_face(self, experiment: Any, relief: Relief, method: str, **options: Any) -> Any:
        """`experiment` with its relief face rebuilt from `relief` by `method` (the one place that
        knows which face carries the relief: the lit front face, as `diagnose.forward` requires)."""
        return experiment.with_plate(front=self.face(relief, method, **options))

    @property
    def spectral(self) -> bool:
        return len(set(self.wavelengths_nm)) > 1

    def processed_relief(self, height_scale: float, filter_sigma_m: float, noise_removed: bool = False) -> Relief:
        """scale_and_filter(relief, s, sigma), memoised so that the plate's table cache sees one object;
        `noise_removed`: of the relief with its measurement noise removed first (`diagnose.noise_removal`:
        a Wiener filter at the map's own PSD floor)."""
        key = (round(float(height_scale), 12), round(max(float(filter_sigma_m), 0.0), 15), bool(noise_removed))
        if key == (1.0, 0.0, False):
            return self.relief
        if key not in self._reliefs:
            base = self.relief
            if noise_removed:
                if "denoised" not in self._reliefs:
                    from relief_bsdf.diagnose.noise_removal import remove_noise
                    self._reliefs["denoised"] = remove_noise(self.relief)
                base = self._reliefs["denoised"]
            self._reliefs[key] = (base if key[:2] == (1.0, 0.0) else self.scale_and_filter(base, key[0], key[1]))
        return self._reliefs[key]


def _no_skip(context: ReliefContext) -> str | None:
    return None


@dataclass(frozen=True)
class Effect:
    """A candidate effect (see the module docstring)."""

    name: str
    params: tuple
    physics: str
    validity: str
    apply: Callable[[Any, ReliefContext, dict], Any]
    explain: Callable[[dict], str]
    cheap: bool = False
    slow: bool = False
    stokes: bool = False
    skip_reason: Callable[[ReliefContext], "str | None"] = _no_skip
    bracket: Callable[[ReliefContext, Any], dict] | None = None
    face: str = ""
    coordinate: Callable[[ReliefContext], dict] | None = None
    forms: tuple = ()                 # alternative forms of the one effect: ({key: value}, ...) held fixed
                                      # in its fit, the one with the lower chi^2 kept (`fitting.fit_effect`)

    @property
    def neutral(self) -> dict:
        return {p.name: p.neutral for p in self.params}

    @property
    def budgeted(self) -> bool:
        """An evaluation costs seconds (new boundary tables, or a slow cheap effect): short fit grids
        (`fitting`)."""
        return not self.cheap or self.slow

    @property
    def k(self) -> int:
        """Number of fitted parameters (the BIC penalty counts them)."""
        return len(self.params)


# relief_smoothing's form (`Effect.forms`): 1 = the map's measurement noise removed (Wiener filter at its PSD
# floor, `diagnose.noise_removal`) before the Gaussian of filter_sigma_um; 0 = the Gaussian alone
NOISE_FORM = "noise_removed"


def compatible(effects) -> bool:
    """Can these effects act together on one plate?  At most one face swap, and a face swap never
    with a relief operation (module docstring, `face`)."""
    swaps = sum(e.face == "swap" for e in effects)
    ops = sum(e.face == "relief" for e in effects)
    return swaps == 0 or (swaps == 1 and ops == 0)


def apply_all(experiment: Any, context: ReliefContext, effects, values: dict) -> Any:
    """The plate description with every effect of `effects` at `values` (module docstring).

    Non-face effects are applied one after the other (each changes its own part of the
    description); the relief operations are merged: heights scaled by `height_scale` and
    low-passed by `filter_sigma_um` in ONE `processed_relief(s, sigma)` (their neutral values
    when the effect is absent; of the map with its noise removed first when relief_smoothing's
    form says so, NOISE_FORM), then the face is rebuilt once with the baseline's method.
    """
    ops = [e for e in effects if e.face == "relief"]
    for e in effects:
        if e.face != "relief":
            experiment = e.apply(experiment, context, values)
    if ops:
        s = float(values.get("height_scale", 1.0)) if any(e.name == "relief_scale" for e in ops) else 1.0
        smooth = any(e.name == "relief_smoothing" for e in ops)
        g_um = float(values.get("filter_sigma_um", 0.0)) if smooth else 0.0
        noise = smooth and float(values.get(NOISE_FORM, 0.0)) > 0.5
        if (s, max(g_um, 0.0), noise) != (1.0, 0.0, False):
            experiment = context.with_relief_face(experiment,
                                                  context.processed_relief(s, max(g_um, 0.0) * 1e-6, noise),
                                                  context.method)
    return experiment
