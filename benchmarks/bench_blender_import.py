"""Import speed of a 1024 x 1024 height map into Blender (target: under 2 s).

Times, in one run of this process (bpy module, CPU):
- `import`: the whole operator `bpy.ops.relief.import_heightmap` on an .npz file
  (read, statistics, mesh build, properties), median of --repeat runs;
- `mesh`: `relief_addon.mesh_import.build_mesh` alone (position + .corner_vert attributes
  with foreach_set, mesh.update(calc_edges=True));
- `from_pydata`: the same grid through Mesh.from_pydata, the plain Blender route, as the
  reference for the mesh-building part;
- `z_scale`: rewriting z for a new display exaggeration.
Prints one line per figure and a last line of JSON.

    .venv/bin/python benchmarks/bench_blender_import.py [--size 1024] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402


def _t(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    n = a.size
    import relief_addon
    from relief_addon.mesh_import import build_mesh, grid_faces
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    bpy.ops.wm.read_factory_settings(use_empty=True)
    relief_addon.register()
    rng = np.random.default_rng(0)
    h = 1e-6 * rng.standard_normal((n, n))
    with tempfile.TemporaryDirectory() as d:
        path = write_relief(Path(d) / "bench.npz", Relief(h, 1e-6, 1e-6))

        def op():
            bpy.ops.relief.import_heightmap(filepath=str(path))

        t_import = _t(op, a.repeat)
    t_mesh = _t(lambda: build_mesh("m", h, 1e-6, 1e-6), a.repeat)
    xs = (np.arange(n) * 1e-6)
    verts = np.stack(np.broadcast_arrays(xs[None, :], xs[:, None], h), -1).reshape(-1, 3)
    faces = grid_faces(n, n)

    def pydata():
        me = bpy.data.meshes.new("p")
        me.from_pydata(verts.tolist(), [], faces.tolist())
        me.update(calc_edges=True)

    t_py = _t(pydata, 1)
    obj = bpy.context.active_object
    t_z = _t(lambda: setattr(obj, "relief_z_scale", obj.relief_z_scale * 1.5), a.repeat)
    relief_addon.unregister()
    res = {"size": n, "import_s": t_import, "mesh_s": t_mesh, "from_pydata_s": t_py, "z_scale_s": t_z,
           "mesh_speedup_vs_from_pydata": t_py / t_mesh, "under_2s": t_import < 2.0}
    print(f"import operator {n}x{n}: {t_import:.3f} s (target < 2 s)")
    print(f"mesh build (attributes + foreach_set): {t_mesh:.3f} s; from_pydata: {t_py:.3f} s "
          f"({t_py / t_mesh:.1f}x slower)")
    print(f"z exaggeration rewrite: {t_z * 1e3:.1f} ms")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    from measure import bench
    sys.exit(bench("bench_blender_import", main))
