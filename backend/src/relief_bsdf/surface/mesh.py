"""Height map -> seamless periodic triangle mesh, for ray tracing the real relief.

Geometry (assumptions stated):
- The relief is a single-valued height field z(x, y) sampled on a regular grid; between
  samples it is the piecewise-linear surface of two triangles per grid cell (the diagonal
  runs from (i, j) to (i+1, j+1)).  Every triangle therefore has a normal with n_z > 0:
  the upper medium is always "above" the surface and a vertical line crosses it once.
  These triangles are the facets of `surface.stats.facet_slopes` (the one slope definition).
- The tile is periodic.  A periodic relief (synthetic) keeps its own period: the
  wrap-around cells joining the last row/column to the first are included, so the
  surface is seamless and a ray leaving the tile sideways re-enters from the opposite
  side onto the same surface.  A measured (non-periodic) relief is made periodic by even
  mirror extension without repeated edge samples, rows 0..ny-1, ny-2..1 (period 2 ny - 2)
  and the same for columns: heights and slope magnitudes are continuous across the seams,
  the slope distribution of an isotropic surface is unchanged in distribution (x and y
  slopes change sign in the mirrored copies), at 4x the triangle count.  The mirrored
  seams are a symmetry the real surface does not have: a small bias for long correlated
  features, documented in the table's metadata.
- NaN holes cannot be meshed: they are refused unless the caller asks for Laplace
  filling (`fill_holes`), which is then recorded in the relief's history.

Units: the mesh is expressed in units of the x pitch (`unit_m = dx_m`), centred on the
tile centre, so float32 coordinates keep ~1e-5 px resolution on a 1024 px tile.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.surface.relief import Relief


@dataclass(frozen=True)
class TileMesh:
    """A periodic triangle mesh of one relief tile.

    vertices: (V, 3) float32 in units of `unit_m`, x in [-Lx/2, Lx/2], y in [-Ly/2, Ly/2].
    triangles: (T, 3) int32 vertex indices, counter-clockwise seen from above (normals +z).
    period: (Lx, Ly) tile period in units of `unit_m`.
    z_min, z_max: height range of the surface (units of `unit_m`).
    shape: (ny, nx) samples of the periodic tile (after mirroring, if any).
    mirrored: True when a non-periodic relief was mirror-extended.
    history: what was done to the heights to mesh them (holes filled, mirrored).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    unit_m: float
    period: tuple
    z_min: float
    z_max: float
    shape: tuple
    mirrored: bool
    history: tuple = ()

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def triangle_normals(self) -> np.ndarray:
        """(T, 3) float32 unit normals, all with n_z > 0."""
        v = self.vertices.astype(np.float64)
        t = self.triangles
        n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return n.astype(np.float32)


def periodic_heights(relief: Relief, fill_holes: bool | int | None = None) -> tuple[np.ndarray, bool, tuple]:
    """Heights (metres) of one periodic tile of `relief`, whether it was mirrored, and history steps.

    fill_holes: None/False refuses NaN points; True fills every hole by Laplace interpolation;
    an int fills holes no wider than that many pixels (wider ones are still refused).
    """
    where = relief.source or "relief"
    relief.require_valid()
    steps: tuple = ()
    if not relief.valid.all():
        if fill_holes is None or fill_holes is False:
            raise InputError(where, f"{(~relief.valid).sum()} height samples are invalid (NaN); the ray tracer "
                             "needs a closed surface: fill them (--fill-holes on the command line, `relief fill MAP "
                             "-o FILLED.x3p`, fill_holes = true under [relief] in a sample.toml, or the method "
                             "option fill_holes=true / a largest gap in px)")
        filled = relief.fill_holes(None if fill_holes is True else int(fill_holes))
        if not filled.valid.all():
            raise InputError(where, f"{(~filled.valid).sum()} invalid points remain after filling holes no wider "
                             f"than {fill_holes} px; fill wider holes or crop them away")
        relief = filled
        steps += (filled.history[-1],)
    h = np.asarray(relief.heights_m, dtype=np.float64)
    if relief.periodic:
        return h, False, steps
    ny, nx = h.shape
    if ny < 3 or nx < 3:
        raise InputError(where, f"a non-periodic height map of shape {h.shape} is too small to mirror-extend")
    rows = np.concatenate([np.arange(ny), np.arange(ny - 2, 0, -1)])
    cols = np.concatenate([np.arange(nx), np.arange(nx - 2, 0, -1)])
    h = h[np.ix_(rows, cols)]
    steps += (f"mirror-extended to a periodic tile of {h.shape[0]} x {h.shape[1]} samples",)
    return h, True, steps


