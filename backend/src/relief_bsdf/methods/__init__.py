"""Boundary-BSDF methods: turn a relief and a material into BsdfTables, behind one signature.

    reconstruct(relief, material, request, method, progress=None) -> list[BsdfTable]

returning one table per side of incidence in `request.incident_from`.  The methods (and the
fast surrogates `microfacet+dw` and `flat`) are listed once, in `methods.registry` (name,
module, typed options class, physics, regime of validity); `Request` (methods.request) holds
the table axes and effort; each method reads its options only through its options class
(methods.options), so an unknown or mistyped option is a RequestError naming it.
"""
from __future__ import annotations

from relief_bsdf.methods.options import (AutoOptions, FlatOptions, KirchhoffOptions, MethodOptions,
                                         MicrofacetDwOptions, MicrofacetOptions, NormalsOptions, RayleighRiceOptions,
                                         RayOptions, TwoScaleOptions)
from relief_bsdf.methods.registry import REGISTRY, MethodEntry, entry, method_names, options_for
from relief_bsdf.methods.request import Request

# name -> module (kept for callers of the old mapping; the registry is the source)
METHODS = {name: e.module for name, e in REGISTRY.items()}

__all__ = ["reconstruct", "get_method", "Request", "REGISTRY", "METHODS", "MethodEntry", "entry", "method_names",
           "options_for", "MethodOptions", "KirchhoffOptions", "RayleighRiceOptions", "MicrofacetOptions",
           "MicrofacetDwOptions", "NormalsOptions", "RayOptions", "AutoOptions", "FlatOptions",
           "TwoScaleOptions"]


def get_method(name: str):
    """The module implementing method `name` (it has a `reconstruct` function)."""
    return entry(name).load()


def reconstruct(relief, material, request, method: str, progress=None):
    """Run method `method` on the relief: the one entry point the CLI, fit, plate and Blender use.

    The request's options are checked against the method's options class first, so a typo
    fails before any work.
    """
    e = entry(method)
    request.validate()
    e.parse_options(request.options)
    material.check(request.wavelengths_nm, "--n/--cauchy")
    tables = e.load().reconstruct(relief, material, request, progress=progress)
    return _with_axis_slopes(tables, relief)


def _with_axis_slopes(tables: list, relief) -> list:
    """The tables with the relief's rms slopes along x and y in their `relief` record (what an export needs
    to tell an anisotropic relief's one-azimuth table: io.radiance_xml), where the method did not write them."""
    from relief_bsdf.surface.stats import rms_slope_xy
    if relief is None or not any("rms_slope_x" not in (t.relief or {}) for t in tables):
        return tables                            # (the flat face and analytic faces come without a relief)
    sx, sy = rms_slope_xy(relief)               # NaN where an axis has no two valid neighbours
    for t in tables:
        t.relief = {**(t.relief or {}), "rms_slope_x": sx, "rms_slope_y": sy}
    return tables
