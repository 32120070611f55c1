"""Strict readers for recording.csv and sample.toml (formats.md)."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.core.index import CauchyIndex, ConstantIndex
from relief_bsdf.io.recording import (RECORDING_COLUMNS, InstrumentSpec, PlateSpec, Recording, Sample,
                                   read_recording, read_sample, write_recording, write_sample)

HEADER = ",".join(RECORDING_COLUMNS)
GOOD_ROWS = [
    "550,30,0,R,30,180,12.5,0.3",
    "550,30,0,R,10,0,0.02,",
    "550,30,0,T,20,180,0.4,0.01",
    "633,0,0,T,0,0,25.0,",
]


def write(tmp_path, lines, name="recording.csv"):
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def test_reads_good_file(tmp_path):
    p = write(tmp_path, ["# relief-recording/1", "# instrument: test gonio", HEADER, *GOOD_ROWS])
    rec = read_recording(p)
    assert len(rec) == 4
    assert rec.side.tolist() == ["R", "R", "T", "T"]
    assert rec.bsdf_sr[0] == 12.5 and rec.theta_s_deg[2] == 20.0
    assert np.isnan(rec.sigma_sr[1]) and rec.sigma_sr[0] == 0.3
    assert rec.comments == ["instrument: test gonio"]
    assert rec.path == p


def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(1)
    n = 50
    rec = Recording(wavelength_nm=np.full(n, 532.1), theta_i_deg=np.full(n, 45.0), phi_i_deg=np.zeros(n),
                    side=np.where(np.arange(n) % 2, "R", "T"), theta_s_deg=np.linspace(0, 90, n),
                    phi_s_deg=np.full(n, 180.0), bsdf_sr=rng.random(n) / 3,
                    sigma_sr=np.where(np.arange(n) % 3, rng.random(n) * 1e-3, np.nan))
    p = write_recording(tmp_path / "r.csv", rec, comments=["made by a test"])
    back = read_recording(p)
    for name in ("wavelength_nm", "theta_i_deg", "phi_i_deg", "theta_s_deg", "phi_s_deg", "bsdf_sr"):
        assert np.array_equal(getattr(back, name), getattr(rec, name)), name
    assert np.array_equal(np.isnan(back.sigma_sr), np.isnan(rec.sigma_sr))
    assert np.array_equal(back.sigma_sr[np.isfinite(rec.sigma_sr)], rec.sigma_sr[np.isfinite(rec.sigma_sr)])
    assert back.side.tolist() == rec.side.tolist()
    assert back.comments == ["made by a test"]
    # subset and with_values keep the geometry
    sub = back.subset(back.side == "R")
    assert len(sub) == n // 2 and set(sub.side) == {"R"}
    new = back.with_values(np.ones(n))
    assert np.all(new.bsdf_sr == 1) and np.all(np.isnan(new.sigma_sr))
    assert np.array_equal(new.theta_s_deg, back.theta_s_deg)


@pytest.mark.parametrize("lines, line_no, words", [
    (["# relief-recording/2", HEADER, GOOD_ROWS[0]], 1, "first line"),
    (["wavelength_nm,theta_i_deg", HEADER, GOOD_ROWS[0]], 1, "first line"),
    (["# relief-recording/1", "wavelength_nm,theta_i_deg,phi_i_deg,side,phi_s_deg,theta_s_deg,bsdf_sr,sigma_sr",
      GOOD_ROWS[0]], 2, "header"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,180,abc,"], 3, "bsdf_sr"),
    (["# relief-recording/1", HEADER, "550,30,0,X,30,180,1,"], 3, "side"),
    (["# relief-recording/1", HEADER, "550,90,0,R,30,180,1,"], 3, "theta_i"),
    (["# relief-recording/1", HEADER, "550,-1,0,R,30,180,1,"], 3, "theta_i"),
    (["# relief-recording/1", HEADER, GOOD_ROWS[0], "550,30,0,R,90.5,180,1,"], 4, "theta_s"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,180,-0.1,"], 3, "negative"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,180,nan,"], 3, "finite"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,180,1,-2"], 3, "sigma"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,180,1"], 3, "8"),
    (["# relief-recording/1", HEADER, "550,30,0,R,30,360,1,"], 3, "phi_s"),
    (["# relief-recording/1", HEADER, "0,30,0,R,30,180,1,"], 3, "wavelength"),
])
def test_malformed_rows_name_line(tmp_path, lines, line_no, words):
    p = write(tmp_path, lines)
    with pytest.raises(InputError) as e:
        read_recording(p)
    msg = str(e.value)
    assert f"{p}:{line_no}" in msg
    assert words in msg


def test_duplicate_rows_report_both_lines(tmp_path):
    p = write(tmp_path, ["# relief-recording/1", HEADER, GOOD_ROWS[0], GOOD_ROWS[1], "# c",
                         "550.0,30,0.0,R,30,180,99,"])
    with pytest.raises(InputError) as e:
        read_recording(p)
    assert f"{p}:6" in str(e.value) and "line 3" in str(e.value) and "duplicate" in str(e.value)


@pytest.mark.parametrize("content", ["", "\n\n", "# relief-recording/1\n", "# relief-recording/1\n" + HEADER + "\n"])
def test_empty_or_header_only(tmp_path, content):
    p = tmp_path / "r.csv"
    p.write_text(content)
    with pytest.raises(InputError) as e:
        read_recording(p)
    assert str(p) in str(e.value)


def test_missing_and_binary(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_recording(tmp_path / "nope.csv")
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00garbage\x80")
    with pytest.raises(InputError, match="UTF-8|first line"):
        read_recording(p)


def test_sigma_fallback_fills_only_unknown_sigmas(tmp_path):
    """Unknown sigma -> sqrt((3 % of the value)^2 + floor^2), floor = 1e-3 of the peak; known kept."""
    rec = read_recording(write(tmp_path, ["# relief-recording/1", HEADER, *GOOD_ROWS]))
    out = rec.with_sigma_fallback()
    assert np.isnan(rec.sigma_sr[1]) and np.isnan(rec.sigma_sr[3])      # the original is not modified
    assert out.sigma_sr[0] == 0.3 and out.sigma_sr[2] == 0.01
    floor = 1e-3 * 25.0
    assert out.sigma_sr[1] == pytest.approx(np.hypot(0.03 * 0.02, floor), rel=1e-12)
    assert out.sigma_sr[3] == pytest.approx(np.hypot(0.03 * 25.0, floor), rel=1e-12)
    assert np.array_equal(out.bsdf_sr, rec.bsdf_sr) and np.array_equal(out.side, rec.side)
    assert out.path == rec.path and out.comments == rec.comments
    # zero or negative sigma counts as unknown too; an all-zero recording gets the absolute floor
    zero = rec.with_values(np.zeros(len(rec)), np.zeros(len(rec))).with_sigma_fallback()
    assert np.all(zero.sigma_sr == 1e-6)


def test_writer_refuses_invalid():
    rec = Recording([550, 550], [0, 0], [0, 0], ["R", "R"], [10, 10], [0, 0], [1, 2], [np.nan, np.nan])
    with pytest.raises(ValueError, match="duplicate"):
        write_recording("/tmp/should_not_exist.csv", rec)
    rec2 = Recording([550], [0], [0], ["R"], [10], [0], [-1], [np.nan])
    with pytest.raises(ValueError):
        write_recording("/tmp/should_not_exist.csv", rec2)


# ---------------------------------------------------------------- sample.toml

GOOD_TOML = """format = "relief-sample/1"

