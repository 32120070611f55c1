"""The application layer: one function per job over a typed description, returning a typed output.

    run_reconstruct(ReconstructJob)  -> ReconstructOutput   a relief's boundary tables (HDF5)
    run_simulate(SimulateJob)        -> SimulateOutput      the plate on a recording's rows
    run_fit(FitJob)                  -> FitOutput           relief scale / filter, tables, report
    run_diagnose(DiagnoseJob)        -> DiagnoseOutput      the missing physics, report
    run_infer(InferJob)              -> InferOutput         a relief from a measured plate
    run_conceal(ConcealJob)          -> ConcealOutput       validation cases, key apart
    run_fill(FillJob) / run_crop(CropJob)                   height-map preparation
    run_export(ExportJob)            -> ExportOutput        CSV, IS-BSDF, Radiance XML, HDF5
    run_render(RenderJob)            -> RenderOutput        Cycles plate renders (the Blender layer's)

Every job takes `progress` (progress.Progress) and `cancel` (control.CancelToken), checked between
its stages and at every task boundary; a job reads its inputs, runs the computation of the layers
below (surface, methods, plate, fit, diagnose, infer, validation) and writes its outputs (atomically).
The `relief` command line (`cli`) and the Blender add-on (`relief_addon`) call only this layer for
this work: the import contract (docs/architecture.md) keeps everything below from importing it.
Loaded lazily (PEP 562): `import relief_bsdf.jobs` stays cheap (Blender).
"""
from relief_bsdf._lazy import lazy_exports

_EXPORTS = {
    "CancelToken": "control", "watched": "control",
    "ReconstructJob": "reconstruct", "ReconstructOutput": "reconstruct", "run_reconstruct": "reconstruct",
    "SimulateJob": "simulate", "SimulateOutput": "simulate", "run_simulate": "simulate",
    "FitJob": "fit", "FitOutput": "fit", "run_fit": "fit",
    "DiagnoseJob": "diagnose", "DiagnoseOutput": "diagnose", "run_diagnose": "diagnose",
    "InferJob": "infer", "InferOutput": "infer", "run_infer": "infer",
    "ConcealJob": "conceal", "ConcealOutput": "conceal", "run_conceal": "conceal",
    "FillJob": "maps", "FillOutput": "maps", "run_fill": "maps",
    "CropJob": "maps", "CropOutput": "maps", "run_crop": "maps",
    "ExportJob": "export", "ExportOutput": "export", "run_export": "export",
    "RenderJob": "render", "RenderOutput": "render", "run_render": "render",
}
__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
