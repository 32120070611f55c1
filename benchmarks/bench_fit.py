"""Benchmark of the demo fit with the real-relief default, against the raw Embree limit in the same run.

Figures (this run, this machine; the cores may be shared, so quote the ratios):
- fit: `relief fit scenes/demo/sample.toml` with the default method (`auto`, resolved once: ray
  tracing for a relief rough on the wavelength scale), its forward evaluations (new ones, not
  replays; `evaluations_by_model`: on the model of record and on the search model, fit.forward),
  wall seconds, seconds per evaluation, the metric before/after, the parameters and their 68 %
  intervals; target: the demo fit in 90 s on 2 quiet cores.
- tables: one evaluation's boundary tables (outside + inside) timed alone on the processed demo
  relief, with the Embree segments they traced (the ray tables' per-task metadata), so segments per second
  of the whole table pipeline (BVH build, tracing, physics, binning).
- embree_only: rays shot down onto the same relief's mesh through `scene.run` on two threads, their
  origins in 32-pixel block raster order as the ray method sorts them (directions 0-60 deg): the
  segments per second Embree alone reaches on it.  ratio = tables segments/s / embree_only.
- peak_rss_mb.
The last line is one JSON object.

    .venv/bin/python benchmarks/bench_fit.py [--sample scenes/demo/sample.toml] [--max-iter 40]
"""
from __future__ import annotations

import sys

import argparse
import json
import resource
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def embree_segments_per_s(relief, n_rays: int = 2_000_000, threads: int = 2, seed: int = 1) -> float:
    """Segments per second of `scene.run` alone on the relief's mesh (rays down at random angles)."""
    from relief_bsdf.methods.ray import ReliefTracer
    tr = ReliefTracer(relief)
    rng = np.random.default_rng(seed)
    Lx, Ly = float(tr.Lx), float(tr.Ly)
    o = np.stack([rng.uniform(-Lx / 2, Lx / 2, n_rays), rng.uniform(-Ly / 2, Ly / 2, n_rays),
                  np.full(n_rays, float(tr.z_top))], 1).astype(np.float32)
    # raster order by 32-pixel blocks, as the ray method sorts its origins (BVH cache locality)
    block = 32 * max(relief.dx_m, relief.dy_m)
    order = np.lexsort(((o[:, 0] + Lx / 2) // block, (o[:, 1] + Ly / 2) // block))
    o = o[order]
    th = np.radians(rng.uniform(0, 60, n_rays))
    ph = rng.uniform(0, 2 * np.pi, n_rays)
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)], 1).astype(np.float32)
    parts = np.array_split(np.arange(n_rays), threads)

    def work(ix):
        for b in np.array_split(ix, max(1, ix.size // 65536)):
            tr.scene.run(o[b], d[b])
    ths = [threading.Thread(target=work, args=(p,)) for p in parts]
    t0 = time.perf_counter()
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    return n_rays / (time.perf_counter() - t0)


def tables_once(fwd, s: float, g: float) -> dict:
    """Time one evaluation's boundary tables alone (cache cleared) and count their segments."""
    from relief_bsdf.plate import current_memory
    current_memory().clear()
    t0 = time.perf_counter()
    _, t_out, t_in = fwd.tables(s, g)
    dt = time.perf_counter() - t0
    segs = sum(int(task.get("segments", 0)) for t in (t_out, t_in) if t is not None
               for task in t.metadata.get("tasks", []))
    return {"seconds": dt, "segments": segs, "segments_per_s": segs / dt if dt > 0 else float("nan")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sample", default=str(REPO / "scenes/demo/sample.toml"))
    ap.add_argument("--max-iter", type=int, default=40)
    a = ap.parse_args(argv)
    from relief_bsdf.jobs import FitJob, run_fit
    from relief_bsdf.io.heightmaps import read_relief
    from relief_bsdf.io.recording import read_sample
    sample = read_sample(a.sample)
    relief = read_relief(sample.relief_path)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        doc = run_fit(FitJob(Path(a.sample), Path(tmp) / "fit", max_iter=a.max_iter)).doc
        wall = time.perf_counter() - t0
        evals = int(doc["evaluations_computed"])
    print(f"demo fit ({doc['method']}): {wall:.1f} s, {evals} evaluations ({wall / max(evals, 1):.2f} s each); "
          f"metric {doc['rms_before']:.3g} -> {doc['rms_after']:.3g}; {doc['parameters']} {doc['intervals']}")
    out = {"fit_seconds": wall, "evaluations": evals, "evaluations_by_model": doc.get("evaluations_by_model", {}),
           "seconds_per_evaluation": wall / max(evals, 1),
           "method": doc["method"], "method_reason": doc.get("method_reason", ""), "rms_before": doc["rms_before"],
           "rms_after": doc["rms_after"], "parameters": doc["parameters"], "intervals": doc["intervals"]}
    if doc["method"] == "ray":
        from relief_bsdf.fit.baseline import baseline
        from relief_bsdf.fit.forward import Forward
        fwd = Forward.of(baseline(sample))          # the fit's own forward model (relief levelled, auto decided)
        tb = tables_once(fwd, doc["parameters"]["height_scale"], doc["parameters"]["filter_sigma_um"])
        raw = embree_segments_per_s(relief)
        print(f"one evaluation's tables: {tb['seconds']:.2f} s, {tb['segments']} segments, "
              f"{tb['segments_per_s'] / 1e6:.2f} M/s; Embree alone on this relief {raw / 1e6:.2f} M/s; "
              f"ratio {tb['segments_per_s'] / raw:.2f}")
        out.update({"tables": tb, "embree_only_segments_per_s": raw, "ratio_to_embree": tb["segments_per_s"] / raw})
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    from measure import bench
    sys.exit(bench("bench_fit", main))
