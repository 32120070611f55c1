"""The project's own readers of instrument formats, used where SurfaceTopography is missing.

SurfaceTopography (the reader of most instrument formats in `io.heightmaps`) publishes no
wheels for some platforms Blender runs on (e.g. Windows), so an extension zip for such a
platform bundles none.  These readers cover the most common open formats from their public
descriptions, with numpy and the standard library only:

- X3P, ISO 25178-72 (XML 3D surface profile, openGPS): a zip archive with `main.xml`
  (Record1: axes CX, CY, CZ with AxisType I/A, DataType I/L/F/D = int16/int32/float32/
  float64, Increment, Offset; Record3: MatrixDimension SizeX, SizeY, SizeZ and either a
  PointDataLink to a little-endian binary file, x fastest then y, or an inline DataList) and
  an optional ValidPointsLink bit mask.  All lengths are metres by the standard.  Heights
  z = raw * CZ.Increment + CZ.Offset for integer data (Increment 1 and Offset 0 when absent);
  NaN marks invalid points in float data.
- GWY (Gwyddion native): magic `GWYP`, then one serialised GwyContainer.  A serialised object
  is its type name (NUL-terminated), a uint32 byte size and components, each a name
  (NUL-terminated), a one-letter type (b bool, c char, i int32, q int64, d float64,
  s string, o object; upper case = array, preceded by a uint32 count) and the value, all
  little-endian.  The first channel `/0/data` is a GwyDataField: xres, yres, xreal, yreal
  (physical sizes), si_unit_xy / si_unit_z (GwySIUnit, `unitstr`) and `data` (yres rows of
  xres float64).  A mask `/0/mask` (1 = masked) marks invalid points.

- PLU (Sensofar confocal / interferometric profilers, the layout SurfaceTopography reads):
  a 500-byte little-endian header (date 128 bytes, time uint32, comment 256 bytes; calibration:
  uint32 rows, columns, N_tall, float32 dy_multip, um per pixel in x and y, offsets x, y, um per
  pixel tall, offset z; measurement: uint32 type (3 = topography), algorithm, method, objective,
  area type; 40 bytes of scan settings; 8 bytes of flags, the second the number of layers;
  uint32 factor), then per layer uint32 rows and columns and rows x columns float32 heights
  in micrometres (1000001 = not measured), then float32 min and max.  Pitch = um per pixel.

The proprietary instrument formats (Zygo MetroPro .dat, Wyko .opd, Bruker NanoScope .di/.spm, ...)
are read by `io.native_instruments`, registered in `READERS` below.

`wanted(suffix)` says whether `read_relief` should use these readers: the format is one of
them and SurfaceTopography cannot be imported.  `read(path, pitch, channel)` returns
(heights_m[y, x], dx_m, dy_m, periodic, metadata); `read_relief` finishes it as for any file.
Errors are `InputError`s naming the file.
"""
from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np

from relief_bsdf.errors import InputError

_X3P_TYPES = {"I": "<i2", "L": "<i4", "F": "<f4", "D": "<f8"}
_SI_PREFIX = {"": 1.0, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "n": 1e-9, "p": 1e-12, "k": 1e3}


def surface_topography_available() -> bool:
    """SurfaceTopography imports (present *and* loadable: a copy without its compiled
    dependencies, muFFT / muGrid, counts as missing)."""
    try:
        import SurfaceTopography  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError, or a broken native extension
        return False
    return True


def wanted(suffix: str) -> bool:
    """True when a file with this suffix is to be read here (see module doc)."""
    return suffix.lower() in READERS and not surface_topography_available()


