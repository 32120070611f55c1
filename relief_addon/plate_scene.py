"""Plate over a checkerboard under diffuse light (paper figure 11), before / after a fit.

`prepare_plates(source, ...)` is bpy-free (worker thread): it reads a fit folder (fit.json)
or a sample.toml, derives the boundary tables of the relief as measured and as fitted (or,
for a bare sample, a smooth plate and the measured relief) and bakes their lookup rows.
`render_side_by_side(plates, out)` builds one Cycles scene per plate on the main thread,
renders it, and writes the images side by side (left: before, right: after) through
OpenImageIO (`relief_bsdf.io.oiio`).

Scene (metres): a checkerboard (5 mm squares, diffuse, albedo 0.05 / 0.8) on z = 0; the
plate (50 x 50 mm, the sample's thickness) 30 mm above it, so that the scattering visibly
blurs the board; its rough face carries the baked node group and every other face is smooth
glass of the same index; a uniform white world (diffuse light, radiance 1); a perspective
camera 30 degrees off the normal; the plate's label on a dark strip along the bottom.  Cycles,
Standard view transform, OpenImageDenoise and an indirect clamp (`_denoise`): a 256 px wide
image at 32 samples takes seconds.
"""
from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np

PLATE_SIZE_M = 0.05
GAP_M = 0.03
CHECKER_M = 0.005


def _sample_path_from_fit(fit_dir: Path, doc: dict) -> Path:
    from relief_bsdf.errors import InputError
    s = Path(doc.get("sample", ""))
    for cand in (s, fit_dir / s, fit_dir.parent / s, fit_dir.parent / s.name):
        if cand.is_file():
            return cand
    raise InputError(fit_dir / "fit.json", f"the sample {str(s)!r} it names cannot be found")


def _tables(relief, material, method: str, progress=None):
    from relief_bsdf.plate import ReliefFace, TableGrid
    theta_out = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 89.0])
    face = ReliefFace(relief, method=method, samples=100_000, seed=0)
    grid = TableGrid(2.0, 10.0, 10.0, direct_theta_step_deg=None)      # a picture: no direct grid (plate.grid)
    out, ins = face.tables(material, grid, [550.0], theta_out, True, progress)
    return [t for t in (out, ins) if t is not None]


def prepare_plates(source, albedo=None, closure: str = "metallic", progress=None) -> list[dict]:
    """[before, after] plates: {"label", "lut", "thickness_m", "rough_face", "ior"} (no bpy)."""
    from relief_bsdf.bake import bake_lut
    from relief_bsdf.errors import InputError
    from relief_bsdf.fit.optimise import process_relief
    from relief_bsdf.plate import flat_tables
    from relief_bsdf.io.heightmaps import read_sample_relief
    from relief_bsdf.io.recording import read_sample
    src = Path(source)
    if src.is_dir():
        fj = src / "fit.json"
        if not fj.is_file():
            raise InputError(src, "not a fit folder (no fit.json); give a sample.toml or the folder of `relief fit`")
        doc = json.loads(fj.read_text())
        sample = read_sample(_sample_path_from_fit(src, doc))
        par = doc.get("parameters", {})
        method = doc.get("method", "auto")
        relief = read_sample_relief(sample)
        variants = [("before fit", process_relief(relief, 1.0, 0.0)),
                    ("after fit", process_relief(relief, float(par.get("height_scale", 1.0)),
                                                 float(par.get("filter_sigma_um", 0.0))))]
    elif src.is_file() and src.suffix.lower() == ".toml":
        sample = read_sample(src)
        method = "auto"                 # the relief's own physics (plate.choice)
        variants = [("smooth", None), ("measured relief", read_sample_relief(sample))]
    else:
        raise InputError(src, "expected a sample.toml or a fit folder")
    mat = sample.material
    plates = []
    for k, (label, relief) in enumerate(variants):
        if progress:
            progress(k, len(variants), label)
        if relief is None:
            tables = list(flat_tables(mat, [550.0], np.arange(0.0, 90.0, 10.0), np.arange(0.0, 90.0, 10.0),
                                      np.linspace(0, 90, 10), np.arange(-15.0, 360.0, 30.0)))
        else:
            tables = _tables(relief, mat, method)
        lut = bake_lut(tables, f"{sample.path.stem} {label}", albedo=albedo, reflection_closure=closure)
        outside = next((t for t in tables if t.incident_from == "outside"), None)
        plates.append({"label": label, "lut": lut, "thickness_m": sample.plate.thickness_mm * 1e-3,
                       "rough_face": sample.plate.rough_face, "ior": lut.ior, "table_outside": outside})
    if progress:
        progress(len(variants), len(variants), "baked")
    return plates


# ====================================================================== Blender side


