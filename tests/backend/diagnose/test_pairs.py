"""A trading pair whose fitted correlation is near 1 is not named on its own strength (stepwise._separate_pair).

Oracle: a stand-in forward model whose lobe width grows with the relief scale s and the blur b alike,
w = W0 (s + b / B_DEG), so the two trade almost exactly; each has a small signature of its own
(`own`: a floor that only the scale lifts, a wing that only the blur adds) whose size against the
rows' known noise decides whether the rows separate them.  The chi^2 each member's removal costs is
then known in closed form to the order of that signature."""
import math

import numpy as np
import pytest

from relief_bsdf.diagnose.effects import get_effect
from relief_bsdf.diagnose.fitting import polish
from relief_bsdf.diagnose.run import explain
from relief_bsdf.diagnose.stepwise import (PAIR_CORRELATION, Step, _correlations, _separate_pair, alternatives,
                                           overwhelming_bar, steps_record)

from test_stepwise import AnalyticForward  # noqa: E402  (tests/backend/diagnose)

W0_RAD = 0.12
B_DEG = 4.0


class PairForward(AnalyticForward):
    """Lobe width W0 (s + b / B_DEG), its in-plane integral kept; plus `own_s` (s - 1) on a flat floor and
    `own_b` b on the far wing: the parts of each effect that the other cannot mimic."""

    own_s = 0.0
    own_b = 0.0

    def model(self, values: dict) -> np.ndarray:
        s = values.get("height_scale", 1.0)
        b = values.get("blur_deg", 0.0)
        w = W0_RAD * (s + b / B_DEG)
        th = np.radians(self.rows.theta_s_deg)
        lobe = np.where(self.t, 0.8, 0.1) * np.exp(-(th / w) ** 2) * (W0_RAD / w) + 0.02
        wing = np.exp(-((th - 0.6) / 0.1) ** 2)
        return lobe + self.own_s * (s - 1.0) + self.own_b * b * wing


def _pair_forward(truth, own_s, own_b, seed=3):
    cls = type("P", (PairForward,), {"own_s": own_s, "own_b": own_b})
    return cls(truth, seed=seed)


EFFS = (get_effect("relief_scale"), get_effect("instrument_blur"))


def _both_named(fwd, start):
    """The step that named both: the joint least-chi^2 point (the joint refit's polish) and its Jacobian."""
    vals, chi, J = polish(fwd, EFFS, start, steps=12)
    _, v, s = fwd.evaluate_set(EFFS, vals)
    n = len(fwd.rows)
    base = Step((), {}, fwd.misfit(*fwd.baseline()), 0, fwd.baseline())
    tried = [{"effect": "instrument_blur", "parameters": {"blur_deg": vals["blur_deg"]}, "chi2": chi, "k": 1}]
    step = Step(("relief_scale", "instrument_blur"), vals, chi, 2, (v, s), "instrument_blur", 0.0, (), tried, J)
    step.correlations = _correlations(step)
    return base, step, n


def _removal_cost(fwd, keep, n, step):
    """Oracle: chi^2 of the model without the other member, refitted by scipy's least squares, less the pair's."""
    from scipy.optimize import least_squares
    p = get_effect(keep).params[0]
    y, sg = fwd.rows.bsdf_sr, fwd.rows.sigma_sr
    ls = least_squares(lambda x: (y - fwd.model({p.name: x[0]})) / sg, [step.values[p.name]],
                       bounds=([p.lower], [p.upper]), xtol=1e-12, ftol=1e-12)
    return 2 * ls.cost - step.chi2


def test_a_pair_the_rows_do_not_separate_is_reported_not_named():
    """Truth: a scale of 1.2 and no blur; the scale's own floor (0.003 /sr) costs chi^2 ~ 20 when the blur
    takes the scale's place, under the overwhelming bar (50 for these 140 rows): both members fit the lobe
    and neither is separated.  The one kept is the one whose removal costs more (the scale, by its floor),
    the blur is an alternative with the correlation."""
    fwd = _pair_forward({"height_scale": 1.2}, own_s=0.003, own_b=0.0)
    base, step, n = _both_named(fwd, {"height_scale": 1.1, "blur_deg": 0.4})
    r = step.correlations[0]["correlation"]
    assert abs(r) > PAIR_CORRELATION
    out = _separate_pair(fwd, step, n)
    assert out.effects == ("relief_scale",) and out.dropped == ("instrument_blur",)
    assert out.values["height_scale"] == pytest.approx(1.2, abs=0.02) and out.jacobian is not None
    (note,) = out.pairs
    assert note["named"] == "relief_scale" and note["alternative"] == "instrument_blur"
    assert not note["separated"] and note["correlation"] == r
    # the costs of removal are the refitted chi^2 differences (oracle: scipy's least squares with one member),
    # on the QBIC scale: divided by the pair's reduced chi^2, less the member's BIC penalty ln n
    c = step.chi2 / (n - 2)
    for keep, removed in (("relief_scale", "instrument_blur"), ("instrument_blur", "relief_scale")):
        oracle = _removal_cost(fwd, keep, n, step) / c - math.log(n)
        assert note["cost_of_removal"][removed] == pytest.approx(oracle, abs=0.3)
    assert 0 < note["cost_of_removal"]["relief_scale"] < overwhelming_bar(n)
    # the report: an alternatives entry with the correlation, words that say the pair is not separated
    steps = [base, out]
    alts = alternatives(steps, n)
    assert alts == [{"named": "relief_scale", "alternative": "instrument_blur",
                     "bic_difference": note["bic_difference"], "alternative_parameters": note["alternative_parameters"],
                     "correlation": r, "separated": False}]
    assert note["alternative_parameters"]["blur_deg"] > 0.4        # the blur alone widens the lobe as the scale did
    words = explain(["relief_scale"], out.values, {"rms0": 5.0, "rms1": 1.0, "n": n, "chi0": 1e4, "consistent": False},
                    ([], []), alike=alts)
    assert "do not separate them" in words and f"{r:+.2f}" in words
    record = steps_record([base, Step(("relief_scale",), {"height_scale": 1.2}, step.chi2 + 1e4, 1, step.model,
                                      "relief_scale"), out], n)[0][1]
    assert "trade against each other" in record["pairs"][0]
    assert any(c["effect"] == "instrument_blur" and "not separated" in c["reason"] for c in record["candidates"])


