"""Height-map files in and out: `read_relief` and `write_relief`.

Which reader handles a file (by extension, then content):

- ``.npz``: numpy archive with ``heights`` (2-D, metres, NaN = no data), ``dx`` and
  ``dy`` (metres); optional ``periodic`` (bool) and ``info_json`` (provenance written
  by `write_relief`).
- ``.tif``/``.tiff``/``.exr``: a 32-bit (or 16-bit half / 64-bit) float image read with
  OpenImageIO (`relief_bsdf.io.oiio`).  Image row r is relief row r (y = r * dy), column
  c is x = c * dx.  Images carry no physical units, so the lateral pitch comes from,
  in this order: the ``pitch_m=(dx, dy)`` argument; a sidecar JSON file named
  ``<image file name>.json`` (e.g. ``relief.exr.json``) with keys ``dx_m``, ``dy_m``
  and optional ``z_unit`` ("m" default, or "mm", "um", "nm", ...) and ``periodic``;
  the ``relief:dx_m`` / ``relief:dy_m`` / ``relief:z_unit`` attributes that
  `write_relief` stores in EXR headers.  Otherwise the read fails.  Multi-channel
  images need ``channel=`` (index or name) unless a channel is called Z, height or Y.
  Integer images are refused (they do not say how counts map to metres).
- ``.sdf``: ISO 25178-71 surface data file (ASCII ``aISO-1.0``/``aBCR-1.0`` or binary
  ``bISO-1.0``/``bBCR-1.0``), read here because SurfaceTopography has no reader for
  it.  Scales are in metres by the standard; ``BAD`` cells (ASCII) are invalid.
- everything else (x3p, gwy, sur, Zygo dat/datx, Sensofar plu/plux, Wyko opd/opdx,
  Bruker .di/.spm, Nanosurf nid/ezd, Asylum ibw, Agilent mi, FRT frt, Keyence vk,
  al3d, nc, h5, mat, ...): SurfaceTopography's ``open_topography``.

Units: SurfaceTopography reports one length unit per channel for both the heights
and the physical sizes; we convert both to metres.  Known exception: Agilent/
Molecular Imaging ``.mi`` files store ``xLength``/``yLength`` in metres while the
buffer (height) unit is e.g. um, and SurfaceTopography 1.18 labels the lateral
sizes with the height unit; we read the lateral sizes as metres for that reader
(checked against the file's own header: 20 um scan, 256 px -> 78.1 nm pitch).
A pitch outside [1e-11, 1] m is refused as implausible (pass ``pitch_m``).

Bounds and plausibility (checked *before* the pixels are allocated):

- size: a map declaring more than `max_pixels()` pixels is refused (default
  `DEFAULT_MAX_PIXELS` = 2**25, about 33.5 million, i.e. 5792 x 5792, 270 MB as float64 and
  several times that in the methods' working arrays).  Raise it with the CLI flag
  ``--max-pixels N``, the environment variable ``RELIEF_MAX_PIXELS`` or `pixel_limit(n)`.
  The declared size is read from the npz member headers, the image spec, the SDF header,
  the X3P main.xml and SurfaceTopography's channel description;
- BSDF tables (io.hdf5): every dataset's declared shape is checked the same way before it is
  read: at most `max_pixels()` cells (16 values per cell for the Mueller matrices);
- X3P: the declared increments must be positive and finite, the MD5 checksums of the point
  data and of main.xml are verified (a mismatch is a warning naming the file);
- images: an error OpenImageIO records while reading (a truncated or corrupt TIFF / EXR)
  refuses the file;
- implausible values warn (`relief_bsdf.errors.InputWarning`, saying why): an rms height
  above 1 mm (micro-reliefs are nm to um; a wrong height unit is the usual cause) or a
  pitch above 1 mm (a lateral unit read wrong);
- a map without two adjacent valid points along x and along y is refused (no slope can be
  formed: e.g. a 2 x 2 map with 3 NaN).

Other shapes of valid input: an X3P zipped with its folder (a ``.zip`` or ``.x3p`` whose
main.xml sits in one subfolder) is repacked and read as the X3P it holds; one of the project's
BSDF tables (``.h5``) given as a height map is refused in one line saying so.

Periodicity: a file that states it (an npz ``periodic``, a sidecar's ``periodic``, the EXR
attribute ``relief:periodic``, the comment of an X3P this project wrote, a reader reporting a
periodic topography) sets ``Relief.periodic`` and names itself in
``metadata["periodic_source"]``; otherwise ``periodic`` is False here and
`read_prepared_relief` (what the CLI reads maps with) decides by the user's statement or the
wrap-around test (surface.periodicity).

Invalid points stay NaN (masked arrays from SurfaceTopography, NaN in images/npz);
nothing is filled or levelled here (`read_prepared_relief` fills when asked).  A 1-D profile is refused with a message
saying 2-D work needs an area scan; an all-NaN map is refused.
"""
from __future__ import annotations

import contextlib
import contextvars
import datetime
import hashlib
import io
import json
import os
import struct
import warnings
import zipfile
from importlib import metadata as _metadata
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.io.atomic import atomic_path, write_bytes_atomic, write_text_atomic
from relief_bsdf.errors import InputError, warn_input
from relief_bsdf.surface.relief import Relief

IMAGE_SUFFIXES = (".tif", ".tiff", ".exr")
WRITE_SUFFIXES = (".npz", ".x3p", ".exr", ".tif", ".tiff")

#: length units (as SurfaceTopography and sidecars spell them) -> metres
LENGTH_UNITS = {"m": 1.0, "dm": 1e-1, "cm": 1e-2, "mm": 1e-3, "µm": 1e-6, "μm": 1e-6, "um": 1e-6,
                "nm": 1e-9, "Å": 1e-10, "A": 1e-10, "pm": 1e-12, "km": 1e3}