def _checker_material():
    import bpy
    mat = bpy.data.materials.new("Relief checkerboard")
    nt = mat.node_tree
    nt.nodes.clear()
    tc = nt.nodes.new("ShaderNodeTexCoord")
    ck = nt.nodes.new("ShaderNodeTexChecker")
    ck.inputs["Color1"].default_value = (0.8, 0.8, 0.8, 1.0)
    ck.inputs["Color2"].default_value = (0.05, 0.05, 0.05, 1.0)
    ck.inputs["Scale"].default_value = 1.0 / CHECKER_M / 2.0   # object coordinates in metres
    d = nt.nodes.new("ShaderNodeBsdfDiffuse")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(tc.outputs["Object"], ck.inputs["Vector"])
    nt.links.new(ck.outputs["Color"], d.inputs["Color"])
    nt.links.new(d.outputs[0], out.inputs["Surface"])
    return mat


def build_scene(plate: dict, width: int, samples: int):
    """A new scene with board, plate (baked rough face) and camera; returns the scene."""
    import bpy
    from mathutils import Vector
    from .bake_nodes import assign_to_rough_face, build_node_group, lut_image
    sc = bpy.data.scenes.new(f"Relief plate {plate['label']}")
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = samples
    _denoise(sc)
    sc.cycles.max_bounces = 12
    sc.cycles.transmission_bounces = 12
    sc.cycles.glossy_bounces = 8
    sc.cycles.transparent_max_bounces = 8
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.render.resolution_x = width
    sc.render.resolution_y = int(round(width * 0.75))
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    w = bpy.data.worlds.new("Relief diffuse light")
    sc.world = w
    bg = w.node_tree.nodes.get("Background") or w.node_tree.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    # board
    me = bpy.data.meshes.new("Relief board")
    s = 0.15
    me.from_pydata([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)], [], [(0, 1, 2, 3)])
    me.materials.append(_checker_material())
    board = bpy.data.objects.new("Relief board", me)
    sc.collection.objects.link(board)
    # plate: a box, bottom at GAP_M
    t = plate["thickness_m"]
    h = PLATE_SIZE_M / 2
    z0, z1 = GAP_M, GAP_M + t
    v = [(-h, -h, z0), (h, -h, z0), (h, h, z0), (-h, h, z0), (-h, -h, z1), (h, -h, z1), (h, h, z1), (-h, h, z1)]
    f = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    pm = bpy.data.meshes.new("Relief plate")
    pm.from_pydata(v, [], f)
    pm.update()
    pobj = bpy.data.objects.new("Relief plate", pm)
    sc.collection.objects.link(pobj)
    img = lut_image(plate["lut"])
    group = build_node_group(plate["lut"], img)
    assign_to_rough_face(pobj, group, plate["rough_face"])
    pobj["relief_rough_face"] = plate["rough_face"]
    # camera 30 degrees off the normal
    cam = bpy.data.cameras.new("Relief camera")
    cam.lens = 50.0
    co = bpy.data.objects.new("Relief camera", cam)
    sc.collection.objects.link(co)
    d = Vector((0.0, -math.sin(math.radians(30)), math.cos(math.radians(30))))
    target = Vector((0.0, 0.0, GAP_M))
    co.location = target + d * 0.16
    co.rotation_euler = (-d).to_track_quat("-Z", "Y").to_euler()
    sc.camera = co
    cam.clip_start = 0.005
    _label(sc, co, plate["label"])
    return sc


def _denoise(sc) -> None:
    """Denoise the demo picture (OpenImageDenoise, in Cycles' CPU build of Blender 4 / 5), and
    clamp indirect samples at 10: the checkerboard seen through the rough face is lit only
    indirectly, and rare paths through the plate's polished sides otherwise leave a line of
    hot pixels along its edges.  (For pictures only: radiometric renders, goniophotometer.py,
    clamp nothing and denoise nothing.)"""
    import _cycles
    sc.cycles.use_denoising = bool(getattr(_cycles, "with_openimagedenoise", False))
    if sc.cycles.use_denoising:
        sc.cycles.denoiser = "OPENIMAGEDENOISE"
        sc.cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    sc.cycles.sample_clamp_indirect = 10.0


def _emission(name: str, rgb):
    import bpy
    m = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    nt = m.node_tree
    nt.nodes.clear()
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (*rgb, 1.0)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(em.outputs[0], out.inputs["Surface"])
    return m


def _label(sc, cam_obj, text: str) -> None:
    """The plate's label ("before fit", "after fit", ...) in white on a dark strip along the
    bottom of the frame: a text object and a plane parented to the camera, 1 cm in front of it
    (inside the view, in front of everything else), emissive so no light or glass changes them."""
    import bpy
    d = 0.01
    cam = cam_obj.data
    half_w = 0.5 * d * cam.sensor_width / cam.lens          # landscape frame: the sensor width is horizontal
    half_h = half_w * sc.render.resolution_y / sc.render.resolution_x
    strip_h = 0.22 * half_h
    me = bpy.data.meshes.new("Relief label strip")
    y0, y1 = -half_h, -half_h + strip_h
    me.from_pydata([(-half_w, y0, -d), (half_w, y0, -d), (half_w, y1, -d), (-half_w, y1, -d)], [], [(0, 1, 2, 3)])
    me.materials.append(_emission("Relief label strip", (0.02, 0.02, 0.02)))
    strip = bpy.data.objects.new("Relief label strip", me)
    cu = bpy.data.curves.new("Relief label", "FONT")
    cu.body = text
    cu.size = 0.7 * strip_h
    cu.align_x, cu.align_y = "CENTER", "CENTER"
    cu.materials.append(_emission("Relief label text", (1.0, 1.0, 1.0)))
    txt = bpy.data.objects.new("Relief label", cu)
    txt.location = (0.0, y0 + 0.5 * strip_h, -0.999 * d)
    for ob in (strip, txt):
        sc.collection.objects.link(ob)
        ob.parent = cam_obj
        ob.visible_shadow = False


