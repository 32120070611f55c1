"""Measured plate files through the command line: `relief info`, `relief plot`, `relief export` on RPC
Photonics text and measured IS-BSDF files (../shared/data/measured), and `relief info SAMPLE.toml`
for a sample whose recording is a list of measured files (io.measured)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.cli import main
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.io.measured import read_measured
from relief_bsdf.io.recording import read_recording

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "io"))
from test_measured import EDS10, ISBSDF, ISBSDF_FILES, _sample_toml, _small_rpc  # noqa: E402
from test_radiance_xml import boundary_table  # noqa: E402


def run_cli(capsys, *args):
    capsys.readouterr()
    rc = main([str(a) for a in args])
    o, e = capsys.readouterr()
    return rc, o, e


@pytest.fixture
def table_file(tmp_path):
    return save_tables(tmp_path / "t.h5", [boundary_table("outside"), boundary_table("inside")])


@pytest.mark.shared_data
def test_info_rpc_file(capsys):
    rc, o, e = run_cli(capsys, "info", EDS10 / "EDS10 5-45.txt", "--json")
    assert rc == 0, e
    d = json.loads(o)
    assert d["kind"] == "measured" and d["format"] == "rpc-photonics" and d["rows"] == 86 * 360
    assert d["wavelength_nm"] is None and "--wavelength-nm" in d["wavelength"]
    assert d["incidences_deg"] == [[5.0, 45.0]] and d["sides"] == ["T"]
    (lb,) = d["lobes"]
    assert 0.88 <= lb["integral"] <= 0.90 and lb["offset_deg"] < 0.2
    assert lb["centroid_deg"][0] == pytest.approx(5.0, abs=0.2) and lb["centroid_deg"][1] == pytest.approx(225, abs=1)
    rc, o, e = run_cli(capsys, "info", EDS10 / "EDS10 5-45.txt")
    assert rc == 0 and "RPC Photonics" in o and "phi_s + 180" in o and "0.8947" in o


@pytest.mark.shared_data
@pytest.mark.parametrize("name", ["test_13_brdf_one_wavelength_BTDF_zemax_reference.bsdf",
                                  "test_13_planesymmetric_brdf_zemax.bsdf"])
def test_info_measured_isbsdf(capsys, name):
    rc, o, e = run_cli(capsys, "info", ISBSDF / name, "--json")
    assert rc == 0, e
    d = json.loads(o)
    side, stated = ISBSDF_FILES[name]
    assert d["kind"] == "measured" and d["format"] == "is-bsdf" and d["sides"] == [side]
    assert d["wavelength_nm"] == stated
    assert d["rows"] == len(read_measured(ISBSDF / name, wavelength_nm=None if stated else 550.0))
    assert len(d["lobes"]) == len(d["incidences_deg"]) and all(lb["integral"] > 0 for lb in d["lobes"])


def test_info_sample_with_measured_recording(tmp_path, capsys):
    _small_rpc(tmp_path, "a 0-0.txt", 0.0)
    _small_rpc(tmp_path, "a 5-0.txt", 5.0)
    p = _sample_toml(tmp_path, '["a 0-0.txt", "a 5-0.txt"]', "wavelength_nm = 633.0\n")
    rc, o, e = run_cli(capsys, "info", p)
    assert rc == 0, e
    assert o.count("(RPC Photonics text)") == 2 and "24 at 633 nm" in o and "(0, 0), (5, 0)" in o
    rc, o, e = run_cli(capsys, "info", p, "--json")
    d = json.loads(o)
    assert d["kind"] == "sample" and len(d["recording_files"]) == 2 and d["recording_wavelength_nm"] == 633.0
    # without the wavelength: info still shows the sample and names the key its recording needs
    p = _sample_toml(tmp_path, '["a 0-0.txt"]')
    rc, o, e = run_cli(capsys, "info", p)
    assert rc == 0 and "not readable yet" in o and "a 0-0.txt" in o and "[recording] wavelength_nm" in o


def test_export_rpc_rows_and_errors(tmp_path, capsys):
    src = _small_rpc(tmp_path, "s 5-0.txt")
    rc, o, e = run_cli(capsys, "export", src, "--format", "recording-csv", "-o", tmp_path / "m.csv")
    assert rc == 2 and not (tmp_path / "m.csv").exists()
    assert "s 5-0.txt" in e and "--wavelength-nm" in e and len(e.strip().splitlines()) == 1
    rc, o, e = run_cli(capsys, "export", src, "--format", "recording-csv", "--wavelength-nm", 633, "-o",
                       tmp_path / "m.csv")
    assert rc == 0, e
    rec = read_recording(tmp_path / "m.csv")
    want = read_measured(src, wavelength_nm=633.0)
    np.testing.assert_array_equal(rec.bsdf_sr, want.bsdf_sr)
    np.testing.assert_allclose(rec.sigma_sr, want.sigma_sr)
    assert any("phi_s + 180" in c for c in rec.comments)
    # a garbled file: one line naming the file and the line
    bad = tmp_path / "bad.txt"
    bad.write_text(src.read_text().replace("1.0000\t90.0000\t2.0900", "1.0000\t90.0000"))
    rc, o, e = run_cli(capsys, "export", bad, "--format", "recording-csv", "--wavelength-nm", 633, "-o",
                       tmp_path / "b.csv")
    assert rc == 2 and f"{bad}:9" in e and len(e.strip().splitlines()) == 1 and "Traceback" not in e


@pytest.mark.shared_data
def test_export_rpc_as_table_keeps_the_transmittance(tmp_path, capsys):
    """An RPC file as an HDF5 table (to bake or compare): T of the 1-degree cells within 0.005 of the
    rows' integral into 0-85 deg (0.8979; the cells integrate the readings' linear interpolant, 0.8999:
    the two quadratures of the 1-degree grid differ by 0.2 %)."""
    rc, o, e = run_cli(capsys, "export", EDS10 / "EDS10 0-0.txt", "--format", "hdf5", "--wavelength-nm", 633,
                       "--n", 1.5, "-o", tmp_path / "m.h5")
    assert rc == 0, e
    (t,) = load_tables(tmp_path / "m.h5")
    assert t.wavelength_nm.tolist() == [633.0] and t.material["inside"]["n"] == 1.5
    h = t.hemispherical()
    assert h["T"][0, 0, 0] == pytest.approx(0.8979, abs=0.005) and h["R"][0, 0, 0] == 0.0
    from relief_bsdf.bake import bake_lut           # and it bakes like any table
    assert np.all(np.isfinite(bake_lut([t], "measured").image_pixels()))


@pytest.mark.shared_data
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if "one_wavelength" in n else n
                                  for n in ISBSDF_FILES])
def test_readme_commands_on_the_measured_isbsdf_files(tmp_path, capsys, table_file, name):
    """README: `relief plot t.h5 measured_BTDF.bsdf --n 1.5 -o cmp.png` and `relief export measured.bsdf
    --format recording-csv -o m.csv` on every measured file; the wavelength is the header's where it
    states one, else the reconstruction's (plot) or --wavelength-nm (export; asked for by name)."""
    path = ISBSDF / name
    side, stated = ISBSDF_FILES[name]
    rc, o, e = run_cli(capsys, "plot", table_file, path, "--n", 1.5, "-o", tmp_path / "cmp.png")
    assert rc == 0, e
    assert (tmp_path / "cmp.png").stat().st_size > 20000
    rc, o, e = run_cli(capsys, "export", path, "--format", "recording-csv", "-o", tmp_path / "m.csv")
    if stated is None:
        assert rc == 2 and name in e and "--wavelength-nm" in e and "pass wavelength_nm" not in e
        rc, o, e = run_cli(capsys, "export", path, "--format", "recording-csv", "--wavelength-nm", 550,
                           "-o", tmp_path / "m.csv")
    assert rc == 0, e
    rec = read_recording(tmp_path / "m.csv")
    assert set(rec.side) == {side} and np.all(rec.wavelength_nm == 550.0)
    assert len(rec) == len(read_measured(path, wavelength_nm=None if stated else 550.0))


