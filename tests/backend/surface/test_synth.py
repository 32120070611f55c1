"""Synthetic reliefs come back with the requested statistics (synth.py + stats.py).

Statistical tolerance: a tile of side T = N pixels holds ~ (T/L)^2 correlation areas;
the realisation's slope and correlation length scatter by ~ L/T relative (here
L/T ~ 1/50 for the Gaussian tiles, so 5 % is > 2 sigma).  The exponential ACF has
heavier tails, so its correlation length is checked on the mean of three seeds.
The rms height is normalised exactly by design (exact_rms=True).
"""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.surface.stats import psd_2d, relief_stats
from relief_bsdf.surface.synth import (DotPattern, RandomFieldSpec, lgp_dots, psd_model, random_relief,
                                      relief_from_spec)

S, L, D = 50e-9, 5e-6, 0.5e-6       # rms height, correlation length (10 px), pitch


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gaussian_statistics(seed):
    r = random_relief(512, D, S, L, kind="gaussian", seed=seed)
    assert r.periodic and r.shape == (512, 512)
    s = relief_stats(r)
    assert s.rms_height_m == pytest.approx(S, rel=1e-9)
    assert s.rms_slope == pytest.approx(2 * S / L, rel=0.05)
    assert s.rms_slope_x == pytest.approx(np.sqrt(2) * S / L, rel=0.05)
    assert s.correlation_length_m == pytest.approx(L, rel=0.05)
    assert abs(s.skewness) < 0.1 and s.kurtosis == pytest.approx(3.0, abs=0.2)


def test_unnormalised_rms_is_statistically_right():
    vals = [relief_stats(relief_from_spec(RandomFieldSpec(256, 256, D, S, L, exact_rms=False), seed=k)).rms_height_m
            for k in range(4)]
    assert np.mean(vals) == pytest.approx(S, rel=0.05)
    assert len(set(vals)) == 4


def test_exponential_statistics():
    stats = [relief_stats(random_relief(512, D, S, L, kind="exponential", seed=k)) for k in range(3)]
    assert all(s.rms_height_m == pytest.approx(S, rel=1e-9) for s in stats)
    assert np.mean([s.correlation_length_m for s in stats]) == pytest.approx(L, rel=0.05)
    # the exponential surface is much rougher at the pixel scale than the Gaussian one
    g = relief_stats(random_relief(512, D, S, L, kind="gaussian", seed=0))
    assert min(s.rms_slope for s in stats) > 2 * g.rms_slope


def test_anisotropy_stretches_along_angle():
    r = relief_from_spec(RandomFieldSpec(512, 512, D, S, L, anisotropy=2.0, angle_deg=0.0), seed=4)
    s = relief_stats(r)
    assert s.correlation_length_x_m == pytest.approx(2 * L, rel=0.05)
    assert s.correlation_length_y_m == pytest.approx(L, rel=0.05)
    assert s.rms_slope_x == pytest.approx(np.sqrt(2) * S / (2 * L), rel=0.05)
    r90 = relief_from_spec(RandomFieldSpec(512, 512, D, S, L, anisotropy=2.0, angle_deg=90.0), seed=4)
    s90 = relief_stats(r90)
    assert s90.correlation_length_y_m > 1.5 * s90.correlation_length_x_m


def test_seeded_and_periodic():
    a = random_relief(64, D, S, 3e-6, seed=7)
    b = random_relief(64, D, S, 3e-6, seed=7)
    c = random_relief(64, D, S, 3e-6, seed=8)
    assert np.array_equal(a.heights_m, b.heights_m) and not np.array_equal(a.heights_m, c.heights_m)
    # seamless tile: the wrap-around step is no larger than typical interior steps
    h = a.heights_m
    inner = np.abs(np.diff(h, axis=1)).mean()
    assert np.abs(h[:, 0] - h[:, -1]).mean() < 2 * inner


def test_psd_matches_model():
    r = random_relief(256, D, S, L, seed=3)
    fx, fy, psd = psd_2d(r)
    FX, FY = np.meshgrid(fx, fy)
    model = psd_model("gaussian", FX, FY, S, L, L)
    band = (np.hypot(FX, FY) > 0) & (np.hypot(FX, FY) < 0.5 / L)
    # mean over many frequency cells: |noise|^2 averages to 1
    assert psd[band].mean() / model[band].mean() == pytest.approx(1.0, rel=0.1)


def test_bad_requests():
    with pytest.raises(InputError):
        random_relief(64, D, S, 0.5 * D)             # under 2 pixels
    with pytest.raises(InputError):
        random_relief(64, D, S, 40 * D)              # tile shorter than 2 L
    with pytest.raises(InputError):
        random_relief(64, D, -S, L)
    with pytest.raises(InputError):
        random_relief(64, D, S, 3e-6, kind="fractal")


def test_lgp_dots_geometry():
    r = lgp_dots(256, 1e-6, DotPattern(64e-6, 12e-6, 3e-6, shape="cap", jitter=0.3), seed=1)
    assert r.periodic
    h = r.heights_m
    assert h.max() == pytest.approx(3e-6, rel=0.02) and h.min() == 0.0
    # 16 dots of base radius 12 um: covered fraction = 16 pi a^2 / tile area
    assert (h > 0).mean() == pytest.approx(16 * np.pi * 12e-6**2 / (256e-6) ** 2, rel=0.05)
    assert r.metadata["dot_count"] == 16
    # spherical-cap volume pi h (3 a^2 + h^2) / 6 per dot
    vol = h.sum() * 1e-12
    assert vol == pytest.approx(16 * np.pi * 3e-6 * (3 * 12e-6**2 + 3e-6**2) / 6, rel=0.02)
    pits = lgp_dots(256, 1e-6, DotPattern(64e-6, 12e-6, -3e-6, shape="gaussian", jitter=0.0, micro_rms_m=10e-9),
                    seed=1)
    assert pits.heights_m.min() < -2.5e-6
    outside = pits.heights_m == 0
    assert outside.mean() > 0.5                       # micro-roughness only inside dots
    with pytest.raises(InputError, match="overlap"):
        lgp_dots(256, 1e-6, DotPattern(20e-6, 12e-6, 3e-6))
