"""`relief fill RELIEF -o OUT.(x3p|npz)`: fill the missing points of a height map.

Method (surface.relief.Relief.fill_holes): harmonic (Laplace) interpolation; each filled point
is the mean of its four neighbours, the valid points around a hole held fixed, solved exactly.
It assumes the surface inside a hole is the smoothest one that meets the hole's rim: it adds
no roughness of its own, so large holes under-state the roughness there (the share filled is
printed; crop such regions away instead with `relief crop`).  The step is kept in the written
file's history.
"""
from __future__ import annotations

import argparse

def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("fill", help="fill the missing points of a height map (harmonic interpolation)",
                       description=__doc__.split("\n", 2)[2].strip())
    p.add_argument("relief", metavar="RELIEF", help="height map (.x3p, .gwy, .sur, .sdf, .tif, .exr, .npz, ...)")
    p.add_argument("--max-gap-px", type=int, default=None, metavar="N",
                   help="fill only holes no wider than N points (distance to the nearest valid point); "
                        "wider ones stay missing (default: fill every hole)")
    p.add_argument("--pitch-um", default=None, help="lateral pitch DX[,DY] in um for files without one (images)")
    p.add_argument("-o", "--out", required=True, help="output height map (.x3p or .npz)")
    from relief_bsdf.cli.maps import add_relief_args
    add_relief_args(p)
    return p


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.cli.cmd_info import _pitch
    from relief_bsdf.cli.maps import relief_options, show_prepared
    from relief_bsdf.jobs import FillJob, run_fill
    r = run_fill(FillJob(Path(args.relief), Path(args.out), max_gap_px=args.max_gap_px, pitch_m=_pitch(args.pitch_um),
                         options=relief_options(args)))
    show_prepared(r.relief, args)
    total = r.relief.heights_m.size
    missing, left = r.missing, r.left
    if missing == 0:
        print(f"nothing to fill: every one of the {total} points is valid; wrote {args.out} unchanged")
        return 0
    print(f"filled {missing - left} of {total} points ({(missing - left) / total:.2%}) by harmonic (Laplace) "
          f"interpolation" + (f"; {left} points in holes wider than {args.max_gap_px} px stay missing"
                              if left else "") + f"; wrote {args.out}")
    return 0