def read(path: Path, pitch: tuple | None, channel=None) -> tuple[np.ndarray, float, float, bool, dict]:
    """Read `path` with the reader of its suffix; `channel` (index or name) picks a channel of a
    multi-channel file (default: its first height channel)."""
    h, dx, dy, meta = READERS[path.suffix.lower()](path, channel)
    meta["reader"] = f"relief_bsdf.io.native_readers ({path.suffix.lower()[1:]})"
    if pitch is not None:
        meta["pitch_in_file_m"] = [dx, dy]
        meta["pitch_source"] = "argument"
        dx, dy = pitch
    else:
        meta["pitch_source"] = "file"
        if not (1e-11 <= dx <= 1.0 and 1e-11 <= dy <= 1.0):
            raise InputError(path, f"implausible pitch {dx:g} x {dy:g} m in the file; pass pitch_m")
    return h, float(dx), float(dy), False, meta


# ------------------------------------------------------------------------------------- X3P

def _strip_ns(root: ET.Element) -> None:
    for el in root.iter():
        if isinstance(el.tag, str) and "}" in el.tag:
            el.tag = el.tag.split("}", 1)[1]


def _axis(rec1: ET.Element, name: str, path: Path) -> dict:
    ax = rec1.find(f"Axes/{name}")
    if ax is None:
        raise InputError(path, f"X3P main.xml has no axis {name}")
    get = lambda k, d=None: (ax.findtext(k) or d)  # noqa: E731
    return {"type": get("AxisType", "I"), "data": get("DataType", "D"), "inc": float(get("Increment", "1")),
            "off": float(get("Offset", "0"))}


def read_x3p(path: Path) -> tuple[np.ndarray, float, float, dict]:
    """ISO 25178-72 X3P (module doc) -> heights (ny, nx) in metres, dx, dy, metadata."""
    try:
        with zipfile.ZipFile(path) as z:
            root = ET.fromstring(z.read("main.xml"))
            _strip_ns(root)
            rec1, rec3 = root.find("Record1"), root.find("Record3")
            if rec1 is None or rec3 is None:
                raise InputError(path, "X3P main.xml lacks Record1 or Record3")
            feature = (rec1.findtext("FeatureType") or "SUR").strip()
            if feature != "SUR":
                raise InputError(path, f"X3P feature type {feature!r}: a profile or point cloud, not an area "
                                       "height map (need SUR)")
            cx, cy, cz = (_axis(rec1, n, path) for n in ("CX", "CY", "CZ"))
            if cx["type"] != "I" or cy["type"] != "I":
                raise InputError(path, "X3P with absolute (non-gridded) x/y axes is not supported")
            dims = rec3.find("MatrixDimension")
            if dims is None:
                raise InputError(path, "X3P Record3 has no MatrixDimension")
            nx, ny, nz = (int(dims.findtext(k) or 1) for k in ("SizeX", "SizeY", "SizeZ"))
            if nz != 1:
                raise InputError(path, f"X3P with {nz} layers (SizeZ); need one height layer")
            dtype = _X3P_TYPES.get(cz["data"])
            if dtype is None:
                raise InputError(path, f"X3P CZ data type {cz['data']!r} unknown (I, L, F or D)")
            link = rec3.findtext("DataLink/PointDataLink")
            if link:
                raw = np.frombuffer(z.read(link.strip()), dtype=dtype)
            else:
                items = [d.text for d in rec3.findall("DataList/Datum")]
                raw = np.array([float(t) if t and t.strip() else np.nan for t in items])
            valid_link = rec3.findtext("ValidPointsLink")
            valid = None
            if valid_link:
                bits = np.unpackbits(np.frombuffer(z.read(valid_link.strip()), np.uint8), bitorder="little")
                valid = bits[:nx * ny].astype(bool)
    except (zipfile.BadZipFile, KeyError, ET.ParseError, OSError, ValueError) as e:
        raise InputError(path, f"cannot read as X3P: {type(e).__name__}: {e}") from None
    if raw.size != nx * ny:
        raise InputError(path, f"X3P data has {raw.size} values, MatrixDimension says {nx} x {ny}")
    h = raw.astype(float)
    if cz["data"] in ("I", "L"):
        h = h * cz["inc"] + cz["off"]
    if valid is not None and valid.size == h.size:
        h[~valid] = np.nan
    meta = {"file_unit": "m", "lateral_unit": "m", "channel": "Z", "channels": ["Z"],
            "instrument": (root.findtext("Record2/Instrument/Manufacturer") or "").strip()}
    return h.reshape(ny, nx), cx["inc"], cy["inc"], meta


