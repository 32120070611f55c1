"""Measured directional albedo of the Cycles closures the bake uses (Glossy and Refraction BSDF).

The bake (`relief_bsdf.bake`) turns a table's hemispherical reflectance R(theta) and
transmittance T(theta) into closure weights: weight = R / A(closure, roughness, theta), where
A is the closure's own directional albedo in Cycles.  Cycles 4.x/5.x compensate multiple
scattering with internal lookup tables (its Multiscatter GGX glossy is ~1 everywhere; its
rough Refraction BSDF exceeds 1 at grazing view from the outside and falls far below 1 from
the inside, past the critical angle), so A is *measured* here by rendering, not modelled.

Measurement (reciprocity, Cycles' path tracer evaluates closures for the view direction):
a patch seen by an orthographic camera at angle theta from its normal under a uniform
environment of radiance 1 restricted to one hemisphere shows radiance
L = integral f(l -> v) cos(theta_l) d omega_l = A(v).  The lit hemisphere is the viewer's
(glossy) or the opposite one (refraction).  One render per (closure, IOR, theta) holds a strip
of patches, one per roughness.

Run (a few minutes on 2 cores):  python relief_addon/cycles_calibration.py [--out FILE]
Output: relief_addon/data/cycles_albedo.npz with axes `theta_deg`, `roughness`, `ior`,
`ior_metallic` and arrays `glossy` (R, theta; Multiscatter GGX), `metallic` (ior_metallic, R,
theta; physical-conductor Fresnel with extinction 0, GGX), `refraction_front` and
`refraction_back` (ior, R, theta; GGX), plus the Blender version it was measured with
(5.0.1 for the file shipped).  `--kinds` re-measures some closures and keeps the others.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

THETA_DEG = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 85.0, 89.0])
ROUGHNESS = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0])
IOR = np.array([1.1, 1.3, 1.5, 1.7, 2.0, 2.5])
# Metallic BSDF (physical conductor Fresnel, extinction 0 = a dielectric's microfacet Fresnel):
# front faces use IOR = n, back faces 1 / n (total internal reflection past the critical angle)
IOR_METALLIC = np.array([0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.1, 1.3, 1.5, 1.7, 2.0, 2.5])
KINDS = ("glossy", "metallic", "refraction_front", "refraction_back")
PX = 8          # pixels per patch (square tiles)
DEFAULT_OUT = Path(__file__).resolve().parent / "data" / "cycles_albedo.npz"


def _scene(samples: int):
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = samples
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.use_denoising = False
    sc.cycles.max_bounces = 2
    sc.view_settings.view_transform = "Standard"
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    return sc


def hemisphere_world(scene, upper: bool):
    """World of radiance 1 for directions with z > 0 (upper) or z < 0, black elsewhere."""
    import bpy
    w = bpy.data.worlds.new("calibration")
    scene.world = w
    nt = w.node_tree
    nt.nodes.clear()
    tc = nt.nodes.new("ShaderNodeTexCoord")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    cmp = nt.nodes.new("ShaderNodeMath")
    cmp.operation = "GREATER_THAN" if upper else "LESS_THAN"
    cmp.inputs[1].default_value = 0.0
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(tc.outputs["Generated"], sep.inputs[0])
    nt.links.new(sep.outputs["Z"], cmp.inputs[0])
    nt.links.new(cmp.outputs[0], bg.inputs["Strength"])
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    return w


def ortho_camera(scene, theta_deg: float, below: bool, width_m: float, aspect: float):
    """Orthographic camera looking at the origin from (0, sin t, +-cos t); image x = world x."""
    import bpy
    from mathutils import Matrix, Vector
    cam = bpy.data.cameras.new("probe")
    cam.type = "ORTHO"
    cam.ortho_scale = width_m
    cam.clip_start = 0.01
    cam.clip_end = 1000.0
    ob = bpy.data.objects.new("probe", cam)
    scene.collection.objects.link(ob)
    scene.camera = ob
    t = math.radians(theta_deg)
    z = Vector((0.0, math.sin(t), -math.cos(t) if below else math.cos(t)))
    x = Vector((1.0, 0.0, 0.0)) if not below else Vector((-1.0, 0.0, 0.0))
    y = z.cross(x)
    rot = Matrix((x, y, z)).transposed().to_4x4()
    ob.matrix_world = Matrix.Translation(z * 50.0) @ rot
    return ob


def render_pixels(scene, path: Path) -> np.ndarray:
    """Render with write_still and read the float RGB back (rows from the bottom)."""
    import bpy
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(h, w, 4)[..., :3]


def _strip(kind: str, ior: float, theta_deg: float, samples: int, tmp: Path) -> np.ndarray:
    import bpy
    sc = _scene(samples)
    gap = 1.5
    n = ROUGHNESS.size
    upper_light = kind != "refraction_front"
    hemisphere_world(sc, upper_light)
    length = 2.0 * gap / max(math.cos(math.radians(theta_deg)), 1e-3)
    for k, r in enumerate(ROUGHNESS):
        mat = bpy.data.materials.new(f"m{k}")
        nt = mat.node_tree
        nt.nodes.clear()
        if kind == "glossy":
            b = nt.nodes.new("ShaderNodeBsdfGlossy")
            b.distribution = "MULTI_GGX"
            b.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        elif kind == "metallic":
            b = nt.nodes.new("ShaderNodeBsdfMetallic")
            b.fresnel_type = "PHYSICAL_CONDUCTOR"
            b.distribution = "GGX"
            b.inputs["IOR"].default_value = (ior, ior, ior)
            b.inputs["Extinction"].default_value = (0.0, 0.0, 0.0)
        else:
            b = nt.nodes.new("ShaderNodeBsdfRefraction")
            b.distribution = "GGX"
            b.inputs["IOR"].default_value = ior
            b.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        b.inputs["Roughness"].default_value = float(r)
        o = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(b.outputs[0], o.inputs["Surface"])
        me = bpy.data.meshes.new(f"p{k}")
        x0 = (k - (n - 1) / 2) * gap
        me.from_pydata([(x0 - 0.5, -length / 2, 0), (x0 + 0.5, -length / 2, 0), (x0 + 0.5, length / 2, 0),
                        (x0 - 0.5, length / 2, 0)], [], [(0, 1, 2, 3)])
        me.materials.append(mat)
        sc.collection.objects.link(bpy.data.objects.new(f"p{k}", me))
    ortho_camera(sc, theta_deg, below=(kind == "refraction_back"), width_m=n * gap, aspect=1.0)
    sc.render.resolution_x = n * 12
    sc.render.resolution_y = 12
    px = render_pixels(sc, tmp / "strip.exr")
    # patch k covers image columns [12 k + 2, 12 k + 10); keep the central 4 columns, all rows
    vals = np.array([px[2:10, 12 * k + 4: 12 * k + 8, 0].mean() for k in range(n)])
    if kind == "refraction_back":
        vals = vals[::-1]      # the camera's x axis is mirrored from below
    return vals


def measure(samples: int = 128, progress=print, kinds=KINDS) -> dict:
    import bpy
    out = {"theta_deg": THETA_DEG, "roughness": ROUGHNESS, "ior": IOR, "ior_metallic": IOR_METALLIC,
           "blender_version": np.array(bpy.app.version_string)}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if "glossy" in kinds:
            out["glossy"] = np.stack([_strip("glossy", 1.5, t, samples, tmp) for t in THETA_DEG], axis=1)
        for kind in kinds:
            if kind == "glossy":
                continue
            grid = IOR_METALLIC if kind == "metallic" else IOR
            arr = np.zeros((grid.size, ROUGHNESS.size, THETA_DEG.size))
            for a, ior in enumerate(grid):
                for b, t in enumerate(THETA_DEG):
                    arr[a, :, b] = _strip(kind, float(ior), float(t), samples, tmp)
                progress(f"{kind} ior {ior}")
            out[kind] = arr
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="measure Cycles closure albedos for the bake")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--kinds", default=",".join(KINDS), help="closures to (re)measure; others are kept")
    a = ap.parse_args(argv)
    res = measure(a.samples, kinds=[k for k in a.kinds.split(",") if k])
    if a.out.exists():                      # keep what was not re-measured
        old = dict(np.load(a.out))
        old.update(res)
        res = old
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(a.out, **res)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    if "--" in sys.argv:
        sys.argv = [sys.argv[0]] + sys.argv[sys.argv.index("--") + 1:]
    sys.exit(main())
