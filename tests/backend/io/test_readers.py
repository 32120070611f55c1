"""Height-map readers and writers (readers.py, oiio.py)."""
from __future__ import annotations

import json
import re
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.io import oiio
from relief_bsdf.errors import InputError
from relief_bsdf.io.heightmaps import read_relief, write_relief
from relief_bsdf.surface.relief import Relief

TOPO = Path(__file__).resolve().parents[2] / "data" / "topography"   # tests/data/topography (SOURCE.md)
UNIT = {"nm": 1e-9, "um": 1e-6, "µm": 1e-6, "mm": 1e-3}


def reference_table() -> list[tuple[str, float | None, str]]:
    """(file, rms height in m or None for the line profile, note) from the data README."""
    rows = []
    for line in (TOPO / "README.md").read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 4 and cells[0].startswith("ST_"):
            m = re.fullmatch(r"([\d.]+)\s*(nm|um|µm|mm)", cells[3])
            assert m, f"cannot parse rms {cells[3]!r}"
            rows.append((cells[0], float(m.group(1)) * UNIT[m.group(2)], cells[4] if len(cells) > 4 else ""))
    return rows


REFERENCE = reference_table()


def test_reference_table_covers_every_file():
    listed = {r[0] for r in REFERENCE}
    present = {p.name for p in TOPO.iterdir() if p.name.startswith("ST_")}
    assert listed == present and len(listed) >= 10


@pytest.mark.parametrize("name, rms_m, note", [r for r in REFERENCE if "profile" not in r[2]],
                         ids=[r[0] for r in REFERENCE if "profile" not in r[2]])
def test_instrument_file_rms_within_1_percent(name, rms_m, note):
    r = read_relief(TOPO / name)
    assert r.heights_m.ndim == 2 and r.valid_fraction > 0.5
    rms = float(np.nanstd(r.level(1).heights_m))
    assert rms == pytest.approx(rms_m, rel=0.01), f"{name}: rms {rms:.4g} m vs README {rms_m:.4g} m"
    assert r.metadata["reader"] and r.metadata["file_unit"]
    # lateral pitch: between 0.1 nm and 100 um for these instruments
    assert 1e-10 < r.dx_m < 1e-4 and 1e-10 < r.dy_m < 1e-4


def test_line_profile_refused():
    with pytest.raises(InputError) as e:
        read_relief(TOPO / "ST_dektak-1.csv")
    assert "line profile" in str(e.value) and "ST_dektak-1.csv" in str(e.value)


def test_x3p_anisotropic_pitch_and_orientation():
    r = read_relief(TOPO / "ST_x3p-2.x3p")
    assert r.shape == (650, 650)
    assert r.dx_m == pytest.approx(0.128e-6, rel=0.01) and r.dy_m == pytest.approx(0.315e-6, rel=0.01)


def test_mi_lateral_size_in_metres():
    # the .mi header says xLength = 2e-5 (metres) for 256 px: 78.1 nm pitch, heights in um
    r = read_relief(TOPO / "ST_mi-1.mi")
    assert r.dx_m == pytest.approx(20e-6 / 256, rel=1e-6)


def test_frt_holes_stay_invalid():
    r = read_relief(TOPO / "ST_frt-1.frt")
    assert r.valid_fraction == pytest.approx(0.69, abs=0.01)
    # filling the 31 % of holes would invent relief: rms grows several-fold
    assert np.isnan(r.heights_m).sum() > 0.3 * r.heights_m.size


def test_channels_of_multichannel_afm():
    r0 = read_relief(TOPO / "ST_spot_1-1000nm.ibw")
    r1 = read_relief(TOPO / "ST_spot_1-1000nm.ibw", channel="HeightRetrace")
    assert r0.metadata["channel"] == "HeightTrace" and r1.metadata["channel"] == "HeightRetrace"
    # trace and retrace of the same surface agree closely but are not the same array
    assert not np.array_equal(r0.heights_m, r1.heights_m)
    with pytest.raises(InputError, match="no channel"):
        read_relief(TOPO / "ST_di-1.di", channel="Nonexistent")
    with pytest.raises(InputError, match="not heights"):
        read_relief(TOPO / "ST_di-1.di", channel="Phase")
    with pytest.raises(InputError, match="out of range"):
        read_relief(TOPO / "ST_di-1.di", channel=9)


def test_pitch_argument_overrides():
    r = read_relief(TOPO / "ST_nid-1.nid", pitch_m=(1e-6, 2e-6))
    assert (r.dx_m, r.dy_m) == (1e-6, 2e-6) and r.metadata["pitch_source"] == "argument"
    assert r.metadata["pitch_in_file_m"][0] == pytest.approx(78.125e-9)


# ---------------------------------------------------------------- corrupt inputs

