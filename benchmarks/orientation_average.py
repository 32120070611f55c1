"""Experiment (issue 18 item 2, not a model of the package): a plate of bench_forward_accuracy with its
relief's inside table averaged over the relief's orientation, against the independent photon Monte Carlo.

The deterministic engine's loop turns the one inside table (traced at incidence azimuth 0) about the
normal for light at every azimuth.  Here the inside table is traced at 0-150 deg every 30 deg, each
turned back to the 0-deg frame (a whole number of 5-deg azimuth cells) and averaged: the table of the
relief at a random orientation.  Prints rms z of the plate with the table as is and averaged (both as
a TableFace: no inside sectors), and the transmitted rows at theta_i 60, theta_s <= 11 deg.
Session 28: dots 1.66 -> 1.27 (T 2.04 -> 1.16, R 1.17 -> 1.38), gauss_mid 0.96 -> 0.96.  Needs the
recording cached by bench_forward_accuracy.py --cache DIR (1 M photons, 0/30/60 deg).

    RELIEF_BACKEND=serial .venv/bin/python benchmarks/orientation_average.py dots --cache DIR
"""
import argparse
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_forward_accuracy as B  # noqa: E402  (the cases and plates of the forward-accuracy benchmark)
from relief_bsdf.core.index import ConstantIndex  # noqa: E402
from relief_bsdf.plate import (Experiment, FlatFace, Instrument, Plate, ReliefFace, TableFace, TableGrid,  # noqa: E402
                               simulate)
# internal pieces on purpose: the experiment compares the one 0-deg inside table with its orientation average,
# neither of which the public `plate.faces.inside_sectors` gives (session 29: the engine's sector loop for every
# order, which the dots now get through `plate.faces.azimuth_dependent`, replaced this average: dots 1.30)
from relief_bsdf.plate.sector_loop import _phi_slice  # noqa: E402
from relief_bsdf.plate.faces.derive import _reconstruct_side  # noqa: E402

if __name__ == "__main__":
    warnings.simplefilter("ignore")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="?", default="dots")
    ap.add_argument("--cache", required=True, help="bench_forward_accuracy.py's --cache folder")
    a = ap.parse_args()
    name = a.case
    case, relief = B.CASES[name], B.make_relief(name)
    rows = B.rows_of((0.0, 30.0, 60.0))
    d = np.load(f"{a.cache}/rec_{name}_1000000_0_30_60.npz")
    rec, sig = d["rec"], d["sig"]
    grid = TableGrid()
    face = ReliefFace(relief, method="ray", samples=400000, seed=0)
    ex = Experiment(Plate(case.thickness_mm * 1e-3, ConstantIndex(case.n_glass), face, FlatFace()),
                    Instrument(detector_half_angle_deg=case.half_angle_deg))
    mat = ex.plate.material
    t_out, t_in = face.tables(mat, grid, [550.0], np.unique(rows.theta_i_deg))
    phis = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0)
    sec = _reconstruct_side(face, mat, grid, (550.0,), grid.inside_incidences_deg(), "inside", None, phi_i_deg=phis)
    A = len(sec.phi_s_edges_deg) - 1
    step = 360.0 / A
    acc = {}
    for ip, p in enumerate(phis):
        one = _phi_slice(sec, ip)
        sh = int(round(p / step))
        for nm in ("values_per_sr", "mueller_per_sr", "sigma_per_sr"):
            a = getattr(one, nm)
            if a is not None:
                a = np.roll(np.asarray(a, float), -sh, axis=5)
                acc[nm] = acc.get(nm, 0) + a / len(phis)
        for nm in ("specular_R", "specular_T", "lost", "specular_mueller_R", "specular_mueller_T"):
            a = getattr(one, nm)
            if a is not None:
                acc[nm] = acc.get(nm, 0) + np.asarray(a, float) / len(phis)
    avg = replace(_phi_slice(sec, 0), phi_i_deg=np.array([0.0]),
                  **{k: (v.astype(np.float32) if k in ("values_per_sr", "mueller_per_sr", "sigma_per_sr") else v)
                     for k, v in acc.items()})
    side, ti, ts = np.asarray(rows.side).astype(str), np.asarray(rows.theta_i_deg), np.asarray(rows.theta_s_deg)
    m = (side == "T") & (ti == 60) & (ts <= 11)
    print("rec    ", " ".join(f"{v:.4f}" for v in rec[m]))
    for label, tin in (("as is", t_in), ("phi 0 of sectors", _phi_slice(sec, 0)), ("averaged", avg)):
        e2 = ex.with_plate(front=TableFace(tin, t_out))
        v = simulate(e2, rows, grid=grid).values_per_sr
        z = B.zstats(v, rec, sig, rows)
        print(f"{label:16s} rms z {z['rms_z']:.2f} (R {z['rms_z_R']:.2f}, T {z['rms_z_T']:.2f})",
              " ".join(f"{x:.4f}" for x in v[m]), flush=True)