def build_tile_mesh(relief: Relief, fill_holes: bool | int | None = None) -> TileMesh:
    """Seamless periodic mesh of the relief: 2 triangles per cell, wrap-around cells included."""
    h_m, mirrored, steps = periodic_heights(relief, fill_holes)
    ny, nx = h_m.shape
    unit = float(relief.dx_m)
    sy = float(relief.dy_m) / unit
    x = np.arange(nx + 1, dtype=np.float64) - nx / 2.0
    y = (np.arange(ny + 1, dtype=np.float64) - ny / 2.0) * sy
    verts = np.empty((ny + 1, nx + 1, 3), dtype=np.float32)
    verts[..., 0] = x[None, :]
    verts[..., 1] = y[:, None]
    z_min, z_max = _fill_vertex_heights(verts, h_m, unit)
    idx = np.arange((ny + 1) * (nx + 1), dtype=np.int64).reshape(ny + 1, nx + 1)
    v00 = idx[:-1, :-1].ravel()
    v10 = idx[:-1, 1:].ravel()
    v01 = idx[1:, :-1].ravel()
    v11 = idx[1:, 1:].ravel()
    tris = np.empty((2 * v00.size, 3), dtype=np.int32)
    # counter-clockwise seen from +z: (00, 10, 11) and (00, 11, 01)
    tris[0::2, 0] = v00
    tris[0::2, 1] = v10
    tris[0::2, 2] = v11
    tris[1::2, 0] = v00
    tris[1::2, 1] = v11
    tris[1::2, 2] = v01
    return TileMesh(vertices=verts.reshape(-1, 3), triangles=tris, unit_m=unit,
                    period=(float(nx), float(ny) * sy), z_min=z_min, z_max=z_max,
                    shape=(ny, nx), mirrored=mirrored, history=steps)


def _fill_vertex_heights(verts: np.ndarray, h_m: np.ndarray, unit: float) -> tuple[float, float]:
    """Write the levelled heights (units of `unit`) into the (ny+1, nx+1, 3) vertex grid's z, the
    last row/column repeating the first (wrap-around cells); (z_min, z_max)."""
    ny, nx = h_m.shape
    z = (h_m - np.mean(h_m)) / unit
    zz = verts[..., 2]
    zz[:ny, :nx] = z
    zz[ny, :nx] = z[0]
    zz[:ny, nx] = z[:, 0]
    zz[ny, nx] = z[0, 0]
    return float(z.min()), float(z.max())


def remesh_heights(mesh: TileMesh, relief: Relief, fill_holes: bool | int | None = None) -> TileMesh:
    """`mesh` with the heights of `relief` on the same grid (same shape, pitch and periodicity):
    the triangle index buffer and the x, y of the vertices are reused, only z is rewritten.

    Equal to `build_tile_mesh(relief, fill_holes)` (tested); for fits that re-trace a relief whose
    heights change (scale, filter) but whose grid does not.
    """
    h_m, mirrored, steps = periodic_heights(relief, fill_holes)
    if h_m.shape != tuple(mesh.shape) or mirrored != mesh.mirrored or float(relief.dx_m) != mesh.unit_m \
            or abs(float(relief.dy_m) / float(relief.dx_m) * h_m.shape[0] - mesh.period[1]) > 1e-9 * mesh.period[1]:
        raise InputError(relief.source or "relief", f"heights of shape {relief.shape} (pitch {relief.dx_m:g} x "
                         f"{relief.dy_m:g} m, periodic {relief.periodic}) do not fit the mesh's grid "
                         f"{mesh.shape} (mirrored {mesh.mirrored}): build a new mesh")
    ny, nx = h_m.shape
    verts = mesh.vertices.copy().reshape(ny + 1, nx + 1, 3)
    z_min, z_max = _fill_vertex_heights(verts, h_m, mesh.unit_m)
    return TileMesh(vertices=verts.reshape(-1, 3), triangles=mesh.triangles, unit_m=mesh.unit_m,
                    period=mesh.period, z_min=z_min, z_max=z_max, shape=mesh.shape, mirrored=mirrored,
                    history=steps)
