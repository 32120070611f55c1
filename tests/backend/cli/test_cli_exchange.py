"""Exchange formats through the command line: `relief export --format radiance-xml|is-bsdf|hdf5`,
`relief plot A B` with measured files, a measured file compared with a recording and baked."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.cli import main
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.io.recording import read_recording

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "io"))
from test_radiance_xml import boundary_table, load_bsdf  # noqa: E402


def run_cli(capsys, *args):
    capsys.readouterr()
    rc = main([str(a) for a in args])
    o, e = capsys.readouterr()
    return rc, o, e


@pytest.fixture
def table_file(tmp_path):
    return save_tables(tmp_path / "b.h5", [boundary_table("outside"), boundary_table("inside")])


@pytest.mark.slow
def test_export_radiance_xml_loads_in_radiance(tmp_path, capsys, table_file):
    """Radiance caches BSDFs by file name (without directory): every test loads a distinct name."""
    from pyradiance import bsdf as rbsdf      # test-only oracle (requirements/test.txt): never skipped
    rc, o, e = run_cli(capsys, "export", table_file, "--format", "radiance-xml", "-o", tmp_path / "cli_export_pair.xml")
    assert rc == 0, e
    sd = load_bsdf(tmp_path / "cli_export_pair.xml")
    t = load_tables(table_file)[0]
    got = rbsdf.direct_hemi(sd, 150.0, 0.0, rbsdf.SAMPLE_T | rbsdf.SAMPLE_SP | rbsdf.SAMPLE_DF)
    assert got == pytest.approx(t.hemispherical()["T"][0, 3, 0], rel=0.03)
    # one side only: a clear error naming the missing side, exit 2
    one = save_tables(tmp_path / "one.h5", [boundary_table("outside")])
    rc, o, e = run_cli(capsys, "export", one, "--format", "radiance-xml", "-o", tmp_path / "x.xml")
    assert rc == 2 and "inside" in e and not (tmp_path / "x.xml").exists()


@pytest.mark.slow
def test_measured_isbsdf_plotted_compared_and_baked(tmp_path, capsys, table_file):
    """A measured-like IS-BSDF pair (no relief comments) becomes a table: plotted beside the
    reconstruction, written as recording rows that match the table it came from, and baked."""
    rc, o, e = run_cli(capsys, "export", table_file, "--format", "is-bsdf", "-o", tmp_path / "m.bsdf")
    assert rc == 0 and "m_BRDF.bsdf" in o and "m_BTDF.bsdf" in o
    for name in ("m_BRDF.bsdf", "m_BTDF.bsdf"):              # strip our tags: a foreign measurement
        p = tmp_path / name
        p.write_text("\n".join(l for l in p.read_text().splitlines() if not l.startswith("#")))
    rc, o, e = run_cli(capsys, "plot", table_file, tmp_path / "m_BTDF.bsdf", "--wavelength-nm", 550, "--n", 1.5,
                       "-o", tmp_path / "cmp.png")
    assert rc == 0, e
    assert (tmp_path / "cmp.png").stat().st_size > 20000
    rc, o, e = run_cli(capsys, "export", tmp_path / "m_BRDF.bsdf", "--format", "recording-csv", "--wavelength-nm",
                       550, "--n", 1.5, "-o", tmp_path / "m.csv")
    assert rc == 0, e
    rec = read_recording(tmp_path / "m.csv")
    t = load_tables(table_file)[0]
    near = (rec.theta_i_deg == 30.0) & (rec.theta_s_deg > 15) & (rec.theta_s_deg < 60)
    want = t.eval(550.0, rec.theta_i_deg[near], rec.phi_i_deg[near], rec.side[near], rec.theta_s_deg[near],
                  rec.phi_s_deg[near])
    assert np.median(np.abs(rec.bsdf_sr[near] / want - 1)) < 0.03   # both sides' blocks, centring undone
    rc, o, e = run_cli(capsys, "export", tmp_path / "m_BRDF.bsdf", "--format", "hdf5", "--wavelength-nm", 550,
                       "--n", 1.5, "-o", tmp_path / "m.h5")
    assert rc == 0, e
    from relief_bsdf.bake import bake_lut
    (m,) = load_tables(tmp_path / "m.h5")
    assert m.material["inside"]["n"] == 1.5
    lut = bake_lut([m], "measured")
    assert np.all(np.isfinite(lut.image_pixels()))


@pytest.mark.slow
def test_plot_xml_beside_table(tmp_path, capsys, table_file):
    rc, o, e = run_cli(capsys, "export", table_file, "--format", "radiance-xml", "-o", tmp_path / "b.xml")
    rc, o, e = run_cli(capsys, "plot", table_file, tmp_path / "b.xml", "--side", "T", "-o", tmp_path / "p.png")
    assert rc == 0 and (tmp_path / "p.png").exists()
    rc, o, e = run_cli(capsys, "plot", tmp_path / "b.txt")
    assert rc == 2 and "b.txt" in e


def test_isbsdf_undeviated_option_and_bad_n(tmp_path, capsys, table_file):
    rc, o, e = run_cli(capsys, "export", table_file, "--format", "is-bsdf", "--btdf-centre", "undeviated",
                       "-o", tmp_path / "u.bsdf")
    assert rc == 0
    assert "btdf_centre = undeviated" in (tmp_path / "u_BTDF.bsdf").read_text()
    rc, o, e = run_cli(capsys, "export", table_file, "--format", "hdf5", "--n", -1, "-o", tmp_path / "z.h5")
    assert rc == 2 and "--n" in e