def test_a_member_the_rows_separate_stays_named_and_its_partner_is_not():
    """The scale's own floor now stands far out of the noise: removing the scale costs more than the
    overwhelming bar (the rows separate it), removing the blur costs nothing (truth: no blur)."""
    fwd = _pair_forward({"height_scale": 1.2}, own_s=0.007, own_b=0.0)
    base, step, n = _both_named(fwd, {"height_scale": 1.1, "blur_deg": 0.4})
    assert abs(step.correlations[0]["correlation"]) > PAIR_CORRELATION
    out = _separate_pair(fwd, step, n)
    assert out.effects == ("relief_scale",)
    (note,) = out.pairs
    assert note["separated"] and note["cost_of_removal"]["relief_scale"] > overwhelming_bar(n)
    assert note["cost_of_removal"]["instrument_blur"] < overwhelming_bar(n)


def test_a_pair_both_separated_stays_named():
    """Both present, each with a signature of its own that its removal cannot hide (the overwhelming bar
    passed): both stay, with their correlation, although it is past the bar."""
    fwd = _pair_forward({"height_scale": 1.2, "blur_deg": 0.8}, own_s=0.007, own_b=0.003)
    base, step, n = _both_named(fwd, {"height_scale": 1.15, "blur_deg": 0.6})
    assert abs(step.correlations[0]["correlation"]) > PAIR_CORRELATION
    out = _separate_pair(fwd, step, n)
    assert out.effects == step.effects and not out.pairs and out.values == step.values
    for keep in ("relief_scale", "instrument_blur"):       # each removal costs more than the bar (oracle)
        assert _removal_cost(fwd, keep, n, step) / (step.chi2 / (n - 2)) - math.log(n) > overwhelming_bar(n)


class WavyForward(AnalyticForward):
    """The blur's rows: the lobe plus A sin(pi b / 2) on it, so chi^2 has two valleys of the same depth, at
    b = 0 and b = 2 deg (the truth is b = 0), with a ridge between them at b = 1."""

    def model(self, values: dict) -> np.ndarray:
        return super().model(values) * (1.0 + 0.3 * math.sin(0.5 * math.pi * values.get("blur_deg", 0.0)))


def test_the_second_start_is_skipped_only_inside_the_answers_bowl():
    """`_same_basin` compares one evaluation at the other start with the quadratic model about the answer.
    Inside one bowl (the pair stand-in, scale and blur with signatures of their own): skipped, and a polish
    from the other start (the oracle) ends at the same answer.  Across a ridge (WavyForward: the quadratic
    model at b = 0 predicts a large rise at b = 2, where chi^2 is as low as at b = 0): polished."""
    from relief_bsdf.diagnose.stepwise import _pair_starts, _same_basin
    fwd = _pair_forward({"height_scale": 1.2, "blur_deg": 0.8}, own_s=0.05, own_b=0.05)
    vals, chi, J = polish(fwd, EFFS, {"height_scale": 1.1, "blur_deg": 0.5}, steps=12)
    other = {"height_scale": 1.0, "blur_deg": 2.0}
    assert _same_basin(fwd, EFFS, vals, J, other)
    back = polish(fwd, EFFS, other, steps=12)
    assert back[1] == pytest.approx(chi, abs=0.05)
    fwd.evaluations = 0
    first = {"instrument_blur": {"parameters": {"blur_deg": 2.0}}}
    got = _pair_starts(fwd, EFFS, vals, chi, J, first, "instrument_blur")
    assert got[0] == vals and fwd.evaluations <= 2              # the other start evaluated once, no polish
    wavy = WavyForward({}, seed=4)
    blur = (get_effect("instrument_blur"),)
    at0, chi0, J0 = polish(wavy, blur, {"blur_deg": 0.05}, steps=12)
    assert at0["blur_deg"] == pytest.approx(0.0, abs=0.05)
    assert wavy.evaluate_set(blur, {"blur_deg": 2.0})[0] == pytest.approx(chi0, abs=5.0)      # the other valley
    assert not _same_basin(wavy, blur, at0, J0, {"blur_deg": 2.0})
