"""Operators: thin wrappers over the backend's jobs (relief_bsdf.jobs), bpy data only on the main thread.

Each long operator builds a job's description from its properties and the scene's settings
(`prepare`, main thread), runs the job (`work`, any thread, cancellable: relief_addon.jobs), and
turns what the job returns into meshes, node groups and reports (`finish`, main thread).
"""
from __future__ import annotations

import json
from pathlib import Path

import bpy
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from .jobs import JobOperator
from .presets import ITEMS as PRESET_ITEMS
from .props import DEFAULT_METHOD, METHOD_ITEMS, SIDE_ITEMS

# every suffix the backend reads: npz, images (OpenImageIO), .sdf, and SurfaceTopography's readers
BASE_SUFFIXES = ("npz", "x3p", "gwy", "sur", "sdf", "tif", "tiff", "exr")


def reader_suffixes() -> tuple:
    ext = set(BASE_SUFFIXES)
    try:
        from SurfaceTopography.IO import readers
        for r in readers:
            try:
                ext.update(e.lower() for e in r.file_extensions())
            except Exception:  # noqa: BLE001 - a reader without the method
                pass
    except Exception:  # noqa: BLE001 - SurfaceTopography missing on this platform
        pass
    return tuple(sorted(ext))


def abspath(p: str) -> Path:
    """Blender path ('//' = the .blend's folder; the per-user cache when the file is unsaved)."""
    from .paths import resolve
    return resolve(p)


def _floats(text: str, what: str) -> tuple:
    from relief_bsdf.errors import InputError
    try:
        vals = tuple(float(t) for t in text.replace(";", ",").split(",") if t.strip())
    except ValueError:
        raise InputError(what, f"expected comma-separated numbers, got {text!r}") from None
    if not vals:
        raise InputError(what, "no value given")
    return vals


def _require(module: str, what: str):
    """Import a backend module or raise an error naming the missing feature."""
    import importlib
    from relief_bsdf.errors import InputError
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise InputError(what, f"this backend has no {module} ({e}); update relief-bsdf") from None


# ====================================================================== import


def _import_file(context, path: Path, pitch_um: float, z_scale: float):
    from relief_bsdf.io.heightmaps import read_relief
    from .mesh_import import import_relief
    from relief_bsdf.errors import InputError
    pitch = (pitch_um * 1e-6, pitch_um * 1e-6) if pitch_um > 0 else None
    try:
        relief = read_relief(path, pitch_m=pitch)
    except ImportError as e:                # e.g. no SurfaceTopography wheel for this platform
        raise InputError(path, f"this format needs {e.name or e}, which is not available in this "
                         "Blender (x3p, gwy, plu, sdf, npz, TIFF and EXR files still work)") from None
    s = context.scene.relief
    request = {"ior": s.ior, "wavelengths_nm": _floats(s.wavelengths_nm, "wavelengths"),
               "theta_i_deg": _floats(s.theta_i_deg, "incidences")}
    obj = import_relief(relief, z_scale=z_scale, collection=context.collection, regime_request=request)
    from .mesh_import import frame_in_views
    frame_in_views(obj, context.scene)
    for o in context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    return obj


