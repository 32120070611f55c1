"""A virtual goniophotometer in Cycles: measure what a material really renders.

Two measurements on a flat square patch (1 m, normal +z, the material on it), both read
from an orthographic camera that sees only the patch, rendered with write_still and read
back as float32 (Standard view transform, no denoising, no adaptive sampling):

- `bsdf(material, theta_i, theta_s, phi_s, side)`: a sun lamp (collimated, strength E in
  W/m^2 across its beam, angle 0) lights the patch from (theta_i, phi_i = 0); the camera looks
  from (theta_s, phi_s) on side R (z > 0) or T (z < 0).  The pixel radiance is
  L = f(i -> s) E cos(theta_i), hence f = L / (E cos theta_i) (formats.md, Nicodemus BSDF).
  Cycles does not scale radiance by n^2 across a refraction (it renders basic radiance
  L / n^2), so for side T with the camera inside a medium of index n_s the physical radiance
  BTDF is the returned value times n_s^2 / n_i^2.
- `directional(material, theta, side)`: the environment has radiance 1 over one hemisphere
  (the viewer's for R, the opposite one for T) and 0 over the other; the camera looks from
  theta above the patch.  The pixel is L = integral f(l -> v) cos(theta_l) d omega_l, which
  for a reciprocal reflection lobe is the directional-hemispherical reflectance R(theta),
  and for the transmission closure the directional transmittance seen from v (the quantity
  the bake targets, see relief_bsdf.bake).

Each render is a few pixels at a few hundred samples: about 0.3-1 s on 2 cores.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector


def _direction(theta_deg: float, phi_deg: float, below: bool = False) -> Vector:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return Vector((math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), -math.cos(t) if below else math.cos(t)))


def _look_from(ob, d: Vector, distance: float = 20.0) -> None:
    """Place `ob` at distance along d, its -Z axis toward the origin."""
    z = d.normalized()
    helper = Vector((0.0, 0.0, 1.0)) if abs(z.z) < 0.99 else Vector((1.0, 0.0, 0.0))
    x = helper.cross(z).normalized()
    y = z.cross(x)
    ob.matrix_world = Matrix.Translation(z * distance) @ Matrix((x, y, z)).transposed().to_4x4()


def new_scene(samples: int = 256, resolution: int = 6) -> bpy.types.Scene:
    """An empty scene set up for radiometry (Cycles CPU, Standard view, float EXR output)."""
    scene = bpy.data.scenes.new("Relief goniophotometer")
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 4
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.resolution_x = resolution
    scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.film_transparent = False
    return scene


def _world(scene, mode: str) -> None:
    """mode: 'black', 'upper' (radiance 1 for z > 0) or 'lower' (z < 0)."""
    w = bpy.data.worlds.new("Relief probe world")
    scene.world = w
    nt = w.node_tree
    nt.nodes.clear()
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    if mode == "black":
        bg.inputs["Strength"].default_value = 0.0
        return
    tc = nt.nodes.new("ShaderNodeTexCoord")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    cmp = nt.nodes.new("ShaderNodeMath")
    cmp.operation = "GREATER_THAN" if mode == "upper" else "LESS_THAN"
    cmp.inputs[1].default_value = 0.0
    nt.links.new(tc.outputs["Generated"], sep.inputs[0])
    nt.links.new(sep.outputs["Z"], cmp.inputs[0])
    nt.links.new(cmp.outputs[0], bg.inputs["Strength"])


def _patch(scene, material) -> bpy.types.Object:
    me = bpy.data.meshes.new("Relief probe patch")
    me.from_pydata([(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)], [], [(0, 1, 2, 3)])
    me.materials.append(material)
    ob = bpy.data.objects.new("Relief probe patch", me)
    scene.collection.objects.link(ob)
    return ob


def _camera(scene, theta_deg: float, phi_deg: float, below: bool) -> None:
    cam = bpy.data.cameras.new("Relief probe camera")
    cam.type = "ORTHO"
    # the patch's projection is at least cos(theta) wide: keep the view inside it
    cam.ortho_scale = 0.4 * max(math.cos(math.radians(theta_deg)), 0.05)
    cam.clip_start = 0.1
    cam.clip_end = 100.0
    ob = bpy.data.objects.new("Relief probe camera", cam)
    scene.collection.objects.link(ob)
    scene.camera = ob
    _look_from(ob, _direction(theta_deg, phi_deg, below))


def _render_mean(scene) -> np.ndarray:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "probe.exr"
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True, scene=scene.name)
        img = bpy.data.images.load(str(path))
        px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        bpy.data.images.remove(img)
    return px.reshape(-1, 4)[:, :3].astype(float).mean(axis=0)


def _cleanup(scene) -> None:
    for ob in list(scene.collection.objects):
        data = ob.data
        bpy.data.objects.remove(ob)
        if isinstance(data, bpy.types.Mesh):
            bpy.data.meshes.remove(data)
        elif isinstance(data, bpy.types.Camera):
            bpy.data.cameras.remove(data)
        elif isinstance(data, bpy.types.Light):
            bpy.data.lights.remove(data)
    if scene.world is not None:
        bpy.data.worlds.remove(scene.world)
    bpy.data.scenes.remove(scene)


def bsdf(material, theta_i_deg: float, theta_s_deg: float, phi_s_deg: float, side: str = "R",
         irradiance_w_m2: float = 1.0, samples: int = 256) -> np.ndarray:
    """Rendered BSDF (1/sr, RGB) for light from (theta_i, 0) toward (theta_s, phi_s) on `side`."""
    scene = new_scene(samples)
    try:
        _world(scene, "black")
        _patch(scene, material)
        light = bpy.data.lights.new("Relief probe sun", "SUN")
        light.energy = irradiance_w_m2
        light.angle = 0.0
        lo = bpy.data.objects.new("Relief probe sun", light)
        scene.collection.objects.link(lo)
        _look_from(lo, _direction(theta_i_deg, 0.0))
        _camera(scene, theta_s_deg, phi_s_deg, below=(side == "T"))
        L = _render_mean(scene)
        return L / (irradiance_w_m2 * math.cos(math.radians(theta_i_deg)))
    finally:
        _cleanup(scene)


def directional(material, theta_deg: float, side: str = "R", samples: int = 256) -> np.ndarray:
    """Rendered directional reflectance (side R) or transmittance (side T) seen from theta above."""
    scene = new_scene(samples)
    try:
        _world(scene, "upper" if side == "R" else "lower")
        _patch(scene, material)
        _camera(scene, theta_deg, 0.0, below=False)
        return _render_mean(scene)
    finally:
        _cleanup(scene)


def radiance(material, theta_deg: float, phi_deg: float = 0.0, below: bool = False, samples: int = 16) -> np.ndarray:
    """Mean radiance (RGB) of the patch seen from (theta, phi), above or below, in a black world
    (for emissive materials, e.g. to read lookup images back through Cycles)."""
    scene = new_scene(samples)
    try:
        _world(scene, "black")
        _patch(scene, material)
        _camera(scene, theta_deg, phi_deg, below)
        return _render_mean(scene)
    finally:
        _cleanup(scene)
