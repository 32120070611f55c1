"""What a new user meets first, through the command line: maps with holes (`relief fill`,
`--fill-holes`), windows (`relief crop`, `--crop`, `--downsample`), periodicity (`--periodic`,
`[relief] periodic`, the wrap-around test), clean warnings, valid inputs of other shapes,
output folders, `--help` defaults and `--version`."""
from __future__ import annotations

import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.cli import main
from relief_bsdf.io.heightmaps import write_relief
from relief_bsdf.surface.periodicity import WRAP_RATIO_MAX, wrap_ratios
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import random_relief

TOPO = Path(__file__).resolve().parents[2] / "data" / "topography"         # instrument files kept in the repository
CASES = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "validation" / "cases"
INSTRUMENT_FILES = ["ST_di-1.di", "ST_frt-1.frt", "ST_metropro-1.dat", "ST_mi-1.mi", "ST_nid-1.nid", "ST_opd-1.opd",
                    "ST_plu-1.plu", "ST_spot_1-1000nm.ibw", "ST_x3p-2.x3p"]


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def tile(n: int = 64, seed: int = 1) -> Relief:
    """A seamless periodic tile, 64 x 64, 0.25 um pitch, rms 0.1 um, correlation 1 um."""
    return random_relief(n, 0.25e-6, 0.1e-6, 1e-6, "gaussian", seed)


def save_npz(path: Path, relief: Relief, state_periodic: bool = False) -> Path:
    """An npz as another tool writes it: heights, dx, dy, and `periodic` only if stated."""
    extra = {"periodic": np.bool_(relief.periodic)} if state_periodic else {}
    np.savez(path, heights=relief.heights_m, dx=relief.dx_m, dy=relief.dy_m, **extra)
    return path


