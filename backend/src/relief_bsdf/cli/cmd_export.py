"""`relief export TABLE.h5 --format recording-csv|is-bsdf [--from outside|inside] -o OUT`."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("export", help="export a BSDF table as recording-layout CSV or Zemax IS-BSDF",
                       description="recording-csv: every tabulated cell value as a recording.csv row (cell "
                                   "centres, sigma empty when unknown); the delta-like specular parts are "
                                   "listed in comments. is-bsdf: Zemax/Radiant tabulated .bsdf, one file per "
                                   "side (BRDF, BTDF) and wavelength.")
    p.add_argument("table", help="BSDF table (.h5)")
    p.add_argument("--format", required=True, choices=("recording-csv", "is-bsdf"))
    p.add_argument("--from", dest="incident_from", choices=("outside", "inside"),
                   help="which table (light arriving from outside or inside); default: outside if present")
    p.add_argument("-o", "--out", required=True, help="output file")
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


def run(args) -> int:
    from relief_bsdf.io.hdf5 import load_tables, table_for
    from relief_bsdf.errors import InputError
    tables = load_tables(args.table)
    if args.incident_from:
        table = table_for(tables, args.incident_from, args.table)
    else:
        table = next((t for t in tables if t.incident_from == "outside"), tables[0])
    out = Path(args.out)
    if args.format == "recording-csv":
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
        return 0
    from relief_bsdf.io.isbsdf import export_isbsdf
    paths = export_isbsdf(table, out)
    for p in paths:
        print(f"wrote {p}")
    return 0