#: SurfaceTopography readers whose physical sizes are in metres whatever the channel unit says
_LATERAL_IN_METRES = {"MIReader"}
_PITCH_RANGE_M = (1e-11, 1.0)
#: plausibility: above these a warning says why (below the hard limits)
PLAUSIBLE_RMS_HEIGHT_M = 1e-3
PLAUSIBLE_PITCH_M = 1e-3

#: documented default of the size limit (pixels of one height map), see the module doc
DEFAULT_MAX_PIXELS = 2 ** 25
_MAX_PIXELS: contextvars.ContextVar[int | None] = contextvars.ContextVar("relief_max_pixels", default=None)


def max_pixels() -> int:
    """The size limit in force: `pixel_limit` block, else $RELIEF_MAX_PIXELS, else DEFAULT_MAX_PIXELS."""
    v = _MAX_PIXELS.get()
    if v is not None:
        return v
    env = os.environ.get("RELIEF_MAX_PIXELS")
    if env:
        try:
            n = int(float(env))
        except ValueError:
            raise InputError("$RELIEF_MAX_PIXELS", f"expected a whole number of pixels, got {env!r}") from None
        if n < 1:
            raise InputError("$RELIEF_MAX_PIXELS", f"must be >= 1, got {env!r}")
        return n
    return DEFAULT_MAX_PIXELS


@contextlib.contextmanager
def pixel_limit(n: int | None):
    """Put a size limit (pixels) in force for a `with` block; None keeps the one in force."""
    if n is None:
        yield
        return
    token = _MAX_PIXELS.set(int(n))
    try:
        yield
    finally:
        _MAX_PIXELS.reset(token)


def check_declared_size(path: Path, shape: tuple, what: str = "height map", per_pixel: int = 1) -> None:
    """Refuse (InputError) a declared size beyond `per_pixel` x `max_pixels()` values before anything is
    allocated (`per_pixel`: values one cell may carry, e.g. 16 for a table's 4x4 Mueller matrices)."""
    dims = [int(d) for d in shape]
    if any(d < 0 for d in dims):
        raise InputError(path, f"the file declares a negative size {' x '.join(map(str, dims))}")
    n = int(np.prod(dims, dtype=object)) if dims else 1
    limit = max_pixels() * int(per_pixel)
    if n > limit:
        raise InputError(path, f"the {what} declares {' x '.join(map(str, dims))} = {n} values, more than the limit "
                               f"of {limit} (about {8 * n / 1e9:.2g} GB as float64); raise it with --max-pixels "
                               "or RELIEF_MAX_PIXELS if this is meant")


def _unit_factor(unit: Any, where: Path, what: str) -> float:
    if unit is None:
        raise InputError(where, f"the file gives no length unit for the {what}")
    if unit not in LENGTH_UNITS:
        raise InputError(where, f"unknown length unit {unit!r} for the {what} "
                                f"(known: {', '.join(sorted(LENGTH_UNITS))})")
    return LENGTH_UNITS[unit]


def _check_pitch(dx: float, dy: float, where: Path, source: str) -> None:
    lo, hi = _PITCH_RANGE_M
    for name, v in (("dx", dx), ("dy", dy)):
        if not (np.isfinite(v) and lo <= v <= hi):
            raise InputError(where, f"implausible lateral pitch {name} = {v:.4g} m from {source} "
                                    f"(expected {lo:g} to {hi:g} m); pass pitch_m=(dx, dy) explicitly")


def _check_pitch_arg(pitch_m: Any, where: Path) -> tuple[float, float]:
    try:
        dx, dy = (float(v) for v in pitch_m)
    except (TypeError, ValueError):
        raise InputError(where, f"pitch_m must be two numbers (dx, dy) in metres, got {pitch_m!r}") from None
    if not (dx > 0 and dy > 0 and np.isfinite(dx) and np.isfinite(dy)):
        raise InputError(where, f"pitch_m must be positive, got {pitch_m!r}")
    return dx, dy


def _finish(path: Path, heights_m: np.ndarray, dx: float, dy: float, periodic: bool, meta: dict) -> Relief:
    h = np.asarray(heights_m, dtype=float)
    if h.ndim == 1 or (h.ndim == 2 and min(h.shape) == 1):
        raise InputError(path, f"this is a 1-D line profile ({h.size} points), not a height map; "
                               "2-D work (BSDF reconstruction, plate simulation) needs an area scan")
    relief = Relief(h, float(dx), float(dy), periodic=bool(periodic), source=str(path), metadata=meta)
    if relief.valid_fraction == 0.0:
        raise InputError(path, "the height map has no valid points (every value is NaN / not measured)")
    v = np.isfinite(relief.heights_m)
    if not ((v[:, 1:] & v[:, :-1]).any() and (v[1:, :] & v[:-1, :]).any()):
        raise InputError(path, f"the height map ({h.shape[0]} x {h.shape[1]}, {int(v.sum())} valid) has no two "
                               "adjacent valid points along x and along y: no slope, no BSDF can be formed")
    _warn_implausible(path, relief.heights_m[v], float(dx), float(dy))
    return relief


def _warn_implausible(path: Path, valid_m: np.ndarray, dx: float, dy: float) -> None:
    rms = float(np.std(valid_m))
    if not np.isfinite(rms) or rms > PLAUSIBLE_RMS_HEIGHT_M:
        warn_input(path, f"implausible rms height {rms:.4g} m (micro-reliefs are nm to um; above "
                         f"{PLAUSIBLE_RMS_HEIGHT_M * 1e3:g} mm the height unit is probably wrong)")
    if max(dx, dy) > PLAUSIBLE_PITCH_M:
        warn_input(path, f"implausible lateral pitch {dx:.4g} x {dy:.4g} m (above {PLAUSIBLE_PITCH_M * 1e3:g} mm "
                         "a profilometer map is unusual; the lateral unit is probably wrong; pass pitch_m)")


