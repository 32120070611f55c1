"""`relief render (SAMPLE.toml | FITDIR) -o OUT.png`: plate renders before / after, side by side.

Runs the scene code `relief_addon.render_plate` through the bpy module (Cycles, CPU).  The
`relief_addon` package (the Blender layer) ships in the same installed distribution as this
backend (backend/pyproject.toml maps it beside `relief_bsdf`), so the command works from an
installed package; an editable install of a checkout finds it in the checkout.  The only
backend command that needs bpy, and bpy is imported only when it runs.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from relief_bsdf.errors import InputError


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("render", help="render the plate before / after the fit over a checkerboard (Cycles)")
    p.add_argument("source", help="sample.toml or a fit folder (fit.json)")
    p.add_argument("-o", "--out", required=True, help="output image (.png or .exr)")
    p.add_argument("--width", type=int, default=256, help="pixels per image (default 256)")
    p.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    return p


def _checkout_root() -> Path | None:
    """The source checkout holding this backend (editable installs), if any."""
    for root in Path(__file__).resolve().parents:
        if (root / "relief_addon" / "render_plate.py").is_file() and (root / "backend").is_dir():
            return root
    return None


def _scene_module():
    """`relief_addon.render_plate`: from the installed distribution, else from the checkout."""
    try:
        return importlib.import_module("relief_addon.render_plate")
    except ModuleNotFoundError as e:
        if e.name not in ("relief_addon", "relief_addon.render_plate"):
            raise
    root = _checkout_root()
    if root is None:
        raise InputError("relief render", "the relief_addon package (the Blender layer) is not installed: "
                                          "reinstall relief-bsdf (it ships relief_addon beside relief_bsdf)")
    sys.path.append(str(root))
    return importlib.import_module("relief_addon.render_plate")


def run(args) -> int:
    src = Path(args.source)
    if not src.exists():
        raise InputError(src, "no such sample.toml or fit folder")
    try:
        import bpy  # noqa: F401
    except ImportError as e:
        raise InputError("relief render", f"needs the bpy module (pip install bpy): {e}") from None
    from relief_bsdf.progress import TerminalBar
    out = _scene_module().render(src, args.out, args.width, args.samples, progress=TerminalBar("render"))
    print(f"wrote {out}")
    if src.is_dir() and (src / "fit.json").is_file() and Path(out).suffix.lower() == ".png":
        print(f"wrote {_embed_in_report(src, Path(out))} (with the plate render)")
    return 0


def _embed_in_report(fit_dir: Path, png: Path) -> Path:
    """Rewrite the fit folder's report.html with the plate render (before | after) embedded."""
    import json
    from relief_bsdf.report.fit_report import write_fit_report
    doc = json.loads((fit_dir / "fit.json").read_text())
    plots = {k: v for k, v in (doc.get("files") or {}).items() if isinstance(v, str) and v.endswith(".png")}
    return write_fit_report(fit_dir / "report.html", doc, plots,
                            renders={"the plate over a checkerboard, before | after the fit (Cycles)": png})
