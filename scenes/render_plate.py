"""Plate renders before / after a fit, side by side (the paper's figure 11), in Cycles.

    blender --background --python scenes/render_plate.py -- SOURCE -o OUT.png [--width 256] [--samples 32]
    relief render SOURCE -o OUT.png                      (same code through the bpy module)

SOURCE is a fit folder (written by `relief fit`, with fit.json: left = the relief as measured,
right = the fitted relief) or a sample.toml (left = a smooth plate, right = the measured
relief).  Each plate: the sample's thickness and index, the baked "Relief BSDF" node group on
its rough face, smooth glass elsewhere, 30 mm above a checkerboard, under a uniform white sky
(diffuse light).  The image is written with OpenImageIO (PNG, or float EXR by extension).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _paths() -> None:
    """Make the add-on and the backend importable inside a Blender binary too.

    Under `blender --python` the backend's dependencies come from the installed extension's
    bundled wheels or, in a checkout prepared with `make venv`, from .venv (appended last,
    so Blender's own numpy and bpy stay first).
    """
    for p in (ROOT, ROOT / "backend" / "src"):
        if str(p) not in sys.path:
            sys.path.append(str(p))
    try:
        import h5py  # noqa: F401
        import scipy  # noqa: F401
    except ImportError:
        for sp in sorted((ROOT / ".venv" / "lib").glob("python3.*/site-packages")):
            if str(sp) not in sys.path:
                sys.path.append(str(sp))


_paths()


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
    from relief_addon.bake_nodes import closure_albedo, has_metallic_bsdf
    from relief_addon.plate_scene import prepare_plates, render_side_by_side
    from relief_bsdf.errors import InputError
    if width < 8 or samples < 1:
        raise InputError("--width/--samples", "need a width of at least 8 pixels and at least 1 sample")
    plates = prepare_plates(source, closure_albedo(), "metallic" if has_metallic_bsdf() else "glossy", progress)
    return render_side_by_side(plates, out, width=width, samples=samples)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from relief_bsdf.errors import InputError
    try:
        out = render(args.source, args.out, args.width, args.samples)
    except InputError as e:
        print(f"render_plate: error: {e.one_line()}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    code = main(argv)
    if code:
        sys.exit(code)
