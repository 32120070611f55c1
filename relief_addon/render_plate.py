"""Plate renders before / after a fit, side by side (the paper's figure 11), in Cycles.

The scene code behind both entry points (it ships inside the installed `relief-bsdf`
distribution as the top-level package `relief_addon`, beside `relief_bsdf`, so it works
without a source checkout):

    relief render SOURCE -o OUT.png [--width 256] [--samples 32]          (the bpy module)
    blender --background --python scenes/render_plate.py -- SOURCE -o OUT.png [...]

SOURCE is a fit folder (written by `relief fit`, with fit.json: left = the relief as measured,
right = the fitted relief) or a sample.toml (left = a smooth plate, right = the measured
relief).  Each plate: the sample's thickness and index, the baked "Relief BSDF" node group on
its rough face, smooth glass elsewhere, 30 mm above a checkerboard, under a uniform white sky
(diffuse light).  The image is written with OpenImageIO (PNG, or float EXR by extension).
Needs bpy (inside Blender or the bpy module); imports it only when rendering.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="render_plate.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="fit folder (fit.json) or sample.toml")
    ap.add_argument("-o", "--out", required=True, help="output image (.png, .exr, ...)")
    ap.add_argument("--width", type=int, default=256, help="pixels per image (default 256)")
    ap.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    return ap


def render(source, out, width: int = 256, samples: int = 32, progress=None) -> Path:
    """Prepare (derive + bake) both plates and render them side by side into `out`."""
    import bpy  # noqa: F401  (inside Blender or the bpy module)
    from relief_bsdf.errors import InputError

    from .bake_nodes import closure_albedo, has_metallic_bsdf
    from .plate_scene import prepare_plates, render_side_by_side
    if width < 8 or samples < 1:
        raise InputError("--width/--samples", "need a width of at least 8 pixels and at least 1 sample")
    from .workers import running_backend
    with running_backend():             # workers start from this package, never re-run a calling script
        plates = prepare_plates(source, closure_albedo(), "metallic" if has_metallic_bsdf() else "glossy", progress)
    return render_side_by_side(plates, out, width=width, samples=samples)


def main(argv=None) -> int:
    """Command-line entry of the Blender script (scenes/render_plate.py)."""
    args = build_parser().parse_args(argv)
    from relief_bsdf.errors import InputError
    try:
        out = render(args.source, args.out, args.width, args.samples)
    except InputError as e:
        print(f"render_plate: error: {e.one_line()}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
