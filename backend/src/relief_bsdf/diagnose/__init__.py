"""The diagnosis: name every physics the simulation of a sample leaves out (`relief diagnose`).

Flow: sample.toml -> baseline Experiment of the one plate model (`forward`; what sample.toml
states, e.g. the absorption, is in it and held fixed) -> where the baseline misses the
recording (`mismatch`) -> candidate effects (`effects`, one module per effect, each a change of
the plate description; several act together through `effects.apply_all`) fitted by least
censored chi^2 (`fitting`) -> stepwise selection by BIC with a noise gate, joint refit of the
named effects (`stepwise`) -> closure test, 68 % intervals from the chi^2 curvature, which
effect explains which region, or the account of what no candidate explains (`run`) ->
the diagnosis's document (`run`) and its page (`report`), written by the job `jobs.run_diagnose`.
"""
from relief_bsdf.diagnose.effects import Effect, Param, ReliefContext, all_effects, apply_all, get_effect
from relief_bsdf.diagnose.fitting import fit_effect, intervals, refit_joint
from relief_bsdf.diagnose.forward import DEFAULT_METHOD, DiagnosisForward, build_forward
from relief_bsdf.diagnose.mismatch import attribute, classify, locate, residual_z
from relief_bsdf.diagnose.run import Diagnosis, diagnosis, select
from relief_bsdf.diagnose.stepwise import passes, stepwise

__all__ = ["Diagnosis", "diagnosis", "select", "stepwise", "passes", "fit_effect", "refit_joint", "intervals",
           "build_forward",
           "DiagnosisForward", "DEFAULT_METHOD", "Effect", "Param", "ReliefContext", "all_effects", "apply_all",
           "get_effect", "locate", "classify", "attribute", "residual_z"]
