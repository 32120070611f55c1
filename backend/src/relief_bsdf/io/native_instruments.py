"""The project's own readers of proprietary instrument formats, used where
SurfaceTopography is missing; registered in `io.native_readers.READERS`.

Each reader follows the vendor's or a public description of the layout (named in its doc),
checked against the real files in shared/data/topography.  Every reader returns
(heights_m[y, x], dx_m, dy_m, metadata): heights and pitch in metres, NaN where the instrument
marks a point as not measured, row 0 = the first line of the map as SurfaceTopography and
Gwyddion show it.  Declared sizes go through `heightmaps.check_declared_size` before any array
is allocated, and every offset is checked against the file length, so a truncated or
malformed file is an `InputError` naming the file, never an IndexError or a huge allocation.

The height of an interferometer pixel is a phase count times a length per count (MetroPro,
Wyko); of an AFM pixel a digitiser count times volts per count times the scanner's nm per
volt (NanoScope).  These calibrations are the instrument's own; nothing here re-derives them.
"""
from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from relief_bsdf.errors import InputError

_SI_PREFIX = {"": 1.0, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "μ": 1e-6, "~": 1e-6, "n": 1e-9, "p": 1e-12,
              "k": 1e3, "c": 1e-2, "d": 1e-1}
_ANGSTROM = ("Å", "A", "Ang", "ang", "Angstrom")


def length_factor(unit: str) -> float | None:
    """Metres per `unit` ("nm", "um", "µm", "mm", "m", "Å"...); None when it is not a length."""
    u = (unit or "").strip()
    if u in _ANGSTROM:
        return 1e-10
    if u.endswith("m") and u[:-1] in _SI_PREFIX:
        return _SI_PREFIX[u[:-1]]
    return None


def _need(path: Path, buf: bytes, end: int, what: str) -> None:
    """InputError unless the file holds `end` bytes (a truncated file stops here, not in numpy)."""
    if end > len(buf):
        raise InputError(path, f"truncated file: the {what} needs {end} bytes, the file has {len(buf)}")


def _check_size(path: Path, shape: tuple, what: str) -> None:
    from relief_bsdf.io.heightmaps import check_declared_size
    check_declared_size(path, shape, what)


def _single(path: Path, channel, name: str) -> None:
    if channel not in (None, 0, "0", name):
        raise InputError(path, f"the file holds one height channel ({name!r}); no channel {channel!r}")


def _select(path: Path, names: list[str], usable: list[bool], channel) -> int:
    """Index of the requested channel (index or name), default the first height (length) channel."""
    if channel is None:
        if not any(usable):
            raise InputError(path, f"no height channel among {names}")
        return usable.index(True)
    if isinstance(channel, str) and not channel.lstrip("-").isdigit():
        hits = [i for i, n in enumerate(names) if n == channel] or \
               [i for i, n in enumerate(names) if n.lower() == channel.lower()]
        if not hits:
            raise InputError(path, f"no channel {channel!r}; channels are {names}")
        i = hits[0]
    else:
        i = int(channel)
        if not 0 <= i < len(names):
            raise InputError(path, f"channel {i} out of range 0..{len(names) - 1} ({names})")
    if not usable[i]:
        raise InputError(path, f"channel {names[i]!r} does not hold heights (no length unit); choose one of "
                               f"{[n for n, u in zip(names, usable) if u]}")
    return i


def _meta(unit: str, lateral: str, channels: list[str], index: int, **extra) -> dict:
    return {"file_unit": unit, "lateral_unit": lateral, "channel": channels[index], "channel_index": index,
            "channels": channels, **extra}


# ------------------------------------------------------------------------ Zygo MetroPro .dat

_METROPRO_MAGIC = {b"\x88\x1b\x03\x6f": 834, b"\x88\x1b\x03\x70": 834, b"\x88\x1b\x03\x71": 4096}
_METROPRO_PHASE_COUNTS = {0: 4096, 1: 32768, 2: 131072}
_METROPRO_INVALID = 2147483640


