"""The probe corpus of bad inputs as a test suite: every bad input exits 2 with one line naming the file.

Every file is built here, on the fly, in a temporary folder.  Each case runs the command line
in-process (`relief_bsdf.cli.main`) and asserts the exit code, that stderr is one line (bar
notes), and that it names the offending file and says what is wrong.  Warnings (accepted but
implausible input) exit 0 with one ``relief: warning:`` line naming the file.
"""
from __future__ import annotations

import io
import json
import os
import re
import shutil
import stat
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.cli import main
from relief_bsdf.io.heightmaps import write_relief
from relief_bsdf.surface.relief import Relief

REPO = Path(__file__).resolve().parents[3]
DEMO = REPO / "scenes" / "demo"


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def error_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("relief: note:")]


def assert_refused(capsys, name: str, *argv, why: str) -> str:
    """Exit 2, one line on stderr naming `name` (a file) and matching `why` (a regex)."""
    rc, out, err = run(capsys, *argv)
    lines = error_lines(err)
    assert rc == 2, f"exit {rc}, stderr: {err}"
    assert len(lines) == 1, f"expected one line, got: {err}"
    assert name in lines[0], f"{name!r} not named in: {lines[0]}"
    assert re.search(why, lines[0], re.I), f"{why!r} not in: {lines[0]}"
    return lines[0]


def small_relief(n: int = 16, rms_m: float = 50e-9, pitch_m: float = 1e-6, seed: int = 0) -> Relief:
    h = np.random.default_rng(seed).standard_normal((n, n)) * rms_m
    return Relief(h, pitch_m, pitch_m, periodic=True, source="test")


# ---------------------------------------------------------------------------------------------
# height maps

def _x3p_with(tmp_path: Path, edit_xml=None, edit_data=None, name: str = "r.x3p") -> Path:
    """An X3P written by `write_relief`, its main.xml / point data then edited (checksums left as they were)."""
    src = write_relief(tmp_path / ("src-" + name), small_relief())
    with zipfile.ZipFile(src) as z:
        parts = {n: z.read(n) for n in z.namelist()}
    if edit_xml:
        parts["main.xml"] = edit_xml(parts["main.xml"].decode()).encode()
    if edit_data:
        parts["bindata/data.bin"] = edit_data(parts["bindata/data.bin"])
    out = tmp_path / name
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in parts.items():
            z.writestr(n, b)
    return out


def _first_increment_zero(xml: str) -> str:
    return re.sub(r"<Increment>[^<]*</Increment>", "<Increment>0.0</Increment>", xml, count=1)


def test_x3p_zero_increment(tmp_path, capsys):
    f = _x3p_with(tmp_path, edit_xml=_first_increment_zero)
    assert_refused(capsys, str(f), "info", f, why="increment")


def test_x3p_declaring_a_huge_grid_is_refused_before_allocating(tmp_path, capsys):
    f = _x3p_with(tmp_path, edit_xml=lambda x: x.replace("<SizeX>16</SizeX>", "<SizeX>200000</SizeX>")
                  .replace("<SizeY>16</SizeY>", "<SizeY>200000</SizeY>"))
    assert_refused(capsys, str(f), "info", f, why="limit.*--max-pixels")


def test_x3p_checksum_mismatch_warns_naming_the_file(tmp_path, capsys):
    def flip(data: bytes) -> bytes:
        a = np.frombuffer(data, "<f8").copy()
        a[3] += 1e-9
        return a.tobytes()
    f = _x3p_with(tmp_path, edit_data=flip)
    rc, out, err = run(capsys, "info", f)
    assert rc == 0
    warn = [ln for ln in err.splitlines() if "warning" in ln]
    assert len(warn) == 1 and str(f) in warn[0] and "MD5" in warn[0]
    # the untouched file reads without a word
    good = _x3p_with(tmp_path, name="good.x3p")
    rc, out, err = run(capsys, "info", good)
    assert rc == 0 and err == ""


def _npz_declaring(path: Path, shape: tuple, data_bytes: int = 1024) -> Path:
    """An .npz whose heights.npy header declares `shape` but holds only `data_bytes` of data."""
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("heights.npy", hdr.getvalue() + bytes(data_bytes))      # the header starts with the magic
        for k in ("dx", "dy"):
            b = io.BytesIO()
            np.save(b, np.float64(1e-6))
            z.writestr(f"{k}.npy", b.getvalue())
    return path