def render_scene(sc, path: Path) -> np.ndarray:
    """Render `sc` to a float EXR and return RGB (H, W, 3), top row first."""
    import bpy
    sc.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=sc.name)
    img = bpy.data.images.load(str(path))
    wdt, hgt = img.size
    px = np.empty(wdt * hgt * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(hgt, wdt, 4)[::-1, :, :3]


def _srgb(lin: np.ndarray) -> np.ndarray:
    """Standard view transform: linear -> sRGB display encoding (IEC 61966-2-1)."""
    x = np.clip(lin, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_image(path: Path, rgb_display: np.ndarray) -> Path:
    """Write an RGB image (display-encoded floats in [0, 1], top row first) with OpenImageIO, atomically."""
    from relief_bsdf.io import oiio as oiio_loader
    from relief_bsdf.io.atomic import atomic_path
    oiio = oiio_loader.load()
    path = Path(path)
    data = np.ascontiguousarray(rgb_display, dtype=np.float32)
    h, w, c = data.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise RuntimeError(f"OpenImageIO cannot write {path.suffix} files: {oiio.geterror()}")
        fmt = oiio.FLOAT if path.suffix.lower() == ".exr" else oiio.UINT8
        spec = oiio.ImageSpec(w, h, c, fmt)
        if not out.open(str(tmp), spec):
            raise RuntimeError(f"OpenImageIO: {out.geterror()}")
        out.write_image(data)
        out.close()
    return path


def render_side_by_side(plates: list[dict], out, width: int = 256, samples: int = 32,
                        keep_scenes: bool = False) -> Path:
    """Render every plate and write them side by side (left to right) to `out` (PNG / EXR / ...)."""
    out = Path(out)
    frames = []
    with tempfile.TemporaryDirectory() as d:
        for k, p in enumerate(plates):
            sc = build_scene(p, width, samples)
            frames.append(render_scene(sc, Path(d) / f"plate{k}.exr"))
            if not keep_scenes:
                _remove_scene(sc)
    gap = np.ones((frames[0].shape[0], max(2, width // 64), 3), np.float32)
    parts = []
    for k, f in enumerate(frames):
        if k:
            parts.append(gap)
        parts.append(f if out.suffix.lower() == ".exr" else _srgb(f))
    image = np.concatenate(parts, axis=1)
    if out.suffix.lower() != ".exr":
        image = with_bsdf_panel(image, plates)
    return write_image(out, image)


def with_bsdf_panel(image: np.ndarray, plates: list[dict]) -> np.ndarray:
    """`image` (display-encoded RGB) with the boundary BSDF curves of the plates below it
    (`relief_bsdf.report.plots.before_after_figure`: in-plane T and R for light from outside,
    one line style per plate, the haze in the legend), as wide as the renders; unchanged when a
    plate has no outside table.  bpy-free."""
    tables = [p.get("table_outside") for p in plates]
    if any(t is None for t in tables):
        return image
    from relief_bsdf.report.plots import before_after_figure, figure_rgb
    w = image.shape[1]
    panel = figure_rgb(before_after_figure(tables, [p["label"] for p in plates], width_px=w,
                                           height_px=max(240, int(round(0.55 * w)))))
    panel = panel[:, :w] if panel.shape[1] >= w else np.pad(panel, ((0, 0), (0, w - panel.shape[1]), (0, 0)),
                                                               constant_values=1.0)
    gap = np.ones((max(2, w // 128), w, 3), np.float32)
    return np.concatenate([image, gap, panel.astype(np.float32)], axis=0)


def _remove_scene(sc) -> None:
    import bpy
    for ob in list(sc.collection.objects):
        data = ob.data
        bpy.data.objects.remove(ob)
        try:
            if isinstance(data, bpy.types.Curve) and data.users == 0:
                bpy.data.curves.remove(data)
            elif isinstance(data, bpy.types.Mesh) and data.users == 0:
                bpy.data.meshes.remove(data)
            elif isinstance(data, bpy.types.Camera) and data.users == 0:
                bpy.data.cameras.remove(data)
        except ReferenceError:       # already freed with its object
            pass
    if sc.world is not None and sc.world.users <= 1:
        bpy.data.worlds.remove(sc.world)
    bpy.data.scenes.remove(sc)
