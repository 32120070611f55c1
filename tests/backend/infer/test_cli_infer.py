"""`relief infer` refuses what it cannot read with one rc-2 line naming the file."""
from __future__ import annotations

from pathlib import Path

from relief_bsdf.cli import main


def _sample(tmp_path: Path, recording: str, rough: str = "front") -> Path:
    p = tmp_path / "sample.toml"
    p.write_text(f'''format = "relief-sample/1"
[plate]
thickness_mm = 2.0
rough_face = "{rough}"
[relief]
[instrument]
detector_half_angle_deg = 0.5
[recording]
file = "{recording}"
wavelength_nm = 633.0
''')
    return p


def _one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(err) == 1, err
    return err[0]


def test_unreadable_recording_is_one_rc2_line(tmp_path, capsys):
    (tmp_path / "junk.txt").write_bytes(b"\x00\x01 not a measurement\n")
    p = _sample(tmp_path, "junk.txt")
    assert main(["infer", str(p), "-o", str(tmp_path / "out")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("relief infer: error:") and "junk.txt" in line
    assert not (tmp_path / "out" / "infer.json").exists()


def test_missing_sample_and_missing_recording(tmp_path, capsys):
    assert main(["infer", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "out")]) == 2
    assert "nope.toml" in _one_error_line(capsys)
    p = _sample(tmp_path, "absent.txt")
    assert main(["infer", str(p), "-o", str(tmp_path / "out")]) == 2
    assert "absent.txt" in _one_error_line(capsys)


def test_relief_on_the_back_face_is_refused(tmp_path, capsys):
    (tmp_path / "r.txt").write_text("!! x\n!!BSDF Data\n0 0\n0 0 1\n")
    p = _sample(tmp_path, "r.txt", rough="back")
    assert main(["infer", str(p), "-o", str(tmp_path / "out")]) == 2
    assert "rough_face" in _one_error_line(capsys)


def test_an_oblique_in_plane_scan_is_refused_with_one_line(tmp_path, capsys):
    """The inversion reads the lobe over the direction plane, or an in-plane scan at normal incidence read as
    isotropic (infer.slopes.isotropic_reading); an in-plane scan whose incidence nearest the normal is oblique
    gives neither (one rc-2 line naming the file, no traceback)."""
    rows = ["# relief-recording/1", "wavelength_nm,theta_i_deg,phi_i_deg,side,theta_s_deg,phi_s_deg,bsdf_sr,sigma_sr"]
    for ts in range(0, 40, 2):
        for ps in (0, 180):
            rows.append(f"633,5,0,T,{ts},{ps},{10.0 if ts < 6 else 0.01},0.01")
    (tmp_path / "inplane.csv").write_text("\n".join(rows) + "\n")
    p = _sample(tmp_path, "inplane.csv")
    assert main(["infer", str(p), "-o", str(tmp_path / "out")]) == 2
    line = _one_error_line(capsys)
    assert "inplane.csv" in line and "in-plane" in line