def test_npz_declaring_8192_squared_is_refused_fast(tmp_path, capsys):
    f = _npz_declaring(tmp_path / "big.npz", (8192, 8192))
    assert f.stat().st_size < 10_000
    assert_refused(capsys, str(f), "info", f, why=r"8192 x 8192.*limit")
    # the limit is documented and overridable: with a higher one the (truncated) data itself is the problem
    rc, out, err = run(capsys, "--max-pixels", 2 ** 27, "info", f)
    assert rc == 2 and "limit" not in err and str(f) in err


def test_max_pixels_flag_lowers_the_limit(tmp_path, capsys):
    f = write_relief(tmp_path / "r.npz", small_relief(32))
    assert run(capsys, "info", f)[0] == 0
    assert_refused(capsys, str(f), "--max-pixels", "1000", "info", f, why="32 x 32.*limit of 1000")


def test_map_of_2x2_with_3_nan(tmp_path, capsys):
    f = tmp_path / "nan.npz"
    np.savez(f, heights=np.array([[1e-7, np.nan], [np.nan, np.nan]]), dx=1e-6, dy=1e-6)
    assert_refused(capsys, str(f), "info", f, why="adjacent valid points")


def test_ascii_sdf_with_a_bad_number(tmp_path, capsys):
    f = tmp_path / "bad.sdf"
    vals = " ".join(["1.0"] * 15 + ["1.0e-x"])
    f.write_text("aISO-1.0\nManufacID = t\nNumPoints = 4\nNumProfiles = 4\nXscale = 1e-6\nYscale = 1e-6\n"
                 f"Zscale = 1e-9\nDataType = 7\n*\n{vals}\n*\n")
    assert_refused(capsys, str(f), "info", f, why="'1.0e-x'.*not a number")


def test_binary_sdf_declaring_a_huge_grid(tmp_path, capsys):
    f = tmp_path / "big.sdf"
    hdr = struct.pack("<8s10s12s12sHHddddBBB", b"bISO-1.0", b"t", b"", b"", 65535, 65535, 1e-6, 1e-6, 1e-9, 1e-9,
                      0, 7, 0)
    f.write_bytes(hdr + bytes(64))
    assert_refused(capsys, str(f), "info", f, why="65535 x 65535.*limit")


def test_sidecar_that_is_a_folder(tmp_path, capsys):
    f = write_relief(tmp_path / "r.tif", small_relief())
    side = tmp_path / "r.tif.json"
    side.unlink()
    side.mkdir()
    assert_refused(capsys, str(side), "info", f, why="not a regular file")


def test_truncated_float_tiff_is_refused(tmp_path, capsys):
    full = write_relief(tmp_path / "full.tif", small_relief(256))
    f = tmp_path / "cut.tif"
    f.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    shutil.copy(tmp_path / "full.tif.json", tmp_path / "cut.tif.json")
    assert run(capsys, "info", full)[0] == 0
    assert_refused(capsys, str(f), "info", f, why="truncated or corrupt")


def test_implausible_heights_and_pitch_warn_saying_why(tmp_path, capsys):
    f = write_relief(tmp_path / "tall.npz", small_relief(rms_m=100.0))
    rc, out, err = run(capsys, "info", f)
    warn = [ln for ln in err.splitlines() if "warning" in ln]
    assert rc == 0 and len(warn) == 1 and str(f) in warn[0] and "rms height" in warn[0] and "unit" in warn[0]
    g = write_relief(tmp_path / "wide.npz", small_relief(pitch_m=0.01))
    rc, out, err = run(capsys, "info", g)
    warn = [ln for ln in err.splitlines() if "warning" in ln]
    assert rc == 0 and len(warn) == 1 and str(g) in warn[0] and "pitch" in warn[0]


def test_info_on_a_fifo_does_not_block(tmp_path, capsys):
    f = tmp_path / "pipe.csv"
    os.mkfifo(f)
    assert_refused(capsys, str(f), "info", f, why="not a regular file")


