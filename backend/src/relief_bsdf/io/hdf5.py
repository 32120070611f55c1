"""Self-describing HDF5 storage of BSDF tables (h5py).

Layout (format "relief-bsdf-table/1"): the root carries `format` and `tables`
(comma-separated group names, e.g. "outside,inside"); each group holds one
`BsdfTable` with its axes as datasets (each with a `units` attribute), the values
(chunked per incidence, gzip-compressed), the per-incidence specular and lost
fractions, and JSON metadata attributes (method, material, relief, metadata).
"""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from relief_bsdf.io.atomic import atomic_path
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError

FORMAT = "relief-bsdf-table/1"
_AXES = {"wavelength_nm": "nm", "theta_i_deg": "deg", "phi_i_deg": "deg",
         "theta_s_edges_deg": "deg", "phi_s_edges_deg": "deg"}
_PER_INCIDENCE = ("specular_R", "specular_T", "lost")
_OPTIONAL = ("sigma_per_sr", "mueller_per_sr", "specular_mueller_R", "specular_mueller_T")


def save_tables(path: str | Path, tables: list[BsdfTable], compression: int = 4) -> Path:
    """Write tables (one per side of incidence) atomically to `path`."""
    names = [t.incident_from for t in tables]
    if len(set(names)) != len(names):
        raise ValueError("at most one table per side of incidence")
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["tables"] = ",".join(names)
            for t in tables:
                g = f.create_group(t.incident_from)
                for ax, unit in _AXES.items():
                    d = g.create_dataset(ax, data=getattr(t, ax))
                    d.attrs["units"] = unit
                chunks = (1, 1, 1) + t.values_per_sr.shape[3:]
                d = g.create_dataset("values_per_sr", data=t.values_per_sr.astype(np.float32), chunks=chunks,
                                     compression="gzip", compression_opts=compression, shuffle=True)
                d.attrs["units"] = "1/sr"
                d.attrs["axes"] = "wavelength_nm,theta_i_deg,phi_i_deg,side(R,T),theta_s,phi_s"
                d.attrs["meaning"] = "Nicodemus BSDF averaged over each scatter cell in projected solid angle"
                for opt in _OPTIONAL:
                    arr = getattr(t, opt)
                    if arr is None:
                        continue
                    ch = chunks + arr.shape[6:] if arr.ndim >= 6 else None   # per incidence, like the values
                    s = g.create_dataset(opt, data=arr.astype(np.float32), chunks=ch,
                                         compression="gzip", compression_opts=compression, shuffle=True)
                    s.attrs["units"] = "1/sr" if opt.endswith("per_sr") else "fraction of incident power"
                for name in _PER_INCIDENCE:
                    d = g.create_dataset(name, data=getattr(t, name))
                    d.attrs["units"] = "fraction of incident power"
                g.attrs["incident_from"] = t.incident_from
                g.attrs["method"] = t.method
                for key in ("material", "relief", "metadata"):
                    g.attrs[key] = json.dumps(getattr(t, key), default=_json_default)
    return Path(path)


def load_tables(path: str | Path) -> list[BsdfTable]:
    """Read every table in an HDF5 file written by `save_tables`.

    Anything that is not such a file (another HDF5 layout, missing or mistyped groups,
    datasets or attributes, inconsistent shapes) raises an `InputError` naming the file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a regular file (a folder?); expected an HDF5 BSDF table (.h5)")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(path, f"not a readable HDF5 file ({e})") from None
    with f:
        if f.attrs.get("format") != FORMAT:
            raise InputError(path, f"not a relief BSDF table (format attribute {f.attrs.get('format')!r}, "
                             f"expected {FORMAT!r})")
        listed = f.attrs.get("tables")
        if not isinstance(listed, (str, bytes)) or not str(listed).strip():
            raise InputError(path, "not a relief BSDF table: the root attribute 'tables' (comma-separated group "
                                   "names) is missing or empty")
        listed = listed.decode() if isinstance(listed, bytes) else listed
        return [_load_group(f, path, name.strip()) for name in listed.split(",")]


def _load_group(f: h5py.File, path: Path, name: str) -> BsdfTable:
    if name not in f or not isinstance(f[name], h5py.Group):
        raise InputError(path, f"table group {name!r} listed but missing")
    g = f[name]
    from relief_bsdf.io.heightmaps import check_declared_size
    for key, ds in g.items():            # declared shapes bounded before any dataset is read (io.heightmaps)
        if isinstance(ds, h5py.Dataset):
            check_declared_size(path, ds.shape or (), f"table {name!r} dataset {key!r}",
                                per_pixel=16 if "mueller" in key else 1)
    try:
        kw = {ax: np.asarray(g[ax][()], dtype=float) for ax in _AXES}
        kw.update({n: np.asarray(g[n][()], dtype=float) for n in _PER_INCIDENCE})
        kw.update({n: g[n][()].astype(np.float64) for n in _OPTIONAL if n in g})
        return BsdfTable(values_per_sr=np.asarray(g["values_per_sr"][()], dtype=np.float64),
                         incident_from=str(g.attrs["incident_from"]), method=str(g.attrs["method"]),
                         material=json.loads(g.attrs["material"]), relief=json.loads(g.attrs["relief"]),
                         metadata=json.loads(g.attrs["metadata"]), **kw)
    except KeyError as e:
        raise InputError(path, f"table {name!r} lacks {e}") from None
    except (ValueError, TypeError, IndexError, AttributeError, OSError) as e:
        raise InputError(path, f"table {name!r} is malformed ({type(e).__name__}: {str(e)[:160]})") from None


def table_for(tables: list[BsdfTable], incident_from: str, where: str | Path = "table") -> BsdfTable:
    for t in tables:
        if t.incident_from == incident_from:
            return t
    raise InputError(where, f"no table for light arriving from {incident_from}")


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
