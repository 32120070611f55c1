"""Any BSDF table file as `BsdfTable`s: the project's HDF5 tables, IS-BSDF (OpticStudio / Radiant
`.bsdf`) and WINDOW/Radiance XML BSDFs.  A measured file read here can be plotted beside a
reconstruction, written as recording rows, converted to HDF5 and baked like any table.

    .h5 / .hdf5       io.hdf5.load_tables (every table in the file)
    .bsdf / .isbsdf   io.isbsdf.import_isbsdf (one table: the BRDF and/or BTDF blocks of the file
                      and, for a file named *_BRDF.bsdf or *_BTDF.bsdf, its partner beside it)
    .xml              io.radiance_xml.read_radiance_xml (the outside and inside tables)
    RPC Photonics     io.measured.measured_table (recognised by content: line 1 starts with '!!'; a
    text (any name)   plate's measured BTDF, one incidence; its wavelength must be given)

The wavelength of an IS-BSDF file is its own where it states one (a `# relief:` tag, or a header
comment `#Wavelength (nm) = 550.0`), else `wavelength_nm` (the command line's --wavelength-nm).
"""
from __future__ import annotations

from pathlib import Path

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError

SUFFIXES = (".h5", ".hdf5", ".bsdf", ".isbsdf", ".xml")


def _isbsdf_partners(path: Path) -> list[Path]:
    """The file and, for X_BRDF.bsdf / X_BTDF.bsdf, the other scatter type if it exists."""
    stem = path.stem
    for mine, other in (("_BRDF", "_BTDF"), ("_BTDF", "_BRDF")):
        if mine in stem:
            partner = path.with_name(stem.replace(mine, other) + path.suffix)
            return [path, partner] if partner.exists() else [path]
    return [path]


def read_table_file(path: str | Path, wavelength_nm: float | None = None, n: float | None = None) -> list[BsdfTable]:
    """Every table a BSDF file holds (module doc).  `wavelength_nm` is needed for IS-BSDF files that do
    not state it.  `n`, the refractive index of the dielectric (outside: n = 1), is recorded as the
    `material` of tables that have none (a bake needs it) and says where an untagged measured BTDF
    is centred (the refracted direction for that index pair; without `n`: 1 and 1, a sample in air)."""
    if n is not None and not n > 0:
        raise InputError("--n", f"refractive index must be > 0, got {n}")
    tables = _read(Path(path), wavelength_nm, n)
    if n is None:
        return tables
    from dataclasses import replace
    mat = {"inside": {"model": "constant", "n": float(n), "k": 0.0},
           "outside": {"model": "constant", "n": 1.0, "k": 0.0}}
    return [t if t.material else replace(t, material=mat) for t in tables]


def _read(path: Path, wavelength_nm: float | None, n: float | None) -> list[BsdfTable]:
    suffix = path.suffix.lower()
    from relief_bsdf.io.measured import sniff
    if path.is_file() and sniff(path) == "rpc":
        from relief_bsdf.io.measured import measured_table, read_rpc
        return [measured_table(read_rpc(path), wavelength_nm)]
    if suffix not in SUFFIXES:
        raise InputError(path, f"not a BSDF table file (expected one of {', '.join(SUFFIXES)})")
    if not path.exists():
        raise InputError(path, "file not found")
    if suffix in (".h5", ".hdf5"):
        from relief_bsdf.io.hdf5 import load_tables
        return load_tables(path)
    if suffix == ".xml":
        from relief_bsdf.io.radiance_xml import read_radiance_xml
        return read_radiance_xml(path, wavelength_nm=wavelength_nm)
    from relief_bsdf.io.isbsdf import import_isbsdf, read_isbsdf
    files = _isbsdf_partners(path)
    first = read_isbsdf(files[0])
    frm = first.relief_tag("incident_from") or "outside"
    if first.relief_tag("wavelength_nm") is None:
        from relief_bsdf.io.measured import WAVELENGTH_OPTION, header_wavelength_nm
        stated = header_wavelength_nm(first.comments)
        if stated is not None:
            wavelength_nm = stated
        elif wavelength_nm is None:
            raise InputError(path, "the IS-BSDF file does not state its wavelength (no '#Wavelength (nm) = ...' "
                                   f"line); give it with {WAVELENGTH_OPTION}")
    pair = (None, None) if n is None else ((1.0, float(n)) if frm == "outside" else (float(n), 1.0))
    return [import_isbsdf(files, wavelength_nm=wavelength_nm, n_incident=pair[0], n_transmitted=pair[1])]


def pick_table(tables: list[BsdfTable], incident_from: str | None, where: str | Path) -> BsdfTable:
    """The table for light from `incident_from` (None: outside if present, else the first)."""
    if incident_from is None:
        return next((t for t in tables if t.incident_from == "outside"), tables[0])
    for t in tables:
        if t.incident_from == incident_from:
            return t
    raise InputError(where, f"no table for light arriving from {incident_from}")