[plate]
thickness_mm = 2.0
refractive_index = 1.49
rough_face = "front"
absorption_per_mm = 0.0

[relief]
file = "relief.npz"

[instrument]
detector_half_angle_deg = 1.0
polarization = "unpolarized"

[recording]
file = "data/recording.csv"
"""


def make_sample(tmp_path, text=GOOD_TOML):
    (tmp_path / "relief.npz").write_bytes(b"x")
    (tmp_path / "data").mkdir(exist_ok=True)
    (tmp_path / "data" / "recording.csv").write_text("x")
    p = tmp_path / "sample.toml"
    p.write_text(text)
    return p


def test_reads_good_sample(tmp_path):
    s = read_sample(make_sample(tmp_path))
    assert s.plate.thickness_mm == 2.0 and s.plate.rough_face == "front"
    assert isinstance(s.plate.index, ConstantIndex) and s.plate.index.real == 1.49
    assert s.plate.absorption_per_mm == 0.0
    assert s.relief_path == tmp_path / "relief.npz"
    assert s.recording_path == tmp_path / "data" / "recording.csv"
    assert s.instrument.detector_half_angle_deg == 1.0 and s.instrument.polarization == "unpolarized"
    m = s.material
    assert m.inside.n(550)[()] == 1.49 and m.outside.n(550)[()] == 1.0
    # detector solid angle of a 1 degree cone ~ pi a^2
    assert s.instrument.detector_solid_angle_sr == pytest.approx(np.pi * np.radians(1.0) ** 2, rel=1e-4)


def test_cauchy_and_optional_keys(tmp_path):
    text = GOOD_TOML.replace("refractive_index = 1.49", "cauchy = [1.48, 4200.0, 0.0]")
    text = text.replace("absorption_per_mm = 0.0\n", "").replace('polarization = "unpolarized"\n', "")
    s = read_sample(make_sample(tmp_path, text))
    assert isinstance(s.plate.index, CauchyIndex)
    assert s.plate.index.n(600.0) == pytest.approx(1.48 + 4200 / 600**2)
    assert s.plate.absorption_per_mm is None
    assert s.instrument.polarization == "unpolarized"


@pytest.mark.parametrize("old, new, words", [
    ("thickness_mm = 2.0", "thicknes_mm = 2.0", "plate.thicknes_mm"),          # typo -> unknown key
    ("thickness_mm = 2.0\n", "", "plate.thickness_mm"),                         # missing required
    ("thickness_mm = 2.0", 'thickness_mm = "2"', "plate.thickness_mm"),          # wrong type
    ("thickness_mm = 2.0", "thickness_mm = -1.0", "plate.thickness_mm"),
    ("refractive_index = 1.49", "refractive_index = 1.49\ncauchy = [1.5, 0.0]", "both"),
    ("refractive_index = 1.49\n", "", "refractive_index"),
    ("refractive_index = 1.49", "cauchy = [1.5]", "plate.cauchy"),
    ('rough_face = "front"', 'rough_face = "top"', "plate.rough_face"),
    ("detector_half_angle_deg = 1.0", "detector_half_angle_deg = 0.0", "detector_half_angle_deg"),
    ("detector_half_angle_deg = 1.0", "detector_half_angle_deg = true", "detector_half_angle_deg"),
    ('polarization = "unpolarized"', 'polarization = "circular"', "polarization"),
    ('file = "relief.npz"', 'file = "missing.x3p"', "relief.file"),
    ('file = "data/recording.csv"', 'file = "recording.csv"', "recording.file"),
    ('format = "relief-sample/1"', 'format = "relief-sample/2"', "format"),
    ("[instrument]", "[instrument]\ncolor = 3", "instrument.color"),
    ("[recording]", "[recordings]", "recordings"),
    ("thickness_mm = 2.0", "thickness_mm = = 2", "TOML"),
])
def test_malformed_sample(tmp_path, old, new, words):
    assert old in GOOD_TOML
    p = make_sample(tmp_path, GOOD_TOML.replace(old, new, 1))
    with pytest.raises(InputError) as e:
        read_sample(p)
    assert str(p) in str(e.value)
    assert words in str(e.value)


def test_check_files_off(tmp_path):
    p = tmp_path / "sample.toml"
    p.write_text(GOOD_TOML)
    s = read_sample(p, check_files=False)
    assert s.relief_path.name == "relief.npz"
    with pytest.raises(InputError, match="not found"):
        read_sample(p)


def test_write_sample_round_trip(tmp_path):
    s = Sample(path=tmp_path / "s.toml", plate=PlateSpec(3.0, CauchyIndex(1.49, 3000.0, 1e7), "back", 0.05),
               relief_path=tmp_path / "r.x3p", instrument=InstrumentSpec(0.5, "s"),
               recording_path=tmp_path / "sub" / "rec.csv")
    p = write_sample(tmp_path / "s.toml", s)
    back = read_sample(p, check_files=False)
    assert back.plate == s.plate
    assert back.instrument == s.instrument
    assert back.relief_path.resolve() == s.relief_path.resolve()
    assert back.recording_path.resolve() == s.recording_path.resolve()
    assert 'file = "sub/rec.csv"' in p.read_text()
    d = {"plate": {"thickness_mm": 1, "refractive_index": 1.5, "rough_face": "front"},
         "relief": {"file": "r.npz"}, "instrument": {"detector_half_angle_deg": 2.0},
         "recording": {"file": "rec.csv"}}
    back2 = read_sample(write_sample(tmp_path / "d.toml", d), check_files=False)
    assert back2.plate.thickness_mm == 1.0 and back2.instrument.polarization == "unpolarized"
    with pytest.raises(InputError, match="rough_face"):
        write_sample(tmp_path / "bad.toml", {**d, "plate": {**d["plate"], "rough_face": "side"}})
    assert not (tmp_path / "bad.toml").exists()