# ---------------------------------------------------------------------------------------------
# tables (HDF5)

def test_hdf5_file_that_is_not_a_table(tmp_path, capsys):
    import h5py
    f = tmp_path / "other.h5"
    with h5py.File(f, "w") as h:
        h["data"] = np.arange(4.0)
    assert_refused(capsys, str(f), "export", f, "--format", "recording-csv", "-o", tmp_path / "o.csv",
                   why="not a relief BSDF table")
    assert_refused(capsys, str(f), "info", f, why="no height-map channel")
    g = tmp_path / "half.h5"
    with h5py.File(g, "w") as h:
        h.attrs["format"] = "relief-bsdf-table/1"
    assert_refused(capsys, str(g), "export", g, "--format", "recording-csv", "-o", tmp_path / "o.csv",
                   why="'tables'")
    assert_refused(capsys, str(g), "info", g, why="'tables'")
    k = tmp_path / "grp.h5"
    with h5py.File(k, "w") as h:
        h.attrs["format"] = "relief-bsdf-table/1"
        h.attrs["tables"] = "outside"
        h.create_group("outside")["values_per_sr"] = np.zeros(3)
    assert_refused(capsys, str(k), "plot", k, "-o", tmp_path / "p.png", why="table 'outside'")


# ---------------------------------------------------------------------------------------------
# sample.toml

def _sample(tmp_path: Path, plate: str = "thickness_mm = 2.0\nrefractive_index = 1.49",
            half: str = "1.0", relief: str = "relief.x3p", bom: bool = False) -> Path:
    for n in ("relief.x3p", "recording.csv"):
        if not (tmp_path / n).exists():
            shutil.copy(DEMO / n, tmp_path / n)
    text = (f'format = "relief-sample/1"\n[plate]\n{plate}\nrough_face = "front"\n[relief]\nfile = "{relief}"\n'
            f'[instrument]\ndetector_half_angle_deg = {half}\n[recording]\nfile = "recording.csv"\n')
    f = tmp_path / "sample.toml"
    f.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return f


@pytest.mark.parametrize("plate, half, why", [
    ("thickness_mm = 2.0\nrefractive_index = 1.0", "1.0", r"refractive index 1 .*no boundary"),
    ("thickness_mm = 2.0\nrefractive_index = 1e10", "1.0", r"refractive index 1e\+10 .*plausible"),
    ("thickness_mm = 2.0\nrefractive_index = 1.49", "1e-9", r"detector_half_angle_deg: 1e-09"),
    ("thickness_mm = 1e-7\nrefractive_index = 1.49", "1.0", r"thickness_mm: 1e-07"),
    ("thickness_mm = 2.0\ncauchy = [1.0, 0.0]", "1.0", r"plate.cauchy.*refractive index 1 "),
])
def test_sample_values_out_of_range(tmp_path, capsys, plate, half, why):
    s = _sample(tmp_path, plate=plate, half=half)
    assert_refused(capsys, str(s), "simulate", s, "-o", tmp_path / "out", why=why)
    assert not (tmp_path / "out").exists()


def test_sample_with_bom_is_read(tmp_path, capsys):
    s = _sample(tmp_path, bom=True)
    rc, out, err = run(capsys, "info", s, "--json")
    assert rc == 0 and json.loads(out)["kind"] == "sample"


def test_sample_relief_path_that_is_a_folder(tmp_path, capsys):
    (tmp_path / "folder.x3p").mkdir()
    s = _sample(tmp_path, relief="folder.x3p")
    line = assert_refused(capsys, str(s), "simulate", s, "-o", tmp_path / "out", why="is a folder")
    assert "folder.x3p" in line and "not found" not in line


# ---------------------------------------------------------------------------------------------
# flags and output paths (checked before any computation)

def test_dask_with_an_http_address(tmp_path, capsys):
    f = write_relief(tmp_path / "r.npz", small_relief())
    assert_refused(capsys, "--dask", "reconstruct", f, "--method", "microfacet", "--n", "1.5", "-o",
                   tmp_path / "t.h5", "--dask", "http://localhost:8787", why="http:// is not a Dask scheduler")