# ====================================================================== reading


def read_relief(path: str | Path, pitch_m: Any = None, channel: int | str | None = None,
                z_unit: str | None = None) -> Relief:
    """Read a height map file into a `Relief` (heights and pitch in metres).

    pitch_m: (dx, dy) in metres; required for images without sidecar, overrides the
        file's own pitch otherwise (recorded in metadata["pitch_source"]).
    channel: index or name of the data channel (multi-channel AFM files, images);
        default: the file's default height channel.
    z_unit: unit of the heights for files that carry none (images, default "m").
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "height map file not found")
    if not path.is_file():
        raise InputError(path, "not a regular file")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes)")
    pitch = _check_pitch_arg(pitch_m, path) if pitch_m is not None else None
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        _refuse_bsdf_table(path)
    if suffix == ".npz":
        return _read_npz(path, pitch)
    if suffix in IMAGE_SUFFIXES:
        return _read_image(path, pitch, channel, z_unit)
    if suffix == ".sdf":
        return _read_sdf(path, pitch)
    if suffix in (".x3p", ".zip"):
        inner = _x3p_folder_prefix(path)
        if inner:
            return _read_zipped_x3p_folder(path, inner, pitch, channel)
    if suffix == ".x3p":
        check_x3p(path)                 # size, increments, checksums: before any reader allocates anything
    # --- hook: the project's own readers where SurfaceTopography is missing (io/native_readers.py)
    from relief_bsdf.io import native_readers
    if native_readers.wanted(suffix):
        return _finish(path, *native_readers.read(path, pitch, channel))
    # --- end of hook
    return _read_surface_topography(path, pitch, channel)


def _refuse_bsdf_table(path: Path) -> None:
    """InputError when `path` is one of the project's BSDF tables (io.hdf5) rather than a height map."""
    try:
        import h5py
        from relief_bsdf.io.hdf5 import FORMAT
        with h5py.File(path, "r") as f:
            is_table = f.attrs.get("format") == FORMAT or "outside" in f or "inside" in f
    except OSError:
        return
    if is_table:
        raise InputError(path, "is a BSDF table, not a height map (give the height map the table was made from)")


def read_prepared_relief(path: str | Path, options=None, pitch_m: Any = None,
                         channel: int | str | None = None) -> Relief:
    """`read_relief`, then the user's choices (`surface.preparation.ReliefOptions`: crop, downsample,
    periodicity, hole filling) applied by `surface.preparation.prepare_relief`, each in the history."""
    from relief_bsdf.surface.preparation import ReliefOptions, prepare_relief
    return prepare_relief(read_relief(path, pitch_m=pitch_m, channel=channel), options or ReliefOptions())


def read_sample_relief(sample, overrides=None) -> Relief:
    """The relief of a sample (io.recording.Sample) with its [relief] keys applied, and `overrides`
    (a ReliefOptions, e.g. from the command line) taking precedence over them."""
    options = sample.relief_options if overrides is None else sample.relief_options.overridden(overrides)
    return read_prepared_relief(sample.relief_path, options)


def _npz_declared_shapes(path: Path) -> dict[str, tuple]:
    """Shape of every member array, from the .npy headers only (nothing is allocated)."""
    shapes = {}
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _, _ = np.lib.format.read_array_header_1_0(f)
                else:
                    shape, _, _ = np.lib.format.read_array_header_2_0(f)
            shapes[name] = tuple(shape)
    return shapes


