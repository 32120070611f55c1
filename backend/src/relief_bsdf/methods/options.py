"""Typed options of the reconstruction methods: one frozen dataclass per method.

`Request.options` stays a plain mapping (the command line's ``--option KEY=VALUE``, JSON
values, and what fit / plate / Blender pass), but no method reads that mapping: each one
turns it into its options class with `from_mapping(d, where)`, which

- rejects an unknown key with a RequestError naming it and listing the known ones
  ("unknown option 'bandlimted' for method kirchhoff; known: band_limited, ..."),
- rejects a value of the wrong type or outside its range, naming the option,
- fills every absent option with its documented default.

Every field states its unit in its name (``_rad``, ``_dcos`` = direction cosines, ``_px``).
The options change how a method computes, never the physics it models; the physics and the
regime of validity of each method are stated in its module and in `methods.registry`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

from relief_bsdf.errors import RequestError

# ------------------------------------------------------------------ value kinds


def _bad(name: str, where: str, expected: str, value: Any) -> RequestError:
    return RequestError(f"option {name!r} for method {where} must be {expected}, got {value!r}", f"options.{name}")


def _as_bool(v, name, where):
    if isinstance(v, bool):
        return v
    if isinstance(v, int) and v in (0, 1):
        return bool(v)
    raise _bad(name, where, "true or false", v)


def _as_int(v, name, where):
    if isinstance(v, bool):
        raise _bad(name, where, "an integer", v)
    if isinstance(v, int):
        return int(v)
    if isinstance(v, float) and math.isfinite(v) and v == int(v):
        return int(v)
    raise _bad(name, where, "an integer", v)


def _as_float(v, name, where):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(float(v)):
        raise _bad(name, where, "a number", v)
    return float(v)


def _as_str(v, name, where):
    if not isinstance(v, str):
        raise _bad(name, where, "a string", v)
    return v


def _as_floats(v, name, where):
    """One number or a list of numbers -> tuple of floats."""
    if isinstance(v, (list, tuple)):
        if not v:
            raise _bad(name, where, "a number or a non-empty list of numbers", v)
        return tuple(_as_float(x, name, where) for x in v)
    return _as_float(v, name, where)


_KINDS = {"bool": _as_bool, "int": _as_int, "float": _as_float, "str": _as_str, "floats": _as_floats}


def opt(default: Any, kind: str, doc: str, *, optional: bool = False, choices: tuple | None = None,
        minimum: float | None = None, maximum_excl: float | None = None):
    """A documented option field: kind in bool | int | float | str | floats; optional allows None."""
    return field(default=default, metadata={"kind": kind, "doc": doc, "optional": optional, "choices": choices,
                                            "minimum": minimum, "maximum_excl": maximum_excl})


def _convert(f: dataclasses.Field, value: Any, where: str) -> Any:
    md = f.metadata
    if value is None and md.get("optional"):
        return None
    v = _KINDS[md["kind"]](value, f.name, where)
    if md.get("choices") is not None and v not in md["choices"]:
        raise _bad(f.name, where, "one of " + ", ".join(map(str, md["choices"])), value)
    lo, hi = md.get("minimum"), md.get("maximum_excl")
    for x in (v if isinstance(v, tuple) else (v,)):
        if lo is not None and x < lo:
            raise _bad(f.name, where, f">= {lo:g}", value)
        if hi is not None and not x < hi:
            raise _bad(f.name, where, f"< {hi:g}", value)
    return v


# ------------------------------------------------------------------ base


@dataclass(frozen=True)
class MethodOptions:
    """Base of the per-method option classes (parse, list, export back to a mapping)."""

    METHOD: ClassVar[str] = ""

    @classmethod
    def known(cls) -> tuple[str, ...]:
        """Names of the options this method accepts."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def describe(cls) -> dict[str, str]:
        """option name -> its documentation line (default included)."""
        return {f.name: f"{f.metadata['doc']} (default {f.default!r})" for f in dataclasses.fields(cls)}

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any] | "MethodOptions" | None, where: str | None = None):
        """Typed options from a mapping; RequestError naming an unknown or mistyped option."""
        where = where or cls.METHOD
        if isinstance(d, cls):
            return d
        if isinstance(d, MethodOptions):
            d = d.as_mapping()
        d = dict(d or {})
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - set(fields))
        if unknown:
            names = ", ".join(repr(k) for k in unknown)
            raise RequestError(f"unknown option{'s' if len(unknown) > 1 else ''} {names} for method {where}; "
                               f"known: {', '.join(fields) or '(none)'}", f"options.{unknown[0]}")
        obj = cls(**{k: _convert(fields[k], v, where) for k, v in d.items()})
        obj._check(where)
        return obj

    @classmethod
    def from_request(cls, request, where: str | None = None):
        """`from_mapping(request.options)`."""
        return cls.from_mapping(getattr(request, "options", None), where)

    def _check(self, where: str) -> None:
        """Checks that involve several fields (overridden where needed)."""

    def as_mapping(self) -> dict[str, Any]:
        """Every option with its value (lists for tuples), e.g. for table metadata."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


# ------------------------------------------------------------------ the methods


@dataclass(frozen=True)
class KirchhoffOptions(MethodOptions):
    """Options of the Kirchhoff (tangent-plane) method; see methods.kirchhoff for the q_z scheme."""

    METHOD: ClassVar[str] = "kirchhoff"
    qz_tolerance: float = opt(1e-3, "float", "rms error of the q_z expansion of the Kirchhoff field, relative to the "
                              "diffuse field (methods.qz_expansion; the diffuse power's error is about twice it)",
                              minimum=0.0)
    max_qz_nodes: int = opt(64, "int", "most q_z nodes (FFTs) per side; the bound reached is reported",
                            minimum=2)
    fft_workers: int = opt(2, "int", "scipy.fft workers in this process (1 inside a pool worker)", minimum=1)
    band_limited: bool = opt(False, "bool", "take the relief as band-limited: directions beyond the pitch's band "
                             "get no power instead of refusing the request")
    band_limit_heights: bool = opt(True, "bool", "low-pass the heights to the spatial frequencies that scatter into "
                                   "the requested directions (what was removed is in metadata height_band_limit)")
    coherence_instances: int = opt(8, "int", "random phase screens averaged for partial coherence (>= 2)")
    smoothing_dcos: float | None = opt(None, "float", "filter width in direction cosines (None: from speckle and "
                                       "cells)", optional=True, minimum=0.0)
    polarized: bool = opt(False, "bool", "also fill the Mueller matrices (facet Fresnel Mueller matrix)")
    backend: str | None = opt(None, "str", "map_tasks backend (None: as configured)", optional=True)


@dataclass(frozen=True)
class RayleighRiceOptions(MethodOptions):
    """Options of the first-order perturbation (Rayleigh-Rice) method."""

    METHOD: ClassVar[str] = "rayleigh-rice"
    psd_isotropic: bool | None = opt(None, "bool", "force the PSD to be treated as isotropic (True) or not (False); "
                                     "None: detected from the slope tensor", optional=True)
    smoothing_dcos: float | None = opt(None, "float", "filter width in direction cosines (None: from the cells)",
                                       optional=True, minimum=0.0)
    polarized: bool = opt(True, "bool", "fill the Mueller matrices")
    backend: str | None = opt(None, "str", "map_tasks backend (None: as configured)", optional=True)


from relief_bsdf.core.microfacet import DISTRIBUTIONS  # noqa: E402  (the one list of distributions)

SHADOWING = ("smith", "vcavity", "incident", "none")


@dataclass(frozen=True)
class MicrofacetOptions(MethodOptions):
    """Options of the analytic microfacet (Walter et al. 2007) method."""

    METHOD: ClassVar[str] = "microfacet"
    alpha: float | tuple | None = opt(None, "floats", "roughness alpha of one lobe or of each mixture lobe "
                                      "(None: fitted to the relief's slopes)", optional=True)
    weights: tuple | None = opt(None, "floats", "weights of the mixture lobes given in alpha", optional=True)
    distribution: str = opt("beckmann", "str", "microfacet distribution", choices=DISTRIBUTIONS)
    shadowing: str = opt("smith", "str", "shadowing-masking term", choices=SHADOWING)
    lobes: int = opt(1, "int", "mixture lobes fitted to the relief's slopes when alpha is not given", minimum=1)
    subsamples: int | None = opt(None, "int", "quadrature points per cell axis (None or 0: from the lobe width)",
                                 optional=True, minimum=0)
    polarized: bool = opt(False, "bool", "fill the Mueller matrices")
    tile_uncertainty: bool = opt(True, "bool", "sigma from the tile's realisation (sub-tile refits of the lobes; "
                                 "only when the lobes are fitted to a relief)")


@dataclass(frozen=True)
class MicrofacetDwOptions(MethodOptions):
    """Options of the fast surrogate microfacet+dw (roughness and sigma come from the relief)."""

    METHOD: ClassVar[str] = "microfacet+dw"
    polarized: bool = opt(False, "bool", "fill the Mueller matrices of the diffuse lobe")


HEURISTICS = ("smith", "cosine")


def _grazing(v, name, where):
    if v in (None, False, "off", "none", ""):
        return None
    if v is True:
        return "smith"
    if v not in HEURISTICS:
        raise RequestError(f"grazing_heuristic must be off, smith or cosine, got {v!r}", f"options.{name}")
    return v


_KINDS["grazing"] = _grazing


@dataclass(frozen=True)
class NormalsOptions(MethodOptions):
    """Options of the normal-density Monte Carlo method."""

    METHOD: ClassVar[str] = "normals"
    grazing_heuristic: str | None = opt(None, "grazing", "correction of grazing facets: off (None), smith, cosine",
                                        optional=True)
    max_bounces: int = opt(100, "int", "interactions before a path counts as lost", minimum=1)
    specular_tol_rad: float = opt(1e-5, "float", "angle within which an exit counts as the specular delta")
    batch: int = opt(250_000, "int", "paths traced per numpy batch", minimum=1)
    polarized: bool = opt(False, "bool", "not available: the normals method is unpolarised")
    tile_uncertainty: bool = opt(True, "bool", "add the finite tile's realisation uncertainty to sigma (sub-tile "
                                 "batch means of the first facet)")

    def _check(self, where):
        if self.polarized:
            raise RequestError("the normals method is unpolarised (scalar Fresnel); use ray or microfacet for "
                               "Mueller tables", "options.polarized")


def _fill_holes(v, name, where):
    if isinstance(v, bool):
        return v
    if isinstance(v, int):
        return int(v)
    raise _bad(name, where, "true, false or a largest gap in px (integer)", v)


_KINDS["fill_holes"] = _fill_holes


@dataclass(frozen=True)
class RayOptions(MethodOptions):
    """Options of the geometric-optics ray tracer (methods.ray)."""

    METHOD: ClassVar[str] = "ray"
    polarized: bool = opt(True, "bool", "carry Stokes vectors and fill the Mueller matrices")
    max_bounces: int = opt(100, "int", "interactions before a ray counts as lost", minimum=1)
    first_hit_split: bool = opt(True, "bool", "follow both Fresnel branches at the first hit (variance reduction)")
    specular_tol_rad: float = opt(1e-5, "float", "angle within which an exit counts as the specular delta",
                                  minimum=0.0, maximum_excl=0.01)
    fill_holes: bool | int | None = opt(None, "fill_holes", "NaN heights: None/False refuse, True fill all, a "
                                          "number = largest gap filled, in px", optional=True)
    threads: int | None = opt(None, "int", "tracing threads in this process (a pool worker uses one; "
                              "None or 0: the tracer's default)", optional=True, minimum=0)
    block_px: int | None = opt(None, "int", "tile block size of the ray ordering, px", optional=True, minimum=1)
    backend: str | None = opt(None, "str", "map_tasks backend (None: as configured)", optional=True)
    tile_uncertainty: bool = opt(True, "bool", "add the finite tile's realisation uncertainty (sub-tile batch "
                                 "means) to sigma; False: Monte-Carlo sigma only (comparisons on one tile)")
    sparse_cells: bool = opt(False, "bool", "allow more scatter cells than the tile has facets (cells read "
                             "together, e.g. the plate's direct grid integrated over a detector cone)")
    beam_divergence_deg: float = opt(0.0, "float", "each ray's incidence spread by a 2-D Gaussian of this 1-sigma "
                                     "per axis, deg (a divergent source beam; 0: collimated)", minimum=0.0,
                                     maximum_excl=15.0)
    phi_i_spread_deg: float = opt(0.0, "float", "each ray's incidence azimuth drawn uniformly within +- this of the "
                                  "request's, its exit turned back by its own offset: the table averages the incidence "
                                  "azimuths of a sector, in the frame of its centre, deg (0: one azimuth)", minimum=0.0,
                                  maximum_excl=90.0)
    phi_i_turn_deg: float = opt(0.0, "float", "the relief lit from this incidence azimuth (every ray's incidence "
                                "turned by it about the normal, its exit turned back): the table of light arriving "
                                "from that azimuth, in the frame of its incidence, deg (0: the relief's own frame)",
                                minimum=-360.0, maximum_excl=360.0)


@dataclass(frozen=True)
class TwoScaleOptions(MethodOptions):
    """Options of the two-scale composite (methods.two_scale): the split, the haze, and the ray options of the
    large scale."""

    METHOD: ClassVar[str] = "two_scale"
    f_cut_per_um: float | None = opt(None, "float", "cut-off spatial frequency between the large and the fine scale, "
                                     "1/um (None: the lowest at which the fine scale's Rayleigh parameter is at most "
                                     "fine_rayleigh)", optional=True, minimum=0.0)
    fine_rayleigh: float = opt(0.05, "float", "the fine scale's Rayleigh parameter (4 pi n sigma_F / lambda)^2 at the "
                               "automatic cut", minimum=1e-6, maximum_excl=0.1 + 1e-12)
    tilt_convolution: bool = opt(True, "bool", "spread the fine scale's haze over the large scale's facet "
                                 "orientations (the ray lobe's spread)")
    max_bounces: int = opt(100, "int", "ray: interactions before a ray counts as lost", minimum=1)
    threads: int | None = opt(None, "int", "ray: tracing threads in this process", optional=True, minimum=0)
    tile_uncertainty: bool = opt(True, "bool", "ray: add the finite tile's realisation uncertainty to sigma")
    backend: str | None = opt(None, "str", "map_tasks backend (None: as configured)", optional=True)


@dataclass(frozen=True)
class FlatOptions(MethodOptions):
    """The flat face has no options (Fresnel only)."""

    METHOD: ClassVar[str] = "flat"
    polarized: bool = opt(True, "bool", "accepted for symmetry; the delta parts always carry Mueller matrices")


# the options auto's candidates understand (auto forwards those the chosen method knows)
AUTO_CANDIDATES = (RayleighRiceOptions, KirchhoffOptions, RayOptions, TwoScaleOptions)


@dataclass(frozen=True)
class AutoOptions(MethodOptions):
    """Options of `auto`: its own (quiet) plus any option of a candidate method, forwarded to the chosen one."""

    METHOD: ClassVar[str] = "auto"
    quiet: bool = opt(False, "bool", "do not print the one-line reason to stderr")
    forwarded: tuple = field(default=(), metadata={"kind": "forwarded", "doc": "(internal) candidate options"})

    @classmethod
    def known(cls) -> tuple[str, ...]:
        names = ["quiet"]
        for c in AUTO_CANDIDATES:
            names += [n for n in c.known() if n not in names]
        return tuple(names)

    @classmethod
    def describe(cls) -> dict[str, str]:
        out = {"quiet": "do not print the one-line reason to stderr (default False)"}
        for c in AUTO_CANDIDATES:
            for k, v in c.describe().items():
                out[k] = out.get(k) or f"{c.METHOD}: {v}"
        return out

    @classmethod
    def from_mapping(cls, d, where: str | None = None):
        where = where or cls.METHOD
        if isinstance(d, cls):
            return d
        d = dict(d or {})
        known = cls.known()
        unknown = sorted(set(d) - set(known))
        if unknown:
            names = ", ".join(repr(k) for k in unknown)
            raise RequestError(f"unknown option{'s' if len(unknown) > 1 else ''} {names} for method {where}; "
                               f"known: {', '.join(known)}", f"options.{unknown[0]}")
        quiet = _as_bool(d.pop("quiet", False), "quiet", where)
        for c in AUTO_CANDIDATES:                 # type-check each value against every candidate knowing it
            c.from_mapping({k: v for k, v in d.items() if k in c.known()}, where)
        return cls(quiet=quiet, forwarded=tuple(sorted(d.items())))

    def for_method(self, options_class: type[MethodOptions]) -> dict[str, Any]:
        """The forwarded options the chosen method knows."""
        return {k: v for k, v in self.forwarded if k in options_class.known()}

    def as_mapping(self) -> dict[str, Any]:
        return {"quiet": self.quiet, **dict(self.forwarded)}
