"""Locate OpenImageIO without importing Blender.

The bpy wheel bundles OpenImageIO's Python module inside its private interpreter
tree (``bpy/<version>/python/lib/python3.X/site-packages/OpenImageIO``).  Importing
bpy just to reach it would start Blender, so we find the package directory through
``importlib.util.find_spec("bpy")`` (which does not execute bpy) and load only the
OpenImageIO package from there.  Only that one package is loaded; the rest of the
bundled site-packages is never put on ``sys.path`` (it may hold other numpy builds).
Falls back to a plain ``import OpenImageIO`` (a pip-installed wheel) when no bpy
bundle is found.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

_MODULE: ModuleType | None = None


def _bundled_package_dirs() -> list[Path]:
    spec = importlib.util.find_spec("bpy")
    if spec is None:
        return []
    roots = [Path(p) for p in (spec.submodule_search_locations or [])]
    if not roots and spec.origin:
        roots = [Path(spec.origin).parent]
    found = []
    for root in roots:
        found += sorted(root.glob("*/python/lib/python3*/site-packages/OpenImageIO/__init__.py"))
    return [p.parent for p in found]


def _load_from(pkg_dir: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location("OpenImageIO", pkg_dir / "__init__.py",
                                                  submodule_search_locations=[str(pkg_dir)])
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load OpenImageIO from {pkg_dir}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["OpenImageIO"] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop("OpenImageIO", None)
        raise
    return mod


def load() -> ModuleType:
    """Return the OpenImageIO module (cached); ImportError if none can be found."""
    global _MODULE
    if _MODULE is not None:
        return _MODULE
    if "OpenImageIO" in sys.modules:
        _MODULE = sys.modules["OpenImageIO"]
        return _MODULE
    errors = []
    for d in _bundled_package_dirs():
        try:
            _MODULE = _load_from(d)
            return _MODULE
        except ImportError as e:  # pragma: no cover - depends on the install
            errors.append(f"{d}: {e}")
    try:
        _MODULE = importlib.import_module("OpenImageIO")
        return _MODULE
    except ImportError as e:
        errors.append(f"import OpenImageIO: {e}")
    raise ImportError("OpenImageIO not found (neither bundled with bpy nor installed): " + "; ".join(errors))


def available() -> bool:
    try:
        load()
        return True
    except ImportError:
        return False