def _read_npz(path: Path, pitch: tuple | None) -> Relief:
    try:
        shapes = _npz_declared_shapes(path)
    except Exception as e:  # zipfile.BadZipFile, ValueError (not .npy), EOFError, OSError, ...
        raise InputError(path, f"not a readable .npz archive ({type(e).__name__}: {e})") from None
    for name, shape in shapes.items():
        check_declared_size(path, shape, f"array {name!r}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # zipfile.BadZipFile, ValueError, EOFError, OSError, ...
        raise InputError(path, f"not a readable .npz archive ({type(e).__name__}: {e})") from None
    if "heights" not in data:
        raise InputError(path, f"missing array 'heights' (found: {', '.join(sorted(data)) or 'nothing'}); "
                               "expected heights (m), dx, dy (m)")
    h = data["heights"]
    if h.dtype.kind not in "fiu":
        raise InputError(path, f"'heights' must be numeric, got dtype {h.dtype}")
    meta: dict = {"reader": "npz", "file_unit": "m"}
    if pitch is None:
        for k in ("dx", "dy"):
            if k not in data:
                raise InputError(path, f"missing scalar '{k}' (lateral pitch in metres)")
            if data[k].size != 1:
                raise InputError(path, f"'{k}' must be a scalar (metres), got shape {data[k].shape}")
        dx, dy = float(data["dx"].reshape(())), float(data["dy"].reshape(()))
        meta["pitch_source"] = "file"
    else:
        dx, dy = pitch
        meta["pitch_source"] = "argument"
    if h.ndim != 1:
        _check_pitch(dx, dy, path, "the npz dx/dy (metres expected)")
    periodic = bool(data["periodic"].reshape(())) if "periodic" in data else False
    if "periodic" in data:
        meta["periodic_source"] = "the npz key periodic"
    if "info_json" in data:
        try:
            meta["written_by"] = json.loads(str(data["info_json"]))
        except ValueError:
            pass
    return _finish(path, h.astype(float), dx, dy, periodic, meta)


def _read_sidecar(path: Path) -> dict | None:
    side = path.with_name(path.name + ".json")
    if not side.exists():
        return None
    if not side.is_file():
        raise InputError(side, "the sidecar is not a regular file (a folder?); expected a JSON file with dx_m, dy_m")
    try:
        d = json.loads(side.read_text(encoding="utf-8-sig"))
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(side, f"sidecar is not valid JSON ({e})") from None
    except OSError as e:
        raise InputError(side, f"cannot read the sidecar ({e.strerror or e})") from None
    if not isinstance(d, dict):
        raise InputError(side, "sidecar must be a JSON object with dx_m, dy_m and optional z_unit")
    allowed = {"dx_m", "dy_m", "z_unit", "periodic", "source", "history", "comment"}
    extra = set(d) - allowed
    if extra:
        raise InputError(side, f"unknown key(s) {sorted(extra)}; expected dx_m, dy_m, optional z_unit, periodic")
    for k in ("dx_m", "dy_m"):
        if k not in d:
            raise InputError(side, f"missing key {k} (lateral pitch in metres)")
        if isinstance(d[k], bool) or not isinstance(d[k], (int, float)) or not d[k] > 0:
            raise InputError(side, f"key {k} must be a positive number of metres, got {d[k]!r}")
    if "z_unit" in d and d["z_unit"] not in LENGTH_UNITS:
        raise InputError(side, f"key z_unit: unknown unit {d['z_unit']!r} (known: {', '.join(sorted(LENGTH_UNITS))})")
    d["_path"] = str(side)
    return d


def _read_image(path: Path, pitch: tuple | None, channel: int | str | None, z_unit: str | None) -> Relief:
    from relief_bsdf.io import oiio
    try:
        OIIO = oiio.load()
    except ImportError as e:
        raise InputError(path, f"reading TIFF/EXR needs OpenImageIO: {e}") from None
    inp = OIIO.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"not a readable image ({OIIO.geterror().strip() or 'unknown error'})")
    try:
        spec = inp.spec()
        fmt = str(spec.format)
        if fmt not in ("float", "half", "double"):
            raise InputError(path, f"image pixels are {fmt}, not floating point; a height map image must be "
                                   "32-bit float (integer counts do not say how many metres they are)")
        names = list(spec.channelnames)
        if spec.nchannels == 1:
            ci = 0
        elif channel is not None:
            if isinstance(channel, str) and not channel.lstrip("-").isdigit():
                if channel not in names:
                    raise InputError(path, f"no channel {channel!r}; channels are {names}")
                ci = names.index(channel)
            else:
                ci = int(channel)
                if not 0 <= ci < spec.nchannels:
                    raise InputError(path, f"channel {ci} out of range 0..{spec.nchannels - 1} ({names})")
        else:
            pick = [n for n in ("Z", "z", "height", "Height", "Y") if n in names]
            if not pick:
                raise InputError(path, f"image has {spec.nchannels} channels {names}; choose one with channel=")
            ci = names.index(pick[0])
        check_declared_size(path, (max(1, spec.depth), spec.height, spec.width), "image")
        if spec.nchannels > 64:
            raise InputError(path, f"the image declares {spec.nchannels} channels; a height map has one (or a few)")
        pixels = inp.read_image(format="float")
        if pixels is None or inp.has_error:
            why = " ".join(inp.geterror().split())[:200] or "unknown error"
            raise InputError(path, f"cannot read the pixels (truncated or corrupt image: {why})")
        attrs = {k: spec.getattribute(k) for k in ("relief:dx_m", "relief:dy_m", "relief:z_unit",
                                                      "relief:periodic")}
    finally:
        inp.close()
    err = OIIO.geterror()
    pixels = np.asarray(pixels, dtype=float)
    if pixels.ndim == 3:
        pixels = pixels[:, :, ci]
    meta: dict = {"reader": f"OpenImageIO {OIIO.VERSION_STRING}", "channel": names[ci] if names else str(ci),
                  "image_format": fmt}
    if err.strip():
        meta["reader_warning"] = err.strip()
    side = _read_sidecar(path)
    periodic = False
    if pitch is not None:
        dx, dy = pitch
        meta["pitch_source"] = "argument"
    elif side is not None:
        dx, dy = float(side["dx_m"]), float(side["dy_m"])
        meta["pitch_source"] = side["_path"]
    elif attrs["relief:dx_m"] is not None and attrs["relief:dy_m"] is not None:
        dx, dy = float(attrs["relief:dx_m"]), float(attrs["relief:dy_m"])
        meta["pitch_source"] = "image attributes relief:dx_m, relief:dy_m"
    else:
        raise InputError(path, f"no lateral pitch: an image carries no physical size; pass pitch_m=(dx, dy) "
                               f"or write a sidecar {path.name}.json with dx_m, dy_m (metres)")
    if side is not None:
        periodic = bool(side.get("periodic", False))
        if "periodic" in side:
            meta["periodic_source"] = f"the sidecar {Path(side['_path']).name}"
    elif attrs["relief:periodic"] is not None:
        periodic = str(attrs["relief:periodic"]).lower() in ("1", "true")
        meta["periodic_source"] = "the image attribute relief:periodic"
    unit = z_unit or (side or {}).get("z_unit") or attrs["relief:z_unit"] or "m"
    if unit not in LENGTH_UNITS:
        raise InputError(path, f"unknown height unit {unit!r}")
    meta["file_unit"] = unit
    meta["z_unit_source"] = ("argument" if z_unit else "sidecar" if side and "z_unit" in side
                             else "image attribute" if attrs["relief:z_unit"] else "default (metres)")
    _check_pitch(dx, dy, path, meta["pitch_source"])
    return _finish(path, pixels * LENGTH_UNITS[unit], dx, dy, periodic, meta)