@pytest.mark.parametrize("name", ["ST_x3p-2.x3p", "ST_di-1.di", "ST_opd-1.opd", "ST_plu-1.plu", "ST_nid-1.nid"])
def test_truncated_instrument_files(tmp_path, name):
    data = (TOPO / name).read_bytes()
    p = tmp_path / name
    p.write_bytes(data[: len(data) // 8])
    with pytest.raises(InputError) as e:
        read_relief(p)
    assert name in str(e.value)


@pytest.mark.parametrize("suffix", [".x3p", ".di", ".npz", ".exr", ".tif", ".sdf", ".gwy", ".sur", ".xyz"])
def test_empty_and_garbage_files(tmp_path, suffix):
    p = tmp_path / f"empty{suffix}"
    p.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_relief(p)
    g = tmp_path / f"garbage{suffix}"
    g.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8)))
    with pytest.raises(InputError) as e:
        read_relief(g)
    assert g.name in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_relief(tmp_path / "nothing.x3p")


# ---------------------------------------------------------------- npz, images, x3p writer

def _relief(nan=True, periodic=False):
    rng = np.random.default_rng(3)
    h = rng.normal(0, 50e-9, (24, 31))
    if nan:
        h[3:6, 4:9] = np.nan
    return Relief(h, 0.5e-6, 0.7e-6, periodic=periodic, source="test")


@pytest.mark.parametrize("suffix", [".npz", ".x3p", ".exr", ".tif"])
def test_write_read_round_trip(tmp_path, suffix):
    r = _relief(periodic=(suffix == ".npz"))
    p = write_relief(tmp_path / f"r{suffix}", r)
    b = read_relief(p)
    assert b.shape == r.shape and (b.dx_m, b.dy_m) == (r.dx_m, r.dy_m)
    assert np.array_equal(np.isnan(b.heights_m), np.isnan(r.heights_m))
    rtol = 0 if suffix in (".npz", ".x3p") else 1e-7     # images hold float32
    np.testing.assert_allclose(b.heights_m, r.heights_m, rtol=rtol, atol=0)
    assert b.periodic == r.periodic


@pytest.mark.parametrize("suffix", [".npz", ".x3p", ".exr", ".tif"])
def test_periodic_flag_survives(tmp_path, suffix):
    r = _relief(nan=False, periodic=True)
    assert read_relief(write_relief(tmp_path / f"p{suffix}", r)).periodic


def test_x3p_is_valid_iso_container(tmp_path):
    import hashlib
    import xml.etree.ElementTree as ET

    import SurfaceTopography as ST
    r = _relief(nan=False)
    p = write_relief(tmp_path / "r.x3p", r)
    with zipfile.ZipFile(p) as z:
        names = set(z.namelist())
        assert {"main.xml", "bindata/data.bin", "md5checksum.hex"} <= names
        xml = z.read("main.xml")
        data = z.read("bindata/data.bin")
        assert z.read("md5checksum.hex").decode().split()[0] == hashlib.md5(xml).hexdigest()
    root = ET.fromstring(xml)
    assert root.find("Record3/DataLink/MD5ChecksumPointData").text == hashlib.md5(data).hexdigest().upper()
    assert root.find("Record1/Axes/CZ/DataType").text == "D"
    assert int(root.find("Record3/MatrixDimension/SizeX").text) == r.shape[1]
    # the maintained reader gets exactly our numbers back (it indexes [x, y])
    t = ST.open_topography(str(p)).topography()
    assert np.array_equal(t.heights().T, r.heights_m)
    assert t.physical_sizes == pytest.approx(r.size_m, rel=1e-15)



def test_x3p_float32_data_type(tmp_path):
    import xml.etree.ElementTree as ET

    import SurfaceTopography as ST
    r = _relief(nan=True)
    p = write_relief(tmp_path / "f.x3p", r, x3p_data_type="F")
    with zipfile.ZipFile(p) as z:
        assert ET.fromstring(z.read("main.xml")).find("Record1/Axes/CZ/DataType").text == "F"
        assert len(z.read("bindata/data.bin")) == 4 * r.heights_m.size
    back = read_relief(p)
    ok = np.isfinite(r.heights_m)
    np.testing.assert_array_equal(np.isfinite(back.heights_m), ok)
    np.testing.assert_allclose(back.heights_m[ok], r.heights_m[ok], rtol=1e-7, atol=0)
    assert np.array_equal(ST.open_topography(str(p)).topography().heights().T[ok],
                          r.heights_m.astype(np.float32)[ok])
    with pytest.raises(InputError, match="x3p_data_type"):
        write_relief(tmp_path / "g.x3p", r, x3p_data_type="I")

def test_npz_errors(tmp_path):
    p = tmp_path / "a.npz"
    np.savez(p, heights=np.full((8, 8), np.nan), dx=1e-6, dy=1e-6)
    with pytest.raises(InputError, match="no valid points"):
        read_relief(p)
    np.savez(p, z=np.zeros((8, 8)), dx=1e-6, dy=1e-6)
    with pytest.raises(InputError, match="heights"):
        read_relief(p)
    np.savez(p, heights=np.zeros((8, 8)), dx=1e-6)
    with pytest.raises(InputError, match="dy"):
        read_relief(p)
    np.savez(p, heights=np.zeros((8, 8)), dx=5.0, dy=5.0)         # pixels, not metres
    with pytest.raises(InputError, match="implausible"):
        read_relief(p)
    np.savez(p, heights=np.zeros(100), dx=1e-6, dy=1e-6)
    with pytest.raises(InputError, match="line profile"):
        read_relief(p)


