"""`relief simulate` and `relief fit` on small samples, and their bad-input exits."""
import json

import numpy as np
import pytest

from relief_bsdf.cli import main
from relief_bsdf.io.heightmaps import write_relief
from relief_bsdf.io.recording import Recording, read_recording, write_recording, write_sample
from relief_bsdf.surface.synth import random_relief


def make_sample(tmp_path, *, cauchy=None, theta_s_max=89.0, half_angle=1.0, relief=True, recording=True):
    if relief:
        write_relief(tmp_path / "relief.npz", random_relief(48, 0.125e-6, 30e-9, 1.0e-6, "gaussian", seed=2))
    ts = np.arange(1.0, 89.5, 8.0)
    if theta_s_max >= 90.0:
        ts = np.append(ts, theta_s_max)
    rows = [(550.0, ti, 0.0, sd, t, ps) for ti in (0.0, 30.0) for sd in "RT" for ps in (0.0, 180.0) for t in ts]
    a = np.array(rows, dtype=object)
    if recording:
        rec = Recording(a[:, 0].astype(float), a[:, 1].astype(float), a[:, 2].astype(float), a[:, 3].astype(str),
                        a[:, 4].astype(float), a[:, 5].astype(float), np.ones(len(rows)), np.full(len(rows), 0.05))
        write_recording(tmp_path / "recording.csv", rec)
    plate = {"thickness_mm": 2.0, "rough_face": "front"}
    plate.update({"cauchy": cauchy} if cauchy else {"refractive_index": 1.5})
    write_sample(tmp_path / "sample.toml", {
        "plate": plate, "relief": {"file": "relief.npz"},
        "instrument": {"detector_half_angle_deg": half_angle, "polarization": "unpolarized"},
        "recording": {"file": "recording.csv"}})
    return tmp_path / "sample.toml"


@pytest.mark.slow
def test_simulate_writes_the_recording_rows(tmp_path):
    s = make_sample(tmp_path)
    # plumbing on a tiny relief: the fast surrogate, named (the default, auto, is tested below)
    assert main(["simulate", str(s), "-o", str(tmp_path / "out"), "--method", "microfacet+dw"]) == 0
    sim = read_recording(tmp_path / "out" / "simulated.csv")
    rec = read_recording(tmp_path / "recording.csv")
    assert len(sim) == len(rec)
    np.testing.assert_array_equal(sim.theta_s_deg, rec.theta_s_deg)
    np.testing.assert_array_equal(sim.side, rec.side)
    assert np.all(sim.bsdf_sr >= 0) and np.all(np.isfinite(sim.bsdf_sr))
    # the in-plane specular row (theta_s = 30 is not on the 8-degree grid) is absent; the lobe is there
    assert sim.bsdf_sr.max() > 10 * np.median(sim.bsdf_sr)


@pytest.mark.slow
def test_fit_cli_writes_fit_json_and_resumes(tmp_path, capsys):
    s = make_sample(tmp_path)
    out = tmp_path / "fit"
    args = ["fit", str(s), "-o", str(out), "--max-iter", "4", "--theta-step-deg", "3", "--phi-step-deg", "15",
            "--method", "microfacet+dw"]
    assert main(args) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["format"] == "relief-fit/1"
    assert set(doc["parameters"]) >= {"height_scale", "filter_sigma_um"}
    assert doc["rms_after"] <= doc["rms_before"]
    assert doc["iterations"][0]["parameters"]["height_scale"] == 1.0
    assert doc["metric"].startswith("rms z") and "log-chi" in doc["search_objective"]
    assert doc["grid"]["theta_step_deg"] == 3 and doc["grid"]["sectors"] == "auto"   # the grid it used, on record
    assert "inside_sectors" not in doc                   # a surrogate face: no sector tables
    for f in ("checkpoint.json", "boundary.h5", "relief_optimised.npz", "report.html", "in_plane_after.png",
              "residual_before.png", "simulated.csv"):
        assert (out / f).exists(), f
    _check_fit_isbsdf_files(out, doc)    # the saved boundary tables reproduce the fitted simulation through `relief simulate --table`
    assert main(["simulate", str(s), "-o", str(tmp_path / "sim"), "--table", str(out / "boundary.h5")]) == 0
    a = read_recording(out / "simulated.csv").bsdf_sr
    b = read_recording(tmp_path / "sim" / "simulated.csv").bsdf_sr
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-9)   # tables are stored as float32
    n_ck = len(_saved_evaluations(out / "checkpoint.json"))
    assert main(args) == 0               # replayed from the checkpoint: same answer
    doc2 = json.loads((out / "fit.json").read_text())
    assert doc2["parameters"] == doc["parameters"] and doc2["rms_after"] == doc["rms_after"]
    assert len(_saved_evaluations(out / "checkpoint.json")) == n_ck


