"""Residual metric (residual.py): chi-like on logs, floor, sigma propagation."""
import numpy as np
import pytest

from relief_bsdf.fit.residual import LogChiMetric, mismatch_share


def test_metric_is_about_one_for_data_within_their_noise():
    rng = np.random.default_rng(3)
    truth = np.logspace(-3, 2, 4000)  # five decades of dynamic range
    sigma = 0.05 * truth
    meas = truth + sigma * rng.standard_normal(truth.size)
    m = LogChiMetric(floor_rel=1e-6, model_rel=0.0)
    assert m.value(truth, meas, sigma) == pytest.approx(1.0, abs=0.06)


def test_metric_weighs_every_decade_alike_and_grows_with_error():
    m = LogChiMetric(floor_rel=1e-12, model_rel=0.0, noise_quantile=None)     # no floor at all
    meas = np.array([1e-3, 1e2])
    sig = 0.02 * meas
    r = m.residuals(meas * 1.1, meas, sig)
    assert r[0] == pytest.approx(r[1], rel=1e-6)          # same relative error -> same residual
    assert r[0] == pytest.approx(np.log(1.1) / 0.02, rel=1e-3)
    assert m.value(meas * 1.3, meas, sig) > m.value(meas * 1.1, meas, sig)


def test_floor_hides_differences_far_below_it_and_unknown_sigma_uses_default():
    m = LogChiMetric(floor_rel=1e-2)
    meas = np.array([1.0, 1.0, 1.0, 1e-7])
    sim = np.array([1.0, 1.0, 1.0, 1e-5])                  # 100x off, but far below the floor
    assert abs(m.residuals(sim, meas)[3]) < 0.1
    r_nan = m.residuals(np.array([1.1]), np.array([1.0]), np.array([np.nan]))[0]
    assert r_nan == pytest.approx((np.log(1.11) - np.log(1.01)) / np.hypot(0.05 / 1.01, 0.01), rel=1e-9)


def test_mismatch_share_points_at_the_bad_incidence():
    class Rec:
        side = np.array(["R"] * 4 + ["T"] * 4)
        theta_i_deg = np.array([0, 0, 60, 60] * 2, float)
        bsdf_sr = np.ones(8)
        sigma_sr = np.full(8, 0.05)
    sim = np.ones(8)
    sim[6:] = 2.0
    share = mismatch_share(Rec, sim)
    assert share[0]["side"] == "T" and share[0]["theta_i_deg"] == 60 and share[0]["share"] > 0.99


def test_a_perfect_simulation_scores_one_on_a_recording_whose_wings_sit_at_the_noise_floor():
    """Wings at the detector's floor (readings clipped at 0): the floor b follows the recording's noise
    floor, so the log residual stays linear over the noise and a perfect simulation scores ~1 (with
    b = 1 % of the median alone it scored 1.37 on this recording)."""
    from relief_bsdf.fit.residual import LogChiMetric
    from relief_bsdf.validation.record import Goniophotometer, instrument_noise
    x = np.linspace(-89, 89, 1000)
    clean = 20 * np.exp(-0.5 * (x / 8) ** 2) + 0.05 * np.exp(-0.5 * (x / 15) ** 2) + 1e-4
    noisy, sigma = instrument_noise(clean, np.zeros_like(clean), Goniophotometer(1500.0, 0.015, 1e-3),
                                    np.random.default_rng(1))
    assert np.mean(noisy == 0) > 0.1                     # many clipped readings
    assert 0.9 < LogChiMetric().value(clean, noisy, sigma) < 1.1
    assert LogChiMetric(noise_quantile=0.0).floor(noisy, sigma) >= 1e-3 - 1e-12
    assert LogChiMetric().value(2 * clean, noisy, sigma) > 5
