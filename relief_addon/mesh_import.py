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


def _id_safe(v):
    if isinstance(v, (list, tuple)):
        return [float(x) if isinstance(x, (int, float)) else str(x) for x in v]
    if isinstance(v, bool):
        return int(v)
    return v


def import_relief(relief, name: str | None = None, z_scale: float = 1.0,
                  collection: bpy.types.Collection | None = None) -> bpy.types.Object:
    """Create the relief object (mesh + properties) in `collection` (default: the scene's)."""
    from concurrent.futures import ThreadPoolExecutor
    name = name or Path(relief.source or "relief").stem
    # statistics (numpy FFTs, no bpy) on a worker thread while the mesh is built here
    with ThreadPoolExecutor(max_workers=1) as pool:
        stats = pool.submit(relief_stats, relief)
        me = build_mesh(name, relief.heights_m, relief.dx_m, relief.dy_m, z_scale)
        stats = stats.result()
    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    obj["relief_source"] = str(relief.source)
    obj["relief_pitch_m"] = [float(relief.dx_m), float(relief.dy_m)]
    obj["relief_stats"] = {k: _id_safe(v) for k, v in stats.items()}
    obj.relief_z_scale = z_scale
    return obj