def test_output_folder_that_is_a_file(tmp_path, capsys):
    s = _sample(tmp_path)
    out = tmp_path / "out"
    out.write_text("a file")
    assert_refused(capsys, str(out), "fit", s, "-o", out, why="is a file; expected an output folder")


def test_output_file_that_is_a_folder(tmp_path, capsys):
    out = tmp_path / "o.npz"
    out.mkdir()
    assert_refused(capsys, str(out), "synth", "--size", "16", "--pitch-um", "1", "--rms-height-um", "0.1",
                   "--corr-length-um", "3", "-o", out, why="is a folder")


def test_output_under_a_file_and_unwritable(tmp_path, capsys):
    (tmp_path / "plain").write_text("x")
    out = tmp_path / "plain" / "t.npz"
    assert_refused(capsys, str(out), "synth", "--size", "16", "--pitch-um", "1", "--rms-height-um", "0.1",
                   "--corr-length-um", "3", "-o", out, why="is a file, not a folder")
    assert_refused(capsys, "/proc/relief-test/t.npz", "synth", "--size", "16", "--pitch-um", "1",
                   "--rms-height-um", "0.1", "--corr-length-um", "3", "-o", "/proc/relief-test/t.npz",
                   why="cannot write")


def test_fit_output_checked_before_the_work(tmp_path, capsys, monkeypatch):
    """The output check comes first: the (long) fit is never started."""
    import relief_bsdf.jobs.fit as fit_job

    def boom(*a, **k):
        raise AssertionError("the fit ran before its output path was checked")
    monkeypatch.setattr(fit_job, "run_fit", boom)
    s = _sample(tmp_path)
    (tmp_path / "f").write_text("x")
    assert_refused(capsys, str(tmp_path / "f"), "fit", s, "-o", tmp_path / "f", why="expected an output folder")


# ---------------------------------------------------------------------------------------------
# outputs: umask, stale temporaries

def test_outputs_honour_the_umask_and_stale_parts_are_removed(tmp_path, capsys):
    from relief_bsdf.io.atomic import _host_tag
    dead = 2 ** 22 + 12345                        # above the default pid_max: no such process
    stale = tmp_path / f".r.{_host_tag()}-{dead}.0badc0de.part.npz"
    stale.write_bytes(b"half a file")
    old = os.umask(0o027)
    try:
        rc, out, err = run(capsys, "synth", "--size", "16", "--pitch-um", "1", "--rms-height-um", "0.1",
                           "--corr-length-um", "3", "-o", tmp_path / "r.npz")
    finally:
        os.umask(old)
    assert rc == 0, err
    assert stat.S_IMODE((tmp_path / "r.npz").stat().st_mode) == 0o640
    assert not stale.exists()
    assert not [p for p in tmp_path.iterdir() if ".part" in p.name]


def test_sample_that_is_a_fifo_or_folder_and_a_checkpoint_dir_that_is_a_file(tmp_path, capsys):
    fifo = tmp_path / "s.toml"
    os.mkfifo(fifo)
    assert_refused(capsys, str(fifo), "simulate", fifo, "-o", tmp_path / "out", why="not a regular file")
    (tmp_path / "d.toml").mkdir()
    assert_refused(capsys, str(tmp_path / "d.toml"), "fit", tmp_path / "d.toml", "-o", tmp_path / "out",
                   why="is a folder")
    (tmp_path / "ok").mkdir()
    s = _sample(tmp_path / "ok")
    (tmp_path / "ck").write_text("x")
    assert_refused(capsys, str(tmp_path / "ck"), "simulate", s, "-o", tmp_path / "out", "--checkpoint-dir",
                   tmp_path / "ck", why="is a file")


# ---------------------------------------------------------------------------------------------
# flat maps: accepted, described without RuntimeWarnings and in strict JSON; refused by name where no
# slope can be formed

