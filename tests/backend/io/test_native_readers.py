"""The project's own X3P / GWY / PLU readers, run with SurfaceTopography made unavailable (issue 16, item 1).

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

SHARED = Path(__file__).resolve().parents[3].parent / "shared"
X3P = SHARED / "data" / "topography" / "ST_x3p-2.x3p"


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
    path = SHARED / "data" / "topography" / name
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
