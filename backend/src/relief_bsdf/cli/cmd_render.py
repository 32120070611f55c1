"""`relief render (SAMPLE.toml | FITDIR) -o OUT.png`: plate renders before / after, side by side.

Runs the scene script `scenes/render_plate.py` of this checkout through the bpy module
(Cycles, CPU).  The only backend command that needs bpy; the Blender layer itself lives
in relief_addon/ (see the script's docstring for the scene).
"""
from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from relief_bsdf.errors import InputError


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("render", help="render the plate before / after the fit over a checkerboard (Cycles)")
    p.add_argument("source", help="sample.toml or a fit folder (fit.json)")
    p.add_argument("-o", "--out", required=True, help="output image (.png or .exr)")
    p.add_argument("--width", type=int, default=256, help="pixels per image (default 256)")
    p.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    return p


def _scene_script() -> Path:
    here = Path(__file__).resolve()
    for root in here.parents:
        cand = root / "scenes" / "render_plate.py"
        if cand.is_file() and (root / "relief_addon").is_dir():
            return cand
    raise InputError("relief render", "scenes/render_plate.py and relief_addon/ not found: "
                     "`relief render` runs from a source checkout of relief-bsdf")


def run(args) -> int:
    src = Path(args.source)
    if not src.exists():
        raise InputError(src, "no such sample.toml or fit folder")
    try:
        import bpy  # noqa: F401
    except ImportError as e:
        raise InputError("relief render", f"needs the bpy module (pip install bpy): {e}") from None
    script = _scene_script()
    spec = importlib.util.spec_from_file_location("relief_render_plate", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    from relief_bsdf.progress import TerminalBar
    out = mod.render(src, args.out, args.width, args.samples, progress=TerminalBar("render"))
    print(f"wrote {out}")
    return 0
