"""The job `relief render`: the plate over a checkerboard before / after a fit, side by side (Cycles).

The scene is the Blender layer's: this backend never imports bpy nor the add-on's code.  It names
the renderer it needs as a plug-in interface (`PlateRenderer`) and finds the one installed under
the entry-point group `relief_bsdf.renderers`, name "plate" (backend/pyproject.toml registers
`relief_addon.render_plate:render`, shipped in the same distribution).  A source checkout that
was never installed has no entry points: then the module `FALLBACK_MODULE` of the checkout beside
this backend.  Either way the dependency points from the Blender layer's registration to this
interface, never from the backend to the add-on (the import contract, docs/architecture.md).
From a fit folder (fit.json), a PNG render is also embedded in the folder's report.html.
"""
from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from relief_bsdf.errors import InputError
from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.progress import Progress

ENTRY_POINT_GROUP = "relief_bsdf.renderers"
ENTRY_POINT_NAME = "plate"
FALLBACK_MODULE = "relief_addon.render_plate"


class PlateRenderer(Protocol):
    """render(source, out, width, samples, progress) -> the image written: both plates (before | after)
    prepared, baked and rendered side by side into `out` (.png or .exr)."""

    def __call__(self, source: Path, out: Path, width: int, samples: int, progress: Any = None) -> Path: ...


@dataclass(frozen=True)
class RenderJob:
    """Render `source` (a sample.toml or a fit folder with fit.json) into `out` (.png or .exr), `width`
    pixels per image, `samples` Cycles samples per pixel."""

    source: Path
    out: Path
    width: int = 256
    samples: int = 32


@dataclass(frozen=True)
class RenderOutput:
    """The image written and, for a fit folder's PNG, its report.html with the render embedded."""

    image: Path
    report: Path | None = None


def _checkout_root() -> Path | None:
    """The source checkout holding this backend (editable installs), if any."""
    for root in Path(__file__).resolve().parents:
        if (root / "relief_addon" / "render_plate.py").is_file() and (root / "backend").is_dir():
            return root
    return None


def plate_renderer() -> PlateRenderer:
    """The installed PlateRenderer (module doc); InputError naming what is missing."""
    from importlib.metadata import entry_points
    for ep in entry_points(group=ENTRY_POINT_GROUP, name=ENTRY_POINT_NAME):
        return ep.load()
    try:
        return importlib.import_module(FALLBACK_MODULE).render
    except ModuleNotFoundError as e:
        if e.name not in ("relief_addon", FALLBACK_MODULE):
            raise
    root = _checkout_root()
    if root is None:
        raise InputError("relief render", "the relief_addon package (the Blender layer) is not installed: "
                                          "reinstall relief-bsdf (it ships relief_addon beside relief_bsdf)")
    sys.path.append(str(root))
    return importlib.import_module(FALLBACK_MODULE).render


def run_render(job: RenderJob, progress: Progress | None = None, cancel: CancelToken | None = None) -> RenderOutput:
    src = Path(job.source)
    if not src.exists():
        raise InputError(src, "no such sample.toml or fit folder")
    try:
        import bpy  # noqa: F401
    except ImportError as e:
        raise InputError("relief render", f"needs the bpy module (pip install bpy): {e}") from None
    check(cancel, "rendering")
    out = Path(plate_renderer()(src, job.out, job.width, job.samples, progress=watched(progress, cancel)))
    report = None
    if src.is_dir() and (src / "fit.json").is_file() and out.suffix.lower() == ".png":
        report = embed_in_report(src, out)
    return RenderOutput(out, report)


def embed_in_report(fit_dir: Path, png: Path) -> Path:
    """Rewrite the fit folder's report.html with the plate render (before | after) embedded."""
    import json
    from relief_bsdf.report.fit_report import write_fit_report
    doc = json.loads((fit_dir / "fit.json").read_text())
    plots = {k: v for k, v in (doc.get("files") or {}).items() if isinstance(v, str) and v.endswith(".png")}
    return write_fit_report(fit_dir / "report.html", doc, plots,
                            renders={"the plate over a checkerboard, before | after the fit (Cycles)": png})
