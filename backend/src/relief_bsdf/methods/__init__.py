"""Reconstruction methods: one module each, behind one signature.

    reconstruct(relief, material, request, progress=None) -> list[BsdfTable]

returning one table per side of incidence in `request.incident_from`.  `METHODS`
maps the command-line names (formats.md) to modules, imported lazily so a method's
heavy dependencies (embreex, FFT planners) load only when used.
"""
from __future__ import annotations

import importlib

from relief_bsdf.errors import RequestError

METHODS = {
    "microfacet": "microfacet",
    "normals": "normals",
    "ray": "ray",
    "kirchhoff": "kirchhoff",
    "rayleigh-rice": "rayleigh_rice",
    "auto": "auto",
}


def get_method(name: str):
    """The module implementing method `name` (it has a `reconstruct` function)."""
    if name not in METHODS:
        raise RequestError(f"unknown method {name!r}; choose from {', '.join(METHODS)}", "--method")
    return importlib.import_module(f"{__name__}.{METHODS[name]}")


def reconstruct(relief, material, request, method: str, progress=None):
    """Run method `name` on the relief: the one entry point the CLI, fit and Blender use."""
    request.validate()
    material.check(request.wavelengths_nm, "--n/--cauchy")
    return get_method(method).reconstruct(relief, material, request, progress=progress)