class RELIEF_OT_import_heightmap(bpy.types.Operator, ImportHelper):
    """Import a measured surface height map as a mesh (true heights in metres)"""

    bl_idname = "relief.import_heightmap"
    bl_label = "Import Surface Height Map"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ""
    filter_glob: StringProperty(default=";".join(f"*.{e}" for e in BASE_SUFFIXES), options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    pitch_um: FloatProperty(name="Pitch (um)", default=0.0, min=0.0,
                            description="Lateral pitch for images without sidecar; 0 = from the file")
    z_scale: FloatProperty(name="Height exaggeration", default=1.0, min=0.0,
                           description="Display factor for z (true heights are kept)")

    def execute(self, context):
        paths = [Path(self.directory) / f.name for f in self.files if f.name] if self.files and self.directory \
            else [Path(self.filepath)]
        made = []
        for p in paths:
            try:
                made.append(_import_file(context, p, self.pitch_um, self.z_scale))
            except Exception as exc:  # noqa: BLE001 - report, never a console-only traceback
                from .jobs import _error_text
                self.report({"ERROR"}, f"Import: {_error_text(exc)}")
                return {"CANCELLED"}
        for o in made:
            self.report({"INFO"}, f"Imported {o.name}: {len(o.data.vertices)} vertices")
        return {"FINISHED"}

    def invoke(self, context, event):
        if self.filepath or (self.files and self.directory):
            return self.execute(context)
        self.filter_glob = ";".join(f"*.{e}" for e in reader_suffixes())
        return ImportHelper.invoke(self, context, event)


class RELIEF_FH_heightmap(bpy.types.FileHandler):
    bl_idname = "RELIEF_FH_heightmap"
    bl_label = "Surface height map"
    bl_import_operator = "relief.import_heightmap"
    # instrument formats only: generic suffixes the readers also try (.txt, .csv, .h5, .zip,
    # .npy, .mat, .xlsx) would capture unrelated drops
    bl_file_extensions = ";".join(f".{e}" for e in BASE_SUFFIXES + (
        "plu", "plux", "opd", "opdx", "datx", "frt", "nid", "mi", "ibw", "spm", "vk3", "vk4", "vk6", "vk7", "lext",
        "oir", "poir", "al3d", "bcr", "bcrf", "ezd", "hfm", "nc", "zon", "tom", "top", "stp", "cur", "jpk", "apx"))

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type in ("VIEW_3D", "OUTLINER")


def menu_import(self, context):
    self.layout.operator(RELIEF_OT_import_heightmap.bl_idname, text="Surface height map")


# ====================================================================== reconstruct


def _relief_source(context) -> tuple[str, list | None]:
    from relief_bsdf.errors import InputError
    obj = context.active_object
    if obj is None or "relief_source" not in obj:
        raise InputError("active object", "select an imported relief (File > Import > Surface height map)")
    pitch = obj.get("relief_pitch_m")
    return obj["relief_source"], (list(pitch) if pitch is not None else None)


class RELIEF_OT_reconstruct(JobOperator, bpy.types.Operator):
    """Reconstruct the BSDF table of the active relief and bake it to a node group"""

    bl_idname = "relief.reconstruct"
    bl_label = "Reconstruct BSDF"
    bl_options = {"REGISTER"}
    job_label = "Reconstruct"

    method: EnumProperty(name="Method", items=METHOD_ITEMS, default=DEFAULT_METHOD)
    wavelengths_nm: StringProperty(name="Wavelengths (nm)", default="")
    theta_i_deg: StringProperty(name="Incidences (deg)", default="")
    sides: EnumProperty(name="Sides", items=SIDE_ITEMS, default="both")
    samples: IntProperty(name="Samples", default=0, min=0, description="0 = the scene setting")
    ior: FloatProperty(name="Refractive index", default=0.0, min=0.0, description="0 = the scene setting")
    relief_path: StringProperty(name="Relief file", default="", subtype="FILE_PATH",
                                description="Height map (default: the active imported relief)")
    filepath: StringProperty(name="Table", default="", subtype="FILE_PATH", description="Output table (.h5)")
    bake: BoolProperty(name="Bake", default=True, description="Bake the table to a node group when done")

    def invoke(self, context, event):
        s = context.scene.relief
        # the panel's settings fill what the caller did not set
        if not self.properties.is_property_set("method"):
            self.method = s.method
        if not self.properties.is_property_set("sides"):
            self.sides = s.sides
        return JobOperator.invoke(self, context, event)

    def prepare(self, context):
        from relief_bsdf.core.index import ConstantIndex, Material
        from relief_bsdf.methods.request import Request
        s = context.scene.relief
        if self.relief_path:
            src, pitch = str(abspath(self.relief_path)), None
        else:
            src, pitch = _relief_source(context)
        sides = ("outside", "inside") if self.sides == "both" else (self.sides,)
        req = Request(wavelengths_nm=_floats(self.wavelengths_nm or s.wavelengths_nm, "wavelengths"),
                      theta_i_deg=_floats(self.theta_i_deg or s.theta_i_deg, "incidences"),
                      incident_from=sides, samples=int(self.samples or s.samples), seed=int(s.seed)).validate()
        out = abspath(self.filepath or s.table_path)
        albedo = None
        if self.bake:
            from .bake_nodes import closure_albedo
            albedo = closure_albedo()
        from .bake_nodes import GROUP_PREFIX, group_for_table, has_metallic_bsdf
        from .paths import in_cache, stored
        before = group_for_table(stored(out))          # a re-run updates the group baked from this table
        return {"relief": src, "pitch": pitch, "options": map_options(s),
                "material": Material(ConstantIndex(float(self.ior or s.ior))),
                "request": req, "method": self.method, "out": out, "bake": self.bake, "albedo": albedo,
                "content_named": in_cache(out),        # the shared cache of unsaved sessions (paths.py)
                "closure": "metallic" if has_metallic_bsdf() else "glossy",
                "name": before.name[len(GROUP_PREFIX):] if before is not None else Path(src).stem}

    @staticmethod
    def work(p, progress, cancel=None):
        from relief_bsdf.jobs import ReconstructJob, run_reconstruct
        out = p["out"]
        if p.get("content_named"):
            # unsaved sessions share the cache: write under a private name, then name the file by its content
            from .paths import scratch_name
            out = scratch_name(out)
        pitch = tuple(p["pitch"]) if p["pitch"] is not None else None
        job = ReconstructJob(Path(p["relief"]), Path(out), p["material"], p["request"], method=p["method"],
                             options=p.get("options"), pitch_m=pitch)          # the job `relief reconstruct` runs
        r = run_reconstruct(job, progress, cancel)
        tables, relief = r.tables, r.relief
        as_read = _as_read(relief, p) if relief.history else None
        if p.get("content_named"):
            from .paths import content_named
            out = content_named(r.out)
        lut = None
        if p["bake"]:
            from relief_bsdf.bake import bake_lut
            lut = bake_lut(tables, p["name"], albedo=p["albedo"], reflection_closure=p["closure"])
        return {"tables": tables, "out": out, "lut": lut, "as_read": as_read}

    def finish(self, context, r):
        from .paths import stored
        context.scene.relief.table_path = stored(r["out"])
        if r.get("as_read") is not None:           # the map as read (crop, downsample, fill): its own statistics
            obj = context.active_object
            if obj is not None and "relief_source" in obj:
                obj["relief_as_read"] = r["as_read"]
            st, reg = r["as_read"]["stats"], r["as_read"]["regime"]
            self.report({"INFO"}, f"As read ({'; '.join(r['as_read']['steps'])}): "
                                  f"{int(st['shape'][1])} x {int(st['shape'][0])} points, rms height "
                                  f"{st['rms_height_m'] * 1e6:.4g} um, rms slope {st['rms_slope']:.4g}, "
                                  f"{reg.get('regime', 'regime not assessed')}")
        rows = r["tables"][0].albedo_rows()
        msg = ", ".join(f"{x['theta_i_deg']:.0f} deg: R {x['R']:.3f} T {x['T']:.3f}" for x in rows[:4])
        self.report({"INFO"}, f"Wrote {r['out']} ({msg}{', ...' if len(rows) > 4 else ''})")
        if r["lut"] is not None:
            group, _ = _install_lut(context, r["lut"], assign=False, table=stored(r["out"]))
            context.scene.relief.last_group = group.name


# ====================================================================== bake


FACES_ITEMS = [("AUTO", "Auto", "A plate made by the add-on: its rough face; any other mesh: every face"),
               ("ALL", "Every face", "Every face, the relief's frame from each face's normal (sphere, lens, ...)"),
               ("FRONT", "Front (+z)", "The faces looking along +z (object space): a plate's lit face"),
               ("BACK", "Back (-z)", "The faces looking along -z (object space): a plate's back face")]


def _install_lut(context, lut, assign: bool, fitted=None, table: str = "", name: str | None = None,
                 faces: str = "AUTO"):
    """The node group of `lut`; with `assign`, its material on the active mesh's `faces` (FACES_ITEMS).
    Returns (group, words on where it went or None)."""
    from .bake_nodes import FACES_WORDS, assign_to_rough_face, build_node_group, lut_image, relief_faces
    group = build_node_group(lut, lut_image(lut), fitted=fitted, name=name, table=table)
    obj = context.active_object
    where = None
    if assign and obj is not None and obj.type == "MESH":
        face = relief_faces(obj) if faces == "AUTO" else faces.lower()
        slot = assign_to_rough_face(obj, group, face)
        n = sum(1 for p in obj.data.polygons if p.material_index == slot)
        where = f"on {n} of {len(obj.data.polygons)} faces of {obj.name} ({FACES_WORDS[face]})"
    return group, where


def _fitted_table(op, context) -> Path | None:
    """The fitted table: the operator's `fitted`, else boundary.h5 in the scene's fit folder."""
    if op.fitted:
        return abspath(op.fitted)
    fit_dir = context.scene.relief.fit_dir
    cand = abspath(fit_dir) / "boundary.h5" if fit_dir else None
    return cand if cand is not None and cand.is_file() else None


class RELIEF_OT_bake_bsdf(JobOperator, bpy.types.Operator):
    """Bake a BSDF table (HDF5) to the node group "Relief BSDF: <name>" with packed lookup images"""

    bl_idname = "relief.bake_bsdf"
    bl_label = "Bake BSDF Node Group"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Bake"

    filepath: StringProperty(name="Table", default="", subtype="FILE_PATH",
                             description="The relief's table as measured (default: the scene's table)")
    fitted: StringProperty(name="Fitted table", default="", subtype="FILE_PATH",
                           description="Table of the fitted relief (default: boundary.h5 of the scene's fit)")
    name: StringProperty(name="Name", default="",
                         description="Node group name suffix (default: the group baked from this table before, "
                                     "else the file stem)")
    assign: BoolProperty(name="Assign to active", default=True,
                         description="Add the group's material to the active mesh (existing materials are kept)")
    faces: EnumProperty(name="Faces", items=FACES_ITEMS, default="AUTO",
                        description="Which faces of the active mesh get the relief: the lookup works in each "
                                    "face's own frame (its normal), so any mesh can carry it")

    def prepare(self, context):
        from relief_bsdf.errors import InputError
        from .bake_nodes import GROUP_PREFIX, closure_albedo, group_for_table, has_metallic_bsdf
        from .paths import stored
        path = abspath(self.filepath or context.scene.relief.table_path)
        if not path.is_file():
            raise InputError(path, "BSDF table file not found (reconstruct first or choose a .h5 file)")
        fitted = _fitted_table(self, context)
        if fitted is not None and not fitted.is_file():
            raise InputError(fitted, "fitted table file not found")
        before = group_for_table(stored(path))
        name = self.name or (before.name[len(GROUP_PREFIX):] if before is not None else path.stem)
        return {"path": path, "fitted": fitted, "name": name, "table": stored(path), "albedo": closure_albedo(),
                "closure": "metallic" if has_metallic_bsdf() else "glossy"}

    @staticmethod
    def work(p, progress):
        from relief_bsdf.bake import bake_lut
        from relief_bsdf.io.hdf5 import load_tables
        progress(0, 2, "fitting lobes")
        lut = bake_lut(load_tables(p["path"]), p["name"], albedo=p["albedo"], reflection_closure=p["closure"])
        fitted = None
        if p["fitted"] is not None:
            progress(1, 2, "fitting lobes (fitted table)")
            fitted = bake_lut(load_tables(p["fitted"]), p["name"] + " (fitted)", albedo=p["albedo"],
                              reflection_closure=p["closure"])
        progress(2, 2, "done")
        return {"lut": lut, "fitted": fitted, "table": p["table"], "name": p["name"]}

    def finish(self, context, r):
        group, where = _install_lut(context, r["lut"], self.assign, fitted=r["fitted"], table=r["table"],
                                    name=r["name"], faces=self.faces)
        context.scene.relief.last_group = group.name
        haze = r["lut"].haze
        self.report({"INFO"}, f"Baked {group.name}" + (f" (haze {100 * haze:.1f} %)" if haze == haze else "")
                    + (f"; {where}" if where else ""))


# ====================================================================== plate, fit, diagnose


def _sample_and_out(op, context, sub: str):
    from relief_bsdf.errors import InputError
    s = context.scene.relief
    sample = abspath(op.sample or s.sample_path) if (op.sample or s.sample_path) else None
    if sample is None or not sample.is_file():
        raise InputError(sample or "sample", "choose a sample.toml (Plate & recording panel)")
    from .paths import session_output
    out = session_output(abspath(op.output_dir or s.output_dir) / sub)    # unsaved: this session's own folder
    return sample, out


class RELIEF_OT_simulate_plate(JobOperator, bpy.types.Operator):
    """Simulate the plate of a sample on its recording's rows (writes simulated.csv)"""

    bl_idname = "relief.simulate_plate"
    bl_label = "Simulate Plate"
    job_label = "Simulate"

    sample: StringProperty(name="Sample", default="", subtype="FILE_PATH")
    output_dir: StringProperty(name="Output", default="", subtype="DIR_PATH")
    method: StringProperty(name="Method", default="auto",
                           description="Boundary method: auto (the relief's own physics) or any method name")
    table: StringProperty(name="Table", default="", subtype="FILE_PATH",
                          description="Use this boundary table instead of deriving one")

    def prepare(self, context):
        sample, out = _sample_and_out(self, context, "simulate")
        return {"sample": str(sample), "out": str(out), "method": self.method,
                "table": str(abspath(self.table)) if self.table else None}

    @staticmethod
    def work(p, progress, cancel=None):
        jobs = _require("relief_bsdf.jobs", "simulate")          # the job `relief simulate` runs, its defaults
        job = jobs.SimulateJob(Path(p["sample"]), Path(p["out"]), method=p["method"],
                               table=Path(p["table"]) if p["table"] else None)
        return jobs.run_simulate(job, progress, cancel)

    def finish(self, context, r):
        self.report({"INFO"}, f"Wrote {r.path} ({r.rows} rows; metric, rms z {r.metric:.4g}); {r.physics}")


class RELIEF_OT_fit(JobOperator, bpy.types.Operator):
    """Fit the relief's height scale and smoothing to the sample's recording"""

    bl_idname = "relief.fit"
    bl_label = "Fit to Recording"
    job_label = "Fit"

    sample: StringProperty(name="Sample", default="", subtype="FILE_PATH")
    output_dir: StringProperty(name="Output", default="", subtype="DIR_PATH")
    method: StringProperty(name="Method", default="auto",
                           description="Boundary method: auto (the relief's own physics) or any method name")
    max_iter: IntProperty(name="Iterations", default=60, min=1)

    def prepare(self, context):
        sample, out = _sample_and_out(self, context, "fit")
        return {"sample": str(sample), "out": str(out), "method": self.method, "max_iter": self.max_iter}

    @staticmethod
    def work(p, progress, cancel=None):
        jobs = _require("relief_bsdf.jobs", "fit")
        r = jobs.run_fit(jobs.FitJob(Path(p["sample"]), Path(p["out"]), method=p["method"], max_iter=p["max_iter"]),
                         progress, cancel)
        return {"doc": r.doc, "out": p["out"]}

    def finish(self, context, r):
        from .paths import stored
        context.scene.relief.fit_dir = stored(r["out"])
        d = r["doc"]
        self.report({"INFO"}, f"Fit: metric (rms z) {d['rms_before']:.4g} -> {d['rms_after']:.4g}, "
                              f"parameters {json.dumps(d.get('parameters', {}))}")


class RELIEF_OT_diagnose(JobOperator, bpy.types.Operator):
    """Find the physical effect the model leaves out (writes diagnosis.json and report.html)"""

    bl_idname = "relief.diagnose"
    bl_label = "Diagnose"
    job_label = "Diagnose"

    sample: StringProperty(name="Sample", default="", subtype="FILE_PATH")
    output_dir: StringProperty(name="Output", default="", subtype="DIR_PATH")

    def prepare(self, context):
        sample, out = _sample_and_out(self, context, "diagnose")
        return {"sample": str(sample), "out": str(out)}

    @staticmethod
    def work(p, progress, cancel=None):
        jobs = _require("relief_bsdf.jobs", "diagnose")
        return jobs.run_diagnose(jobs.DiagnoseJob(Path(p["sample"]), Path(p["out"])), progress, cancel).doc

    def finish(self, context, res):
        named = " + ".join(res.get("effects") or [res["effect"]])     # every effect named, most important first
        self.report({"INFO"}, f"Diagnosis: {named} (metric, rms z {res['rms_before']:.4g} -> {res['rms_after']:.4g}): "
                              f"{res['explanation']}")


class RELIEF_OT_infer(JobOperator, bpy.types.Operator):
    """Infer a relief for the sample from its measured plate alone; import it as a mesh and bake its material"""

    bl_idname = "relief.infer"
    bl_label = "Infer Relief"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Infer"

    sample: StringProperty(name="Sample", default="", subtype="FILE_PATH",
                           description="sample.toml whose [recording] holds the measured plate (default: the scene's)")
    output_dir: StringProperty(name="Output", default="", subtype="DIR_PATH")
    bake: BoolProperty(name="Bake", default=True,
                       description="Reconstruct the inferred relief's table (both sides) and bake it onto the mesh")

    def prepare(self, context):
        from relief_bsdf.methods.request import Request
        sample, out = _sample_and_out(self, context, "infer")
        s = context.scene.relief
        p = {"sample": str(sample), "out": str(out), "seed": int(s.seed), "bake": self.bake}
        if self.bake:
            from .bake_nodes import closure_albedo, has_metallic_bsdf
            p.update(request=Request(wavelengths_nm=_floats(s.wavelengths_nm, "wavelengths"),
                                     theta_i_deg=_floats(s.theta_i_deg, "incidences"),
                                     incident_from=("outside", "inside"),
                                     samples=int(s.samples), seed=int(s.seed)).validate(),
                     albedo=closure_albedo(), closure="metallic" if has_metallic_bsdf() else "glossy",
                     method=s.method)
        return p

    @staticmethod
    def work(p, progress, cancel=None):
        """The infer job, then (bake) the reconstruct job on the inferred relief at the index infer used."""
        from relief_bsdf.core.index import ConstantIndex, Material
        from relief_bsdf.io.heightmaps import read_relief
        from relief_bsdf.jobs import InferJob, ReconstructJob, run_infer, run_reconstruct
        r = run_infer(InferJob(Path(p["sample"]), Path(p["out"]), seed=p["seed"]), progress, cancel)
        res = {"doc": r.doc, "relief": read_relief(r.relief), "out": r.out, "lut": None, "table": None}
        if p["bake"]:
            from relief_bsdf.bake import bake_lut
            n = float(r.doc["parameters"]["refractive_index"])
            job = ReconstructJob(r.relief, r.out / "boundary.h5", Material(ConstantIndex(n)), p["request"],
                                 method=p["method"])
            t = run_reconstruct(job, progress, cancel)
            res["table"] = t.out
            res["lut"] = bake_lut(t.tables, f"{Path(p['sample']).stem} inferred", albedo=p["albedo"],
                                  reflection_closure=p["closure"])
        return res

    def finish(self, context, r):
        from .mesh_import import frame_in_views, import_relief
        from .paths import stored
        obj = import_relief(r["relief"], collection=context.collection)
        frame_in_views(obj, context.scene)
        for o in context.view_layer.objects:
            o.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        d = r["doc"]
        msg = (f"Inferred {d['family']} (rms slope {d['rms_slope']:.4g}, n {d['parameters']['refractive_index']:g}"
               f"{'' if d['index_stated'] else ', assumed'}): metric (rms z) flat plate {d['rms_before']:.4g} -> "
               f"{d['rms_after']:.4g}")
        if r["lut"] is not None:
            context.scene.relief.table_path = stored(r["table"])
            group, where = _install_lut(context, r["lut"], assign=True, table=stored(r["table"]))
            context.scene.relief.last_group = group.name
            msg += f"; baked {group.name}" + (f" {where}" if where else "")
        self.report({"INFO"}, msg)


# ====================================================================== render


class RELIEF_OT_render_plate(JobOperator, bpy.types.Operator):
    """Render the plate over a checkerboard before and after the fit, side by side (Cycles)"""

    bl_idname = "relief.render_plate"
    bl_label = "Render Plate"
    job_label = "Render"

    filepath: StringProperty(name="Output", default="", subtype="FILE_PATH")
    source: StringProperty(name="Sample or fit folder", default="", subtype="FILE_PATH",
                           description="sample.toml or a folder written by Fit (default: the scene's)")
    width: IntProperty(name="Width per image", default=0, min=0)
    samples: IntProperty(name="Samples", default=0, min=0)

    def prepare(self, context):
        from relief_bsdf.errors import InputError
        from .bake_nodes import closure_albedo, has_metallic_bsdf
        s = context.scene.relief
        src = self.source or s.fit_dir or s.sample_path
        if not src:
            raise InputError("source", "choose a sample.toml or a fit folder")
        return {"source": str(abspath(src)), "out": str(abspath(self.filepath or s.render_path)),
                "width": self.width or s.render_width, "samples": self.samples or s.render_samples,
                "albedo": closure_albedo(), "closure": "metallic" if has_metallic_bsdf() else "glossy"}

    @staticmethod
    def work(p, progress):
        from .plate_scene import prepare_plates
        return {**p, "plates": prepare_plates(p["source"], p["albedo"], p["closure"], progress)}

    def finish(self, context, r):
        from .plate_scene import render_side_by_side
        out = render_side_by_side(r["plates"], r["out"], width=r["width"], samples=r["samples"])
        self.report({"INFO"}, f"Wrote {out}")


class RELIEF_OT_add_preset(JobOperator, bpy.types.Operator):
    """Add a ready-to-render plate scene of a typical surface (frosted acrylic, anti-glare film, light-guide dots)"""

    bl_idname = "relief.add_preset"
    bl_label = "Add Preset Plate Scene"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Preset"

    preset: EnumProperty(name="Preset", items=PRESET_ITEMS, default="frosted_acrylic")

    def prepare(self, context):
        from .bake_nodes import closure_albedo, has_metallic_bsdf
        s = context.scene.relief
        return {"preset": self.preset, "albedo": closure_albedo(),
                "closure": "metallic" if has_metallic_bsdf() else "glossy",
                "width": s.render_width, "samples": s.render_samples}

    @staticmethod
    def work(p, progress):
        from .presets import preset_plate
        return {**p, "plate": preset_plate(p["preset"], p["albedo"], p["closure"], progress)}

    def finish(self, context, r):
        from .plate_scene import build_scene
        sc = build_scene(r["plate"], r["width"], r["samples"])
        group = next((m.node_tree.nodes[0].node_tree for o in sc.collection.objects if o.type == "MESH"
                      for m in o.data.materials if m and m.name.startswith("Relief BSDF")), None)
        if context.window is not None:
            context.window.scene = sc            # the new scene is shown: F12 renders it
        if group is not None:
            context.scene.relief.last_group = group.name
        haze = r["plate"]["lut"].haze
        self.report({"INFO"}, f"Scene {sc.name!r} ready to render"
                              + (f" (haze {100 * haze:.1f} %)" if haze == haze else ""))


CLASSES = (RELIEF_OT_import_heightmap, RELIEF_FH_heightmap, RELIEF_OT_reconstruct, RELIEF_OT_bake_bsdf,
           RELIEF_OT_simulate_plate, RELIEF_OT_fit, RELIEF_OT_diagnose, RELIEF_OT_infer, RELIEF_OT_render_plate,
           RELIEF_OT_add_preset)


def register():
    for c in CLASSES:
        if c is RELIEF_FH_heightmap and not hasattr(bpy.types, "FileHandler"):
            continue                       # Blender < 4.1: no drag-and-drop handlers
        bpy.utils.register_class(c)
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    for c in reversed(CLASSES):
        if c.is_registered:
            bpy.utils.unregister_class(c)


def map_options(settings):
    """The panel's map choices (fill holes, crop, downsample, periodicity) as the backend's ReliefOptions,
    checked as the command line checks them (an InputError names the setting)."""
    from relief_bsdf.surface.preparation import ReliefOptions, parse_crop
    crop = parse_crop(settings.crop) if settings.crop.strip() else None
    periodic = {"yes": True, "no": False}.get(settings.periodic)
    return ReliefOptions(crop=crop, downsample=int(settings.downsample), fill_holes=bool(settings.fill_holes),
                         periodic=periodic, stated_by="the panel's Periodicity")


def _as_read(relief, p) -> dict:
    """Statistics and optical regime of the map as Reconstruct read it (after the panel's crop, downsample
    and fill), recomputed, with the steps from its history (`relief_bsdf.surface.preparation`)."""
    from .mesh_import import _id_safe, optical_regime, relief_stats
    req = p["request"]
    regime = optical_regime(relief, float(p["material"].inside.n(req.wavelengths_nm[0]).real), req.wavelengths_nm,
                            req.theta_i_deg)
    return {"stats": {k: _id_safe(v) for k, v in relief_stats(relief).items()}, "regime": regime,
            "steps": [str(h) for h in relief.history][-4:]}
