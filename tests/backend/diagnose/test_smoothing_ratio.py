"""relief_smoothing reports the rms-slope ratio its fitted filter implies (map over true relief), with the
interval its filter's interval maps onto: what a user compares with an instrument's noise."""
import numpy as np
import pytest

from relief_bsdf.diagnose.effects import ReliefContext
from relief_bsdf.diagnose.effects.relief_smoothing import derived, slope_ratio
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.stats import rms_height_and_slope
from relief_bsdf.surface.synth import random_relief


@pytest.fixture(scope="module")
def context():
    relief = random_relief(128, 1e-6, 0.5e-6, 5e-6, seed=3)
    return ReliefContext(relief=relief, method="stand-in", face=lambda r, m, **o: r, scale_and_filter=scale_and_filter,
                         wavelengths_nm=(550.0,), detector_half_angle_deg=1.0)


def test_no_smoothing_is_a_ratio_of_one_and_a_filter_raises_it_as_the_slopes_it_removes(context):
    assert slope_ratio(context, 0.0) == pytest.approx(1.0)
    g = 2.0
    smooth = scale_and_filter(context.relief, 1.0, g * 1e-6)
    expect = rms_height_and_slope(context.relief)[1] / rms_height_and_slope(smooth)[1]
    assert expect > 1.2
    assert slope_ratio(context, g) == pytest.approx(expect, rel=1e-12)


def test_the_interval_of_the_ratio_is_the_filters_interval_mapped(context):
    values, ivals = derived(context, {"filter_sigma_um": 1.5}, {"filter_sigma_um": [1.2, 1.8]})
    r = values["slope_ratio_file_over_true"]
    lo, hi = ivals["slope_ratio_file_over_true"]
    assert lo < r < hi
    assert lo == pytest.approx(slope_ratio(context, 1.2)) and hi == pytest.approx(slope_ratio(context, 1.8))
    assert derived(context, {"filter_sigma_um": 1.5}, {})[1] == {}
