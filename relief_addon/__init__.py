"""Relief BSDF: Blender extension (id `relief_addon`).

Measured height maps as meshes with their true heights, BSDF reconstruction from the 3D
view sidebar (tab "Relief"), tabulated shader node groups ("Relief BSDF: <name>") built
from Cycles microfacet closures, and plate renders before / after a fit.  The engine is the
bpy-free backend `relief_bsdf` (bundled as a wheel in the extension); this package only
builds Blender data around it.  Scripted use:

    bpy.ops.relief.import_heightmap(filepath=...)      bpy.ops.relief.reconstruct(...)
    bpy.ops.relief.simulate_plate(...)  bpy.ops.relief.fit(...)  bpy.ops.relief.diagnose(...)
    bpy.ops.relief.bake_bsdf(filepath=TABLE.h5)        bpy.ops.relief.render_plate(filepath=OUT.png)
    bpy.ops.relief.add_preset(preset="frosted_acrylic" | "anti_glare_film" | "light_guide_dots")

Scripts need no `if __name__ == "__main__":` guard, inside Blender, with `blender --background
--python` or with the bpy module: worker processes start from the add-on's own code, never
from the calling script (workers.py).  Preferences (prefs.py): the worker count and the
cache folder that unsaved files use (paths.py: `//` paths of an unsaved file live there and
are copied beside the .blend when it is saved; nothing in /tmp is saved into a .blend).
Imported maps are framed in the 3D views at their true size in metres (mesh_import.py);
baking adds a material slot (existing materials stay) and updates a group baked from the
same table in place; the group "Relief BSDF: <name>" has the inputs Tint, Haze, Fitted and
Rotation (bake_nodes.py).
"""
from __future__ import annotations

from . import operators, panels, paths, prefs, props

_MODULES = (prefs, props, paths, operators, panels)


def register():
    for m in _MODULES:
        m.register()


def unregister():
    for m in reversed(_MODULES):
        m.unregister()
