"""The tabulated BSDF of one boundary and what is derived from it.

    table  BsdfTable: values per projected solid angle on (wavelength, theta_i, phi_i, side R/T,
           theta_s, phi_s) cells, optional Mueller matrices and the delta-like specular parts;
           reciprocity_error (cell measures: core.frames)
    builder  the ONE builder of table cells from sampled exit directions and weights (CellIndex,
             ExitSamples, TableCells, CellAccumulator, specular_flags), used by every sampling method
File formats: relief_bsdf.io (hdf5, isbsdf).  The bake of a table into renderer closures
(it fits microfacet lobes, so it sits above `methods`): relief_bsdf.bake.
"""
from relief_bsdf._lazy import lazy_exports

# name -> sub-module; loaded on first use (PEP 562), so `import relief_bsdf.bsdf.table` stays cheap
_EXPORTS = {
    "BsdfTable": "table", "SIDES": "table", "reciprocity_error": "table",
    "CellIndex": "builder", "ExitSamples": "builder", "TableCells": "builder", "CellAccumulator": "builder",
    "specular_flags": "builder",
}
__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
