"""Relief BSDF: Blender extension (id `relief_addon`).

Measured height maps as meshes with their true heights, BSDF reconstruction from the 3D
view sidebar (tab "Relief"), tabulated shader node groups ("Relief BSDF: <name>") built
from Cycles microfacet closures, and plate renders before / after a fit.  The engine is the
bpy-free backend `relief_bsdf` (bundled as a wheel in the extension); this package only
builds Blender data around it.  Scripted use:

    bpy.ops.relief.import_heightmap(filepath=...)      bpy.ops.relief.reconstruct(...)
    bpy.ops.relief.simulate_plate(...)  bpy.ops.relief.fit(...)  bpy.ops.relief.diagnose(...)
    bpy.ops.relief.bake_bsdf(filepath=TABLE.h5)        bpy.ops.relief.render_plate(filepath=OUT.png)
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
