"""Residual localisation and shape classification (relief_bsdf.diagnose.mismatch) on synthetic scans."""
import numpy as np
import pytest

from relief_bsdf.io.recording import Recording
from relief_bsdf.diagnose.mismatch import classify, locate, residual_z


def _rows(value, sigma, theta_i=(0.0, 40.0), sides=("R", "T")):
    th = np.arange(0.0, 90.0, 2.5)
    W, TI, SD, TS, PS = [], [], [], [], []
    for ti in theta_i:
        for sd in sides:
            for ps in (0.0, 180.0):
                for t in th:
                    W.append(550.0); TI.append(ti); SD.append(sd); TS.append(t); PS.append(ps)
    n = len(W)
    rs = Recording(np.array(W), np.array(TI), np.zeros(n), np.array(SD), np.array(TS), np.array(PS),
                np.zeros(n), np.full(n, sigma))
    return rs


def _lobe(rows, centre_shift=0.0, width=8.0, level=1.0):
    # in-plane signed angle, lobe centred on the specular direction (phi_s = 180 side)
    x = np.where(rows.phi_s_deg == 180.0, rows.theta_s_deg, -rows.theta_s_deg)
    return level * np.exp(-0.5 * ((x - rows.theta_i_deg - centre_shift) / width) ** 2) + 0.01


def test_offset_is_recognised_as_offset():
    rows = _rows(0, 0.002)
    m = _lobe(rows)
    rows.bsdf_sr = m + 0.02
    shapes = classify(rows, m)
    assert shapes[0]["shape"] == "offset"
    assert shapes[0]["explained"] > 0.95
    assert shapes[0]["coefficient"] == pytest.approx(0.02, rel=1e-6)


def test_shift_and_broadening_are_told_apart():
    rows = _rows(0, 0.002)
    m = _lobe(rows)
    rows.bsdf_sr = _lobe(rows, centre_shift=0.6)
    assert classify(rows, m)[0]["shape"] == "shift"
    rows.bsdf_sr = _lobe(rows, width=8.6, level=8.0 / 8.6)
    assert classify(rows, m)[0]["shape"] in ("broadening",)


def test_path_deficit_grows_with_glass_path():
    rows = _rows(0, 0.002, sides=("T",))
    m = _lobe(rows)
    sin_g = np.sin(np.radians(rows.theta_s_deg)) / 1.5
    rows.bsdf_sr = m * np.exp(-0.1 / np.sqrt(1 - sin_g**2))
    assert classify(rows, m, n_glass=1.5)[0]["shape"] == "path_deficit"


def test_locate_finds_the_region_and_shares_sum_to_at_most_one():
    rows = _rows(0, 0.01)
    m = _lobe(rows)
    rows.bsdf_sr = m.copy()
    hit = (rows.side == "T") & (rows.theta_i_deg == 40.0) & (rows.phi_s_deg == 180.0) & \
          (rows.theta_s_deg >= 30) & (rows.theta_s_deg <= 50)
    rows.bsdf_sr[hit] += 0.2
    regs = locate(rows, m)
    assert regs[0]["side"] == "T" and regs[0]["theta_i_deg"] == 40.0 and regs[0]["phi_s_deg"] == 180.0
    assert regs[0]["theta_s_deg"] == [30.0, 50.0]
    assert regs[0]["share"] == pytest.approx(1.0, abs=1e-6)
    assert regs[0]["sign"] == "excess"
    assert sum(r["share"] for r in regs) <= 1.0 + 1e-9


def test_pure_noise_has_no_dominant_region():
    rng = np.random.default_rng(3)
    rows = _rows(0, 0.01)
    m = _lobe(rows)
    rows.bsdf_sr = m + 0.01 * rng.normal(size=m.size)
    z = residual_z(rows, m)
    assert abs(np.mean(z**2) - 1) < 0.2
    regs = locate(rows, m, threshold=2.0)
    assert all(r["share"] < 0.15 for r in regs)
