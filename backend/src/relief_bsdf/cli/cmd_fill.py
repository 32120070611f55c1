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

OUT_SUFFIXES = (".x3p", ".npz")


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


def check_out_suffix(out) -> None:
    from pathlib import Path
    from relief_bsdf.errors import InputError
    if Path(out).suffix.lower() not in OUT_SUFFIXES:
        raise InputError(out, "the output height map must be .x3p or .npz")


def run(args) -> int:
    from relief_bsdf.cli.cmd_info import _pitch
    from relief_bsdf.cli.maps import read_map, show_prepared
    from relief_bsdf.errors import InputError
    from relief_bsdf.io.heightmaps import write_relief
    check_out_suffix(args.out)
    if args.max_gap_px is not None and args.max_gap_px < 1:
        raise InputError("--max-gap-px", f"expected a whole number >= 1, got {args.max_gap_px}")
    relief = read_map(args.relief, args, pitch_m=_pitch(args.pitch_um))
    missing = int((~relief.valid).sum())
    filled = relief.fill_holes(args.max_gap_px) if missing else relief
    left = int((~filled.valid).sum())
    write_relief(args.out, filled)
    show_prepared(filled, args)
    total = filled.heights_m.size
    if missing == 0:
        print(f"nothing to fill: every one of the {total} points is valid; wrote {args.out} unchanged")
        return 0
    print(f"filled {missing - left} of {total} points ({(missing - left) / total:.2%}) by harmonic (Laplace) "
          f"interpolation" + (f"; {left} points in holes wider than {args.max_gap_px} px stay missing"
                              if left else "") + f"; wrote {args.out}")
    return 0