def _one_line(e: BaseException, limit: int = 200) -> str:
    text = " ".join(str(e).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _st_format_for(path: Path) -> str | None:
    """SurfaceTopography's format name for this extension, when exactly one reader claims it."""
    from SurfaceTopography.IO import readers
    ext = path.suffix.lower().lstrip(".")
    claims = [r._format for r in readers if ext in [x.lower() for x in getattr(r, "_file_extensions", [])]]
    return claims[0] if len(claims) == 1 else None


def _surface_topography_version() -> str:
    try:
        return _metadata.version("SurfaceTopography")
    except _metadata.PackageNotFoundError:  # pragma: no cover
        return "?"


def _read_surface_topography(path: Path, pitch: tuple | None, channel: int | str | None) -> Relief:
    import SurfaceTopography as ST
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fmt = _st_format_for(path)
        try:
            reader = ST.open_topography(str(path), format=fmt) if fmt else ST.open_topography(str(path))
        except Exception as e:
            what = f"as a {fmt} file" if fmt else "as a height map"
            raise InputError(path, f"cannot read {what}: {type(e).__name__}: {_one_line(e)} "
                                   "(supported: x3p, gwy, sur, sdf, datx/dat, plu/plux, opd, di/spm, nid, ibw, "
                                   "mi, frt, npz, float tif/exr and the other SurfaceTopography formats)") from None
        try:
            chans = list(reader.channels)
        except Exception as e:  # noqa: BLE001 - a reader failing on a foreign layout
            raise InputError(path, f"cannot read the channels: {type(e).__name__}: {_one_line(e)}") from None
        if not chans:
            raise InputError(path, "the file holds no height-map channel (is it a height map at all? an HDF5 "
                                   "BSDF table needs the relief-bsdf-table/1 layout)")
        if channel is None:
            try:
                ch = reader.default_channel
            except (IndexError, KeyError, AttributeError):
                ch = chans[0]
        elif isinstance(channel, str) and not channel.lstrip("-").isdigit():
            found = [c for c in chans if c.name == channel] or [c for c in chans if c.name.lower() == channel.lower()]
            if not found:
                raise InputError(path, f"no channel {channel!r}; channels are {[c.name for c in chans]}")
            ch = found[0]
        else:
            ci = int(channel)
            if not 0 <= ci < len(chans):
                raise InputError(path, f"channel {ci} out of range 0..{len(chans) - 1} "
                                       f"({[c.name for c in chans]})")
            ch = chans[ci]
        if ch.dim == 1:
            n = ch.nb_grid_pts[0] if ch.nb_grid_pts else "?"
            raise InputError(path, f"this is a 1-D line profile ({n} points), not a height map; "
                                   "2-D work (BSDF reconstruction, plate simulation) needs an area scan")
        unit = ch.unit
        if isinstance(unit, tuple):  # (lateral unit, data unit): a non-height channel such as Phase
            if unit[1] is None or unit[1] not in LENGTH_UNITS:
                raise InputError(path, f"channel {ch.name!r} holds {unit[1] or 'unitless'} data, not heights; "
                                       f"choose a height channel ({[c.name for c in chans]})")
        if ch.nb_grid_pts:
            check_declared_size(path, tuple(ch.nb_grid_pts))
        kw: dict = {}
        if ch.physical_sizes is None:
            if pitch is None:
                raise InputError(path, "the file gives no lateral size; pass pitch_m=(dx, dy) in metres")
            kw["physical_sizes"] = tuple(float(n) for n in ch.nb_grid_pts)
        if unit is None:
            raise InputError(path, f"channel {ch.name!r}: the file gives no height unit; refusing to guess")
        try:
            topo = reader.topography(channel_index=ch.index, **kw)
            raw = topo.heights()
        except Exception as e:
            raise InputError(path, f"cannot read channel {ch.name!r}: {type(e).__name__}: {_one_line(e)} "
                                   "(corrupt or truncated file?)") from None
    t_unit = topo.unit
    lat_unit, z_unit = (t_unit if isinstance(t_unit, tuple) else (t_unit, t_unit))
    zf = _unit_factor(z_unit, path, "heights")
    reader_name = type(reader).__name__
    lf = 1.0 if reader_name in _LATERAL_IN_METRES else _unit_factor(lat_unit, path, "lateral size")
    h = np.ma.filled(np.ma.asarray(raw).astype(float), np.nan)
    if h.ndim != 2:
        raise InputError(path, f"channel {ch.name!r} has {h.ndim} dimension(s); need a 2-D map")
    nx, ny = h.shape                   # SurfaceTopography indexes heights[x, y]
    meta: dict = {"reader": f"SurfaceTopography {_surface_topography_version()} {reader_name}",
                  "channel": ch.name, "channel_index": int(ch.index),
                  "channels": [c.name for c in chans], "file_unit": str(z_unit),
                  "lateral_unit": "m" if reader_name in _LATERAL_IN_METRES else str(lat_unit)}
    info = dict(getattr(topo, "info", {}) or {})
    if "instrument" in info:
        meta["instrument"] = info["instrument"]
    if "acquisition_time" in info:
        meta["acquisition_time"] = str(info["acquisition_time"])
    if pitch is not None:
        dx, dy = pitch
        meta["pitch_source"] = "argument"
        if ch.physical_sizes is not None:
            sx, sy = topo.physical_sizes
            meta["pitch_in_file_m"] = [sx * lf / nx, sy * lf / ny]
    else:
        sx, sy = topo.physical_sizes
        dx, dy = sx * lf / nx, sy * lf / ny
        meta["pitch_source"] = "file"
        _check_pitch(dx, dy, path, f"the file ({sx:g} x {sy:g} {lat_unit})")
    periodic = _x3p_stated_periodic(path)
    if periodic is not None:
        meta["periodic_source"] = "the X3P's relief_bsdf comment (periodic=...)"
    elif getattr(topo, "is_periodic", False):
        periodic = True
        meta["periodic_source"] = "the file (its reader reports a periodic topography)"
    return _finish(path, h.T * zf, dx, dy, bool(periodic), meta)


_X3P_ITEMSIZE = {"I": 2, "L": 4, "F": 4, "D": 8}


def _xml_children(elem) -> dict:
    """Local tag name -> element, for an X3P main.xml element (namespaces dropped)."""
    return {c.tag.rsplit("}", 1)[-1]: c for c in elem}


def _xml_text(elem, *names: str) -> str | None:
    for n in names:
        if elem is None:
            return None
        elem = _xml_children(elem).get(n)
    return None if elem is None or elem.text is None else elem.text.strip()


def check_x3p(path: Path) -> None:
    """Check an ISO 25178-72 X3P before its data is read: declared size within the limit, increments
    positive, point data no larger than declared (InputError); MD5 checksums verified (InputWarning)."""
    import xml.etree.ElementTree as ET
    try:
        with zipfile.ZipFile(path) as z:
            xml = z.read("main.xml")
            root = ET.fromstring(xml)
            r1, r3 = _xml_children(root).get("Record1"), _xml_children(root).get("Record3")
            sizes = [_xml_text(r3, "MatrixDimension", k) for k in ("SizeX", "SizeY", "SizeZ")]
            link = _xml_text(r3, "DataLink", "PointDataLink")
            md5 = _xml_text(r3, "DataLink", "MD5ChecksumPointData")
            ztype = _xml_text(r1, "Axes", "CZ", "DataType") or "D"
            incs = {a: _xml_text(r1, "Axes", a, "Increment") for a in ("CX", "CY")}
            kinds = {a: _xml_text(r1, "Axes", a, "AxisType") for a in ("CX", "CY")}
            names = set(z.namelist())
            data_info = z.getinfo(link) if link and link in names else None
            hex_text = z.read("md5checksum.hex").decode("ascii", "replace") if "md5checksum.hex" in names else None
            if sizes[0] is not None:
                try:
                    dims = [int(v) if v is not None else 1 for v in sizes]
                except ValueError:
                    raise InputError(path, f"X3P MatrixDimension is not whole numbers: {sizes}") from None
                check_declared_size(path, dims)
                need = int(np.prod(dims, dtype=object)) * _X3P_ITEMSIZE.get(ztype, 8)
                if data_info is not None and data_info.file_size > need + 1024:
                    raise InputError(path, f"X3P point data holds {data_info.file_size} bytes, the header declares "
                                           f"{' x '.join(map(str, dims))} values ({need} bytes)")
            for a, text in incs.items():
                if kinds[a] == "I" or text is not None:
                    try:
                        inc = float(text) if text is not None else float("nan")
                    except ValueError:
                        inc = float("nan")
                    if not (np.isfinite(inc) and inc > 0):
                        raise InputError(path, f"X3P axis {a} declares increment {text!r}; the lateral pitch must "
                                               "be a positive number of metres")
            if md5 and data_info is not None:
                got = hashlib.md5(z.read(link)).hexdigest()
                if got.lower() != md5.lower():
                    warn_input(path, f"X3P point data MD5 {got} does not match the checksum in main.xml ({md5}); "
                                     "the file was altered or damaged")
    except (zipfile.BadZipFile, ET.ParseError, KeyError, OSError) as e:
        raise InputError(path, f"not a readable X3P container ({type(e).__name__}: {_one_line(e)})") from None
    if hex_text:
        want = hex_text.split()[0].lower() if hex_text.split() else ""
        if want and want != hashlib.md5(xml).hexdigest():
            warn_input(path, f"X3P main.xml MD5 does not match md5checksum.hex ({want}); the file was altered")


def _x3p_folder_prefix(path: Path) -> str:
    """For a zip whose X3P members (main.xml, bindata/...) sit in one subfolder (an X3P folder
    zipped with its folder), that folder's name with a trailing slash; "" otherwise."""
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (OSError, zipfile.BadZipFile):
        return ""
    if "main.xml" in names:
        return ""
    mains = [n for n in names if n.endswith("/main.xml") and not n.startswith("__MACOSX/")]
    return mains[0][:-len("main.xml")] if len(mains) == 1 else ""


def _read_zipped_x3p_folder(path: Path, prefix: str, pitch: tuple | None, channel) -> Relief:
    """Read the X3P inside folder `prefix` of the zip `path`: its members are repacked at the root of
    a temporary .x3p (the layout ISO 25178-72 requires) and read as usual; the relief names `path`."""
    import dataclasses
    import tempfile
    with tempfile.TemporaryDirectory(prefix="relief-x3p-") as tmp:
        flat = Path(tmp) / (Path(prefix.rstrip("/")).name + ".x3p")
        with zipfile.ZipFile(path) as z, zipfile.ZipFile(flat, "w", zipfile.ZIP_DEFLATED) as out:
            for info in z.infolist():
                if info.filename.startswith(prefix) and not info.is_dir():
                    check_declared_size(path, (info.file_size // 8 + 1,), f"member {info.filename!r}")
                    out.writestr(info.filename[len(prefix):], z.read(info))
        relief = read_relief(flat, pitch_m=pitch, channel=channel)
    meta = {**relief.metadata, "container": f"X3P folder {prefix!r} inside the zip"}
    return dataclasses.replace(relief, source=str(path), metadata=meta)


def _x3p_stated_periodic(path: Path) -> bool | None:
    """An X3P that `write_relief` wrote states its periodic flag in Record2/Comment: True or False;
    None for any other file (it states nothing)."""
    if path.suffix.lower() != ".x3p":
        return None
    try:
        with zipfile.ZipFile(path) as z:
            xml = z.read("main.xml").decode("utf-8", errors="replace")
    except (OSError, KeyError, zipfile.BadZipFile):
        return None
    for flag in (True, False):
        if f"written by relief_bsdf; periodic={'true' if flag else 'false'};" in xml:
            return flag
    return None


# ---------------------------------------------------------------- ISO 25178-71 SDF

_SDF_DTYPES = {0: "u1", 1: "<u2", 2: "<i2", 3: "<f8", 5: "<i4", 6: "<u4", 7: "<f4"}
_SDF_KEYS = ("ManufacID", "CreateDate", "ModDate", "NumPoints", "NumProfiles", "Xscale", "Yscale",
             "Zscale", "Zresolution", "Compression", "DataType", "CheckType")


def _read_sdf(path: Path, pitch: tuple | None) -> Relief:
    """ISO 25178-71 (formerly BCR/EUR 15178) surface data file, ASCII or binary.

    ASCII: magic 'aISO-1.0'/'aBCR-1.0', 'key = value' header lines, a '*' line, the
    NumPoints x NumProfiles values profile by profile (x fastest), a '*' line and an
    optional trailer.  Binary: magic 'bISO-1.0'/'bBCR-1.0' and a packed little-endian
    header (ManufacID 10 chars, CreateDate 12, ModDate 12, NumPoints u16, NumProfiles
    u16, X/Y/Zscale f64, Zresolution f64, Compression u8, DataType u8, CheckType u8),
    then the data.  Heights = value * Zscale (metres), pitch = Xscale, Yscale (metres).
    """
    raw = path.read_bytes()
    magic = raw[:8].decode("latin-1")
    if magic not in ("aISO-1.0", "aBCR-1.0", "bISO-1.0", "bBCR-1.0"):
        raise InputError(path, f"not an ISO 25178-71 SDF file (magic {magic!r}, expected aISO-1.0 or bISO-1.0)")
    hdr: dict = {}
    if magic[0] == "a":
        text = raw.decode("latin-1")
        parts = text.split("\n")
        i = 1
        while i < len(parts) and parts[i].strip() != "*":
            line = parts[i].strip()
            if "=" in line:
                k, v = line.split("=", 1)
                hdr[k.strip()] = v.strip()
            i += 1
        if i >= len(parts):
            raise InputError(path, "SDF header has no terminating '*' line (truncated file?)")
        values: list[str] = []
        i += 1
        while i < len(parts) and parts[i].strip() != "*":
            values += parts[i].split()
            i += 1
        for k in ("NumPoints", "NumProfiles", "Xscale", "Yscale", "Zscale"):
            if k not in hdr:
                raise InputError(path, f"SDF header lacks {k}")
        try:
            nx, ny = int(hdr["NumPoints"]), int(hdr["NumProfiles"])
            xs, ys, zs = float(hdr["Xscale"]), float(hdr["Yscale"]), float(hdr["Zscale"])
        except ValueError as e:
            raise InputError(path, f"SDF header value is not a number ({e})") from None
        check_declared_size(path, (ny, nx))
        if len(values) < nx * ny:
            raise InputError(path, f"SDF data has {len(values)} values, header promises {nx} x {ny} = {nx * ny} "
                                   "(truncated file?)")
        vals = _sdf_ascii_values(path, values[:nx * ny], nx)
    else:
        fmt = "<8s10s12s12sHHddddBBB"
        size = struct.calcsize(fmt)
        if len(raw) < size:
            raise InputError(path, "binary SDF header is truncated")
        fields = struct.unpack(fmt, raw[:size])
        hdr = dict(zip(_SDF_KEYS, fields[1:]))
        nx, ny = hdr["NumPoints"], hdr["NumProfiles"]
        check_declared_size(path, (ny, nx))
        xs, ys, zs = hdr["Xscale"], hdr["Yscale"], hdr["Zscale"]
        dt = _SDF_DTYPES.get(hdr["DataType"])
        if dt is None:
            raise InputError(path, f"SDF DataType {hdr['DataType']} unknown (expected one of {sorted(_SDF_DTYPES)})")
        need = nx * ny * np.dtype(dt).itemsize
        if len(raw) - size < need:
            raise InputError(path, f"SDF data is truncated: {len(raw) - size} bytes for {need} expected")
        vals = np.frombuffer(raw, dtype=dt, count=nx * ny, offset=size).astype(float)
        hdr = {k: (v.decode("latin-1").strip("\x00 ") if isinstance(v, bytes) else v) for k, v in hdr.items()}
    if nx < 1 or ny < 1:
        raise InputError(path, f"SDF grid {nx} x {ny} is empty")
    h = vals.reshape(ny, nx) * zs
    meta = {"reader": "relief_bsdf ISO 25178-71 SDF", "file_unit": "m", "sdf_magic": magic,
            "manufacturer": str(hdr.get("ManufacID", ""))}
    if pitch is not None:
        dx, dy = pitch
        meta["pitch_source"] = "argument"
    else:
        dx, dy = xs, ys
        meta["pitch_source"] = "file"
        if ny > 1:
            _check_pitch(dx, dy, path, "the SDF Xscale/Yscale")
    return _finish(path, h, dx, dy, False, meta)


def _sdf_ascii_values(path: Path, values: list[str], nx: int) -> np.ndarray:
    """ASCII SDF values as floats (BAD -> NaN); InputError naming the first token that is not a number."""
    out = np.empty(len(values))
    for i, v in enumerate(values):
        if v.upper() == "BAD":
            out[i] = np.nan
            continue
        try:
            out[i] = float(v)
        except ValueError:
            raise InputError(path, f"SDF value {v[:40]!r} (point {i % nx}, profile {i // nx}) is not a number "
                                   "(nor BAD)") from None
    return out


# ====================================================================== writing


def _provenance(relief: Relief) -> dict:
    return {"source": relief.source, "history": list(relief.history), "periodic": relief.periodic,
            "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def write_relief(path: str | Path, relief: Relief, x3p_data_type: str = "D") -> Path:
    """Write a relief (atomically) as .npz, .x3p, .exr or .tif (float32 + sidecar JSON).

    .npz keeps float64 heights, pitch, the periodic flag and provenance; .x3p is an
    ISO 25178-72 container with float64 ("D", or "F" = float32 with x3p_data_type) heights in metres (NaN = invalid);
    .exr/.tif store float32 heights in metres, one channel "Z", with the pitch in a
    sidecar ``<name>.json`` (and, for EXR, in the header as relief:dx_m/dy_m).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        buf = io.BytesIO()
        np.savez_compressed(buf, heights=relief.heights_m, dx=np.float64(relief.dx_m), dy=np.float64(relief.dy_m),
                            periodic=np.bool_(relief.periodic), info_json=np.str_(json.dumps(_provenance(relief))))
        return write_bytes_atomic(path, buf.getvalue())
    if suffix == ".x3p":
        return write_bytes_atomic(path, _x3p_bytes(relief, x3p_data_type))
    if suffix in IMAGE_SUFFIXES:
        return _write_image(path, relief)
    raise InputError(path, f"cannot write {suffix or 'files without suffix'}; "
                           f"choose one of {', '.join(WRITE_SUFFIXES)}")


def _write_image(path: Path, relief: Relief) -> Path:
    from relief_bsdf.io import oiio
    OIIO = oiio.load()
    ny, nx = relief.shape
    data = np.ascontiguousarray(relief.heights_m.astype(np.float32)[:, :, None])
    spec = OIIO.ImageSpec(nx, ny, 1, "float")
    spec.channelnames = ("Z",)
    spec.attribute("relief:dx_m", repr(float(relief.dx_m)))
    spec.attribute("relief:dy_m", repr(float(relief.dy_m)))
    spec.attribute("relief:z_unit", "m")
    spec.attribute("relief:periodic", "true" if relief.periodic else "false")
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    with atomic_path(path) as tmp:
        out = OIIO.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"cannot write {path}: {OIIO.geterror()}")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {OIIO.geterror()}")
    side = {"dx_m": float(relief.dx_m), "dy_m": float(relief.dy_m), "z_unit": "m", "periodic": relief.periodic,
            "source": relief.source, "history": list(relief.history)}
    write_text_atomic(path.with_name(path.name + ".json"), json.dumps(side, indent=1) + "\n")
    return path


_X3P_FLOAT_TYPES = {"D": "<f8", "F": "<f4"}


def _x3p_bytes(relief: Relief, data_type: str = "D") -> bytes:
    """ISO 25178-72 X3P: zip with main.xml, bindata/data.bin (x fastest) and md5checksum.hex.

    data_type "D" (float64, default) or "F" (float32: half the size, 7 significant digits, i.e.
    sub-picometre on micrometre reliefs)."""
    if data_type not in _X3P_FLOAT_TYPES:
        raise InputError("x3p_data_type", f"{data_type!r} is not a float X3P data type (expected 'D' or 'F')")
    ny, nx = relief.shape
    data = np.ascontiguousarray(relief.heights_m, dtype=_X3P_FLOAT_TYPES[data_type]).tobytes()   # row y, x fastest
    data_md5 = hashlib.md5(data).hexdigest().upper()
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S+00:00")
    comment = (f"written by relief_bsdf; periodic={'true' if relief.periodic else 'false'}; "
               "heights in metres, NaN = invalid point; "
               f"source: {relief.source}; history: {'; '.join(relief.history) or 'none'}")
    comment = comment.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    xml = f"""<?xml version="1.0" encoding="UTF-8" standalone="no" ?>
<p:ISO5436_2 xmlns:p="http://www.opengps.eu/2008/ISO5436_2" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:schemaLocation="http://www.opengps.eu/2008/ISO5436_2 http://www.opengps.eu/2008/ISO5436_2/ISO5436_2.xsd">
  <Record1>
    <Revision>ISO5436 - 2000</Revision>
    <FeatureType>SUR</FeatureType>
    <Axes>
      <CX>
        <AxisType>I</AxisType>
        <DataType>D</DataType>
        <Increment>{float(relief.dx_m)!r}</Increment>
        <Offset>0.0</Offset>
      </CX>
      <CY>
        <AxisType>I</AxisType>
        <DataType>D</DataType>
        <Increment>{float(relief.dy_m)!r}</Increment>
        <Offset>0.0</Offset>
      </CY>
      <CZ>
        <AxisType>A</AxisType>
        <DataType>{data_type}</DataType>
        <Increment>1.0</Increment>
        <Offset>0.0</Offset>
      </CZ>
    </Axes>
  </Record1>
  <Record2>
    <Date>{now}</Date>
    <Creator>relief_bsdf</Creator>
    <Instrument>
      <Manufacturer>relief_bsdf</Manufacturer>
      <Model>{"synthetic" if relief.periodic else "processed height map"}</Model>
      <Serial>not available</Serial>
      <Version>1</Version>
    </Instrument>
    <CalibrationDate>{now}</CalibrationDate>
    <ProbingSystem>
      <Type>Software</Type>
      <Identification>relief_bsdf</Identification>
    </ProbingSystem>
    <Comment>{comment}</Comment>
  </Record2>
  <Record3>
    <MatrixDimension>
      <SizeX>{nx}</SizeX>
      <SizeY>{ny}</SizeY>
      <SizeZ>1</SizeZ>
    </MatrixDimension>
    <DataLink>
      <PointDataLink>bindata/data.bin</PointDataLink>
      <MD5ChecksumPointData>{data_md5}</MD5ChecksumPointData>
    </DataLink>
  </Record3>
  <Record4>
    <ChecksumFile>md5checksum.hex</ChecksumFile>
  </Record4>
</p:ISO5436_2>
""".encode("utf-8")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("main.xml", xml)
        z.writestr("bindata/data.bin", data)
        z.writestr("md5checksum.hex", f"{hashlib.md5(xml).hexdigest()} *main.xml\n")
    return buf.getvalue()