def _check_fit_isbsdf_files(out, doc):
    """Issue 15 item 2 on the fit's own output: OpticStudio wants one scatter type per .bsdf file and
    a BTDF centred on the refracted ray.  Each file's TIS is the fitted table's diffuse total (the
    tables in boundary.h5), and read back at normal incidence, where the IS-BSDF grid holds the
    table's cell centres, the pair gives the table's values (oblique incidences are interpolated
    between the two grids: io/test_isbsdf.py bounds that error on smooth lobes)."""
    from relief_bsdf.io.hdf5 import load_tables
    from relief_bsdf.io.isbsdf import import_isbsdf, read_isbsdf_all
    for t in load_tables(out / "boundary.h5"):
        names = doc["files"][f"isbsdf_{t.incident_from}"]
        assert sorted(names) == [f"boundary_{t.incident_from}_BRDF.bsdf", f"boundary_{t.incident_from}_BTDF.bsdf"]
        h = t.hemispherical()
        for name in names:
            blocks = read_isbsdf_all(out / name)
            assert len(blocks) == 1 and blocks[0].scatter_type == name[-9:-5]
            side = "R" if blocks[0].scatter_type == "BRDF" else "T"
            if side == "T":
                assert blocks[0].relief_tag("btdf_centre") == "refracted"
            np.testing.assert_allclose(blocks[0].tis[0], h["diffuse_" + side][0, :, 0], rtol=1e-5, atol=1e-9)
        back = import_isbsdf([out / n for n in names], t.theta_s_edges_deg, t.phi_s_edges_deg)
        assert back.incident_from == t.incident_from and t.theta_i_deg[0] == 0.0
        np.testing.assert_allclose(back.values_per_sr[0, 0], t.values_per_sr[0, 0], rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("case, needle", [
    ("no_relief", "relief.file"),
    ("no_recording", "recording.file"),
    ("wavelength", "wavelength"),
    ("theta90", "theta_s_deg"),
    ("cone0", "detector_half_angle_deg"),
])
def test_bad_input_exits_2_naming_file_and_key(tmp_path, capsys, case, needle):
    kw = {"no_relief": dict(relief=False), "no_recording": dict(recording=False),
          "wavelength": dict(cauchy=[1.49, 4000.0]), "theta90": dict(theta_s_max=90.0),
          "cone0": dict(half_angle=0.0)}[case]
    if case == "cone0":
        s = make_sample(tmp_path)
        s.write_text(s.read_text().replace("detector_half_angle_deg = 1.0", "detector_half_angle_deg = 0.0"))
    else:
        s = make_sample(tmp_path, **kw)
    if case == "wavelength":   # Cauchy models are valid 350-1000 nm by default
        rec = read_recording(tmp_path / "recording.csv")
        rec.wavelength_nm[:] = 1200.0
        write_recording(tmp_path / "recording.csv", rec)
    rc = main(["simulate", str(s), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and needle in err[0]
    assert ("sample.toml" in err[0]) or ("recording.csv" in err[0])


def test_fit_cli_rejects_a_bad_inside_step(tmp_path, capsys):
    s = make_sample(tmp_path)
    assert main(["fit", str(s), "-o", str(tmp_path / "f"), "--inside-step-deg", "0"]) == 2
    assert "--inside-step-deg" in capsys.readouterr().err
    assert not (tmp_path / "f" / "fit.json").exists()


@pytest.mark.slow
def test_a_checkpoint_of_another_sample_is_ignored_and_the_true_result_returned(tmp_path, capsys):
    """A finished run's checkpoint copied into a run of another sample (n 1.60 instead of 1.50)
    must not be replayed: the second run gives what a fresh run of its own sample gives."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    sa, sb = make_sample(a), make_sample(b)
    sb.write_text(sb.read_text().replace("refractive_index = 1.5", "refractive_index = 1.6"))
    args = ["--max-iter", "4", "--theta-step-deg", "3", "--phi-step-deg", "15", "--method", "microfacet+dw"]
    assert main(["fit", str(sa), "-o", str(a / "fit")] + args) == 0
    assert main(["fit", str(sb), "-o", str(b / "fresh")] + args) == 0
    (b / "copied").mkdir()
    (b / "copied" / "checkpoint.json").write_bytes((a / "fit" / "checkpoint.json").read_bytes())
    capsys.readouterr()
    assert main(["fit", str(sb), "-o", str(b / "copied")] + args) == 0
    assert "ignored checkpoint" in capsys.readouterr().err
    fresh = json.loads((b / "fresh" / "fit.json").read_text())
    copied = json.loads((b / "copied" / "fit.json").read_text())
    first = json.loads((a / "fit" / "fit.json").read_text())
    assert copied["rms_before"] == fresh["rms_before"] != first["rms_before"]
    assert copied["parameters"] == fresh["parameters"] and copied["evaluations_computed"] > 0


def _saved_evaluations(path):
    """The evaluations a fit checkpoint holds (io.checkpoint's JSON layout, read without its key)."""
    from relief_bsdf.io.checkpoint import decode
    return decode(json.loads(path.read_text())["data"])["evaluations"]


@pytest.mark.slow
def test_simulate_sectors_always_meets_an_isotropic_ray_traced_relief_by_azimuth_and_says_so(tmp_path, capsys):
    """`--sectors always` (TableGrid.sectors): the loop gets the inside sector tables of a ray-traced
    relief whatever its statistics, the physics line names them, and the simulated rows differ from the
    default's (the loop then meets the tile's own azimuth dependence); an unknown choice exits 2."""
    s = make_sample(tmp_path)
    write_relief(tmp_path / "relief.npz", random_relief(128, 0.25e-6, 0.1e-6, 1.0e-6, "gaussian", seed=2))
    common = ["--method", "ray", "--samples", "20000", "--seed", "3"]
    assert main(["simulate", str(s), "-o", str(tmp_path / "auto")] + common) == 0
    auto_out = capsys.readouterr().out
    assert main(["simulate", str(s), "-o", str(tmp_path / "always"), "--sectors", "always"] + common) == 0
    always_out = capsys.readouterr().out
    assert "inside sector tables" not in auto_out
    assert "loop by azimuth sector (2 inside sector tables)" in always_out
    a = read_recording(tmp_path / "auto" / "simulated.csv").bsdf_sr
    b = read_recording(tmp_path / "always" / "simulated.csv").bsdf_sr
    assert not np.allclose(a, b, rtol=1e-4)
    with pytest.raises(SystemExit) as e:
        main(["simulate", str(s), "-o", str(tmp_path / "x"), "--sectors", "sometimes"])
    assert e.value.code == 2 and "--sectors" in capsys.readouterr().err


@pytest.mark.slow
def test_simulate_fit_and_diagnose_report_one_metric_with_one_number(tmp_path, capsys, monkeypatch):
    """`relief simulate` prints the metric that fit.json calls rms_before and diagnosis.json rms_before for
    the same starting relief (fit.residual.rms_z: rms z with the simulation's own sigma); on a sampling
    method, so that sigma is not zero.  Run from the sample's folder with relative paths: the outputs name
    no absolute path of this machine."""
    import re
    s = make_sample(tmp_path)
    monkeypatch.chdir(tmp_path)
    common = ["--method", "normals", "--samples", "20000"]
    assert main(["simulate", "sample.toml", "-o", "sim", *common]) == 0
    printed = float(re.search(r"metric \(rms z\) vs recording ([0-9.eE+-]+)", capsys.readouterr().out).group(1))
    comment = (tmp_path / "sim" / "simulated.csv").read_text()
    in_csv = float(re.search(r"metric \(rms z\) vs recording: ([0-9.eE+-]+)", comment).group(1))
    assert main(["fit", "sample.toml", "-o", "fit", "--max-iter", "2", *common]) == 0
    fit = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert fit["rms_before"] == pytest.approx(in_csv, rel=1e-5) and f"{fit['rms_before']:.4g}" == f"{printed:.4g}"
    assert fit["iterations"][0]["rms"] == fit["rms_before"] and fit["metric"].startswith("rms z")
    assert fit["rms_before"] > 2.0                  # a sample the starting relief misses: not a trivial 0 = 0
    assert main(["diagnose", "sample.toml", "-o", "diag", "--method", "normals", "--photons", "20000",
                 "--effects", "stray_light", "--workers", "1"]) == 0
    diag = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert diag["rms_before"] == pytest.approx(fit["rms_before"], rel=1e-5) and diag["metric"] == fit["metric"]
    for f in ("fit/fit.json", "fit/report.html", "diag/diagnosis.json", "diag/report.html"):
        assert str(tmp_path) not in (tmp_path / f).read_text(), f
    assert s.exists()
