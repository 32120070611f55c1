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
    from relief_bsdf.jobs.export import FORMATS
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


def run(args) -> int:
    from relief_bsdf.jobs import ExportJob, run_export
    r = run_export(ExportJob(Path(args.table), Path(args.out), args.format, incident_from=args.incident_from,
                             btdf_centre=args.btdf_centre, structure=args.structure, depth=args.depth,
                             wavelength_nm=args.wavelength_nm, n=args.n))
    for line in r.notes:
        print(line, file=sys.stderr)
    for line in r.lines:
        print(line)
    return 0
