"""Scene settings (`scene.relief`) and the object property `relief_z_scale`."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

# "//" paths (beside the .blend) are this add-on's convention (paths.py); Blender 4.5+ asks to say so
_REL = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()

METHOD_ITEMS = [
    ("microfacet", "Microfacet", "Analytic Walter / Cook-Torrance lobes fitted to the relief's slopes (fast)"),
    ("normals", "Normals", "Monte Carlo over the relief's facet normals"),
    ("ray", "Ray tracing", "Geometric optics ray tracing of the height field (Embree)"),
    ("kirchhoff", "Kirchhoff", "Scalar Kirchhoff diffraction (wave optics, rough)"),
    ("rayleigh-rice", "Rayleigh-Rice", "First-order vector perturbation (smooth surfaces)"),
    ("auto", "Auto", "Choose the method from the relief's statistics and the wavelength"),
]
#: Reconstruct's default: the relief's own physics, as everywhere in the project
#: (`relief_bsdf.plate.choice.DEFAULT_METHOD`).  `microfacet` fits one isotropic lobe to the slopes,
#: so an anisotropic relief (the shared x3p: correlation 2.2 um along x, 40 um along y) would bake
#: isotropic; `auto` picks the method the panel names (kirchhoff, ray, ...), which keeps it.
from relief_bsdf import defaults as _defaults
DEFAULT_METHOD = _defaults.METHOD
PERIODIC_ITEMS = [
    ("auto", "From the file", "The file's own statement, else the wrap-around test (as the command line)"),
    ("yes", "Seamless tile", "The map repeats seamlessly: traced as one period"),
    ("no", "Measured patch", "A measured patch: mirror-extended for ray tracing, windowed for wave optics"),
]
SIDE_ITEMS = [
    ("outside", "Outside", "Light arriving from outside (air)"),
    ("inside", "Inside", "Light arriving from inside the dielectric"),
    ("both", "Both", "Both sides (needed for plates and the bake's back faces)"),
]


def _z_scale_changed(obj, context):
    from .mesh_import import set_z_scale
    set_z_scale(obj, obj.relief_z_scale)


class ReliefSceneSettings(bpy.types.PropertyGroup):
    method: EnumProperty(name="Method", items=METHOD_ITEMS, default=DEFAULT_METHOD)
    wavelengths_nm: StringProperty(name="Wavelengths (nm)", default=_defaults.as_text(_defaults.WAVELENGTHS_NM),
                                   description="Comma-separated vacuum wavelengths; three or more bake as RGB")
    theta_i_deg: StringProperty(name="Incidences (deg)", default=_defaults.as_text(_defaults.THETA_I_DEG),
                                description="Comma-separated incidence angles theta_i in [0, 90)")
    sides: EnumProperty(name="Sides", items=SIDE_ITEMS, default="both")
    samples: IntProperty(name="Samples", default=_defaults.SAMPLES, min=1,
                         description="Monte-Carlo samples per incidence")
    seed: IntProperty(name="Seed", default=_defaults.SEED, min=0)
    ior: FloatProperty(name="Refractive index", default=1.5, min=1.0001, max=4.0)
    # the map as Reconstruct reads it (the command line's --fill-holes, --crop, --downsample, --periodic)
    fill_holes: BoolProperty(name="Fill holes", default=False,
                             description="Fill missing points first (harmonic interpolation, as relief fill)")
    crop: StringProperty(name="Crop", default="", description="X0,Y0,W,H in points (empty: the whole map)")
    downsample: IntProperty(name="Downsample", default=1, min=1, max=64, description="K x K block means (1: none)")
    periodic: EnumProperty(name="Periodicity", items=PERIODIC_ITEMS, default="auto")
    table_path: StringProperty(options=_REL, name="Table", subtype="FILE_PATH", default="//relief_table.h5",
                               description="BSDF table (HDF5) written by Reconstruct, read by Bake")
    sample_path: StringProperty(options=_REL, name="Sample", subtype="FILE_PATH", default="",
                                description="sample.toml (plate, relief, instrument, recording)")
    output_dir: StringProperty(options=_REL, name="Output", subtype="DIR_PATH", default="//relief_out/",
                               description="Folder for simulate / fit / diagnose results")
    fit_dir: StringProperty(options=_REL, name="Fit result", subtype="DIR_PATH", default="",
                            description="Folder written by Fit (fit.json); used by Render")
    render_path: StringProperty(options=_REL, name="Render", subtype="FILE_PATH", default="//relief_plate.png")
    render_width: IntProperty(name="Width per image", default=256, min=16, max=4096)
    render_samples: IntProperty(name="Render samples", default=32, min=1, max=4096)
    job_status: StringProperty(name="Status", default="")
    last_group: StringProperty(name="Baked group", default="", description="The node group baked last")


CLASSES = (ReliefSceneSettings,)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.relief = PointerProperty(type=ReliefSceneSettings)
    bpy.types.Object.relief_z_scale = FloatProperty(
        name="Height exaggeration", default=1.0, min=0.0, soft_max=1000.0,
        description="Display factor: vertex z = true height (m) x this factor", update=_z_scale_changed)


def unregister():
    del bpy.types.Object.relief_z_scale
    del bpy.types.Scene.relief
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
