"""The search cannot contradict itself: a residual's signature forces its candidate's
fit, a fit that ends at its null value is refitted from spread starts, boundary methods are a verdict on
the method (method_check), never an effect, and trading pairs are reported with their correlation.

Oracles: stand-in forward models whose rows are closed-form functions of the parameters, with Gaussian
noise of known sigma from a seed (test_stepwise.AnalyticForward), so the right answer is known."""
import importlib
import math

import numpy as np
import pytest

from relief_bsdf.diagnose.effects import get_effect
from relief_bsdf.diagnose.fitting import at_null, fit_effect
from relief_bsdf.diagnose.stepwise import method_check, stepwise, steps_record

from test_stepwise import AnalyticForward  # noqa: E402  (tests/backend/diagnose)

sw = importlib.import_module("relief_bsdf.diagnose.stepwise")
fitting = importlib.import_module("relief_bsdf.diagnose.fitting")

ALPHA_TRUE = 0.033


class TrapForward(AnalyticForward):
    """Rows with a back-face-roughness-like response that is strongly non-linear in alpha: nothing below
    alpha 0.02 (the back face's lobe stays inside the detector's specular cone), a haze that grows to its
    full size at alpha 0.033 and turns into a loss beyond 0.046, so the grid of alpha over [0, 0.5] sees
    only the loss and the Gauss-Newton steps from alpha 0 (a difference step of 3 % of the range) see no
    slope: without restarts the fit stays at its null value."""

    def model(self, values: dict) -> np.ndarray:
        base = super().model(values)
        a = values.get("back_alpha", 0.0)
        th = np.radians(self.rows.theta_s_deg)
        haze = 0.05 * np.exp(-(th / 0.6) ** 2)
        x = min(max((a - 0.02) / (ALPHA_TRUE - 0.02), 0.0), 2.0)
        good = math.sin(0.5 * math.pi * x) ** 2                          # 0 below 0.02, 1 at the truth
        bad = min(max((a - 0.046) / 0.05, 0.0), 1.0) * 0.3               # a loss beyond 0.046
        return base + haze * good - bad * base


def test_a_fit_that_ends_at_its_null_value_is_refitted_from_spread_starts(monkeypatch):
    fwd = TrapForward({"back_alpha": ALPHA_TRUE}, seed=5)
    eff = get_effect("back_face_roughness")
    fit = fit_effect(fwd, eff)
    assert fit["parameters"]["back_alpha"] == pytest.approx(ALPHA_TRUE, rel=0.1)
    chi_null = fwd.evaluate_set((eff,), {"back_alpha": 0.0})[0]
    assert fit["chi2"] < chi_null - 1000
    # without the restarts the same fit stays at its null value: the restart is what finds it
    monkeypatch.setattr(fitting, "RESTART_FRACTIONS", ())
    stuck = fit_effect(fwd, eff)
    assert at_null(eff, stuck["parameters"]) and stuck["chi2"] == pytest.approx(chi_null)
    assert "restart" in fit and fit["restart"]["moved"]


def test_the_remainders_signature_forces_its_candidate_from_the_signatures_start():
    """A background only: the baseline's residual is an offset (stray light's signature); stray light is
    fitted at step 1 whatever its screen, from the offset's level, with the reason recorded."""
    fwd = AnalyticForward({"background_per_sr": 0.03}, seed=3)
    steps = stepwise(fwd, ["bulk_absorption", "stray_light", "polarization"], workers=1)
    first = {f["effect"]: f for f in steps[1].tried}
    assert "offset" in first["stray_light"]["forced"]
    assert first["stray_light"]["start"]["background_per_sr"] == pytest.approx(0.03, rel=0.2)
    assert steps[-1].effects == ("stray_light",)
    rec = {c["effect"]: c for c in steps_record(steps, len(fwd.rows))[0][0]["candidates"]}
    assert "signature" in rec["stray_light"]["reason"]


class MethodForward(AnalyticForward):
    """interreflection (a boundary method, k = 0) changes the rows: the baseline by 'ray' is the truth."""

    def evaluate_set(self, effects, values):
        chi, v, s = super().evaluate_set(effects, values)
        if any(e.name == "interreflection" for e in effects):
            v = v / self.scale
            chi = self.misfit(v, s)
        return chi, v, s


@pytest.mark.parametrize("scale, better", [(1.15, "ray"), (1.0, None)])
def test_a_better_boundary_method_is_a_verdict_on_the_method_never_an_effect(scale, better):
    fwd = MethodForward({"background_per_sr": 0.0}, seed=4)
    fwd.scale = scale
    fwd.rows.bsdf_sr = fwd.rows.bsdf_sr / scale          # the recording is the 'ray' model's
    fwd.context = fwd.context.__class__(**{**fwd.context.__dict__, "method": "normals"})
    steps = stepwise(fwd, ["stray_light", "interreflection"], workers=1)
    assert "interreflection" not in steps[-1].effects
    check = method_check(steps, len(fwd.rows), "normals")
    assert check["better"] == better and check["method"] == "normals"
    assert ("not an effect of the sample" in check["verdict"]) == (better is not None)


def test_correlations_of_a_trading_pair_come_from_the_jacobian():
    J = np.array([[1.0, 0.9], [1.0, 1.1], [0.5, 0.4], [2.0, 2.1]])
    step = sw.Step(("relief_scale", "instrument_blur"), {"height_scale": 1.0, "blur_deg": 0.5}, 10.0, 2,
                   (None, None), jacobian=J)
    out = sw._correlations(step)
    cov = np.linalg.inv(J.T @ J)
    r = cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1])
    assert out == [{"pair": ["instrument_blur", "relief_scale"], "parameters": ["blur_deg", "height_scale"],
                    "correlation": pytest.approx(round(r, 4))}]
    assert abs(r) > 0.9
