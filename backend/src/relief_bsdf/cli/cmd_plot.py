"""`relief plot A [B ...]`: in-plane BSDF curves and polar maps of a table, or several tables overlaid.

Any table file works (.h5, measured IS-BSDF .bsdf, WINDOW/Radiance .xml, RPC Photonics text; io.tables),
so a measured file can be drawn beside a reconstruction: `relief plot boundary.h5 measured_BTDF.bsdf`.
An RPC file alone is drawn as the file holds it (io.measured.measured_figure: cuts in and across the
plane of incidence, polar map).
"""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("plot", help="plot BSDF tables (in-plane curves and polar maps) to PNG",
                       description="One table: in-plane BSDF curves per incidence angle (log scale, signed "
                                   "scatter angle, like the paper's figures 4 and 9, delta parts marked) and "
                                   "polar maps of the scatter hemisphere. Several tables: their in-plane curves "
                                   "overlaid, evaluated at the first table's incidence angles.")
    p.add_argument("tables", metavar="TABLE", nargs="+",
                   help="BSDF table files (.h5, .bsdf, .xml) or RPC Photonics text files")
    p.add_argument("-o", "--out", default=None, help="output PNG (default: the first TABLE's name with .png)")
    p.add_argument("--side", choices=("R", "T"), default=None, help="only reflection or transmission (default both)")
    p.add_argument("--from", dest="incident_from", choices=("outside", "inside"), default=None,
                   help="which table of each file (default: outside if present)")
    p.add_argument("--wavelength-nm", type=float, default=None,
                   help="wavelength to show (nearest tabulated); also the wavelength of an IS-BSDF file "
                        "that does not state it")
    p.add_argument("--compare", action="append", default=[], metavar="OTHER",
                   help="another table to overlay (repeatable; same as naming it after the first)")
    p.add_argument("--n", type=float, default=None,
                   help="refractive index of the dielectric, for a measured file that does not state it "
                        "(recorded as the table's material, needed to bake it; centres an untagged BTDF)")
    return p


def specular_note(table, ip: int = 0) -> str:
    """The coherent (specular) parts, which the cells do not show, and the haze per wavelength (its
    colour dependence: a wave-optics relief is sharper in the red), one line per wavelength."""
    from relief_bsdf.bsdf.appearance import appearance
    rows = appearance(table)
    P = len(table.phi_i_deg)
    lines = []
    for iw, wl in enumerate(table.wavelength_nm):
        sr = " ".join(f"{v:.4f}" for v in table.specular_R[iw, :, ip])
        st = " ".join(f"{v:.4f}" for v in table.specular_T[iw, :, ip])
        it0 = min(range(len(table.theta_i_deg)), key=lambda k: abs(table.theta_i_deg[k]))
        hz = rows[(iw * len(table.theta_i_deg) + it0) * P + ip].haze
        lines.append(f"{wl:g} nm: specular R {sr} | specular T {st} | haze (ASTM D1003, plate) {hz:.4f}")
    head = ("specular deltas (not drawn in the cells) per theta_i "
            + ", ".join(f"{t:g}" for t in table.theta_i_deg) + " deg")
    return "\n".join([head] + lines)


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.errors import InputError
    from relief_bsdf.report.plots import compare_figure, save_figure, table_figure
    paths = [Path(p) for p in list(args.tables) + list(args.compare)]
    out = Path(args.out) if args.out else paths[0].with_suffix(".png")
    if out.suffix.lower() != ".png":
        raise InputError(out, "the plot is written as PNG; give a .png file name")
    from relief_bsdf.io.measured import measured_figure, plot_tables, read_rpc, sniff
    if len(paths) == 1 and sniff(paths[0]) == "rpc":       # a measured lobe as the file holds it
        save_figure(measured_figure(read_rpc(paths[0])), out)
        print(f"wrote {out}")
        return 0
    full = plot_tables(paths, args.wavelength_nm, args.n, args.incident_from)
    tables = [t.select(args.wavelength_nm) for t in full]
    sides = (args.side,) if args.side else ("R", "T")
    if len(tables) > 1:
        save_figure(compare_figure(tables, [p.name for p in paths], sides), out)
    else:
        fig = table_figure(tables[0], sides)
        fig.text(0.01, 0.005, specular_note(full[0]), fontsize=7, family="monospace", va="bottom")
        save_figure(fig, out)
    print(f"wrote {out}")
    return 0