# ------------------------------------------------------------------------------------- GWY

class _Gwy:
    """Cursor over Gwyddion's serialised objects (module doc)."""

    _SCALAR = {"b": ("<?", 1), "c": ("<c", 1), "i": ("<i", 4), "q": ("<q", 8), "d": ("<d", 8)}
    _ARRAY = {"C": "u1", "I": "<i4", "Q": "<i8", "D": "<f8"}

    def __init__(self, buf: bytes, path: Path):
        self.buf, self.pos, self.path = buf, 0, path

    def cstr(self) -> str:
        end = self.buf.index(b"\0", self.pos)
        s = self.buf[self.pos:end].decode("utf-8", "replace")
        self.pos = end + 1
        return s

    def u32(self) -> int:
        v = struct.unpack_from("<I", self.buf, self.pos)[0]
        self.pos += 4
        return v

    def obj(self) -> tuple[str, dict]:
        name = self.cstr()
        end = self.pos + 4 + self.u32()
        comps = {}
        while self.pos < end:
            key = self.cstr()
            kind = chr(self.buf[self.pos])
            self.pos += 1
            comps[key] = self.value(kind)
        return name, comps

    def value(self, kind: str):
        if kind in self._SCALAR:
            fmt, n = self._SCALAR[kind]
            v = struct.unpack_from(fmt, self.buf, self.pos)[0]
            self.pos += n
            return v
        if kind == "s":
            return self.cstr()
        if kind == "o":
            return self.obj()
        if kind in self._ARRAY:
            n = self.u32()
            dt = np.dtype(self._ARRAY[kind])
            a = np.frombuffer(self.buf, dt, n, self.pos)
            self.pos += n * dt.itemsize
            return a
        if kind in ("S", "O"):
            n = self.u32()
            return [self.cstr() if kind == "S" else self.obj() for _ in range(n)]
        raise InputError(self.path, f"GWY component of unknown type {kind!r} at byte {self.pos}")


def _gwy_unit(field: dict, key: str, path: Path) -> float:
    unit = field.get(key)
    text = unit[1].get("unitstr", "") if isinstance(unit, tuple) else ""
    text = (text or "m").strip()
    if not text.endswith("m") or text[:-1] not in _SI_PREFIX:
        raise InputError(path, f"GWY {key} is {text!r}, not a length")
    return _SI_PREFIX[text[:-1]]


def read_gwy(path: Path) -> tuple[np.ndarray, float, float, dict]:
    """Gwyddion .gwy (module doc): the first data channel -> heights (ny, nx) m, dx, dy, metadata."""
    buf = path.read_bytes()
    if buf[:4] != b"GWYP":
        raise InputError(path, "not a Gwyddion GWY file (no GWYP magic; the older GWYO format is not read)")
    try:
        _, top = _Gwy(buf[4:], path).obj()
    except (IndexError, ValueError, struct.error) as e:
        raise InputError(path, f"corrupt or truncated GWY file ({type(e).__name__}: {e})") from None
    chans = sorted(int(k.split("/")[1]) for k in top if k.count("/") == 2 and k.endswith("/data")
                   and k.split("/")[1].isdigit())
    if not chans:
        raise InputError(path, "the GWY file holds no image channel (/N/data)")
    c = chans[0]
    name, f = top[f"/{c}/data"]
    if name != "GwyDataField":
        raise InputError(path, f"/{c}/data is a {name}, not a GwyDataField")
    nx, ny = int(f["xres"]), int(f["yres"])
    data = np.asarray(f["data"], float)
    if data.size != nx * ny:
        raise InputError(path, f"GWY channel {c}: {data.size} values for {nx} x {ny}")
    h = data.reshape(ny, nx) * _gwy_unit(f, "si_unit_z", path)
    lat = _gwy_unit(f, "si_unit_xy", path)
    mask = top.get(f"/{c}/mask")
    if isinstance(mask, tuple) and "data" in mask[1] and np.asarray(mask[1]["data"]).size == nx * ny:
        h[np.asarray(mask[1]["data"]).reshape(ny, nx) > 0.5] = np.nan
    title = top.get(f"/{c}/data/title", f"channel {c}")
    meta = {"file_unit": "m", "lateral_unit": "m", "channel": str(title), "channel_index": c,
            "channels": [str(top.get(f"/{k}/data/title", k)) for k in chans]}
    return h, float(f["xreal"]) * lat / nx, float(f["yreal"]) * lat / ny, meta


