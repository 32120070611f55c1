"""`relief export TABLE --format recording-csv|is-bsdf|radiance-xml|hdf5 [--from outside|inside] -o OUT`.

TABLE may be a project table (.h5) or a measured / exchanged file (IS-BSDF .bsdf, WINDOW/Radiance
.xml, RPC Photonics text): io.tables reads them all as BsdfTables.  A measured plate file (RPC text, an
IS-BSDF file without this project's tags) exported as recording-csv gives its own readings as rows
(io.measured: the file's points in the project's frame, sigma by its documented model).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

FORMATS = ("recording-csv", "is-bsdf", "radiance-xml", "hdf5")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("export", help="export a BSDF table: recording CSV, Zemax IS-BSDF, Radiance XML or HDF5",
                       description="recording-csv: every tabulated cell value as a recording.csv row (cell "
                                   "centres, sigma empty when unknown); the delta-like specular parts are "
                                   "listed in comments. is-bsdf: Zemax OpticStudio tabulated .bsdf, one file per "
                                   "scatter type (BRDF, BTDF) and wavelength, BTDF centred on the refracted ray. "
                                   "radiance-xml: LBNL/WINDOW XML BSDF of both sides (front = light from outside), "
                                   "Klems full basis or a tensor tree, as Radiance, WINDOW and EnergyPlus read it. "
                                   "hdf5: the project's table file (e.g. to bake a measured file in Blender).")
    p.add_argument("table", help="BSDF table (.h5, .bsdf IS-BSDF, .xml WINDOW/Radiance)")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--from", dest="incident_from", choices=("outside", "inside"),
                   help="which table (light arriving from outside or inside); default: outside if present")
    p.add_argument("-o", "--out", required=True, help="output file")
    p.add_argument("--btdf-centre", choices=("refracted", "undeviated"), default="refracted",
                   help="is-bsdf: centre of the BTDF's specular coordinates (default refracted, as OpticStudio)")
    p.add_argument("--structure", choices=("klems", "tensor-tree"), default="klems",
                   help="radiance-xml: Klems full basis (default) or a uniform tensor tree")
    p.add_argument("--depth", type=int, default=None,
                   help="radiance-xml tensor tree: 2^depth cells per axis (default: from the narrowest lobe, "
                        "4-6 isotropic, 4-5 otherwise)")
    p.add_argument("--wavelength-nm", type=float, default=None,
                   help="radiance-xml: the wavelength written (nearest tabulated; default 555). "
                        "Reading an IS-BSDF file that does not state its wavelength: its wavelength")
    p.add_argument("--n", type=float, default=None,
                   help="refractive index of the dielectric, for a measured file that does not state it "
                        "(recorded as the table's material, needed to bake it; centres an untagged BTDF)")
    return p


def table_rows(table):
    """Recording with one row per (wavelength, incidence, side, scatter cell) of the table."""
    from relief_bsdf.io.recording import Recording
    W, I, P, K, S, A = table.values_per_sr.shape
    grids = np.meshgrid(table.wavelength_nm, table.theta_i_deg, table.phi_i_deg % 360.0, np.arange(K),
                        table.theta_s_deg, table.phi_s_deg % 360.0, indexing="ij")
    wl, ti, pi, k, ts, ps = (g.ravel() for g in grids)
    sigma = table.sigma_per_sr.ravel() if table.sigma_per_sr is not None else np.full(wl.size, np.nan)
    return Recording(wavelength_nm=wl, theta_i_deg=ti, phi_i_deg=pi, side=np.where(k == 0, "R", "T"),
                     theta_s_deg=ts, phi_s_deg=ps, bsdf_sr=table.values_per_sr.ravel().astype(float),
                     sigma_sr=sigma)


def _write_recording_csv(args, table, out: Path) -> None:
    from relief_bsdf.errors import InputError
    from relief_bsdf.io.recording import write_recording
    rec = table_rows(table)
    if np.any(~np.isfinite(rec.bsdf_sr)) or np.any(rec.bsdf_sr < 0):
        raise InputError(args.table, "table holds negative or non-finite BSDF values; cannot write a recording")
    comments = [f"exported from {args.table} (method {table.method}, light from {table.incident_from})",
                "rows are scatter-cell centres; values are cell averages in 1/sr",
                "specular (delta) parts are not rows: wavelength_nm, theta_i_deg, phi_i_deg, specular_R, specular_T"]
    for w, wl in enumerate(table.wavelength_nm):
        for i, ti in enumerate(table.theta_i_deg):
            for p, pi in enumerate(table.phi_i_deg):
                comments.append(f"specular {wl:g}, {ti:g}, {pi % 360:g}, {table.specular_R[w, i, p]:.6g}, "
                                f"{table.specular_T[w, i, p]:.6g}")
    write_recording(out, rec, comments=comments)
    print(f"wrote {out}: {len(rec)} rows ({table.wavelength_nm.size} wavelength(s), "
          f"{table.theta_i_deg.size * table.phi_i_deg.size} incidence(s), light from {table.incident_from})")


def _azimuth_notes(tables, fmt: str) -> None:
    """One warning line when the file will describe an isotropic boundary although the table is not:
    a table with one incidence azimuth is turned to every orientation by its consumers, which is
    only right when its normal-incidence lobe is round (`lobe_anisotropy` > 1.2: it is not)."""
    from relief_bsdf.io.radiance_xml import lobe_anisotropy
    for t in tables:
        ratio = lobe_anisotropy(t)
        if t.is_isotropic and ratio is not None and ratio > 1.2:
            print(f"relief: warning: {fmt} from one incidence azimuth describes an isotropic boundary, but the "
                  f"table's normal-incidence lobe is {ratio:.2g}x wider along one axis; the azimuthal dependence "
                  "is dropped (reconstruct with --phi-i-deg 0,45,90,135,... to keep it)", file=sys.stderr)
            return


def run(args) -> int:
    from relief_bsdf.errors import InputError
    from relief_bsdf.io.tables import pick_table, read_table_file
    out = Path(args.out)
    if args.depth is not None and not 1 <= args.depth <= 8:
        raise InputError("--depth", f"tensor-tree depth must be 1..8, got {args.depth}")
    from relief_bsdf.io.measured import export_rows, is_measured
    if args.format == "recording-csv" and Path(args.table).is_file() and is_measured(args.table):
        export_rows(args.table, out, args.wavelength_nm, args.n)     # the file's own readings (io.measured)
        return 0
    tables = read_table_file(args.table, wavelength_nm=args.wavelength_nm if args.format != "radiance-xml" else None,
                             n=args.n)
    if args.format == "radiance-xml":
        from relief_bsdf.io.radiance_xml import write_radiance_xml
        notes: list = []
        write_radiance_xml(out, tables, wavelength_nm=args.wavelength_nm, structure=args.structure,
                           depth=args.depth, notes=notes)
        _azimuth_notes(tables, args.format)
        from relief_bsdf.io.radiance_xml import checkbsdf_reciprocity
        rec = checkbsdf_reciprocity(out)
        if rec:
            notes.append("note: checkBSDF reciprocity, mean (max) %: " + ", ".join(
                f"{k} {v[1]:.1f} ({v[2]:.0f})" for k, v in rec.items())
                + f" (transmission differs by n^2 by design between the two media; a table of "
                f"{len(tables[0].theta_i_deg)} incidences, interpolated between them, is only as reciprocal as "
                "that interpolation: tabulate every 5-10 deg to bring it down; io/radiance_xml doc)")
        for line in notes:
            print(f"relief: {line}", file=sys.stderr)
        print(f"wrote {out} ({args.structure}, front = light from outside, back = light from inside)")
        return 0
    if args.format == "hdf5":
        from relief_bsdf.io.hdf5 import save_tables
        save_tables(out, tables)
        print(f"wrote {out}: {len(tables)} table(s) ({', '.join(t.incident_from for t in tables)})")
        return 0
    table = pick_table(tables, args.incident_from, args.table)
    if args.format == "recording-csv":
        _azimuth_notes([table], args.format)
        _write_recording_csv(args, table, out)
        return 0
    _azimuth_notes([table], args.format)
    from relief_bsdf.io.isbsdf import export_isbsdf
    for p in export_isbsdf(table, out, btdf_centre=args.btdf_centre):
        print(f"wrote {p}")
    return 0
