"""3D view sidebar (N panel), tab "Relief": statistics, reconstruct, plate & recording, bake & render."""
from __future__ import annotations

import bpy


class _ReliefPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Relief"


_LENGTH_UNITS = ((1e-6, 1e9, "nm"), (1e-3, 1e6, "um"), (1.0, 1e3, "mm"), (float("inf"), 1.0, "m"))


def fmt_length(*values_m: float) -> str:
    """Lengths in the unit that fits the largest of them: nm below 1 um, um below 1 mm, mm
    below 1 m, else m (4 significant digits)."""
    big = max((abs(v) for v in values_m if v == v), default=0.0)
    scale, unit = next((f, u) for limit, f, u in _LENGTH_UNITS if big < limit)
    return " x ".join(f"{v * scale:.4g}" for v in values_m) + f" {unit}"


def _fmt(key: str, v) -> str:
    if hasattr(v, "to_list"):
        v = v.to_list()
    if key.endswith("_m") and isinstance(v, (int, float)):
        return fmt_length(float(v))
    if key.endswith("_m") and isinstance(v, (list, tuple)) and all(isinstance(x, (int, float)) for x in v):
        return fmt_length(*(float(x) for x in v))
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return " x ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
    return str(v)


def _wrapped(layout, text: str, width: int = 44) -> None:
    line = ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            layout.label(text=line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    if line:
        layout.label(text=line)


def _regime_box(layout, obj) -> None:
    reg = obj.get("relief_regime")
    if reg is None:
        return
    box = layout.box()
    if "error" in reg:
        box.label(text="Optical regime: not assessed", icon="ERROR")
        _wrapped(box, str(reg["error"]))
        return
    box.label(text=f"Optical regime: {reg['regime']}", icon="LIGHT")
    box.label(text=f"auto would pick: {reg['method']} (at {reg['wavelength_nm']:.0f} nm)")
    _wrapped(box, str(reg["summary"]))


def _baked_box(layout, context) -> None:
    name = context.scene.relief.last_group
    g = bpy.data.node_groups.get(name) if name else None
    if g is None:
        return
    box = layout.box()
    box.label(text=g.name, icon="NODETREE")
    haze = g.get("relief_haze", float("nan"))
    box.label(text=f"haze (T, normal incidence): {100 * haze:.1f} %" if haze == haze else "haze: not known "
              "(the table has no normal incidence)")
    an = g.get("relief_anisotropy", 0.0)
    box.label(text=f"anisotropy of the reflection lobe: {an:.2f}" if an else "isotropic lobes")
    tilt = g.get("relief_transmission_tilt", 0.0)
    if tilt:
        # Cycles has no anisotropic rough transmission (relief_bsdf.bake, module doc)
        box.label(text=f"transmitted lobe stretched: facet tilt {tilt:.2f}")
        _wrapped(box, "Cycles has no anisotropic refraction closure: a random facet tilt per "
                 "path sample stretches it")
    elif an:
        box.label(text="transmitted lobes: isotropic (mean width)", icon="ERROR")


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
        _regime_box(lay, obj)
        read = obj.get("relief_as_read")
        if read is not None:                     # Reconstruct's crop / downsample / fill: the map it traced
            box = lay.box()
            box.label(text="As Reconstruct read it")
            for k in ("shape", "rms_height_m", "rms_slope"):
                if k in read["stats"]:
                    box.label(text=f"{k}: {_fmt(k, read['stats'][k])}")
            reg = read.get("regime", {})
            box.label(text=f"Optical regime: {reg.get('regime', 'not assessed')}")
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
        box = col.box()
        box.label(text="The map as read")
        for p in ("fill_holes", "crop", "downsample", "periodic"):
            box.prop(s, p)
        from .prefs import get_prefs
        prefs = get_prefs(context)
        if hasattr(prefs, "bl_rna"):           # registered as an add-on: its preferences
            col.prop(prefs, "workers")
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
        col.operator("relief.infer", text="Infer relief from the recording", icon="MOD_DISPLACE")
        col.prop(s, "fit_dir")


class RELIEF_PT_bake_render(_ReliefPanel, bpy.types.Panel):
    bl_label = "Bake & render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.relief
        col = self.layout.column()
        col.prop(s, "table_path")
        col.operator("relief.bake_bsdf", icon="NODETREE")
        _wrapped(col, "Bake puts the relief on every face of the active mesh (a plate made here: on its rough "
                 "face). The lookup works in each face's own frame: z its normal (outward: the outside rows), "
                 "x the object's x axis on the face (anisotropic lobes only).")
        _baked_box(col, context)
        col.separator()
        col.prop(s, "render_path")
        col.prop(s, "render_width")
        col.prop(s, "render_samples")
        col.operator("relief.render_plate", icon="RENDER_STILL")
        col.separator()
        col.label(text="Presets (scene ready to render):")
        row = col.row(align=True)
        from .presets import PRESETS
        for key, p in PRESETS.items():
            row.operator("relief.add_preset", text=p.label).preset = key
        if s.job_status:
            col.label(text=s.job_status, icon="INFO")


CLASSES = (RELIEF_PT_relief, RELIEF_PT_reconstruct, RELIEF_PT_plate, RELIEF_PT_bake_render)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
