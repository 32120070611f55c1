"""Relief statistics against analytic values (stats.py)."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.stats import (acf_2d, facet_normals, psd_2d, radial_psd, relief_stats, slope_histogram,
                               slopes)

A = 40e-9          # amplitude (m)
PERIOD_PX = 64
DX, DY = 0.25e-6, 0.4e-6


def sinusoid(nx=256, ny=128, periodic=True, tilt=(0.0, 0.0), holes=False):
    x = np.arange(nx) * DX
    y = np.arange(ny) * DY
    X, Y = np.meshgrid(x, y)
    h = A * np.sin(2 * np.pi * X / (PERIOD_PX * DX)) + tilt[0] * X + tilt[1] * Y + 3e-6
    if holes:
        h[10:14, 20:30] = np.nan
        h[60, :] = np.nan
    return Relief(h, DX, DY, periodic=periodic)


def test_sinusoid_height_slope_moments():
    s = relief_stats(sinusoid())
    assert s.rms_height_m == pytest.approx(A / np.sqrt(2), rel=1e-12)
    k = 2 * np.pi / (PERIOD_PX * DX)
    # forward difference of a sine: amplitude A k sinc(k dx / 2) -> exact discrete value
    fd = A * k * np.sin(k * DX / 2) / (k * DX / 2) / np.sqrt(2)
    assert s.rms_slope_x == pytest.approx(fd, rel=1e-9)
    assert s.rms_slope_x == pytest.approx(A * k / np.sqrt(2), rel=1e-3)
    assert s.rms_slope_y == pytest.approx(0.0, abs=1e-12)
    assert s.rms_slope == pytest.approx(s.rms_slope_x)
    assert s.skewness == pytest.approx(0.0, abs=1e-9)
    assert s.kurtosis == pytest.approx(1.5, rel=1e-9)
    assert s.mean_height_m == pytest.approx(3e-6)
    # ACF along x is (A^2/2) cos(2 pi tx / P): 1/e point at acos(1/e) P / (2 pi)
    assert s.correlation_length_x_m == pytest.approx(np.arccos(np.exp(-1)) / (2 * np.pi) * PERIOD_PX * DX, rel=2e-3)


def test_plane_levelling_removes_tilt_and_survives_holes():
    flat = relief_stats(sinusoid(periodic=False))
    tilted = relief_stats(sinusoid(periodic=False, tilt=(0.02, -0.01), holes=True))
    assert tilted.rms_height_m == pytest.approx(flat.rms_height_m, rel=0.02)
    assert tilted.valid_fraction < 1
    # slopes exclude pairs touching invalid points: a pure plane with holes has exact slopes
    plane = Relief(np.where(sinusoid(holes=True).valid, 0.0, np.nan) + 0.03 * np.arange(256) * DX, DX, DY)
    sx, sy = slopes(plane)
    assert np.nanmax(np.abs(sx - 0.03)) < 1e-12 and np.isnan(sx).any()


def test_psd_parseval_and_peak():
    r = sinusoid()
    fx, fy, psd = psd_2d(r, window=None)
    dfx, dfy = fx[1] - fx[0], fy[1] - fy[0]
    assert psd.sum() * dfx * dfy == pytest.approx(A**2 / 2, rel=1e-10)
    iy, ix = np.unravel_index(np.argmax(psd), psd.shape)
    assert abs(fx[ix]) == pytest.approx(1 / (PERIOD_PX * DX)) and fy[iy] == 0
    # a non-periodic map with a Hann window keeps the variance within a few percent
    rng = np.random.default_rng(0)
    noise = Relief(rng.normal(0, 1e-8, (200, 300)), DX, DY)
    fx, fy, psd = psd_2d(noise)                       # auto -> hann
    var = np.nanvar(noise.level(1).heights_m)
    assert psd.sum() * (fx[1] - fx[0]) * (fy[1] - fy[0]) == pytest.approx(var, rel=0.03)
    # white noise has a flat PSD of level sigma^2 dx dy
    f, pr = radial_psd(noise)
    assert np.median(pr[1:]) == pytest.approx(var * DX * DY, rel=0.1)
    with pytest.raises(ValueError):
        psd_2d(noise, window="kaiser")


def test_acf_periodic_and_masked_agree():
    r = sinusoid()
    lx, ly, acf = acf_2d(r)
    i0, j0 = np.argmin(np.abs(ly)), np.argmin(np.abs(lx))
    assert acf[i0, j0] == pytest.approx(A**2 / 2, rel=1e-10)
    np.testing.assert_allclose(acf[i0, :], A**2 / 2 * np.cos(2 * np.pi * lx / (PERIOD_PX * DX)), atol=1e-12 * A**2)
    # the unbiased masked estimator on a non-periodic copy with holes gives the same small-lag ACF
    lxm, lym, acfm = acf_2d(sinusoid(periodic=False, holes=True))
    i0m, j0m = np.argmin(np.abs(lym)), np.argmin(np.abs(lxm))
    for k in (0, 5, 16, 32):
        assert acfm[i0m, j0m + k] == pytest.approx(acf[i0, j0 + k], abs=0.02 * A**2)


def test_facet_normals_of_plane():
    a, b = 0.3, -0.2
    y, x = np.mgrid[0:20, 0:30]
    h = a * x * DX + b * y * DY
    h[5, 5] = np.nan
    n = facet_normals(Relief(h, DX, DY))
    assert n.shape == (2, 19, 29, 3)                  # the two mesh triangles of every cell
    expect = np.array([-a, -b, 1.0]) / np.sqrt(1 + a * a + b * b)
    ok = np.isfinite(n[..., 0])
    # the hole is a corner of both triangles of two cells and of one triangle of two others
    assert ok.sum() == 2 * 19 * 29 - 6
    np.testing.assert_allclose(n[ok], np.broadcast_to(expect, n[ok].shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=-1), 1.0)


def test_slope_histogram_normalised_and_centred():
    rng = np.random.default_rng(2)
    # a plane with small noise: histogram concentrated at its slope
    y, x = np.mgrid[0:64, 0:64]
    h = 0.05 * x * DX + rng.normal(0, 1e-10, x.shape)
    ex, ey, dens = slope_histogram(Relief(h, DX, DY), bins=41, max_slope=0.2)
    cx, cy = 0.5 * (ex[1:] + ex[:-1]), 0.5 * (ey[1:] + ey[:-1])
    w = dens * np.outer(np.diff(ex), np.diff(ey))
    assert w.sum() == pytest.approx(1.0)
    assert (w.sum(axis=1) * cx).sum() == pytest.approx(0.05, abs=0.01)
    assert (w.sum(axis=0) * cy).sum() == pytest.approx(0.0, abs=0.01)


def test_all_nan_refused():
    with pytest.raises(InputError, match="no valid"):
        relief_stats(Relief(np.full((8, 8), np.nan), DX, DY))


def test_as_dict_has_contract_keys():
    d = relief_stats(sinusoid()).as_dict()
    for k in ("rms_height_m", "rms_slope", "rms_slope_x", "rms_slope_y", "correlation_length_m",
              "valid_fraction", "skewness", "kurtosis"):
        assert k in d
    import json
    json.dumps(d, allow_nan=False)


# ---------------------------------------------------------------- anisotropy flag

@pytest.mark.parametrize("angle_deg", [0.0, 45.0, 120.0])
def test_anisotropy_flag_finds_a_lay_at_any_angle(angle_deg):
    """A Gaussian relief with its correlation length stretched 3x along `angle_deg` (surface.synth) has
    rms slopes 3x smaller along the lay than across it, whatever the lay's angle to the pixel axes
    (per-axis rms slopes are equal for a lay at 45 deg and would miss it).  The flag finds the ratio
    (within 10 %: finite tile) and the lay's direction (within 5 deg); an isotropic relief and
    uncorrelated pixel noise are not flagged."""
    from relief_bsdf.surface.stats import map_flags
    from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec
    spec = dict(nx=256, ny=256, pitch_m=0.5e-6, rms_height_m=0.2e-6, corr_length_m=4e-6)
    f = map_flags(relief_from_spec(RandomFieldSpec(**spec, anisotropy=3.0, angle_deg=angle_deg), 1))
    assert f.anisotropic and abs(f.anisotropy / 3.0 - 1.0) < 0.1, f
    assert abs((f.lay_angle_deg - angle_deg + 90.0) % 180.0 - 90.0) < 5.0, f
    assert "across it" in f.statements()[0]
    iso = map_flags(relief_from_spec(RandomFieldSpec(**spec), 1))
    assert not iso.anisotropic and iso.anisotropy < 1.1
    noise = Relief(1e-9 * np.random.default_rng(0).standard_normal((256, 256)), 1e-6, 1e-6, periodic=False,
                   source="white noise")
    assert not map_flags(noise).anisotropic and map_flags(noise).anisotropy < 1.1
