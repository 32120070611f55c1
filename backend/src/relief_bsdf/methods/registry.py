"""The one registry of boundary-BSDF methods: name -> module, options class, physics, validity.

Every way of turning a relief into boundary tables is an entry here: the reconstruction
methods of the command line (formats.md), `auto`, the fast surrogate `microfacet+dw` the fit
uses by default, and the `flat` face.  Each module has

    reconstruct(relief, material, request, progress=None) -> list[BsdfTable]

(one table per side in `request.incident_from`) and reads its options only through its
options class (methods.options).  Modules are imported lazily, so a method's heavy
dependencies (embreex, FFT planners) load only when it is used.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

from relief_bsdf.errors import RequestError
from relief_bsdf.methods import options as _o


@dataclass(frozen=True)
class MethodEntry:
    """One method: where it lives, its options, what physics it computes and where that holds."""

    name: str
    module: str                      # module under relief_bsdf.methods
    options: type                    # its MethodOptions subclass
    physics: str                     # one line
    validity: str                    # regime of validity, one line
    surrogate: bool = False          # a fast model standing in for a method (fit, plate)
    wavelength_free: bool = False    # geometric optics: the wavelength enters through the indices alone

    def load(self):
        """The module implementing this method."""
        return importlib.import_module(f"relief_bsdf.methods.{self.module}")

    def parse_options(self, mapping) -> _o.MethodOptions:
        """Typed options from a request's mapping (RequestError naming a bad option)."""
        return self.options.from_mapping(mapping, self.name)


_ENTRIES = (
    MethodEntry("microfacet", "microfacet", _o.MicrofacetOptions,
                "Walter et al. 2007 rough dielectric: microfacet distribution D, Smith shadowing G, facet Fresnel",
                "geometric optics of one scattering event: lateral scales and heights >> wavelength, "
                "slope statistics of one (or a mixture of) Beckmann / GGX lobes", wavelength_free=True),
    MethodEntry("normals", "normals", _o.NormalsOptions,
                "Monte Carlo over the relief's measured facet normals with scalar Fresnel, multiple bounces",
                "geometric optics, facets >> wavelength; positions ignored (no real shadowing unless heuristic)",
                wavelength_free=True),
    MethodEntry("ray", "ray", _o.RayOptions,
                "geometric-optics ray tracing of the triangulated relief with Fresnel Mueller matrices",
                "rough on the wavelength scale (sigma >= lambda / n, no coherent specular left), "
                "facets >= 10 wavelengths", wavelength_free=True),
    MethodEntry("kirchhoff", "kirchhoff", _o.KirchhoffOptions,
                "scalar Kirchhoff tangent-plane integral of the height map by FFT (q_z node scheme)",
                "radius of curvature >> wavelength (k R_c >= 5), moderate slopes (< 0.5), single scattering"),
    MethodEntry("rayleigh-rice", "rayleigh_rice", _o.RayleighRiceOptions,
                "first-order vector perturbation theory: BSDF = (16 pi^2 / lambda^4) cos cos Q PSD",
                "optically smooth: (4 pi n sigma / lambda)^2 < 0.1 and rms slope < 0.15"),
    MethodEntry("two_scale", "two_scale", _o.TwoScaleOptions,
                "composite: ray tracing of the relief's large scale, its cells times the fine scale's Debye-Waller "
                "factor, plus the fine scale's Rayleigh-Rice haze spread over the facet orientations",
                "large scale rough on the wavelength scale with facets >> wavelength (as ray), fine scale optically "
                "smooth (Rayleigh parameter <= 0.1); a lobe plus a haze (anti-glare film)"),
    MethodEntry("auto", "auto", _o.AutoOptions,
                "chooses rayleigh-rice, kirchhoff, two_scale or ray from the relief's statistics and the request",
                "that of the method chosen (the reason says which condition decided)"),
    MethodEntry("microfacet+dw", "microfacet_dw", _o.MicrofacetDwOptions,
                "microfacet lobe of the rms slope plus a Debye-Waller coherent specular part "
                "exp(-(nu_z sigma)^2) of the rms height",
                "Gaussian height statistics, lateral scales >> wavelength (fast surrogate of the fit)",
                surrogate=True),
    MethodEntry("flat", "flat", _o.FlatOptions,
                "a perfectly flat interface: Fresnel delta parts (Mueller matrices), no diffuse cells",
                "exact for a plane boundary; the relief, if given, is ignored", surrogate=True,
                wavelength_free=True),
)

REGISTRY: dict[str, MethodEntry] = {e.name: e for e in _ENTRIES}


def method_names(surrogates: bool = True) -> tuple[str, ...]:
    """Registered names, in registry order (the command line's --method choices)."""
    return tuple(e.name for e in _ENTRIES if surrogates or not e.surrogate)


def entry(name: str) -> MethodEntry:
    """The registry entry of `name`; RequestError naming the choices for an unknown one."""
    if name not in REGISTRY:
        raise RequestError(f"unknown method {name!r}; choose from {', '.join(REGISTRY)}", "--method")
    return REGISTRY[name]


def options_for(name: str, mapping) -> _o.MethodOptions:
    """Typed options of method `name` from a mapping (or an options object)."""
    return entry(name).parse_options(mapping)


def listing() -> str:
    """One block per method: name, physics, validity, options (for --help and documentation)."""
    lines = []
    for e in _ENTRIES:
        lines.append(f"{e.name}{' (surrogate)' if e.surrogate else ''}: {e.physics}")
        lines.append(f"    valid: {e.validity}")
        known = e.options.known()
        lines.append(f"    options: {', '.join(known) if known else '(none)'}")
    return "\n".join(lines)
