"""`relief info`, `relief synth`, `relief export`: outputs and exit codes (formats.md CLI contract)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.io.isbsdf import read_isbsdf
from relief_bsdf.cli import main
from relief_bsdf.io.heightmaps import read_relief
from relief_bsdf.io.recording import read_recording, write_sample

TOPO = Path(__file__).resolve().parents[2] / "data" / "topography"


def run_cli(capsys, *argv):
    rc = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    return rc, out, err


MATERIAL = {"inside": {"model": "constant", "n": 1.5, "k": 0.0}, "outside": {"model": "constant", "n": 1.0, "k": 0.0}}


def make_table_file(path):
    te, pe = np.linspace(0, 90, 19), np.linspace(0, 360, 25)
    rng = np.random.default_rng(0)
    t_out = BsdfTable([550.0], [0.0, 40.0], [0.0], te, pe, rng.random((1, 2, 1, 2, 18, 24)) * 0.2,
                      specular_R=0.04, specular_T=0.5, method="test",
                      sigma_per_sr=np.full((1, 2, 1, 2, 18, 24), 0.01), material=MATERIAL)
    t_in = BsdfTable([550.0], [0.0, 40.0], [0.0], te, pe, rng.random((1, 2, 1, 2, 18, 24)) * 0.1,
                     incident_from="inside", method="test", material=MATERIAL)
    save_tables(path, [t_out, t_in])
    return t_out, t_in


def test_synth_then_info_json(tmp_path, capsys):
    out = tmp_path / "g.x3p"
    rc, o, e = run_cli(capsys, "synth", "--kind", "gaussian", "--rms-height-um", 0.05, "--corr-length-um", 4,
                       "--size", 256, "--pitch-um", 0.5, "--seed", 3, "-o", out)
    assert rc == 0 and out.exists() and "wrote" in o
    rc, o, e = run_cli(capsys, "info", out, "--json")
    assert rc == 0
    d = json.loads(o)
    assert d["kind"] == "relief" and d["shape"] == [256, 256] and d["pitch_m"] == [0.5e-6, 0.5e-6]
    assert d["valid_fraction"] == 1.0
    # the statistics of the written synthetic relief: requested values within the 5 % tolerance
    assert d["rms_height_m"] == pytest.approx(0.05e-6, rel=1e-6)           # periodic: exact normalisation
    assert d["rms_slope"] == pytest.approx(2 * 0.05 / 4, rel=0.05)
    assert d["correlation_length_m"] == pytest.approx(4e-6, rel=0.05)
    for k in ("rms_slope_x", "rms_slope_y"):
        assert d[k] > 0
    rc, o, e = run_cli(capsys, "info", out)
    assert rc == 0 and "rms height" in o and "rms slope" in o


def test_info_instrument_file_and_profile(capsys):
    rc, o, e = run_cli(capsys, "info", TOPO / "ST_nid-1.nid", "--json")
    assert rc == 0
    d = json.loads(o)
    assert d["rms_height_m"] == pytest.approx(np.nanstd(read_relief(TOPO / "ST_nid-1.nid").level(1).heights_m))
    rc, o, e = run_cli(capsys, "info", TOPO / "ST_dektak-1.csv")
    assert rc == 2 and o == ""
    lines = e.strip().splitlines()
    assert len(lines) == 1 and "ST_dektak-1.csv" in lines[0] and "line profile" in lines[0]
    assert "Traceback" not in e


@pytest.mark.parametrize("content, name", [(b"", "empty.x3p"), (b"PK\x03\x04garbage", "broken.x3p"),
                                           (b"\x00" * 100, "zeros.sur"), (b"# relief-recording/1\nnope\n", "r.csv")])
def test_info_bad_files_exit_2(tmp_path, capsys, content, name):
    p = tmp_path / name
    p.write_bytes(content)
    rc, o, e = run_cli(capsys, "info", p)
    assert rc == 2
    assert len(e.strip().splitlines()) == 1 and name in e and "Traceback" not in e


def test_info_missing_file(tmp_path, capsys):
    rc, o, e = run_cli(capsys, "info", tmp_path / "none.npz")
    assert rc == 2 and "none.npz" in e


def test_info_table_recording_sample(tmp_path, capsys):
    t_out, t_in = make_table_file(tmp_path / "t.h5")
    rc, o, e = run_cli(capsys, "info", tmp_path / "t.h5", "--json")
    assert rc == 0
    d = json.loads(o)
    assert d["kind"] == "bsdf" and d["method"] == "test" and len(d["albedo"]) == 4
    h = t_out.hemispherical()
    row = next(r for r in d["albedo"] if r["from"] == "outside" and r["theta_i_deg"] == 40.0)
    assert row["R"] == pytest.approx(h["R"][0, 1, 0]) and row["specular_T"] == pytest.approx(0.5)
    assert {"wavelength_nm", "theta_i_deg", "phi_i_deg", "from", "R", "T", "specular_R", "specular_T",
            "lost"} <= set(row)
    # export a recording, then info on it and on a sample pointing to it
    rc, o, e = run_cli(capsys, "export", tmp_path / "t.h5", "--format", "recording-csv", "-o", tmp_path / "r.csv")
    assert rc == 0
    rc, o, e = run_cli(capsys, "info", tmp_path / "r.csv", "--json")
    d = json.loads(o)
    assert d["kind"] == "recording" and d["rows"] == 2 * 2 * 18 * 24 and d["sides"] == ["R", "T"]
    np.savez(tmp_path / "rel.npz", heights=np.zeros((4, 4)), dx=1e-6, dy=1e-6)
    s = write_sample(tmp_path / "s.toml", {"plate": {"thickness_mm": 2.0, "refractive_index": 1.49,
                                                      "rough_face": "front"},
                                            "relief": {"file": "rel.npz"},
                                            "instrument": {"detector_half_angle_deg": 1.0},
                                            "recording": {"file": "r.csv"}})
    rc, o, e = run_cli(capsys, "info", s, "--json")
    assert rc == 0 and json.loads(o)["kind"] == "sample"
    rc, o, e = run_cli(capsys, "info", s)
    assert rc == 0 and "1.49" in o
    (tmp_path / "bad.toml").write_text(s.read_text().replace("rough_face", "rough_fase"))
    rc, o, e = run_cli(capsys, "info", tmp_path / "bad.toml")
    assert rc == 2 and "bad.toml" in e and "rough_fase" in e


def test_export_recording_csv_matches_table(tmp_path, capsys):
    t_out, t_in = make_table_file(tmp_path / "t.h5")
    rc, o, e = run_cli(capsys, "export", tmp_path / "t.h5", "--format", "recording-csv", "--from", "inside",
                       "-o", tmp_path / "in.csv")
    assert rc == 0
    rec = read_recording(tmp_path / "in.csv")
    t_in = load_tables(tmp_path / "t.h5")[1]          # values as stored in the file
    assert t_in.incident_from == "inside"
    assert len(rec) == t_in.values_per_sr.size and np.all(np.isnan(rec.sigma_sr))
    # every row is the table evaluated at the cell centre it names
    k = np.arange(0, len(rec), 97)
    v = t_in.eval(rec.wavelength_nm[k], rec.theta_i_deg[k], rec.phi_i_deg[k], rec.side[k],
                  rec.theta_s_deg[k], rec.phi_s_deg[k])
    np.testing.assert_allclose(rec.bsdf_sr[k], v, rtol=1e-12)
    rc, o, e = run_cli(capsys, "export", tmp_path / "t.h5", "--format", "recording-csv", "-o", tmp_path / "o.csv")
    rec_o = read_recording(tmp_path / "o.csv")
    np.testing.assert_allclose(rec_o.sigma_sr, 0.01, rtol=1e-6)   # the outside table carries sigma (float32 in HDF5)
    assert any("specular" in c for c in rec_o.comments)


def test_export_isbsdf(tmp_path, capsys):
    make_table_file(tmp_path / "t.h5")
    rc, o, e = run_cli(capsys, "export", tmp_path / "t.h5", "--format", "is-bsdf", "-o", tmp_path / "z.bsdf")
    assert rc == 0
    b = read_isbsdf(tmp_path / "z_BRDF.bsdf")
    assert b.scatter_type == "BRDF" and list(b.angle_of_incidence_deg) == [0.0, 40.0]
    assert read_isbsdf(tmp_path / "z_BTDF.bsdf").scatter_type == "BTDF"
    assert read_isbsdf(tmp_path / "z_BTDF.bsdf").relief_tag("btdf_centre") == "refracted"   # OpticStudio's
    rc, o, e = run_cli(capsys, "export", tmp_path / "t.h5", "--format", "is-bsdf", "-o", tmp_path / "z.bsdf",
                       "--from", "inside")
    assert rc == 0
    rc, o, e = run_cli(capsys, "export", tmp_path / "nope.h5", "--format", "is-bsdf", "-o", tmp_path / "z.bsdf")
    assert rc == 2 and "nope.h5" in e
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    rc, o, e = run_cli(capsys, "export", tmp_path / "junk.h5", "--format", "recording-csv", "-o", tmp_path / "j.csv")
    assert rc == 2 and "junk.h5" in e and not (tmp_path / "j.csv").exists()


def test_synth_bad_arguments(tmp_path, capsys):
    rc, o, e = run_cli(capsys, "synth", "--rms-height-um", 0.05, "--corr-length-um", 0.1, "--size", 64,
                       "--pitch-um", 0.5, "-o", tmp_path / "a.npz")
    assert rc == 2 and "correlation length" in e
    rc, o, e = run_cli(capsys, "synth", "--rms-height-um", 0.05, "--corr-length-um", 4, "--size", 64,
                       "--pitch-um", 0.5, "-o", tmp_path / "a.png")
    assert rc == 2 and "a.png" in e


def test_console_script_subprocess(tmp_path):
    exe = Path(sys.executable).with_name("relief")
    out = tmp_path / "e.npz"
    p = subprocess.run([str(exe), "synth", "--kind", "exponential", "--rms-height-um", "0.02", "--corr-length-um",
                        "3", "--size", "128", "--pitch-um", "0.5", "-o", str(out)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    r = read_relief(out)
    assert r.periodic and r.shape == (128, 128)
    p = subprocess.run([str(exe), "info", str(tmp_path / "missing.x3p")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "missing.x3p" in p.stderr and "Traceback" not in p.stderr


def test_synth_dots_geometry_read_back(tmp_path, capsys):
    """--kind dots: the written file holds caps of the requested height covering the requested area fraction."""
    out = tmp_path / "dots.npz"
    # tile 256 um; fill 0.2 with a = 8 um asks for a spacing of 31.7 um -> 8 x 8 dots at 32 um (fill 0.196)
    rc, o, e = run_cli(capsys, "synth", "--kind", "dots", "--size", 512, "--pitch-um", 0.5, "--dot-radius-um", 8,
                       "--dot-height-um", 2, "--fill-factor", 0.2, "--jitter", 0.3, "--seed", 4, "-o", out)
    assert rc == 0, e
    assert "64 cap dots" in o and "fill factor" in o
    r = read_relief(out)
    h = r.heights_m
    assert r.periodic and r.shape == (512, 512) and r.dx_m == pytest.approx(0.5e-6)
    assert h.min() == 0.0 and h.max() == pytest.approx(2e-6, rel=0.02)
    assert (h > 0).mean() == pytest.approx(0.2, rel=0.05)
    assert (h > 0).mean() == pytest.approx(64 * np.pi * 8.0**2 / 256.0**2, rel=0.03)   # 64 caps of radius a
    # spherical-cap volume pi h (3 a^2 + h^2) / 6 per dot
    vol = h.sum() * r.dx_m * r.dy_m
    assert vol == pytest.approx(64 * np.pi * 2e-6 * (3 * 8e-6**2 + 2e-6**2) / 6, rel=0.02)

    # pits with a Gaussian profile at an explicit spacing
    out2 = tmp_path / "pits.npz"
    # (jitter 0: dot centres sit 0.25 um from the nearest pixel centres, peak sampled at exp(-1/288) = 0.9965)
    rc, o, e = run_cli(capsys, "synth", "--kind", "dots", "--size", 512, "--pitch-um", 0.5, "--dot-radius-um", 6,
                       "--dot-height-um", -1.5, "--dot-pitch-um", 64, "--dot-shape", "gaussian", "--jitter", 0,
                       "-o", out2)
    assert rc == 0, e
    h2 = read_relief(out2).heights_m
    assert h2.max() == 0.0 and h2.min() == pytest.approx(-1.5e-6, rel=0.02)
    assert (h2 < 0).mean() == pytest.approx(16 * np.pi * 12.0**2 / 256.0**2, rel=0.05)  # cut at 2a


@pytest.mark.parametrize("extra,option", [
    ([], "--dot-radius-um"),                                                       # missing radius
    (["--dot-radius-um", 8, "--dot-height-um", 2], "--dot-pitch-um"),              # neither spacing nor fill
    (["--dot-radius-um", 8, "--dot-height-um", 2, "--dot-pitch-um", 32, "--fill-factor", 0.2], "--dot-pitch-um"),
    (["--dot-radius-um", 8, "--dot-height-um", 2, "--fill-factor", 1.5], "--fill-factor"),
    (["--dot-radius-um", 8, "--dot-height-um", 2, "--fill-factor", 0.7], "--dot-radius-um"),   # dots overlap
    (["--dot-radius-um", 8, "--dot-height-um", 0, "--dot-pitch-um", 32], "--dot-height-um"),
    (["--dot-radius-um", 8, "--dot-height-um", 2, "--dot-pitch-um", 32, "--jitter", 1.2], "--jitter"),
    (["--dot-radius-um", 0.5, "--dot-height-um", 2, "--dot-pitch-um", 32], "--dot-radius-um"),  # under 2 px
    (["--dot-radius-um", 8, "--dot-height-um", 2, "--dot-pitch-um", 32, "--rms-height-um", 0.1], "--rms-height-um"),
])
def test_synth_dots_bad_options_exit_2_naming_the_option(tmp_path, capsys, extra, option):
    out = tmp_path / "d.npz"
    rc, o, e = run_cli(capsys, "synth", "--kind", "dots", "--size", 256, "--pitch-um", 0.5, *extra, "-o", out)
    assert rc == 2 and option in e and len(e.strip().splitlines()) == 1
    assert not out.exists()


def test_synth_random_kind_rejects_dot_options_and_needs_its_own(tmp_path, capsys):
    rc, o, e = run_cli(capsys, "synth", "--kind", "gaussian", "--rms-height-um", 0.05, "--corr-length-um", 4,
                       "--size", 64, "--pitch-um", 0.5, "--dot-radius-um", 3, "-o", tmp_path / "g.npz")
    assert rc == 2 and "--dot-radius-um" in e and "--kind dots" in e
    rc, o, e = run_cli(capsys, "synth", "--corr-length-um", 4, "--size", 64, "--pitch-um", 0.5, "-o", tmp_path / "g.npz")
    assert rc == 2 and "--rms-height-um" in e and "required" in e
    assert not (tmp_path / "g.npz").exists()