def test_x3p_all_nan(tmp_path):
    r = Relief(np.full((6, 7), np.nan), 1e-6, 1e-6)
    p = write_relief(tmp_path / "nan.x3p", r)
    with pytest.raises(InputError, match="no valid points"):
        read_relief(p)


def test_image_pitch_sources_and_units(tmp_path):
    r = _relief()
    p = write_relief(tmp_path / "r.tif", r)
    side = tmp_path / "r.tif.json"
    assert json.loads(side.read_text())["dx_m"] == r.dx_m
    # heights written in micrometres and declared so in the sidecar come back in metres
    um = Relief(r.heights_m * 1e6, r.dx_m, r.dy_m)
    p2 = write_relief(tmp_path / "um.tif", um)
    s2 = json.loads((tmp_path / "um.tif.json").read_text())
    s2["z_unit"] = "um"
    (tmp_path / "um.tif.json").write_text(json.dumps(s2))
    b2 = read_relief(p2)
    np.testing.assert_allclose(b2.heights_m, r.heights_m, rtol=1e-6)
    s2["z_unit"] = "furlong"
    (tmp_path / "um.tif.json").write_text(json.dumps(s2))
    with pytest.raises(InputError, match="z_unit"):
        read_relief(p2)
    s2["z_unit"] = "um"
    s2["dx"] = 1.0                                         # typo for dx_m
    (tmp_path / "um.tif.json").write_text(json.dumps(s2))
    with pytest.raises(InputError, match="unknown key"):
        read_relief(p2)
    # without sidecar a TIFF has no pitch
    side.unlink()
    with pytest.raises(InputError, match="pitch"):
        read_relief(p)
    b = read_relief(p, pitch_m=(2e-6, 3e-6))
    assert (b.dx_m, b.dy_m) == (2e-6, 3e-6)
    # EXR keeps the pitch in its own header too
    pe = write_relief(tmp_path / "r.exr", r)
    (tmp_path / "r.exr.json").unlink()
    be = read_relief(pe)
    assert (be.dx_m, be.dy_m) == (r.dx_m, r.dy_m) and "attributes" in be.metadata["pitch_source"]


def test_integer_image_refused(tmp_path):
    OIIO = oiio.load()
    p = tmp_path / "counts.tif"
    out = OIIO.ImageOutput.create(str(p))
    assert out.open(str(p), OIIO.ImageSpec(8, 6, 1, "uint16"))
    assert out.write_image(np.arange(48, dtype=np.uint16).reshape(6, 8, 1))
    out.close()
    with pytest.raises(InputError, match="floating point"):
        read_relief(p, pitch_m=(1e-6, 1e-6))


def test_oiio_found_without_importing_bpy():
    # a fresh interpreter: other tests in this process may have imported bpy on purpose
    code = ("import sys; from relief_bsdf.io import oiio; assert oiio.available(); "
            "assert 'bpy' not in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def _sdf_ascii(path, h, dx, dy, zscale, bad=None):
    lines = ["aISO-1.0", "ManufacID = test", "CreateDate = 010120250000", "ModDate = 010120250000",
             f"NumPoints = {h.shape[1]}", f"NumProfiles = {h.shape[0]}", f"Xscale = {dx!r}", f"Yscale = {dy!r}",
             f"Zscale = {zscale!r}", "Zresolution = -1", "Compression = 0", "DataType = 3", "CheckType = 0", "*"]
    for row in h:
        lines.append(" ".join("BAD" if not np.isfinite(v) else repr(float(v)) for v in row))
    lines += ["*", ""]
    path.write_text("\n".join(lines))


def test_sdf_ascii_and_binary(tmp_path):
    rng = np.random.default_rng(7)
    counts = rng.integers(-500, 500, (9, 13)).astype(float)
    a = tmp_path / "a.sdf"
    with_bad = counts.copy()
    with_bad[2, 3] = np.nan
    _sdf_ascii(a, with_bad, 1e-6, 2e-6, 1e-9)
    r = read_relief(a)
    assert r.shape == (9, 13) and (r.dx_m, r.dy_m) == (1e-6, 2e-6)
    assert np.isnan(r.heights_m[2, 3]) and r.valid.sum() == 9 * 13 - 1
    np.testing.assert_allclose(r.heights_m[r.valid], (counts * 1e-9)[r.valid])
    b = tmp_path / "b.sdf"
    head = struct.pack("<8s10s12s12sHHddddBBB", b"bISO-1.0", b"test", b"0" * 12, b"0" * 12, 13, 9,
                       1e-6, 2e-6, 1e-9, -1.0, 0, 2, 0)
    b.write_bytes(head + counts.astype("<i2").tobytes())
    rb = read_relief(b)
    np.testing.assert_allclose(rb.heights_m, counts * 1e-9)
    b.write_bytes(head + counts.astype("<i2").tobytes()[:50])
    with pytest.raises(InputError, match="truncated"):
        read_relief(b)
