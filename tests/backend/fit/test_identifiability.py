"""What the fit says the recording determines (fit.optimise).

Two stand-in forward models make the logic testable in seconds: a *geometric-optics-like* plate
whose lobe depends only on the processed relief's rms slope (scale and filter slide along a
ridge), and a *wave-like* plate whose specular peak follows the rms height while the lobe follows
the slope (both parameters visible).  The plate-level check on independently simulated
recordings is `test_fit_real_relief.py`.
"""
import numpy as np
import pytest

from relief_bsdf.fit.optimise import FitSettings, fit_relief, process_relief, relief_rms
from relief_bsdf.criteria import BIC_MARGIN, asks_for, bic, bic_gain, overdispersion
from relief_bsdf.surface.synth import random_relief

X_DEG = np.linspace(-40, 40, 81)


class _Lobe:
    """Lobe of width ~ rms slope (degrees) [+ a specular peak of weight exp(-(sigma / 40 nm)^2)]."""

    def __init__(self, with_specular: bool):
        self.relief = random_relief(48, 0.125e-6, 40e-9, 0.6e-6, "gaussian", seed=3)
        self.with_specular = with_specular

    def simulate(self, s, g):
        sigma, slope = relief_rms(process_relief(self.relief, s, g))
        w = np.degrees(slope) + 0.2
        lobe = np.exp(-0.5 * (X_DEG / w) ** 2) / w
        if not self.with_specular:
            return lobe + 1e-3
        spec = np.exp(-(sigma / 40e-9) ** 2)
        return (1 - spec) * lobe + spec * np.exp(-0.5 * (X_DEG / 1.0) ** 2) + 1e-3


def _noisy(model, s, g, rel=0.02, seed=5):
    clean = model.simulate(s, g)
    sigma = rel * clean
    return clean + sigma * np.random.default_rng(seed).standard_normal(clean.size), sigma


def test_bic_is_the_one_criterion():
    assert bic(10.0, 2, 100) == pytest.approx(10.0 + 2 * np.log(100))
    assert bic_gain(50.0, 1, 20.0, 2, 100) == pytest.approx(30.0 - np.log(100))
    assert asks_for(50.0, 1, 20.0, 2, 100) and not asks_for(25.0, 1, 20.0, 2, 100)
    assert BIC_MARGIN == 10.0


def test_a_model_that_misses_the_noise_needs_proportionally_more_evidence():
    """QBIC: a parameter that lowers chi^2 by 25 on 100 rows is evidence when the model reaches the
    noise (c = 1), but not when its misfit is twice the noise (c = 2: half of the gain is the
    model's own systematic error, bent towards)."""
    n = 100
    assert overdispersion(90.0, 2, n) == 1.0
    assert overdispersion(196.0, 2, n) == pytest.approx(2.0)
    assert bic_gain(115.0, 1, 90.0, 2, n, overdispersion(90.0, 2, n)) > BIC_MARGIN
    assert bic_gain(221.0, 1, 196.0, 2, n, overdispersion(196.0, 2, n)) < BIC_MARGIN
    assert bic_gain(221.0, 1, 196.0, 2, n, 2.0) == pytest.approx(12.5 - np.log(n))


def test_slope_only_plate_gives_the_scale_and_says_the_filter_is_not_needed():
    model = _Lobe(with_specular=False)
    meas, sigma = _noisy(model, 1.22, 0.0)
    res = fit_relief(model, meas, sigma, FitSettings(max_iter=45))
    assert not res.filter_needed and res.filter_sigma_um == 0.0
    assert res.height_scale == pytest.approx(1.22, rel=0.02)
    lo, hi = res.intervals["height_scale"]
    assert lo < res.height_scale < hi and hi / lo < 1.1          # a real, narrow interval
    assert res.intervals["filter_sigma_um"] == [0.0, 0.0]
    assert any("does not ask for filtering" in w for w in res.warnings)
    doc = res.to_json()
    assert doc["identifiability"]["filter_needed"] is False and "BIC" in doc["identifiability"]["criterion"]


def test_slope_only_plate_with_a_filtered_truth_is_a_ridge_reported_at_its_simplest_point():
    """Truth (1.3, 0.15 um): only the rms slope is visible, so the answer is the unfiltered scale
    of equal rms slope, and the fit names the ridge instead of returning an arbitrary point on it."""
    model = _Lobe(with_specular=False)
    meas, sigma = _noisy(model, 1.3, 0.15)
    res = fit_relief(model, meas, sigma, FitSettings(max_iter=45))
    m_true = relief_rms(process_relief(model.relief, 1.3, 0.15))[1]
    m_fit = relief_rms(process_relief(model.relief, res.height_scale, res.filter_sigma_um))[1]
    assert not res.filter_needed
    assert m_fit == pytest.approx(m_true, rel=0.02)              # the combination the data fix
    assert res.ridge and any("ridge" in w for w in res.warnings)


def test_wave_like_plate_needs_both_parameters_and_gives_intervals_that_hold_the_truth():
    model = _Lobe(with_specular=True)
    s_true, g_true = 1.25, 0.15
    meas, sigma = _noisy(model, s_true, g_true)
    res = fit_relief(model, meas, sigma, FitSettings(max_iter=60))
    assert res.filter_needed and res.bic_gain > BIC_MARGIN
    assert res.height_scale == pytest.approx(s_true, rel=0.05)
    assert res.filter_sigma_um == pytest.approx(g_true, rel=0.1)
    (slo, shi), (glo, ghi) = res.intervals["height_scale"], res.intervals["filter_sigma_um"]
    # 68 % intervals: the truth inside a few of them (2.5 sigma here, one noise draw)
    sw, gw = (shi - slo) / 2, (ghi - glo) / 2
    assert abs(s_true - res.height_scale) < 2.5 * sw and abs(g_true - res.filter_sigma_um) < 2.5 * gw
    assert res.correlation is not None and -1 < res.correlation < 1 and not res.ridge
    assert not any("ridge" in w for w in res.warnings)


def test_scale_bounds_are_the_users_and_checked():
    from relief_bsdf.errors import InputError
    with pytest.raises(InputError, match="scale-bounds"):
        FitSettings(scale_bounds=(1.2, 3.0))
    model = _Lobe(with_specular=False)
    meas, sigma = _noisy(model, 1.6, 0.0)
    res = fit_relief(model, meas, sigma, FitSettings(max_iter=30, scale_bounds=(0.5, 1.3)))
    assert res.height_scale <= 1.3 + 1e-9
    assert any("not identifiable" in w or "misses" in w for w in res.warnings)
