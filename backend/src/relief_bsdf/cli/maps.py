"""The height-map flags of every command that reads a map, and the map read with them.

`--crop X0,Y0,W,H`, `--downsample K`, `--fill-holes`, `--periodic` / `--no-periodic`
(formats.md); what they do and in which order: surface.preparation.
"""
from __future__ import annotations

import argparse

from relief_bsdf.cli import _positive_int


def add_relief_args(p: argparse.ArgumentParser, crop: bool = True) -> None:
    """The map flags on parser `p` (`crop=False`: without --crop/--downsample, for `relief crop`'s own)."""
    g = p.add_argument_group("height map", "applied after reading, in this order: crop, downsample, "
                                           "periodicity, hole filling (each recorded in the relief's history)")
    if crop:
        add_crop_args(g)
    g.add_argument("--fill-holes", action="store_true",
                   help="fill missing points by harmonic (Laplace) interpolation from their valid neighbours "
                        "(as `relief fill`); without it a ray-traced map must have none")
    per = g.add_mutually_exclusive_group()
    per.add_argument("--periodic", dest="periodic", action="store_const", const=True, default=None,
                     help="the map is one period of a seamless tile (trace it as one period)")
    per.add_argument("--no-periodic", dest="periodic", action="store_const", const=False,
                     help="the map is a measured patch (mirror-extended where a method needs a period); "
                          "neither flag: the file's own statement, else the wrap-around test "
                          "(surface.periodicity)")


def add_crop_args(g, required: bool = False) -> None:
    g.add_argument("--crop", metavar="X0,Y0,W,H", required=required, default=None,
                   help="keep the window of W x H points from column X0, row Y0 (0-based)")
    g.add_argument("--downsample", metavar="K", type=_positive_int, default=1,
                   help="k x k block means (pitch times K)")


def relief_options(args: argparse.Namespace):
    """The surface.preparation.ReliefOptions the flags state."""
    from relief_bsdf.surface.preparation import ReliefOptions, parse_crop
    crop = getattr(args, "crop", None)
    return ReliefOptions(crop=parse_crop(crop) if crop else None, downsample=getattr(args, "downsample", 1),
                         fill_holes=bool(getattr(args, "fill_holes", False)), periodic=getattr(args, "periodic", None),
                         stated_by="--periodic" if getattr(args, "periodic", None) else "--no-periodic")


def stated_options(args: argparse.Namespace):
    """The flags' ReliefOptions when any map flag was given (to override a sample's [relief] keys), else None."""
    opts = relief_options(args)
    return None if (opts.crop, opts.downsample, opts.fill_holes, opts.periodic) == (None, 1, False, None) else opts


def read_map(path, args: argparse.Namespace, pitch_m=None, channel=None):
    """The height map `path` read and prepared as the flags say ."""
    from relief_bsdf.io.heightmaps import read_prepared_relief
    return read_prepared_relief(path, relief_options(args), pitch_m=pitch_m, channel=channel)


def periodicity_line(relief) -> str:
    """One line for logs: how the map is traced and why (surface.periodicity)."""
    p = relief.metadata.get("periodicity") if isinstance(relief.metadata, dict) else None
    if not p:
        return f"relief {relief.source}: " + ("periodic tile" if relief.periodic else "not periodic")
    from relief_bsdf.surface.periodicity import Periodicity
    return f"relief {relief.source}: {Periodicity(**p).line()}"


def show_prepared(relief, args: argparse.Namespace) -> None:
    """Print how the map is traced and why; after a crop or downsample also its recomputed statistics
    and regime (`relief info`'s summary)."""
    if getattr(args, "crop", None) or getattr(args, "downsample", 1) != 1:
        from relief_bsdf.cli.cmd_info import print_relief_summary
        print_relief_summary(relief)                 # periodicity and hole filling included
        return
    print(periodicity_line(relief))
    for h in relief.history:
        if h.startswith("filled "):
            print(f"relief {relief.source}: {h}")