# ------------------------------------------------------------------------------------- PLU

_PLU_HEADER = 500                  # bytes before the first layer (module doc)
_PLU_UNDEFINED = 1000001.0


def read_plu(path: Path) -> tuple[np.ndarray, float, float, dict]:
    """Sensofar .plu (module doc): the first topography layer -> heights (ny, nx) m, dx, dy, metadata."""
    buf = path.read_bytes()
    if len(buf) < _PLU_HEADER + 8:
        raise InputError(path, f"too short for a Sensofar PLU file ({len(buf)} bytes)")
    um_x, um_y = struct.unpack_from("<ff", buf, 388 + 16)
    kind, _, _, _, area_type = struct.unpack_from("<5I", buf, 428)
    if kind != 3:
        raise InputError(path, f"PLU measurement type {kind}: not a topography (type 3); profiles are not read")
    n_layers = buf[448 + 40 + 1]
    if n_layers < 1:
        raise InputError(path, "the PLU file holds no data layer")
    ny, nx = struct.unpack_from("<II", buf, _PLU_HEADER)
    start = _PLU_HEADER + 8
    if ny < 2 or nx < 2 or start + 4 * nx * ny > len(buf):
        raise InputError(path, f"PLU layer of {nx} x {ny} points does not fit the file (truncated?)")
    h = np.frombuffer(buf, "<f4", nx * ny, start).astype(float).reshape(ny, nx)
    h[h == _PLU_UNDEFINED] = np.nan
    if not (um_x > 0 and um_y > 0):
        raise InputError(path, f"PLU pixel size {um_x} x {um_y} um is not positive")
    meta = {"file_unit": "um", "lateral_unit": "um", "channel": "layer0", "channels": [f"layer{k}" for k in
                                                                                    range(n_layers)],
            "area_type": int(area_type)}
    return h * 1e-6, um_x * 1e-6, um_y * 1e-6, meta


def _one_channel(reader):
    """A reader of single-channel files, taking (path, channel) like the others."""
    def read_one(path: Path, channel=None):
        if channel not in (None, 0, "0"):
            raise InputError(path, f"the file holds one height channel; no channel {channel!r}")
        return reader(path)
    return read_one


from relief_bsdf.io import native_instruments as _inst  # noqa: E402 - after this module's own readers

#: suffix -> reader(path, channel) -> (heights_m[y, x], dx_m, dy_m, metadata)
READERS = {".x3p": _one_channel(read_x3p), ".gwy": _one_channel(read_gwy), ".plu": _one_channel(read_plu),
           ".dat": _inst.read_metropro, ".opd": _inst.read_opd,
           ".di": _inst.read_nanoscope, ".spm": _inst.read_nanoscope, ".nid": _inst.read_nid, ".ezd": _inst.read_nid,
           ".mi": _inst.read_mi, ".frt": _inst.read_frt, ".ibw": _inst.read_ibw,
           ".csv": _inst.read_dektak}
