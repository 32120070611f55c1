"""3D view sidebar (N panel), tab "Relief": statistics, reconstruct, plate & recording, bake & render."""
from __future__ import annotations

import bpy


class _ReliefPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Relief"


def _fmt(key: str, v) -> str:
    if isinstance(v, float):
        if key.endswith("_m"):
            return f"{v * 1e6:.4g} um"
        return f"{v:.4g}"
    if hasattr(v, "to_list"):
        v = v.to_list()
    if isinstance(v, (list, tuple)):
        if key.endswith("_m"):
            return " x ".join(f"{x * 1e6:.4g}" for x in v) + " um"
        return " x ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
    return str(v)


class RELIEF_PT_relief(_ReliefPanel, bpy.types.Panel):
    bl_label = "Relief"

    def draw(self, context):
        lay = self.layout
        lay.operator("relief.import_heightmap", icon="IMPORT")
        obj = context.active_object
        if obj is None or "relief_source" not in obj:
            lay.label(text="No relief selected")
            return
        lay.prop(obj, "relief_z_scale")
        box = lay.box()
        box.label(text=obj.name, icon="MESH_GRID")
        stats = obj.get("relief_stats", {})
        for k in stats.keys():
            row = box.row()
            row.label(text=(k[:-2] if k.endswith("_m") else k).replace("_", " "))
            row.label(text=_fmt(k, stats[k]))
        s = context.scene.relief
        if s.job_status:
            lay.label(text=s.job_status, icon="INFO")


class RELIEF_PT_reconstruct(_ReliefPanel, bpy.types.Panel):
    bl_label = "Reconstruct"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.relief
        col = self.layout.column()
        for p in ("method", "wavelengths_nm", "theta_i_deg", "sides", "samples", "seed", "ior", "table_path"):
            col.prop(s, p)
        op = col.operator("relief.reconstruct", icon="PLAY")
        op.method = s.method
        op.sides = s.sides


class RELIEF_PT_plate(_ReliefPanel, bpy.types.Panel):
    bl_label = "Plate & recording"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.relief
        col = self.layout.column()
        col.prop(s, "sample_path")
        col.prop(s, "output_dir")
        row = col.row(align=True)
        row.operator("relief.simulate_plate", text="Simulate")
        row.operator("relief.fit", text="Fit")
        row.operator("relief.diagnose", text="Diagnose")
        col.prop(s, "fit_dir")


class RELIEF_PT_bake_render(_ReliefPanel, bpy.types.Panel):
    bl_label = "Bake & render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.relief
        col = self.layout.column()
        col.prop(s, "table_path")
        col.operator("relief.bake_bsdf", icon="NODETREE")
        col.separator()
        col.prop(s, "render_path")
        col.prop(s, "render_width")
        col.prop(s, "render_samples")
        col.operator("relief.render_plate", icon="RENDER_STILL")
        if s.job_status:
            col.label(text=s.job_status, icon="INFO")


CLASSES = (RELIEF_PT_relief, RELIEF_PT_reconstruct, RELIEF_PT_plate, RELIEF_PT_bake_render)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
