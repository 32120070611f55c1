"""The project's own X3P / GWY / PLU readers, run with SurfaceTopography made unavailable.

Oracles are independent: SurfaceTopography's readers of the same real X3P and PLU files, and files written
by `gwyfile` (an independent pure-Python implementation of Gwyddion's format).
"""
from __future__ import annotations

import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.io.heightmaps import read_relief

TOPO = Path(__file__).resolve().parents[2] / "data" / "topography"   # tests/data/topography (SOURCE.md)
X3P = TOPO / "ST_x3p-2.x3p"


@pytest.fixture
def no_surface_topography(monkeypatch):
    """SurfaceTopography cannot be imported (as on a platform without its wheel)."""
    for name in [m for m in sys.modules if m == "SurfaceTopography" or m.startswith("SurfaceTopography.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "SurfaceTopography", None)       # `import SurfaceTopography` -> ImportError
    with pytest.raises(ImportError):
        import SurfaceTopography  # noqa: F401
    yield


@pytest.mark.parametrize("name, shape", [("ST_x3p-2.x3p", (650, 650)), ("ST_plu-1.plu", (576, 768))])
def test_own_reader_without_surface_topography_matches_its_reader(name, shape):
    path = TOPO / name
    with_st = read_relief(path)
    assert with_st.metadata["reader"].startswith("SurfaceTopography")
    mp = pytest.MonkeyPatch()
    try:
        mp.setitem(sys.modules, "SurfaceTopography", None)
        own = read_relief(path)
    finally:
        mp.undo()
    assert own.metadata["reader"].startswith("relief_bsdf.io.native_readers")
    assert own.shape == with_st.shape == shape
    assert own.dx_m == with_st.dx_m and own.dy_m == with_st.dy_m
    np.testing.assert_array_equal(own.heights_m, with_st.heights_m)


def test_integer_x3p_with_scale_and_mask(no_surface_topography, tmp_path):
    # int32 heights with a z increment and offset, and a valid-points bit mask (x fastest)
    nx, ny, inc, off = 5, 3, 2e-9, 1e-7
    raw = np.arange(nx * ny, dtype="<i4") - 7
    valid = np.ones(nx * ny, bool)
    valid[[2, 9]] = False
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<p:ISO5436_2 xmlns:p="http://www.opengps.eu/2008/ISO5436_2"><Record1><Revision>ISO5436 - 2000</Revision>
<FeatureType>SUR</FeatureType><Axes><CX><AxisType>I</AxisType><DataType>D</DataType><Increment>1e-6</Increment>
<Offset>0</Offset></CX><CY><AxisType>I</AxisType><DataType>D</DataType><Increment>2e-6</Increment><Offset>0</Offset>
</CY><CZ><AxisType>A</AxisType><DataType>L</DataType><Increment>{inc}</Increment><Offset>{off}</Offset></CZ></Axes>
</Record1><Record3><MatrixDimension><SizeX>{nx}</SizeX><SizeY>{ny}</SizeY><SizeZ>1</SizeZ></MatrixDimension>
<DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink><ValidPointsLink>bindata/valid.bin</ValidPointsLink>
</Record3></p:ISO5436_2>"""
    path = tmp_path / "int.x3p"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("main.xml", xml)
        z.writestr("bindata/data.bin", raw.tobytes())
        z.writestr("bindata/valid.bin", np.packbits(valid, bitorder="little").tobytes())
    r = read_relief(path)
    want = (raw * inc + off).astype(float).reshape(ny, nx)
    want[~valid.reshape(ny, nx)] = np.nan
    np.testing.assert_allclose(r.heights_m, want, rtol=1e-12)
    assert (r.dx_m, r.dy_m) == (1e-6, 2e-6)


def test_gwy_written_by_gwyfile(no_surface_topography, tmp_path):
    from gwyfile.objects import GwyContainer, GwyDataField, GwySIUnit
    rng = np.random.default_rng(0)
    z_um = rng.standard_normal((20, 30)) * 0.05
    mask = np.zeros((20, 30))
    mask[3, 4] = 1.0
    c = GwyContainer()
    c["/0/data"] = GwyDataField(z_um, xreal=30.0, yreal=40.0, si_unit_xy=GwySIUnit(unitstr="um"),
                                si_unit_z=GwySIUnit(unitstr="um"))
    c["/0/data/title"] = "Height"
    c["/0/mask"] = GwyDataField(mask, xreal=30.0, yreal=40.0)
    c.tofile(str(tmp_path / "scan.gwy"))
    r = read_relief(tmp_path / "scan.gwy")
    want = z_um * 1e-6
    want[3, 4] = np.nan
    np.testing.assert_allclose(r.heights_m, want, rtol=1e-12)
    assert r.dx_m == pytest.approx(1e-6) and r.dy_m == pytest.approx(2e-6)
    assert r.metadata["channel"] == "Height"


def test_bad_files_name_the_file(no_surface_topography, tmp_path):
    bad = tmp_path / "broken.x3p"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="broken.x3p.*X3P"):
        read_relief(bad)
    gwy = tmp_path / "old.gwy"
    gwy.write_bytes(b"GWYO" + b"\0" * 40)
    with pytest.raises(InputError, match="old.gwy.*GWYP"):
        read_relief(gwy)
    plu = tmp_path / "short.plu"
    plu.write_bytes(b"\0" * 100)
    with pytest.raises(InputError, match="short.plu.*too short"):
        read_relief(plu)
    cut = tmp_path / "cut.gwy"
    cut.write_bytes(b"GWYPGwyContainer\0" + b"\xff\x00\x00\x00" + b"/0/data\0o")
    with pytest.raises(InputError, match="cut.gwy"):
        read_relief(cut)


def test_surface_topography_still_preferred_when_installed():
    from relief_bsdf.io import native_readers
    assert native_readers.surface_topography_available()
    assert not native_readers.wanted(".x3p")


# ------------------------------------------------------------- instrument formats (io/native_instruments.py)
# Oracles: SurfaceTopography's reader of the same real file (heights, pitch, invalid points), and the rms
# height after mean-plane levelling that tests/data/topography/README.md gives from SurfaceTopography and
# Gwyddion (3 significant figures).  Agreement measured: MetroPro, OPD, NanoScope, Nanosurf, PicoView, FRT and Igor
# bit-identical (NanoScope once 2.2e-16 relative); the tests hold 1e-12 relative.

INSTRUMENT_FILES = [  # name, shape (ny, nx), README rms height (m)
    ("ST_metropro-1.dat", (480, 640), 13.3e-9),
    ("ST_opd-1.opd", (480, 640), 6.72e-9),
    ("ST_di-1.di", (512, 512), 9.84e-9),
    ("ST_nid-1.nid", (256, 256), 7.11e-9),
    ("ST_mi-1.mi", (256, 256), 3.43e-9),
    ("ST_frt-1.frt", (500, 500), 4.40e-6),
    ("ST_spot_1-1000nm.ibw", (256, 256), 9.55e-9),
]


def _read_blocked(path, **kw):
    mp = pytest.MonkeyPatch()
    try:
        mp.setitem(sys.modules, "SurfaceTopography", None)
        return read_relief(path, **kw)
    finally:
        mp.undo()


def _levelled_rms_m(h):
    ny, nx = h.shape
    y, x = np.mgrid[:ny, :nx]
    v = np.isfinite(h)
    a = np.c_[np.ones(v.sum()), x[v], y[v]]
    return float(np.std(h[v] - a @ np.linalg.lstsq(a, h[v], rcond=None)[0]))


@pytest.mark.parametrize("name, shape, rms_m", INSTRUMENT_FILES)
def test_instrument_reader_matches_surface_topography(name, shape, rms_m):
    path = TOPO / name
    with_st = read_relief(path)
    assert with_st.metadata["reader"].startswith("SurfaceTopography")
    own = _read_blocked(path)
    assert own.metadata["reader"] == f"relief_bsdf.io.native_readers ({path.suffix[1:]})"
    assert own.shape == with_st.shape == shape
    assert own.dx_m == pytest.approx(with_st.dx_m, rel=1e-12)
    assert own.dy_m == pytest.approx(with_st.dy_m, rel=1e-12)
    np.testing.assert_array_equal(np.isnan(own.heights_m), np.isnan(with_st.heights_m))
    np.testing.assert_allclose(own.heights_m, with_st.heights_m, rtol=1e-12, atol=0)
    assert _levelled_rms_m(own.heights_m) == pytest.approx(rms_m, rel=0.01)


# where the format's declared content ends: an Asylum .ibw carries 131578 bytes after the sections its
# header declares (not part of the wave), so cutting there truncates nothing the reader uses
DECLARED_END = {"ST_spot_1-1000nm.ibw": 2112969}
TRUNCATIONS = [(name, keep) for name in [f[0] for f in INSTRUMENT_FILES] for keep in (0.25, 0.9, -1)] + \
              [("ST_dektak-1.csv", 0.25), ("ST_dektak-1.csv", 0.9)]   # a text file cut in its last line is
#                                                                      indistinguishable from a complete one


@pytest.mark.parametrize("name, keep", TRUNCATIONS)
def test_truncated_instrument_file_is_an_input_error(no_surface_topography, tmp_path, name, keep):
    data = (TOPO / name).read_bytes()
    n = DECLARED_END.get(name, len(data)) - 1 if keep == -1 else int(len(data) * keep)
    cut = tmp_path / ("cut" + Path(name).suffix)
    cut.write_bytes(data[:n])
    with pytest.raises(InputError, match=f"cut{Path(name).suffix}: truncated file"):
        read_relief(cut)


@pytest.mark.parametrize("name", [f[0] for f in INSTRUMENT_FILES] + ["ST_dektak-1.csv"])
def test_header_only_fragment_is_an_input_error(no_surface_topography, tmp_path, name):
    frag = tmp_path / ("frag" + Path(name).suffix)
    frag.write_bytes((TOPO / name).read_bytes()[:200])
    with pytest.raises(InputError, match=f"frag{Path(name).suffix}"):
        read_relief(frag)


def test_nanoscope_channels(no_surface_topography):
    path = TOPO / "ST_di-1.di"
    retrace = read_relief(path, channel=1)
    assert retrace.metadata["channel"] == "Height" and retrace.metadata["channel_index"] == 1
    assert retrace.shape == (512, 512) and np.isfinite(retrace.heights_m).all()
    with pytest.raises(InputError, match="ST_di-1.di.*'Phase'.*not hold heights"):
        read_relief(path, channel="Phase")
    with pytest.raises(InputError, match="ST_di-1.di.*out of range"):
        read_relief(path, channel=7)


def test_metropro_declared_size_checked_before_allocation(no_surface_topography, tmp_path):
    from relief_bsdf.io.heightmaps import pixel_limit
    data = bytearray((TOPO / "ST_metropro-1.dat").read_bytes())
    path = tmp_path / "big.dat"
    path.write_bytes(bytes(data))
    with pixel_limit(1000), pytest.raises(InputError, match="big.dat.*limit"):
        read_relief(path)


def test_frt_points_not_measured_are_nan_not_zero(no_surface_topography):
    # README: 31 % of the FRT map is not measured; filling it in inflates the rms to ~19 um
    r = read_relief(TOPO / "ST_frt-1.frt")
    assert 0.30 < np.isnan(r.heights_m).mean() < 0.32


def test_nanosurf_and_picoview_channels(no_surface_topography):
    nid = TOPO / "ST_nid-1.nid"
    back = read_relief(nid, channel="Scan backward (Z-Axis)")
    assert back.metadata["channel_index"] == 2 and back.shape == (256, 256)
    fwd = read_relief(nid)
    # forward and backward traces of one scan: the same surface, to within the AFM's noise and hysteresis
    assert np.corrcoef(fwd.heights_m.ravel(), back.heights_m.ravel())[0, 1] > 0.9
    with pytest.raises(InputError, match="ST_mi-1.mi.*'Deflection'.*not hold heights"):
        read_relief(TOPO / "ST_mi-1.mi", channel="Deflection")


def test_igor_wave_channels_and_checksum(no_surface_topography, tmp_path):
    path = TOPO / "ST_spot_1-1000nm.ibw"
    r = read_relief(path, channel="HeightRetrace")
    assert r.metadata["channel_index"] == 1 and r.metadata["channels"][0] == "HeightTrace"
    data = bytearray(path.read_bytes())
    data[100] ^= 0x01                              # one bit of the wave header flipped
    bad = tmp_path / "flipped.ibw"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="flipped.ibw.*checksum"):
        read_relief(bad)


def test_dektak_profile_matches_surface_topography_and_is_refused_as_a_map(no_surface_topography):
    from relief_bsdf.io.native_instruments import read_dektak
    path = TOPO / "ST_dektak-1.csv"
    h, dx, dy, meta = read_dektak(path)
    assert h.shape == (1, 9600) and dx == dy and meta["file_unit"] == "Micrometer"
    with pytest.raises(InputError, match="ST_dektak-1.csv.*1-D line profile \\(9600 points\\)"):
        read_relief(path)
    # README: rms 94 nm (after removing the mean line)
    x = np.arange(h.shape[1])
    assert np.std(h[0] - np.polyval(np.polyfit(x, h[0], 1), x)) == pytest.approx(94e-9, rel=0.01)


def test_dektak_profile_agrees_with_surface_topography():
    import SurfaceTopography as ST
    from relief_bsdf.io.native_instruments import read_dektak
    path = TOPO / "ST_dektak-1.csv"
    h, dx, _, _ = read_dektak(path)
    st = ST.open_topography(str(path)).topography()
    assert st.unit == "µm"
    np.testing.assert_allclose(h[0], np.asarray(st.heights()) * 1e-6, rtol=1e-12, atol=0)
    assert dx * (h.shape[1] - 1) == pytest.approx(st.physical_sizes[0] * 1e-6, rel=1e-12)
