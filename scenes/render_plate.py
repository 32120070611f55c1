"""Plate renders before / after a fit, side by side: the Blender script entry point.

    blender --background --python scenes/render_plate.py -- SOURCE -o OUT.png [--width 256] [--samples 32]
    relief render SOURCE -o OUT.png                      (same code through the bpy module)

The scene code is `relief_addon/render_plate.py` (shipped in the installed distribution, see
its docstring for the scene); this script only makes the checkout's add-on and backend
importable inside a Blender binary, then runs it.
"""
from __future__ import annotations

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

from relief_addon.render_plate import build_parser, main, render  # noqa: E402,F401  (after the paths)

if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    code = main(argv)
    if code:
        sys.exit(code)