@pytest.mark.shared_data
def test_plot_rpc_alone_and_beside_a_table(tmp_path, capsys, table_file):
    rc, o, e = run_cli(capsys, "plot", EDS10 / "EDS10 5-45.txt", "-o", tmp_path / "lobe.png")
    assert rc == 0, e
    assert (tmp_path / "lobe.png").stat().st_size > 30000
    # beside a reconstruction: the RPC file takes the table's wavelength, drawn at its own incidence only
    rc, o, e = run_cli(capsys, "plot", table_file, EDS10 / "EDS10 0-0.txt", "--n", 1.5, "--side", "T",
                       "-o", tmp_path / "cmp.png")
    assert rc == 0, e
    assert (tmp_path / "cmp.png").stat().st_size > 20000


@pytest.mark.filterwarnings("ignore:microfacet table")   # a small tile's sampling note: rows, not values, tested
def test_simulate_a_sample_whose_recording_is_rpc_files(tmp_path, capsys, gaussian_relief):
    """`relief simulate` on a sample with a list of RPC files: one simulated row per measured row."""
    from relief_bsdf.io.heightmaps import write_relief
    _small_rpc(tmp_path, "a 0-0.txt", 0.0)
    _small_rpc(tmp_path, "a 5-0.txt", 5.0)
    p = _sample_toml(tmp_path, '["a 0-0.txt", "a 5-0.txt"]', "wavelength_nm = 633.0\n")
    write_relief(tmp_path / "relief.npz", gaussian_relief(64, 0.5e-6, 0.5e-6, 5e-6))
    rc, o, e = run_cli(capsys, "simulate", p, "--method", "microfacet", "-o", tmp_path / "out")
    assert rc == 0, e
    sim = read_recording(tmp_path / "out" / "simulated.csv")
    rec = read_measured(tmp_path / "a 0-0.txt", wavelength_nm=633.0)
    assert len(sim) == 24 and np.array_equal(sim.theta_s_deg[:12], rec.theta_s_deg)
    assert np.all(sim.bsdf_sr > 0) and set(sim.side) == {"T"}
