"""`relief plot`: in-plane BSDF curves per incidence angle and polar maps of a table, to PNG."""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("plot", help="plot a BSDF table (in-plane curves and polar maps) to PNG",
                       description="In-plane BSDF curves per incidence angle (log scale, signed scatter angle, "
                                   "like the paper's figures 4 and 9) and polar maps of the scatter hemisphere.")
    p.add_argument("table", metavar="TABLE.h5")
    p.add_argument("-o", "--out", default=None, help="output PNG (default: TABLE.png beside the table)")
    p.add_argument("--side", choices=("R", "T"), default=None, help="only reflection or transmission (default both)")
    p.add_argument("--from", dest="incident_from", choices=("outside", "inside"), default=None,
                   help="which table of the file (default: the first)")
    p.add_argument("--wavelength-nm", type=float, default=None, help="wavelength to show (nearest tabulated)")
    p.add_argument("--compare", action="append", default=[], metavar="OTHER.h5",
                   help="overlay the in-plane curves of another table (repeatable; same --from side)")
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
        hz = " ".join(f"{rows[(iw * len(table.theta_i_deg) + it) * P + ip].haze:.4f}"
                      for it in range(len(table.theta_i_deg)))
        lines.append(f"{wl:g} nm: specular R {sr} | specular T {st} | haze (>2.5 deg) {hz}")
    head = ("specular deltas (not drawn in the cells) per theta_i "
            + ", ".join(f"{t:g}" for t in table.theta_i_deg) + " deg")
    return "\n".join([head] + lines)


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.io.hdf5 import load_tables, table_for
    from relief_bsdf.errors import InputError
    from relief_bsdf.report.plots import save_figure, table_figure
    path = Path(args.table)
    tables = load_tables(path)
    table = table_for(tables, args.incident_from, path) if args.incident_from else tables[0]
    full = table
    table = table.select(args.wavelength_nm)
    out = Path(args.out) if args.out else path.with_suffix(".png")
    if out.suffix.lower() != ".png":
        raise InputError(out, "the plot is written as PNG; give a .png file name")
    sides = (args.side,) if args.side else ("R", "T")
    if args.compare:
        from relief_bsdf.report.plots import compare_figure
        others = []
        for o in args.compare:
            ts = load_tables(o)
            others.append(table_for(ts, table.incident_from, o))
        labels = [path.stem] + [Path(o).stem for o in args.compare]
        save_figure(compare_figure([table] + others, labels, sides), out)
    else:
        fig = table_figure(table, sides)
        fig.text(0.01, 0.005, specular_note(full), fontsize=7, family="monospace", va="bottom")
        save_figure(fig, out)
    print(f"wrote {out}")
    return 0