def measured_with_holes(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """A 64 x 64 measured-style map (a tilted plane plus a tile, not periodic) with an interior
    hole and an edge hole; returns the file and the heights before the holes were cut."""
    y, x = np.mgrid[0:64, 0:64]
    h = (2e-9 * x + 1e-9 * y) + tile().heights_m
    holey = h.copy()
    holey[20:28, 30:41] = np.nan
    holey[0, 5:9] = np.nan
    return save_npz(tmp_path / "holes.npz", Relief(holey, 0.25e-6, 0.25e-6)), h


# ---------------------------------------------------------------------------------------------- holes


def test_fill_writes_a_complete_map_and_says_how_much(tmp_path, capsys):
    src, _ = measured_with_holes(tmp_path)
    out = tmp_path / "filled.npz"
    rc, o, e = run_cli(capsys, "fill", src, "-o", out)
    assert rc == 0, e
    assert "filled 92 of 4096 points (2.25%)" in o
    with np.load(out) as z:
        h = z["heights"]
        hist = json.loads(str(z["info_json"]))["history"]
    assert np.isfinite(h).all()
    assert any(s.startswith("filled 92 invalid points") and "harmonic" in s for s in hist)
    assert any(s.startswith("periodicity: ") for s in hist)


def test_harmonic_fill_reproduces_a_plane_in_an_interior_hole():
    """A plane is harmonic: the exact Laplace solution from the rim of an interior hole is the plane."""
    y, x = np.mgrid[0:40, 0:50]
    plane = 3e-9 * x - 2e-9 * y + 5e-9
    holey = plane.copy()
    holey[10:25, 12:30] = np.nan
    filled = Relief(holey, 1e-7, 1e-7).fill_holes()
    np.testing.assert_allclose(filled.heights_m, plane, rtol=0, atol=1e-21)


def test_fill_max_gap_leaves_wide_holes(tmp_path, capsys):
    src, _ = measured_with_holes(tmp_path)
    rc, o, e = run_cli(capsys, "fill", src, "--max-gap-px", 2, "-o", tmp_path / "f.npz")
    assert rc == 0, e
    assert "filled 4 of 4096" in o and "88 points in holes wider than 2 px stay missing" in o


def test_ray_on_a_map_with_holes_points_at_real_options(tmp_path, capsys):
    src, _ = measured_with_holes(tmp_path)
    common = ["--method", "ray", "--n", "1.5", "--theta-i-deg", "0", "--samples", "2000",
              "--theta-step-deg", "10", "--phi-step-deg", "30"]
    rc, o, e = run_cli(capsys, "reconstruct", src, *common, "-o", tmp_path / "t.h5")
    assert rc == 2 and not (tmp_path / "t.h5").exists()
    assert len(e.strip().splitlines()) == 1
    assert "--fill-holes" in e and "relief fill" in e and "Relief.fill_holes" not in e
    # every option the message names works
    rc, o, e = run_cli(capsys, "reconstruct", src, *common, "--fill-holes", "-o", tmp_path / "t.h5")
    assert rc == 0, e
    assert "filled 92 invalid points" in o and "measured patch" in o
    rc, o, e = run_cli(capsys, "reconstruct", src, *common, "--option", "fill_holes=True", "-o", tmp_path / "u.h5")
    assert rc == 0, e


# ---------------------------------------------------------------------------------------------- crop


def test_crop_and_downsample_recompute_the_statistics(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    out = tmp_path / "c.x3p"
    rc, o, e = run_cli(capsys, "crop", src, "--crop", "8,4,32,40", "--downsample", 2, "-o", out)
    assert rc == 0, e
    assert "grid       16 x 20 px, pitch 500 nm x 500 nm" in o
    assert "rms height" in o and "Rayleigh parameter" in o
    assert "cropped to rows 4:44, cols 8:40" in o and "downsampled by 2" in o
    rc, o, e = run_cli(capsys, "info", out, "--json")
    d = json.loads(o)
    assert d["shape"] == [20, 16] and d["pitch_m"] == pytest.approx([0.5e-6, 0.5e-6])
    # the crop's own statistics, not the tile's: recompute them from the window's block means
    win = tile().heights_m[4:44, 8:40].reshape(20, 2, 16, 2).mean(axis=(1, 3))
    yy, xx = np.mgrid[0:20, 0:16]
    a = np.c_[np.ones(win.size), xx.ravel(), yy.ravel()]
    resid = win.ravel() - a @ np.linalg.lstsq(a, win.ravel(), rcond=None)[0]
    assert d["rms_height_m"] == pytest.approx(resid.std(), rel=1e-6)
    assert d["periodic"] is False            # a piece of a tile is no tile


def test_crop_outside_the_map_is_one_line(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile())
    rc, o, e = run_cli(capsys, "crop", src, "--crop", "40,0,32,16", "-o", tmp_path / "c.npz")
    assert rc == 2 and len(e.strip().splitlines()) == 1 and "leaves the map of 64 x 64" in e
    rc, o, e = run_cli(capsys, "crop", src, "--crop", "1,2,3", "-o", tmp_path / "c.npz")
    assert rc == 2 and "--crop" in e and "X0,Y0,W,H" in e
    assert not (tmp_path / "c.npz").exists()


def test_reconstruct_takes_crop_and_downsample(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    rc, o, e = run_cli(capsys, "reconstruct", src, "--method", "microfacet", "--n", "1.5", "--theta-i-deg", "0",
                       "--crop", "0,0,32,32", "--downsample", 2, "-o", tmp_path / "t.h5")
    assert rc == 0, e
    assert "grid       16 x 16 px" in o and "Rayleigh parameter" in o
    from relief_bsdf.io.hdf5 import load_tables
    hist = load_tables(tmp_path / "t.h5")[0].relief["history"]      # the table says what was traced
    assert hist[0] == "cropped to rows 0:32, cols 0:32" and hist[1].startswith("downsampled by 2")
    assert hist[2].startswith("periodicity: measured patch")


# ---------------------------------------------------------------------------------------------- periodicity


def test_wrap_test_on_a_seamless_tile_and_a_piece_of_it():
    r = tile()
    assert max(wrap_ratios(r.heights_m)) <= WRAP_RATIO_MAX
    assert min(wrap_ratios(random_relief(128, 0.25e-6, 0.1e-6, 2e-6, "gaussian", 1).heights_m[10:74, 30:94])) \
        > WRAP_RATIO_MAX


def test_periodicity_precedence_in_info(tmp_path, capsys):
    unstated = save_npz(tmp_path / "u.npz", tile())                       # states nothing: the test decides
    rc, o, e = run_cli(capsys, "info", unstated, "--json")
    p = json.loads(o)["periodicity"]
    assert p["periodic"] is True and p["source"] == "test" and "wrap-around test" in p["reason"]
    rc, o, e = run_cli(capsys, "info", unstated, "--no-periodic", "--json")
    assert json.loads(o)["periodicity"] == {"periodic": False, "source": "user", "reason": "stated by --no-periodic"}
    stated = tile()
    stated = Relief(stated.heights_m, stated.dx_m, stated.dy_m, periodic=False)
    f = save_npz(tmp_path / "s.npz", stated, state_periodic=True)         # the file says: not periodic
    rc, o, e = run_cli(capsys, "info", f, "--json")
    assert json.loads(o)["periodicity"]["source"] == "file" and json.loads(o)["periodic"] is False
    rc, o, e = run_cli(capsys, "info", f)
    assert "periodic   measured patch" in o and "stated by the npz key periodic" in o


def write_small_sample(tmp_path: Path, relief_keys: str) -> Path:
    """sample.toml over the 64 x 64 tile (an npz that states no periodicity) and a 4-row recording."""
    save_npz(tmp_path / "relief.npz", tile())
    (tmp_path / "recording.csv").write_text(
        "# relief-recording/1\nwavelength_nm,theta_i_deg,phi_i_deg,side,theta_s_deg,phi_s_deg,bsdf_sr,sigma_sr\n"
        + "".join(f"550,0,0,{sd},{t},0,1.0,0.05\n" for sd in "RT" for t in (5, 25)))
    f = tmp_path / "sample.toml"
    f.write_text('format = "relief-sample/1"\n[plate]\nthickness_mm = 2.0\nrefractive_index = 1.5\n'
                 f'rough_face = "front"\n[relief]\nfile = "relief.npz"\n{relief_keys}\n'
                 '[instrument]\ndetector_half_angle_deg = 1.0\n[recording]\nfile = "recording.csv"\n')
    return f


@pytest.mark.slow
def test_sample_key_periodic_reaches_simulate(tmp_path, capsys):
    s = write_small_sample(tmp_path, "periodic = false\nfill_holes = true")
    rc, o, e = run_cli(capsys, "simulate", s, "--method", "microfacet+dw", "-o", tmp_path / "out")
    assert rc == 0, e
    assert "measured patch" in o and "stated by [relief] periodic of sample.toml" in o
    rc, o, e = run_cli(capsys, "simulate", s, "--method", "microfacet+dw", "--periodic", "-o", tmp_path / "out2")
    assert rc == 0 and "periodic tile (traced as one period): stated by --periodic" in o     # the flag wins
    rc, o, e = run_cli(capsys, "info", s)
    assert rc == 0 and "not periodic (stated); holes filled before use" in o
    s = write_small_sample(tmp_path, 'periodic = "yes"')
    rc, o, e = run_cli(capsys, "info", s)
    assert rc == 2 and "relief.periodic: expected true or false" in e


def test_instrument_maps_are_not_periodic(capsys):
    for name in INSTRUMENT_FILES:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rc, o, e = run_cli(capsys, "info", TOPO / name, "--json")
        assert rc == 0, (name, e)
        p = json.loads(o)["periodicity"]
        assert p["periodic"] is False and p["source"] == "test", (name, p)


@pytest.mark.shared_data
def test_validation_x3p_tiles_are_found_periodic(capsys):
    files = sorted(CASES.glob("*/relief.x3p"))
    assert len(files) >= 17
    for f in files:
        rc, o, e = run_cli(capsys, "info", f, "--json")
        p = json.loads(o)["periodicity"]
        assert rc == 0 and p["periodic"] is True and p["source"] == "test", (f, p)


# ---------------------------------------------------------------------------------------------- warnings


def test_runtime_warnings_are_one_line_once(capsys):
    from relief_bsdf.cli import input_warnings_as_lines
    with input_warnings_as_lines():
        for _ in range(3):
            warnings.warn("ray table (outside): the tile holds only 2 x 2 sub-tiles", RuntimeWarning)
    err = capsys.readouterr().err
    assert err == "relief: warning: ray table (outside): the tile holds only 2 x 2 sub-tiles\n"


def test_ray_warnings_in_the_cli_have_no_source_lines(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    rc, o, e = run_cli(capsys, "reconstruct", src, "--method", "ray", "--n", "1.5", "--theta-i-deg", "0",
                       "--from", "both", "--samples", "2000", "--theta-step-deg", "10", "--phi-step-deg", "30",
                       "-o", tmp_path / "t.h5")
    assert rc == 0, e
    lines = [ln for ln in e.splitlines() if ln.strip() and "\r" not in ln and not ln.startswith("reconstruct")]
    warn = [ln for ln in lines if "warning" in ln.lower()]
    assert warn, e                                   # a 64 x 64 tile is small: the ray method says so
    for ln in warn:
        assert ln.startswith("relief: warning: ") and ".py" not in ln and "warnings.warn" not in ln
    assert len(warn) == len(set(warn))


# ---------------------------------------------------------------------------------------------- inputs


@pytest.mark.parametrize("suffix", [".zip", ".x3p"])
def test_x3p_zipped_with_its_folder_is_read(tmp_path, capsys, suffix):
    flat = write_relief(tmp_path / "scan.x3p", tile())
    nested = tmp_path / f"folder{suffix}"
    with zipfile.ZipFile(flat) as z, zipfile.ZipFile(nested, "w") as out:
        for info in z.infolist():
            out.writestr("scan/" + info.filename, z.read(info))
    rc, o, e = run_cli(capsys, "info", nested, "--json")
    assert rc == 0, e
    d = json.loads(o)
    rc, o2, e = run_cli(capsys, "info", flat, "--json")
    ref = json.loads(o2)
    assert d["shape"] == ref["shape"] and d["rms_height_m"] == ref["rms_height_m"]
    assert d["source"] == str(nested)


def test_bsdf_table_given_as_relief_is_one_line(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    assert run_cli(capsys, "reconstruct", src, "--method", "microfacet", "--n", "1.5", "--theta-i-deg", "0",
                   "-o", tmp_path / "t.h5")[0] == 0
    rc, o, e = run_cli(capsys, "reconstruct", tmp_path / "t.h5", "--n", "1.5", "-o", tmp_path / "u.h5")
    assert rc == 2 and e.strip().endswith("is a BSDF table, not a height map (give the height map the table was "
                                          "made from)")
    assert len(e.strip().splitlines()) == 1


@pytest.mark.slow
def test_info_reads_radiance_xml(tmp_path, capsys):
    """`relief info` reads a WINDOW/Radiance XML BSDF, as plot and export do."""
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    assert run_cli(capsys, "reconstruct", src, "--method", "microfacet", "--n", "1.5", "--from", "both",
                   "--theta-i-deg", "0,30,60", "--theta-step-deg", "5", "--phi-step-deg", "15",
                   "-o", tmp_path / "b.h5")[0] == 0
    assert run_cli(capsys, "export", tmp_path / "b.h5", "--format", "radiance-xml", "-o", tmp_path / "b.xml")[0] == 0
    rc, o, e = run_cli(capsys, "info", tmp_path / "b.xml")
    assert rc == 0 and "BSDF table" in o, e


def test_failing_output_creates_no_folder(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    out = tmp_path / "no" / "dir" / "t.h5"
    rc, o, e = run_cli(capsys, "reconstruct", src, "--n", "1.5", "-o", out)
    assert rc == 2 and "does not exist" in e and len(e.strip().splitlines()) == 1
    assert not (tmp_path / "no").exists()


# ---------------------------------------------------------------------------------------------- help, version


def test_help_shows_the_defaults_and_version(capsys):
    from relief_bsdf import __version__, defaults
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: auto)" in text
    assert f"(default: {defaults.as_text(defaults.THETA_I_DEG)})" in text
    assert f"(default: {defaults.SAMPLES})" in text and "(default: 550)" in text
    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"relief {__version__}"


def test_reconstruct_method_defaults_to_auto(tmp_path, capsys):
    src = save_npz(tmp_path / "t.npz", tile(), state_periodic=True)
    rc, o, e = run_cli(capsys, "reconstruct", src, "--n", "1.5", "--theta-i-deg", "0", "--samples", "2000",
                       "--theta-step-deg", "10", "--phi-step-deg", "30", "-o", tmp_path / "t.h5")
    assert rc == 0, e
    assert "method auto (" in o


def test_sample_relief_keys_round_trip(tmp_path):
    from relief_bsdf.io.recording import read_sample, write_sample
    s = read_sample(write_small_sample(tmp_path, "periodic = true\nfill_holes = true"))
    assert (s.relief_options.periodic, s.relief_options.fill_holes) == (True, True)
    again = read_sample(write_sample(tmp_path / "again.toml", s))
    assert (again.relief_options.periodic, again.relief_options.fill_holes) == (True, True)
    plain = read_sample(write_sample(tmp_path / "plain.toml", read_sample(write_small_sample(tmp_path, ""))))
    assert (plain.relief_options.periodic, plain.relief_options.fill_holes) == (None, False)


def test_large_fills_iterate_to_the_direct_answer(monkeypatch):
    """Above DIRECT_FILL_MAX unknowns the fill runs conjugate gradients: the same harmonic heights."""
    import relief_bsdf.surface.relief as relief_module
    holey = tile().heights_m.copy()
    holey[10:30, 5:40] = np.nan
    holey[50:, 50:] = np.nan
    r = Relief(holey, 0.25e-6, 0.25e-6)
    direct = r.fill_holes().heights_m
    monkeypatch.setattr(relief_module, "DIRECT_FILL_MAX", 0)
    np.testing.assert_allclose(r.fill_holes().heights_m, direct, rtol=0, atol=1e-8 * np.nanstd(holey))


def test_reconstruct_warns_that_one_azimuth_misdescribes_an_anisotropic_relief(tmp_path, capsys):
    """A corrugated relief (slopes along x only) reconstructed at one incidence azimuth: one warning line
    naming --phi-i-deg; the table records the rms slopes along x and y (what an export judges by); with
    several azimuths, no warning."""
    x = np.arange(64) * 0.25e-6
    h = 0.2e-6 * np.sin(2 * np.pi * x / 4e-6)[None, :] * np.ones((64, 1)) + 0.01e-6 * tile().heights_m / 0.1e-6
    m = save_npz(tmp_path / "ridges.npz", Relief(h, 0.25e-6, 0.25e-6, periodic=True), state_periodic=True)
    rc, o, e = run_cli(capsys, "reconstruct", m, "--method", "microfacet", "--theta-i-deg", "0", "--n", "1.5",
                       "-o", tmp_path / "t.h5")
    assert rc == 0, e
    assert e.count("one incidence azimuth does not describe it") == 1 and "--phi-i-deg" in e
    from relief_bsdf.io.hdf5 import load_tables
    rel = load_tables(tmp_path / "t.h5")[0].relief
    assert rel["rms_slope_x"] > 5 * rel["rms_slope_y"] > 0
    rc, o, e = run_cli(capsys, "reconstruct", m, "--method", "microfacet", "--theta-i-deg", "0", "--n", "1.5",
                       "--phi-i-deg", "0,90", "-o", tmp_path / "t2.h5")
    assert rc == 0 and "does not describe it" not in e
