"""relief-bsdf: optical scattering (BSDF) of a rough boundary from its measured micro-relief.

Data flows one way, one sub-package per step (README "Architecture"):

    io (height maps) -> surface (Relief, statistics) -> methods (boundary BsdfTable, bsdf)
      -> plate (the one forward model: faces, bulk, instrument; deterministic and photon engines)
      -> fit (relief scale / filter) and diagnose (one module per effect) -> report, io (export)

`core` holds the only copies of the optics (index models, Fresnel, Stokes frames, microfacet
distributions, bulk), `validation` the independent generator of test cases (`relief conceal`),
`parallel` where tasks run, `jobs` the application layer (one function per job), `cli` the `relief`
command over it.  This package never imports bpy.

The public face below is loaded lazily (PEP 562), so `import relief_bsdf` stays cheap (Blender).
"""
from relief_bsdf._lazy import lazy_exports

__version__ = "0.1.0"

_EXPORTS = {
    "Relief": "surface", "read_relief": "io", "write_relief": "io",
    "BsdfTable": "bsdf", "Material": "core", "ConstantIndex": "core", "CauchyIndex": "core",
    "SellmeierIndex": "core", "Request": "methods", "reconstruct": "methods",
    "Experiment": "plate", "Plate": "plate", "Bulk": "plate", "Instrument": "plate", "FlatFace": "plate",
    "ReliefFace": "plate", "TableFace": "plate", "MicrofacetFace": "plate", "simulate": "plate",
    "experiment_from_sample": "plate", "run_fit": "jobs",
}
__all__ = ["__version__", *_EXPORTS]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
