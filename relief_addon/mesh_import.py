"""Height map -> Blender mesh with the true heights (bpy only here).

The mesh is a regular grid: vertex (row i, column j) sits at x = (j - (nx-1)/2) dx,
y = (i - (ny-1)/2) dy, z = height * relief_z_scale, all in metres (1 Blender unit = 1 m).
The true heights are kept, unscaled, in the float point attribute `relief_height_m`, so the
display exaggeration can change without losing them: z = relief_height_m * relief_z_scale.
Invalid (NaN) points keep z = 0 and the attribute `relief_valid` = 0; quads touching one are
left out.  Built through the `position` and `.corner_vert` attributes with foreach_set from
float32 / int32 numpy arrays and `mesh.update(calc_edges=True)` (about 0.5 s at 1024^2).
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

HEIGHT_ATTR = "relief_height_m"
VALID_ATTR = "relief_valid"


def grid_faces(ny: int, nx: int, valid: np.ndarray | None = None) -> np.ndarray:
    """(F, 4) int32 corner vertices of the grid quads (counter-clockwise seen from +z)."""
    idx = np.arange(ny * nx, dtype=np.int32).reshape(ny, nx)
    a = idx[:-1, :-1]
    quads = np.stack([a, idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    if valid is not None and not valid.all():
        v = valid.ravel()
        quads = quads[v[quads].all(axis=1)]
    return quads


def build_mesh(name: str, heights_m: np.ndarray, dx_m: float, dy_m: float, z_scale: float = 1.0) -> bpy.types.Mesh:
    """A grid mesh of the height map (see module doc)."""
    h = np.asarray(heights_m, dtype=np.float64)
    ny, nx = h.shape
    valid = np.isfinite(h)
    hz = np.where(valid, h, 0.0).astype(np.float32)
    xs = ((np.arange(nx) - (nx - 1) / 2.0) * dx_m).astype(np.float32)
    ys = ((np.arange(ny) - (ny - 1) / 2.0) * dy_m).astype(np.float32)
    pos = np.empty((ny, nx, 3), np.float32)
    pos[..., 0] = xs[None, :]
    pos[..., 1] = ys[:, None]
    pos[..., 2] = hz * np.float32(z_scale)
    quads = grid_faces(ny, nx, valid)
    me = bpy.data.meshes.new(name)
    me.vertices.add(ny * nx)
    me.loops.add(quads.size)
    me.polygons.add(quads.shape[0])
    me.attributes["position"].data.foreach_set("vector", pos.ravel())
    me.attributes[".corner_vert"].data.foreach_set("value", quads.ravel())
    me.polygons.foreach_set("loop_start", np.arange(0, quads.size, 4, dtype=np.int32))
    me.update(calc_edges=True)
    hat = me.attributes.new(HEIGHT_ATTR, "FLOAT", "POINT")
    hat.data.foreach_set("value", hz.ravel())
    vat = me.attributes.new(VALID_ATTR, "FLOAT", "POINT")
    vat.data.foreach_set("value", valid.astype(np.float32).ravel())
    return me


def set_z_scale(obj: bpy.types.Object, z_scale: float) -> None:
    """Rewrite vertex z = relief_height_m * z_scale (float32 position attribute, ~1 ms at 1024^2)."""
    me = obj.data
    if not isinstance(me, bpy.types.Mesh) or HEIGHT_ATTR not in me.attributes:
        return
    n = len(me.vertices)
    pos = np.empty(3 * n, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    h = np.empty(n, np.float32)
    me.attributes[HEIGHT_ATTR].data.foreach_get("value", h)
    pos = pos.reshape(n, 3)
    pos[:, 2] = h * np.float32(z_scale)
    me.attributes["position"].data.foreach_set("vector", pos.ravel())
    me.update()


def relief_stats(relief) -> dict:
    """Statistics for the panel: the backend's `relief_bsdf.surface.stats` when present, else a
    minimal set (rms height after plane levelling; rms slope magnitude from central
    differences on valid points)."""
    try:
        from relief_bsdf.surface.stats import relief_stats as backend_stats
    except ImportError:
        backend_stats = None
    if backend_stats is not None:
        d = backend_stats(relief).as_dict()
        return {k: v for k, v in d.items() if isinstance(v, (int, float, str, list, tuple))
                and not (isinstance(v, (list, tuple)) and any(x is None for x in v))}
    lv = relief.level(1)
    h = lv.heights_m
    gy, gx = np.gradient(h, relief.dy_m, relief.dx_m)
    s2 = gx**2 + gy**2
    return {"shape": list(relief.shape), "pitch_m": [relief.dx_m, relief.dy_m],
            "valid_fraction": relief.valid_fraction, "rms_height_m": float(np.sqrt(np.nanmean(h**2))),
            "rms_slope": float(np.sqrt(np.nanmean(s2)))}


_UNITS = ((1e-3, "MICROMETERS"), (1e-2, "MILLIMETERS"), (1.0, "CENTIMETERS"), (float("inf"), "METERS"))


def frame_in_views(obj: bpy.types.Object, scene: bpy.types.Scene | None = None) -> dict:
    """Frame a relief object in every 3D view and set a display unit for its size.

    True sizes stay in metres (1 unit = 1 m, `unit_settings.scale_length` untouched); what
    changes is what the views show: the scene's length unit (micrometres for a map under 1 mm,
    millimetres under 1 cm, ...), and in each 3D view of every screen the clip distances
    (start = size / 1000, end = size x 100: the default 10 mm clip start would hide a 0.1 mm
    map, and the tight end keeps metre-sized objects such as the default cube out of sight),
    the grid scale (one grid line per power of ten below the size) and the view centred on the
    object at a distance of twice its size.  Returns the values set.
    """
    scene = scene or bpy.context.scene
    me = obj.data
    n = len(me.vertices)
    pos = np.empty(3 * n, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(n, 3).astype(float)
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    size = float(max(np.max(hi - lo), 1e-9))
    centre = obj.matrix_world @ Vector(tuple(0.5 * (lo + hi)))
    unit = next(u for limit, u in _UNITS if size < limit)
    us = scene.unit_settings
    us.system = "METRIC"
    us.length_unit = unit
    grid = 10.0 ** np.floor(np.log10(size))
    done = {"size_m": size, "length_unit": unit, "clip_start_m": size / 1000.0, "clip_end_m": size * 100.0,
            "grid_scale": float(grid), "views": 0}
    for screen in bpy.data.screens:
        for area in screen.areas:
            for space in area.spaces:
                if space.type != "VIEW_3D":
                    continue
                space.clip_start, space.clip_end = done["clip_start_m"], done["clip_end_m"]
                space.overlay.grid_scale = done["grid_scale"]
                r3d = space.region_3d
                if r3d is not None:
                    r3d.view_location = centre
                    r3d.view_distance = 2.0 * size
                done["views"] += 1
    return done


def _id_safe(v):
    if isinstance(v, (list, tuple)):
        return [float(x) if isinstance(x, (int, float)) else str(x) for x in v]
    if isinstance(v, bool):
        return int(v)
    return v


def optical_regime(relief, ior: float, wavelengths_nm, theta_i_deg) -> dict:
    """The method `auto` would pick for this relief and the scene's request, and why
    (`relief_bsdf.methods.auto.choose`: Rayleigh parameter, k R_c, k l, slopes); light from
    both sides.  An error is returned as {"error": text}, never raised (the import goes on)."""
    try:
        from relief_bsdf.core.index import ConstantIndex, Material
        from relief_bsdf.methods.auto import choose
        from relief_bsdf.methods.request import Request
        req = Request(wavelengths_nm=tuple(wavelengths_nm), theta_i_deg=tuple(theta_i_deg),
                      incident_from=("outside", "inside")).validate()
        c = choose(relief, Material(ConstantIndex(float(ior))), req)
    except Exception as e:  # noqa: BLE001 - shown in the panel instead
        return {"error": f"{type(e).__name__}: {e}"}
    g = c.figures["rayleigh_parameter"]
    regime = "optically smooth" if g < 0.1 else ("locally flat, not small" if c.valid["kirchhoff"][0]
                                                 else "rough (geometric optics)" if c.valid["ray"][0]
                                                 else "between regimes")
    return {"method": c.method, "regime": regime, "summary": c.summary, "rayleigh_parameter": float(g),
            "wavelength_nm": float(c.figures["wavelength_nm"])}


def import_relief(relief, name: str | None = None, z_scale: float = 1.0,
                  collection: bpy.types.Collection | None = None,
                  regime_request: dict | None = None) -> bpy.types.Object:
    """Create the relief object (mesh + properties) in `collection` (default: the scene's).

    regime_request: {"ior", "wavelengths_nm", "theta_i_deg"} to assess the optical regime with
    (`optical_regime`, stored in `relief_regime`); None skips it."""
    from concurrent.futures import ThreadPoolExecutor
    name = name or Path(relief.source or "relief").stem
    # statistics and the regime (numpy, no bpy) on worker threads while the mesh is built here
    with ThreadPoolExecutor(max_workers=2) as pool:
        stats = pool.submit(relief_stats, relief)
        regime = pool.submit(optical_regime, relief, **regime_request) if regime_request else None
        me = build_mesh(name, relief.heights_m, relief.dx_m, relief.dy_m, z_scale)
        stats = stats.result()
        regime = regime.result() if regime is not None else None
    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    obj["relief_source"] = str(relief.source)
    obj["relief_pitch_m"] = [float(relief.dx_m), float(relief.dy_m)]
    obj["relief_stats"] = {k: _id_safe(v) for k, v in stats.items()}
    if regime is not None:
        obj["relief_regime"] = regime
    obj.relief_z_scale = z_scale
    return obj
