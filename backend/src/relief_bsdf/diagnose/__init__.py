"""The diagnosis: name the physics the simulation of a sample leaves out (`relief diagnose`).

Flow: sample.toml -> baseline Experiment of the one plate model (`forward`) -> where the
baseline misses the recording (`mismatch`) -> every candidate effect (`effects`, one module
per effect, each a change of the plate description) fitted by least censored chi^2
(`fitting`) -> selection by BIC with a noise gate (`run.select`) -> diagnosis.json and
report.html (`run`, `report`).
"""
from relief_bsdf.diagnose.effects import Effect, Param, ReliefContext, all_effects, get_effect
from relief_bsdf.diagnose.fitting import fit_effect
from relief_bsdf.diagnose.forward import DEFAULT_METHOD, DiagnosisForward, build_forward
from relief_bsdf.diagnose.mismatch import classify, locate, residual_z
from relief_bsdf.diagnose.run import diagnose, select

__all__ = ["diagnose", "select", "fit_effect", "build_forward", "DiagnosisForward",
           "DEFAULT_METHOD", "Effect", "Param", "ReliefContext", "all_effects", "get_effect", "locate", "classify",
           "residual_z"]
