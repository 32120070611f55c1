"""`relief crop RELIEF --crop X0,Y0,W,H [--downsample K] -o OUT.(x3p|npz)`: a window of a height map.

The window is W x H points from column X0, row Y0 (0-based); `--downsample K` then takes K x K
block means (pitch times K).  The statistics and the scattering regime of the result are
recomputed and shown (as `relief info` shows them); the steps are kept in the file's history.
A piece of a periodic tile is not periodic: the result's periodicity is decided again.
"""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("crop", help="cut a window out of a height map (and downsample it)",
                       description=__doc__.split("\n", 2)[2].strip())
    p.add_argument("relief", metavar="RELIEF", help="height map (.x3p, .gwy, .sur, .sdf, .tif, .exr, .npz, ...)")
    p.add_argument("--pitch-um", default=None, help="lateral pitch DX[,DY] in um for files without one (images)")
    p.add_argument("-o", "--out", required=True, help="output height map (.x3p or .npz)")
    from relief_bsdf.cli.maps import add_crop_args, add_relief_args
    add_relief_args(p, crop=False)
    add_crop_args(p, required=True)
    return p


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.cli.cmd_info import _pitch, print_relief_summary
    from relief_bsdf.cli.maps import relief_options
    from relief_bsdf.jobs import CropJob, run_crop
    r = run_crop(CropJob(Path(args.relief), Path(args.out), pitch_m=_pitch(args.pitch_um),
                         options=relief_options(args)))
    print_relief_summary(r.relief)
    print(f"wrote {args.out}")
    return 0
