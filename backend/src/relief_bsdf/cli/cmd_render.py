"""`relief render (SAMPLE.toml | FITDIR) -o OUT.png`: plate renders before / after, side by side.

The job `relief_bsdf.jobs.render`: the Blender layer's scene (Cycles, CPU) through the bpy module,
found as a plug-in (the entry point `relief_bsdf.renderers` "plate"), so this backend never imports
the add-on.  The only backend command that needs bpy, and bpy is imported only when it runs.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("render", help="render the plate before / after the fit over a checkerboard (Cycles)")
    p.add_argument("source", help="sample.toml or a fit folder (fit.json)")
    p.add_argument("-o", "--out", required=True, help="output image (.png or .exr)")
    p.add_argument("--width", type=int, default=256, help="pixels per image (default 256)")
    p.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    return p


def run(args) -> int:
    from relief_bsdf.jobs import RenderJob, run_render
    from relief_bsdf.progress import TerminalBar
    r = run_render(RenderJob(Path(args.source), Path(args.out), args.width, args.samples), TerminalBar("render"))
    print(f"wrote {r.image}")
    if r.report is not None:
        print(f"wrote {r.report} (with the plate render)")
    return 0