def test_flat_map_info_has_no_runtime_warnings_and_strict_json(tmp_path, capsys):
    import warnings
    f = tmp_path / "flat.npz"
    np.savez(f, heights=np.zeros((32, 32)), dx=1e-6, dy=1e-6)
    for extra in ([], ["--json"]):
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)      # a RuntimeWarning becomes an internal error
            rc, out, err = run(capsys, "info", f, *extra)
        assert rc == 0 and err == "", err
        assert "nan" not in out.lower()
    d = json.loads(out, parse_constant=lambda c: pytest.fail(f"literal {c} is not JSON"))
    assert d["rms_height_m"] == 0.0 and d["correlation_length_m"] is None
    assert d["noise_floor"]["fraction_of_rms"] is None and d["flags"]["kurtosis"] is None


def test_flat_map_for_a_slope_method_is_refused_naming_the_file(tmp_path, capsys):
    f = tmp_path / "flat.npz"
    np.savez(f, heights=np.zeros((32, 32)), dx=1e-6, dy=1e-6)
    assert_refused(capsys, str(f), "reconstruct", f, "--method", "microfacet", "--n", "1.5", "--wavelengths-nm",
                   "550", "--theta-i-deg", "0", "--workers", "1", "-o", tmp_path / "t.h5", why="no measurable slopes")


def test_x3p_bounds_hold_for_the_native_reader_too(tmp_path, capsys, monkeypatch):
    """Without SurfaceTopography (io.native_readers reads the X3P) the same checks run first."""
    from relief_bsdf.io import native_readers
    monkeypatch.setattr(native_readers, "surface_topography_available", lambda: False)
    f = _x3p_with(tmp_path, edit_xml=lambda x: x.replace("<SizeX>16</SizeX>", "<SizeX>200000</SizeX>")
                  .replace("<SizeY>16</SizeY>", "<SizeY>200000</SizeY>"))
    assert_refused(capsys, str(f), "info", f, why="limit.*--max-pixels")
    g = _x3p_with(tmp_path, edit_data=lambda d: d[:8] + bytes([d[8] ^ 1]) + d[9:], name="flip.x3p")
    rc, out, err = run(capsys, "info", g)
    assert rc == 0 and "native_readers" in out, err
    warn = [ln for ln in err.splitlines() if "warning" in ln]
    assert len(warn) == 1 and str(g) in warn[0] and "MD5" in warn[0]


def test_hdf5_table_declaring_a_huge_dataset_is_refused_before_reading(tmp_path, capsys):
    """A tiny file whose unwritten dataset declares 10^11 values (h5py would allocate 800 GB on read)."""
    import h5py
    f = tmp_path / "huge.h5"
    with h5py.File(f, "w") as h:
        h.attrs["format"] = "relief-bsdf-table/1"
        h.attrs["tables"] = "outside"
        g = h.create_group("outside")
        for k, n in (("wavelength_nm", 10), ("theta_i_deg", 100), ("phi_i_deg", 100), ("theta_s_edges_deg", 1001),
                     ("phi_s_edges_deg", 1001)):
            g[k] = np.linspace(0.0, 90.0, n)
        for k in ("specular_R", "specular_T", "lost"):
            g[k] = np.zeros((10, 100, 100))
        g.create_dataset("values_per_sr", shape=(10, 100, 100, 1000, 1000), dtype="f8", chunks=(1, 1, 1, 1000, 1000),
                         compression="gzip")
    assert f.stat().st_size < 5_000_000             # a few MB that declare 800 GB
    assert_refused(capsys, str(f), "info", f, why=r"'values_per_sr'.*limit.*--max-pixels")


def test_isbsdf_declaring_a_huge_grid_is_refused_before_allocating(tmp_path, capsys):
    """Four axis lists of 3000 angles (90 KB) declare 8.1e13 values: refused, not a MemoryError."""
    n = 3000
    angles = " ".join(f"{k * 0.01:.2f}" for k in range(n))
    f = tmp_path / "big.bsdf"
    f.write_text("Source Measured\nSymmetry Asymmetrical\nSpectralContent Monochrome\nScatterType BRDF\n"
                 + "".join(f"{key} {n}\n{angles}\n" for key in ("SampleRotation", "AngleOfIncidence",
                                                                 "ScatterAzimuth", "ScatterRadial"))
                 + "Monochrome\nDataBegin\nTIS 0.5\nDataEnd\n")
    assert_refused(capsys, str(f), "info", f, why=r"3000 x 3000 x 3000 x 3000.*limit.*--max-pixels")