def read_metropro(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Zygo MetroPro .dat (MetroPro Reference Guide, "Data Format" chapter): a big-endian header
    (834 bytes for header formats 1-2, 4096 for format 3), then the intensity arrays
    (uint16, buckets x width x height), then the connected phase array (int32, height rows of
    width values; >= 2147483640 = invalid).  The height of a phase count is
    h = count * S * O * lambda / R  [Reference Guide eq. for the "phase to height" conversion],
    with S the interferometric scale factor (0.5 for a reflection set-up), O the obliquity
    factor, lambda the wavelength in metres and R the phase resolution (4096, 32768 or 131072
    counts per fringe for phase_res 0, 1, 2: using 4096 for a file with phase_res 1 is the 8x
    error one reader library makes); the sign flag inverts it.  Pitch = lateral_res (m).
    Header offsets used: 4 header format, 6 header size, 48 intensity origin/size/buckets,
    64 phase origin/size/bytes, 164 scale factor, 168 wavelength, 176 obliquity,
    184 lateral resolution, 218 phase resolution, 232 sign.
    """
    _single(path, channel, "Default")
    buf = path.read_bytes()
    header_size = _METROPRO_MAGIC.get(buf[:4])
    if header_size is None:
        raise InputError(path, "not a Zygo MetroPro .dat file (magic number 0x881b036f/70/71 missing)")
    _need(path, buf, header_size, "MetroPro header")
    declared = struct.unpack_from(">I", buf, 6)[0]
    if declared != header_size:
        raise InputError(path, f"MetroPro header declares {declared} bytes, its format has {header_size}")
    _, _, ac_w, ac_h, buckets = struct.unpack_from(">hhHHH", buf, 48)
    _, _, nx, ny, cn_bytes = struct.unpack_from(">hhHHI", buf, 64)
    if nx == 0 or ny == 0:
        raise InputError(path, "the MetroPro file holds no phase (height) map (connected size 0)")
    _check_size(path, (ny, nx), "MetroPro phase map")
    _check_size(path, (buckets, ac_h, ac_w), "MetroPro intensity data")
    if cn_bytes != 4 * nx * ny:
        raise InputError(path, f"MetroPro phase map declares {cn_bytes} bytes for {nx} x {ny} int32 values")
    scale, wavelength_m = struct.unpack_from(">ff", buf, 164)
    obliquity, _, lateral_m = struct.unpack_from(">fff", buf, 176)
    phase_res, = struct.unpack_from(">h", buf, 218)
    sign, = struct.unpack_from(">h", buf, 232)
    counts = _METROPRO_PHASE_COUNTS.get(phase_res)
    if counts is None:
        raise InputError(path, f"MetroPro phase resolution code {phase_res} unknown (0, 1 or 2)")
    start = header_size + 2 * buckets * ac_w * ac_h
    _need(path, buf, start + cn_bytes, f"MetroPro phase map of {nx} x {ny}")
    raw = np.frombuffer(buf, ">i4", nx * ny, start).reshape(ny, nx)
    per_count_m = float(scale) * float(obliquity) * float(wavelength_m) / counts
    h = raw * (-per_count_m if sign else per_count_m)
    h[raw >= _METROPRO_INVALID] = np.nan
    meta = _meta("m", "m", ["Default"], 0, wavelength_m=float(wavelength_m), phase_counts_per_fringe=counts)
    return h, float(lateral_m), float(lateral_m), meta


# ------------------------------------------------------------------------ Wyko / Vision .opd

_OPD_ENTRY = 24                     # directory entry: name 16 bytes, int16 type, int32 length, uint16 attr
_OPD_DATA_NAMES = ("RAW DATA", "RAW_DATA", "OPD", "Raw")
_OPD_INVALID = 1e32                 # |value| at or above: not measured (Vision writes ~1e38)


def _opd_blocks(path: Path, buf: bytes) -> list[tuple[str, int, int]]:
    """(name, data offset, length) of each block, from the directory after the 2-byte version."""
    _need(path, buf, 2 + _OPD_ENTRY, "OPD directory")
    name = buf[2:18].split(b"\0", 1)[0].decode("latin-1")
    if name != "Directory":
        raise InputError(path, f"not a Wyko/Vision OPD file (first block {name!r}, expected 'Directory')")
    dir_len = struct.unpack_from("<i", buf, 20)[0]
    if dir_len <= 0 or dir_len % _OPD_ENTRY:
        raise InputError(path, f"OPD directory length {dir_len} is not a positive multiple of {_OPD_ENTRY}")
    _need(path, buf, 2 + dir_len, "OPD directory")
    blocks, pos = [], 2 + dir_len
    for k in range(1, dir_len // _OPD_ENTRY):
        at = 2 + k * _OPD_ENTRY
        bname = buf[at:at + 16].split(b"\0", 1)[0].decode("latin-1")
        length = struct.unpack_from("<i", buf, at + 18)[0]
        if length <= 0:
            continue
        blocks.append((bname, pos, length))
        pos += length
    _need(path, buf, pos, f"OPD directory's {len(blocks)} blocks")
    return blocks


def read_opd(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Wyko / Veeco / Bruker Vision .opd (layout as documented by Gwyddion's opdfile module and the
    Vision export notes): a 2-byte version, a directory of 24-byte entries (the first, 'Directory',
    gives the directory's length), then each block's data in directory order.  Scalars used:
    'Wavelength' (float32, nm), 'Mult' (uint16), 'Pixel_size' (float32, mm), 'Aspect' (float32,
    y pitch / x pitch).  The height array block ('RAW DATA', 'OPD' or 'Raw') starts with uint16
    nx, ny, bytes per value (2: int16, 4: float32), then nx columns of ny values, each column
    stored from the top of the image down.  Heights are in waves: h = value * lambda / Mult;
    |value| >= 1e32 marks a point not measured.  Pitch dx = Pixel_size, dy = Pixel_size * Aspect.
    """
    buf = path.read_bytes()
    blocks = _opd_blocks(path, buf)
    scal = {"Wavelength": ("<f", None), "Mult": ("<H", 1), "Pixel_size": ("<f", None), "Aspect": ("<f", 1.0)}
    val = {k: d for k, (_, d) in scal.items()}
    data = [(n, at, ln) for n, at, ln in blocks if n in _OPD_DATA_NAMES]
    for n, at, ln in blocks:
        if n in scal:
            _need(path, buf, at + struct.calcsize(scal[n][0]), f"OPD block {n!r}")
            val[n] = struct.unpack_from(scal[n][0], buf, at)[0]
    if not data:
        raise InputError(path, f"the OPD file holds no height array (blocks: {[b[0] for b in blocks]})")
    names = [d[0] for d in data]
    i = _select(path, names, [True] * len(names), channel)
    _, at, ln = data[i]
    _need(path, buf, at + 6, "OPD array header")
    nx, ny, elsize = struct.unpack_from("<HHH", buf, at)
    dtype = {2: "<i2", 4: "<f4"}.get(elsize)
    if dtype is None:
        raise InputError(path, f"OPD array of {elsize}-byte values (only 2 and 4 are read)")
    _check_size(path, (nx, ny), "OPD height array")
    _need(path, buf, at + 6 + nx * ny * elsize, f"OPD height array of {nx} x {ny}")
    if val["Wavelength"] is None or val["Pixel_size"] is None or not val["Mult"]:
        raise InputError(path, "the OPD file lacks Wavelength, Mult or Pixel_size: heights or pitch unknown")
    raw = np.frombuffer(buf, dtype, nx * ny, at + 6).astype(float).reshape(nx, ny)
    h = raw[:, ::-1].T * (float(val["Wavelength"]) / val["Mult"] * 1e-6) * 1e-3
    h[~(np.abs(raw[:, ::-1].T) < _OPD_INVALID)] = np.nan
    dx = float(val["Pixel_size"]) * 1e-3
    meta = _meta("mm", "mm", names, i, wavelength_nm=float(val["Wavelength"]))
    return h, dx, dx * float(val["Aspect"]), meta


# ------------------------------------------------------------------------ Bruker NanoScope .di/.spm

_DI_ZSCALE = re.compile(r"^V\s*(?:\[(?P<q>[^\]]*)\])?\s*\((?P<lsb>[-+0-9.eE]+)\s*(?P<hu>\S*)/LSB\)\s*"
                        r"(?P<val>[-+0-9.eE]+)\s*(?P<vu>\S*)")


def _di_header(path: Path, buf: bytes) -> list[tuple[str, dict]]:
    """Sections of the text header: [(section name lower-case, {key lower-case: value})]."""
    end = buf.find(b"\\*File list end")
    if not buf.startswith(b"\\*File list") or end < 0:
        raise InputError(path, "not a Bruker NanoScope file (no '\\*File list' ... '\\*File list end' header)")
    sections: list[tuple[str, dict]] = []
    for line in buf[:end].decode("latin-1").splitlines():
        line = line.strip()
        if line.startswith("\\*"):
            sections.append((line[2:].strip().lower(), {}))
        elif line.startswith("\\") and sections:
            key, _, value = line[1:].partition(": ")
            sections[-1][1][key.strip().lower()] = value.strip()
    return sections


def _di_sensitivity(path: Path, scanner: dict, quantity: str | None) -> tuple[float, str | None]:
    """(soft scale, its unit per volt) of a '@Sens. ...' scanner entry, e.g. 'V 20.8 nm/V'; unit None
    when the entry is missing or gives no length per volt (such a channel is offered but not as heights)."""
    if quantity is None:
        return 1.0, None
    parts = scanner.get("@" + quantity.lower(), "").split()
    if len(parts) < 2 or parts[0] != "V":
        return float("nan"), None       # no calibration: the channel cannot be read as heights
    unit = parts[2].split("/")[0] if len(parts) > 2 and "/" in parts[2] else None
    return float(parts[1]), unit


def _di_image(path: Path, p: dict, scanner: dict) -> dict:
    """One '*Ciao image list' section -> its channel description (offsets, sizes, scale)."""
    try:
        name = re.match(r"^S \[(.*?)\]", p["@2:image data"]).group(1)
        nx, ny, offset = int(p["samps/line"]), int(p["number of lines"]), int(p["data offset"])
        elsize, length = int(p["bytes/pixel"]), int(p["data length"])
        sx, sy, xy_unit = p["scan size"].split(None, 2)
        z = _DI_ZSCALE.match(p["@2:z scale"])
        soft, z_unit = _di_sensitivity(path, scanner, z.group("q"))
        per_count = float(z.group("val")) / 2.0 ** (8 * elsize) * soft
    except (KeyError, AttributeError, ValueError, TypeError) as e:
        raise InputError(path, f"NanoScope image header incomplete or malformed ({type(e).__name__}: {e})") from None
    return {"name": name, "nx": nx, "ny": ny, "offset": offset, "elsize": elsize, "length": length,
            "sx": float(sx), "sy": float(sy), "xy_unit": xy_unit, "z_unit": z_unit, "per_count": per_count}


def read_nanoscope(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Bruker / Veeco / Digital Instruments NanoScope (.di, .spm, .001 ...; NanoScope Analysis
    manual, "File format"): a latin-1 text header of '\\*Section' lines and '\\Key: value'
    lines up to '\\*File list end', one '\\*Ciao image list' section per channel giving
    'Data offset', 'Bytes/pixel' (2 or 4, little-endian signed), 'Samps/line' (x),
    'Number of lines' (y), 'Scan Size: sx sy unit' and '@2:Z scale: V [Sens. Q] (a V/LSB) b V'.
    Height = count * b / 2^(8 * bytes per pixel) * s, with s the sensitivity of quantity Q in the
    scanner list ('@Sens. Zsens: V 20.8 nm/V'): the full digitiser span 2^16 (2^32) counts maps to
    b volts, and s converts volts to length.  Lines are stored from the bottom of the image up.
    Default channel: the first whose sensitivity is a length per volt (a height).
    """
    buf = path.read_bytes()
    sections = _di_header(path, buf)
    scanner: dict = {}
    for name, p in sections:
        if name in ("scanner list", "ciao scan list"):
            scanner.update(p)
    images = [_di_image(path, p, scanner) for name, p in sections if name == "ciao image list"]
    if not images:
        raise InputError(path, "the NanoScope file holds no image ('\\*Ciao image list')")
    last = max(images, key=lambda im: im["offset"] + im["length"])
    _need(path, buf, last["offset"] + last["length"], f"NanoScope image {last['name']!r} (declared data length)")
    names = [im["name"] for im in images]
    usable = [length_factor(im["z_unit"] or "") is not None for im in images]
    i = _select(path, names, usable, channel)
    im = images[i]
    nx, ny, e = im["nx"], im["ny"], im["elsize"]
    _check_size(path, (ny, nx), f"NanoScope image {im['name']!r}")
    if e not in (2, 4) or nx * ny * e > im["length"]:
        raise InputError(path, f"NanoScope image {im['name']!r}: {nx} x {ny} x {e} bytes per pixel does not fit "
                               f"its declared data length {im['length']}")
    _need(path, buf, im["offset"] + nx * ny * e, f"NanoScope image {im['name']!r} of {nx} x {ny}")
    lat = length_factor(im["xy_unit"])
    if lat is None:
        raise InputError(path, f"NanoScope scan size unit {im['xy_unit']!r} is not a length")
    raw = np.frombuffer(buf, f"<i{e}", nx * ny, im["offset"]).reshape(ny, nx)[::-1]
    h = raw * (im["per_count"] * length_factor(im["z_unit"]))
    meta = _meta(im["z_unit"], im["xy_unit"], names, i)
    return h, im["sx"] * lat / nx, im["sy"] * lat / ny, meta


# ------------------------------------------------------------------------ Nanosurf .nid / .ezd

def _ini_sections(text: str) -> dict[str, dict[str, str]]:
    """'[Section]' / 'key=value' text -> {section: {key: value}} (values stripped)."""
    out: dict[str, dict[str, str]] = {}
    cur = out.setdefault("", {})
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            cur = out.setdefault(line[1:-1], {})
        elif "=" in line:
            k, _, v = line.partition("=")
            cur[k.strip()] = v.strip()
    return out


def _nid_channels(path: Path, sec: dict) -> list[dict]:
    """The data sets in file order, each with its name, grid, dtype, z scale and offset."""
    top = sec.get("DataSet", {})
    out, offset = [], 0
    try:
        for g in range(int(top["GroupCount"])):
            for c in range(int(top[f"Gr{g}-Count"])):
                d = sec.get(top.get(f"Gr{g}-Ch{c}") or "\0")
                if d is None:           # a channel listed in the count but not saved
                    continue
                if d.get("SaveMode", "Binary") != "Binary":
                    raise InputError(path, f"Nanosurf data set saved as {d['SaveMode']!r}; only Binary is read")
                nx, ny, bits = int(d["Points"]), int(d["Lines"]), int(d["SaveBits"])
                _check_size(path, (ny, nx), "Nanosurf data set")
                signed = d.get("SaveSign", "Signed") == "Signed"
                dtype = np.dtype(("<" if d.get("SaveOrder", "Intel") == "Intel" else ">")
                                 + ("i" if signed else "u") + str(bits // 8))
                z_range, z_min = float(d["Dim2Range"]), float(d["Dim2Min"])
                out.append({"name": f"{d.get('Frame', f'group {g}')} ({d.get('Dim2Name', c)})", "nx": nx,
                            "ny": ny, "dtype": dtype, "offset": offset, "unit": d.get("Dim2Unit", ""),
                            "per_count": z_range / 2.0 ** bits, "zero": z_min + (z_range / 2 if signed else 0.0),
                            "sx": float(d["Dim0Range"]), "sy": float(d["Dim1Range"]),
                            "lat_unit": d.get("Dim0Unit", "m")})
                offset += nx * ny * dtype.itemsize
    except (KeyError, ValueError, TypeError) as e:
        raise InputError(path, f"Nanosurf header incomplete or malformed ({type(e).__name__}: {e})") from None
    return out


def read_nid(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Nanosurf easyScan / DriveAFM .nid / .ezd (Nanosurf "NID file format" notes): an INI-style
    latin-1 header ('[DataSet]' lists groups 'Gr<g>-Count' and data sets 'Gr<g>-Ch<c>' = the
    section describing each), then '#!' and the binary data sets back to back in that order.
    Each set: 'Points' (x) x 'Lines' (y) integers of 'SaveBits' bits, 'SaveSign', 'SaveOrder'
    (Intel = little-endian); the full integer span 2^bits maps to 'Dim2Range' starting at
    'Dim2Min': z = Dim2Min + (count + 2^(bits-1) [signed]) * Dim2Range / 2^bits, in 'Dim2Unit';
    'Dim0Range' x 'Dim1Range' is the scanned area.  Lines are stored from the bottom up (scan
    direction Up; a 'Down' scan is stored top down).  The channels offered are the data sets
    whose Dim2Unit is a length (as SurfaceTopography numbers them); default the first.
    """
    buf = path.read_bytes()
    if not buf.startswith(b"[DataSet]"):
        raise InputError(path, "not a Nanosurf NID file (no '[DataSet]' header)")
    mark = buf.find(b"\n#!")
    if mark < 0:
        raise InputError(path, "Nanosurf header has no '#!' data marker (truncated file?)")
    sec = _ini_sections(buf[:mark].decode("latin-1"))
    sets = _nid_channels(path, sec)
    heights = [s for s in sets if length_factor(s["unit"]) is not None]
    if not heights:
        raise InputError(path, f"the Nanosurf file holds no height data set ({[s['name'] for s in sets]})")
    start = mark + 3
    if sets:
        last = sets[-1]
        _need(path, buf, start + last["offset"] + last["nx"] * last["ny"] * last["dtype"].itemsize,
              f"Nanosurf data sets ({len(sets)} declared)")
    names = [s["name"] for s in heights]
    i = _select(path, names, [True] * len(names), channel)
    s = heights[i]
    raw = np.frombuffer(buf, s["dtype"], s["nx"] * s["ny"], start + s["offset"]).reshape(s["ny"], s["nx"])
    if sec.get("DataSet-Info", {}).get("Scan direction", "Up") != "Down":
        raw = raw[::-1]
    h = (raw * s["per_count"] + s["zero"]) * length_factor(s["unit"])
    lat = length_factor(s["lat_unit"])
    if lat is None:
        raise InputError(path, f"Nanosurf lateral unit {s['lat_unit']!r} is not a length")
    meta = _meta(s["unit"], s["lat_unit"], names, i)
    return h, s["sx"] * lat / s["nx"], s["sy"] * lat / s["ny"], meta


# ------------------------------------------------------------------------ Agilent / Molecular Imaging .mi

_MI_KEY = 14                        # header lines: a 14-character key field, then the value


def read_mi(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Agilent / Molecular Imaging PicoView .mi image (PicoView file description): text lines of
    a 14-character key field and a value; 'fileType Image'; 'xPixels', 'yPixels', 'xLength',
    'yLength' (metres), 'scanUp' (TRUE: lines stored from the bottom up); one block per buffer
    starting at 'bufferLabel' with 'bufferRange' and 'bufferUnit'; then a line 'data BINARY'
    (int16) or 'data BINARY_32' (int32) and the buffers back to back, each yPixels lines of
    xPixels little-endian integers.  z = count / 2^(bits-1) * bufferRange, in bufferUnit.
    Default channel: the first buffer whose unit is a length (the topography).
    """
    buf = path.read_bytes()
    if not buf.startswith(b"fileType      Image"):
        raise InputError(path, "not a PicoView .mi image (no 'fileType Image'; spectroscopy files are not read)")
    at = buf.find(b"\ndata ")
    if at < 0:
        raise InputError(path, "PicoView header has no 'data' line (truncated file?)")
    end = buf.find(b"\n", at + 1)
    kind = buf[at + 1:end if end >= 0 else len(buf)].decode("latin-1")[_MI_KEY:].strip()
    dtype = {"BINARY": "<i2", "BINARY_32": "<i4"}.get(kind)
    if dtype is None:
        raise InputError(path, f"PicoView data stored as {kind!r}; only BINARY and BINARY_32 are read")
    glob, bufs = {}, []
    for line in buf[:at].decode("latin-1").splitlines():
        key, value = line[:_MI_KEY].strip(), line[_MI_KEY:].strip()
        if key == "bufferLabel":
            bufs.append({})
        (bufs[-1] if bufs else glob)[key] = value
    try:
        nx, ny = int(glob["xPixels"]), int(glob["yPixels"])
        sx, sy = float(glob["xLength"]), float(glob["yLength"])
        ranges = [float(b["bufferRange"]) for b in bufs]
    except (KeyError, ValueError) as e:
        raise InputError(path, f"PicoView header incomplete or malformed ({type(e).__name__}: {e})") from None
    _check_size(path, (len(bufs), ny, nx), "PicoView buffers")
    item = np.dtype(dtype).itemsize
    start = end + 1
    _need(path, buf, start + len(bufs) * nx * ny * item, f"PicoView data ({len(bufs)} buffers of {nx} x {ny})")
    names = [b["bufferLabel"] for b in bufs]
    units = [b.get("bufferUnit", "") for b in bufs]
    i = _select(path, names, [length_factor(u) is not None for u in units], channel)
    raw = np.frombuffer(buf, dtype, nx * ny, start + i * nx * ny * item).reshape(ny, nx)
    if glob.get("scanUp", "FALSE").upper() == "TRUE":
        raw = raw[::-1]
    h = raw / 2.0 ** (8 * item - 1) * ranges[i] * length_factor(units[i])
    return h, sx / nx, sy / ny, _meta(units[i], "m", names, i)


# ------------------------------------------------------------------------ FRT MicroProf .frt

_FRT_MAGIC = b"FRTM_GLIDERV"
_FRT_DTYPE = {16: "<u2", 32: "<i4"}        # block 0x66 gives bits per value
_FRT_UNDEFINED = 1                         # raw value of a point not measured


def _frt_blocks(path: Path, buf: bytes) -> dict[int, tuple[int, int]]:
    """Block id -> (data offset, size) after the 16-byte magic+version and the uint16 block count."""
    version = buf[12:16]
    head = {b"1.00": "<HI", b"1.01": "<HQ"}.get(version)
    if head is None:
        raise InputError(path, f"FRT file version {version!r} not read (1.00, 1.01)")
    _need(path, buf, 18, "FRT header")
    n, = struct.unpack_from("<H", buf, 16)
    pos, blocks, step = 18, {}, struct.calcsize(head)
    for k in range(n):
        if pos == len(buf):             # fewer blocks than counted, ending on a block boundary: accepted
            break
        _need(path, buf, pos + step, f"FRT block header {k} of {n}")
        bid, size = struct.unpack_from(head, buf, pos)
        pos += step
        _need(path, buf, pos + size, f"FRT block 0x{bid:02x} ({k} of {n})")
        blocks.setdefault(bid, (pos, size))
        pos += size
    return blocks


def read_frt(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """FRT MicroProf .frt (FRT's block file description, as also read by Gwyddion's frtfile):
    'FRTM_GLIDERV' + version '1.00' (block header uint16 id, uint32 size) or '1.01' (uint64
    size), a uint16 block count, then blocks.  Used: 0x66 (uint32 nx, ny, bits per value 16 or
    32), 0x67 (float64 scanned size x, y in metres), 0x6c (uint32 range, float64 metres per
    count) and 0x0b (the height counts, ny lines of nx, uint16 or int32).  z = count * metres
    per count; a count of 1 marks a point not measured (NaN; typically a large share of an
    optical scan, which must not be filled in).  Pitch = size / points.
    """
    _single(path, channel, "default")
    buf = path.read_bytes()
    if not buf.startswith(_FRT_MAGIC):
        raise InputError(path, "not an FRT MicroProf file (no FRTM_GLIDERV magic)")
    blocks = _frt_blocks(path, buf)
    for bid in (0x66, 0x67, 0x6C, 0x0B):
        if bid not in blocks:
            raise InputError(path, f"FRT file lacks block 0x{bid:02x} (truncated file?)")
    at = blocks[0x66][0]
    _need(path, buf, at + 12, "FRT block 0x66")
    nx, ny, bits = struct.unpack_from("<3I", buf, at)
    dtype = _FRT_DTYPE.get(bits)
    if dtype is None:
        raise InputError(path, f"FRT height values of {bits} bits (16 or 32 are read)")
    _check_size(path, (ny, nx), "FRT height map")
    _need(path, buf, blocks[0x67][0] + 16, "FRT block 0x67")
    sx, sy = struct.unpack_from("<2d", buf, blocks[0x67][0])
    _need(path, buf, blocks[0x6C][0] + 12, "FRT block 0x6c")
    per_count_m, = struct.unpack_from("<d", buf, blocks[0x6C][0] + 4)
    at, size = blocks[0x0B]
    if size != nx * ny * bits // 8:
        raise InputError(path, f"FRT height block holds {size} bytes, {nx} x {ny} x {bits // 8} declared")
    _need(path, buf, at + size, f"FRT height map of {nx} x {ny}")
    raw = np.frombuffer(buf, dtype, nx * ny, at).reshape(ny, nx)
    h = raw * per_count_m
    h[raw == _FRT_UNDEFINED] = np.nan
    return h, sx / nx, sy / ny, _meta("m", "m", ["default"], 0)


# ------------------------------------------------------------------------ Igor binary wave .ibw

_IBW_BIN_HEADER = 64                # BinHeader5
_IBW_WAVE_HEADER = 320              # WaveHeader5 (the data follows at 64 + 320)
_IBW_TYPES = {2: "f4", 4: "f8", 8: "i1", 0x10: "i2", 0x20: "i4", 0x48: "u1", 0x50: "u2", 0x60: "u4"}
_IBW_LABEL = 32                     # MAX_DIM_LABEL_CHARS + 1


def _ibw_text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def _ibw_header(path: Path, buf: bytes) -> dict:
    """The fields of BinHeader5 / WaveHeader5 used here, with the byte order the version reveals."""
    _need(path, buf, _IBW_BIN_HEADER + _IBW_WAVE_HEADER, "Igor binary wave header")
    order = next((o for o in "<>" if struct.unpack_from(o + "h", buf, 0)[0] == 5), None)
    if order is None:
        raise InputError(path, f"Igor binary wave version {struct.unpack_from('<h', buf, 0)[0]} (only "
                               "version 5, written by Igor Pro 3+ and Asylum AFMs, is read)")
    if np.frombuffer(buf, order + "i2", (_IBW_BIN_HEADER + _IBW_WAVE_HEADER) // 2).sum(dtype=np.int64) % 65536:
        raise InputError(path, "Igor binary wave header checksum does not match (corrupt file)")
    (_, _, wfm, formula, note, data_eu), dim_eu, dim_lab = (struct.unpack_from(order + "hh4i", buf, 0),
                                                            struct.unpack_from(order + "4i", buf, 20),
                                                            struct.unpack_from(order + "4i", buf, 36))
    w = _IBW_BIN_HEADER
    return {"order": order, "wfm": wfm, "formula": formula, "note": note, "data_eu": data_eu,
            "dim_eu": dim_eu, "dim_lab": dim_lab, "type": struct.unpack_from(order + "h", buf, w + 16)[0],
            "n": struct.unpack_from(order + "4i", buf, w + 68), "sfa": struct.unpack_from(order + "4d", buf, w + 84),
            "units": _ibw_text(buf[w + 148:w + 152]),
            "dim_units": [_ibw_text(buf[w + 152 + 4 * k:w + 156 + 4 * k]) for k in range(4)]}


def _ibw_tail(path: Path, buf: bytes, hd: dict, data_end: int) -> tuple[str, list[str], list[str]]:
    """Data units, dimension units and the channel (third dimension) labels from the sections after
    the data: formula, note, extended data units, extended dimension units, dimension labels."""
    pos = data_end + hd["formula"] + hd["note"]
    _need(path, buf, pos + hd["data_eu"] + sum(hd["dim_eu"]) + sum(hd["dim_lab"]), "Igor wave units and labels")
    units = _ibw_text(buf[pos:pos + hd["data_eu"]]) if hd["data_eu"] else hd["units"]
    pos += hd["data_eu"]
    dim_units = []
    for k in range(4):
        dim_units.append(_ibw_text(buf[pos:pos + hd["dim_eu"][k]]) if hd["dim_eu"][k] else hd["dim_units"][k])
        pos += hd["dim_eu"][k]
    labels = []
    for k in range(4):
        if k == 2:
            labels = [_ibw_text(buf[p:p + _IBW_LABEL]) for p in range(pos + _IBW_LABEL, pos + hd["dim_lab"][2],
                                                                      _IBW_LABEL)]
        pos += hd["dim_lab"][k]
    return units, dim_units, labels


def read_ibw(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Igor Pro binary wave, version 5 (.ibw; WaveMetrics Technical Note TN003), as written by
    Asylum Research / Oxford Instruments AFMs: BinHeader5 (64 bytes: version, checksum making the
    int16 sum of both headers 0, wfmSize, formula, note, extended-unit and dimension-label sizes),
    WaveHeader5 (320 bytes: npnts at 12, type at 16, nDim[4] at 68, sfA[4] (delta per point)
    at 84, dataUnits at 148, dimUnits[4] at 152), the data (dimension 0 fastest: x, then y, then
    channels), then formula, note, extended units and dimension labels (32 bytes each, the first
    of a dimension naming the dimension itself).  Heights are the values in dataUnits (NaN stays
    NaN); pitch = sfA[0], sfA[1] in dimUnits; lines are stored from the bottom up.  Channels: the
    labels of dimension 2 (HeightTrace, AmplitudeTrace, ...); default the first.
    """
    buf = path.read_bytes()
    hd = _ibw_header(path, buf)
    if hd["type"] not in _IBW_TYPES:
        raise InputError(path, f"Igor wave number type 0x{hd['type']:x} is not read (complex or text wave?)")
    nx, ny, nc = hd["n"][0], hd["n"][1], max(hd["n"][2], 1)
    if ny == 0 or hd["n"][3] > 1:
        raise InputError(path, f"Igor wave of dimensions {hd['n']}: need a 2-D map or a stack of 2-D channels")
    _check_size(path, (nc, ny, nx), "Igor wave")
    dtype = np.dtype(hd["order"] + _IBW_TYPES[hd["type"]])
    start = _IBW_BIN_HEADER + _IBW_WAVE_HEADER
    if hd["wfm"] != _IBW_WAVE_HEADER + nx * ny * nc * dtype.itemsize:
        raise InputError(path, f"Igor wave size {hd['wfm']} does not match {hd['n']} values of {dtype.itemsize} bytes")
    _need(path, buf, start + nx * ny * nc * dtype.itemsize, f"Igor wave data ({nc} channels of {nx} x {ny})")
    units, dim_units, labels = _ibw_tail(path, buf, hd, start + nx * ny * nc * dtype.itemsize)
    names = (labels + [f"no name ({k + 1})" for k in range(nc)])[:nc]
    zf, fx, fy = (length_factor(u) for u in (units, dim_units[0], dim_units[1]))
    if zf is None or fx is None or fy is None:
        raise InputError(path, f"Igor wave units {units!r} (data), {dim_units[:2]} (x, y): not lengths")
    i = _select(path, names, [True] * nc, channel)
    raw = np.frombuffer(buf, dtype, nx * ny, start + i * nx * ny * dtype.itemsize).reshape(ny, nx)[::-1]
    return raw * zf, hd["sfa"][0] * fx, hd["sfa"][1] * fy, _meta(units, dim_units[0], names, i)


# ------------------------------------------------------------------------ Bruker Dektak stylus .csv

_DEKTAK_Z_UNITS = {"micrometer": 1e-6, "um": 1e-6, "µm": 1e-6, "nanometer": 1e-9, "nm": 1e-9,
                   "angstrom": 1e-10, "å": 1e-10, "a": 1e-10, "millimeter": 1e-3, "mm": 1e-3}


def _dektak_number(path: Path, text: str, what: str) -> float:
    m = re.match(r"\s*([-+0-9.eE]+)\s*um", text)
    if m is None:
        raise InputError(path, f"Dektak header {what} {text!r} is not a length in um")
    return float(m.group(1))


def read_dektak(path: Path, channel=None) -> tuple[np.ndarray, float, float, dict]:
    """Bruker Dektak stylus profiler CSV export (Vision64 'Export to CSV'): a 'Scan Parameters'
    block of 'name,value' lines ('Length,1500.0 um', 'Resolution,0.156 um/sample'), 'Analytical
    Results', then 'Scan Data', a header 'Lateral um,<kind> <unit>,' and one 'x,z,' line per
    sample.  A stylus scan is one line: the result is a 1 x n profile (z in metres, uniform
    spacing (x_last - x_first) / (n - 1), the file's x being rounded to 0.1 um), which
    `read_relief` refuses as not a height map, like SurfaceTopography's reading.  A scan shorter
    than its declared Length (by more than two samples) is a truncated file.
    """
    _single(path, channel, "default")
    text = path.read_bytes().decode("latin-1")
    head, sep, body = text.partition("Scan Data")
    if not head.lstrip().startswith("Scan Parameters") or not sep:
        raise InputError(path, "not a Bruker Dektak CSV export (no 'Scan Parameters' ... 'Scan Data')")
    params = dict(line.split(",", 1) for line in head.splitlines() if line.count(",") >= 1)
    lines = [ln for ln in body.splitlines() if ln.strip()]
    if len(lines) < 3:
        raise InputError(path, "Dektak export holds no scan data (truncated file?)")
    cols = [c.strip() for c in lines[0].split(",")]
    zf = _DEKTAK_Z_UNITS.get(cols[1].split()[-1].lower() if len(cols) > 1 and cols[1] else "")
    if not cols[0].lower().endswith(" um") or zf is None:
        raise InputError(path, f"Dektak data columns {cols[:2]}: expected 'Lateral um' and a height in a length unit")
    _check_size(path, (len(lines) - 1,), "Dektak profile")
    rows = [ln.split(",")[:2] for ln in lines[1:]]
    try:
        bad = next((k for k, r in enumerate(rows) if len(r) < 2), None)
        if bad is not None:
            raise ValueError(f"line {bad + 1} of the scan data, {lines[bad + 1]!r}, has one value")
        xz = np.array([[float(r[0]), float(r[1])] for r in rows])
    except ValueError as e:
        raise InputError(path, f"Dektak scan data is not pairs of numbers ({e}; truncated file?)") from None
    length_um = _dektak_number(path, params.get("Length", ""), "Length")
    step_um = _dektak_number(path, params.get("Resolution", ""), "Resolution")
    span_um = xz[-1, 0] - xz[0, 0]
    if span_um < length_um - 2 * step_um:
        raise InputError(path, f"truncated file: the Dektak scan data ends at {span_um:g} um of the declared "
                               f"Length {length_um:g} um")
    dx = span_um * 1e-6 / (len(xz) - 1)
    return xz[:, 1][None, :] * zf, dx, dx, _meta(cols[1].split()[-1], "um", ["default"], 0,
                                                           profile_points=len(xz))
