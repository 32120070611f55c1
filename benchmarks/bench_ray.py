"""Benchmark of the `ray` method against the raw Embree limit, measured in the same run.

Scene: a periodic 1024 x 1024 Gaussian relief with rms slope magnitude 0.3,
n = 1.5, a parallel beam at 30 degrees traced until every ray has left the relief layer,
binned into a table (1-degree rings x 5-degree azimuths).

Figures (all in this run, on this machine; the cores may be shared with other work, so
the ratios are the meaningful numbers):
- engine: `ray.reconstruct` timing of the tracing (BVH build excluded, reported apart):
  paths completed per second with all bounces and physics (Fresnel, Snell, TIR, periodic
  wrap, first-hit split, binning), polarised (Mueller matrices, the default) and scalar;
  segments (Embree queries) per path.
- embree_only: the very segment batches the engine traced (recorded in an untimed run of the
  same deterministic computation, so the recording copies are not charged to the engine), replayed through
  `scene.run` on the same number of threads: segments per second Embree alone reaches on
  that work.  ratio_to_embree = engine segments/s / Embree-alone segments/s (target >= 0.7).
- ratio_to_embree_cpu: the same ratio in CPU seconds (user + system of the process), less
  sensitive to other work sharing the cores.
- the same ratio for the polarised engine (`ratio_to_embree_polarized`, wall time): polarised tables
  are what `ray.reconstruct` and `relief reconstruct --method ray` give by default (option
  polarized=True); the headline `paths_per_s` / `ratio_to_embree` are the scalar engine.  The
  polarised ratios are medians over --repeat pairs, each an engine run and then Embree alone on its
  batches, back to back in this process (other work on the machine then slows both sides of a pair
  alike): `ratio_to_embree_polarized` the median of the pairs' wall-time ratios,
  `ratio_to_embree_cpu_polarized` the median of their CPU-time ratios; `polarized_pairs` lists every
  pair's (wall, CPU) ratio.
- the scalar engine again without the first-hit split (one outcome per ray, like the
  minimal loop; the split costs one more segment per path and gives the BRDF every ray).
- minimal_loop: a minimal numpy + embreex bounce loop with no physics beyond a Fresnel
  reflect/refract choice (no wrap, no polarisation, no binning), two threads over raster-
  ordered rays: paths/s.  ratio_to_minimal = engine paths/s / minimal paths/s (target >= 0.5).
- fit reuse: the build's split (mesh, Embree buffers, BVH), a new tracer for
  new heights on the same grid (`with_heights`) and the in-place update with BVH refit
  (`update_heights`), seconds.
- peak_rss_mb: peak resident memory of this process.
- polarized_cpu_s: the polarised pairs' CPU seconds (medians): the engine, Embree alone on its batches, and the
  engine outside Embree (per pair, engine less Embree): the part a change to the engine's own work moves,
  and the load-independent form of the ratio.
- ray_kernel: which kernels ran the numpy-side hot steps ("cython": the compiled `relief_bsdf.kernels`;
  "numpy": not built, or RELIEF_RAY_KERNEL=numpy); the same tables either way.
The last line is one JSON object.

    .venv/bin/python benchmarks/bench_ray.py [--size 1024] [--rays 1048576] [--threads N] [--repeat 5]
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import threading
import time

import numpy as np

from relief_bsdf.methods import ray
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.parallel import default_workers
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief

F32 = np.float32


def run_threads(fn, parts):
    """Run fn(part) for each part on its own thread; wall seconds."""
    ths = [threading.Thread(target=fn, args=(p,)) for p in parts]
    t0 = time.perf_counter()
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    return time.perf_counter() - t0


def cpu_s() -> float:
    """CPU seconds (user + system) of this process, all threads."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def embree_replay(scene, batches, threads):
    """(wall, cpu) seconds for Embree alone to intersect the recorded (origins, dirs, tfar) batches."""
    parts = [batches[i::threads] for i in range(threads)]

    def work(bs):
        for o, k, t in bs:
            scene.run(o, k, dists=t.copy(), output=1)

    c0 = cpu_s()
    wall = run_threads(work, parts)
    return wall, cpu_s() - c0


def _minimal_work(tracer, o, k, seed, n_in, segs_out, ti):
    r = np.random.default_rng(seed + ti)
    inside = np.zeros(o.shape[0], bool)
    R0 = F32(((n_in - 1) / (n_in + 1)) ** 2)
    eps = tracer.eps
    segs = 0
    while o.shape[0]:
        segs += o.shape[0]
        res = tracer.scene.run(o, k, output=1)
        hit = res["primID"] >= 0
        if not hit.any():
            break
        o, k, inside = o[hit], k[hit], inside[hit]
        t = res["tfar"][hit]
        n = res["Ng"][hit]
        n /= np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
        c = np.einsum("ij,ij->i", k, n)
        n *= -np.sign(c)[:, None]
        ci = np.abs(c)
        eta = np.where(inside, F32(n_in), F32(1 / n_in))
        s2 = eta * eta * (1 - ci * ci)
        refl = (r.random(ci.size, dtype=F32) < R0 + (1 - R0) * (1 - ci) ** 5) | (s2 >= 1)
        ct = np.sqrt(np.maximum(0, 1 - s2))
        a = np.where(refl, F32(1), eta)
        b = np.where(refl, 2 * ci, eta * ci - ct)
        o = o + t[:, None] * k + np.where(refl, eps, -eps)[:, None] * n
        k = a[:, None] * k + b[:, None] * n
        inside = inside ^ ~refl
    segs_out[ti] = segs


def minimal_paths_per_s(tracer, n_rays, theta_deg, threads, n_in=1.5, seed=1):
    side = int(np.sqrt(n_rays))
    g = (np.arange(side, dtype=np.float64) + 0.5) / side
    X, Y = np.meshgrid(g * float(tracer.Lx) - float(tracer.hx), g * float(tracer.Ly) - float(tracer.hy))
    o_all = np.stack([X.ravel(), Y.ravel(), np.full(side * side, float(tracer.z_top))], axis=1).astype(F32)
    th = np.radians(theta_deg)
    k_all = np.tile(np.array([-np.sin(th), 0, -np.cos(th)], F32), (side * side, 1))
    parts = np.array_split(np.arange(side * side), threads)
    segs = [0] * threads
    args = [(o_all[p].copy(), k_all[p].copy(), ti) for ti, p in enumerate(parts)]
    wall = run_threads(lambda a: _minimal_work(tracer, a[0], a[1], seed, n_in, segs, a[2]), args)
    n = side * side
    return n / wall, sum(segs) / n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--rays", type=int, default=1 << 20)
    ap.add_argument("--threads", type=int, default=default_workers())
    ap.add_argument("--theta", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=5, help="polarised engine / Embree pairs timed (median reported)")
    a = ap.parse_args(argv)

    L = 8e-6                                      # correlation length: 8 px at 1 um pitch
    slope = 0.3                                   # rms slope magnitude = 2 s / L
    t0 = time.perf_counter()
    relief = random_relief(a.size, 1e-6, slope * L / 2, L, seed=7)
    t_synth = time.perf_counter() - t0
    mat = Material(ConstantIndex(1.5))
    tracer = ray.ReliefTracer(relief, threads=a.threads)
    print(f"relief {a.size}^2 ({tracer.mesh.n_triangles} triangles): synth {t_synth:.2f} s, "
          f"mesh + BVH build {tracer.build_s:.2f} s", flush=True)

    def engine(polarized: bool, record: bool, split: bool = True):
        req = Request(theta_i_deg=(a.theta,), samples=a.rays, seed=3,
                      options={"polarized": polarized, "threads": a.threads, "first_hit_split": split})
        tracer.record_segments = [] if record else None
        c0 = cpu_s()
        t = time.perf_counter()
        tab = ray.reconstruct_with(tracer, relief, mat, req)[0]
        wall = time.perf_counter() - t
        cpu = cpu_s() - c0
        rec, tracer.record_segments = tracer.record_segments, None
        d = tab.metadata["tasks"][0]
        h = tab.hemispherical()
        return {"wall_s": wall, "cpu_s": cpu, "paths": d["rays"], "segments": d["segments"],
                "kernel": tab.metadata["ray_kernel"],
                "R": float(h["R"][0, 0, 0]), "T": float(h["T"][0, 0, 0]), "lost": float(h["lost"][0, 0, 0]),
                "mean_bounces": d["mean_bounces"]}, rec

    # the segment batches are recorded in an untimed run (warm-up: page faults, caches); the timed
    # run is the same deterministic computation (same seed, same chunks) without the recording hook
    warm, rec = engine(False, True)
    scal, _ = engine(False, False)
    assert scal["segments"] == warm["segments"] == sum(r[0].shape[0] for r in rec)
    t_emb, cpu_emb = embree_replay(tracer.scene, rec, a.threads)
    emb_seg_s = scal["segments"] / t_emb
    del rec
    nosplit, _ = engine(False, False, split=False)
    warm_p, rec = engine(True, True)
    # the polarised ratio from --repeat pairs (engine run, then Embree alone on its batches), each pair timed
    # back to back: the median pair is reported (a shared machine moves single runs by +-0.03), every pair too
    pairs = []
    for _ in range(max(1, a.repeat)):
        pol_i, _ = engine(True, False)
        t_i, c_i = embree_replay(tracer.scene, rec, a.threads)
        pairs.append((pol_i, t_i, c_i))
    wall_ratios = [t_i / p_i["wall_s"] for p_i, t_i, _ in pairs]      # segments/s engine over segments/s Embree
    cpu_ratios = [c_i / p_i["cpu_s"] for p_i, _, c_i in pairs]
    ratio_wall_p, ratio_cpu_p = float(np.median(wall_ratios)), float(np.median(cpu_ratios))
    pol = pairs[int(np.argsort(wall_ratios)[len(pairs) // 2])][0]      # the median pair's engine run (wall)
    pair_ratios = [(round(w, 3), round(c, 3)) for w, c in zip(wall_ratios, cpu_ratios)]
    # CPU seconds of the pairs (the process's own: far less sensitive to other work than wall time): the engine,
    # Embree alone on its batches, and the engine's time outside Embree (what a change to the engine moves)
    cpu_split = {"engine": float(np.median([p_i["cpu_s"] for p_i, _, _ in pairs])),
                 "embree": float(np.median([c_i for _, _, c_i in pairs])),
                 "outside_embree": float(np.median([p_i["cpu_s"] - c_i for p_i, _, c_i in pairs]))}
    del rec
    min_pps, min_spp = minimal_paths_per_s(tracer, a.rays, a.theta, a.threads)
    pps_s = scal["paths"] / scal["wall_s"]
    pps_p = pol["paths"] / pol["wall_s"]
    seg_s = scal["segments"] / scal["wall_s"]
    t = time.perf_counter()
    tracer_h = tracer.with_heights(relief.scaled(1.1))
    with_heights_s = time.perf_counter() - t
    update_s = tracer_h.update_heights(relief.scaled(1.2)) if tracer_h.direct_buffers else None
    del tracer_h
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"engine scalar   : {pps_s / 1e6:.3f} M paths/s, {scal['segments'] / scal['paths']:.3f} segments/path, "
          f"{seg_s / 1e6:.2f} M segments/s, R {scal['R']:.4f} T {scal['T']:.4f} lost {scal['lost']:.2e}")
    print(f"engine polarised: {pps_p / 1e6:.3f} M paths/s (Mueller 4x4 per ray: {pps_s / pps_p:.2f}x the scalar "
          f"time), R {pol['R']:.4f} T {pol['T']:.4f}; embree alone on its batches: ratio {ratio_wall_p:.3f} wall, "
          f"{ratio_cpu_p:.3f} CPU (medians of {len(pairs)} pairs (wall, CPU): {pair_ratios})")
    print(f"polarised CPU seconds (medians of the pairs, {pol['paths']} paths): engine {cpu_split['engine']:.3f}, "
          f"embree alone {cpu_split['embree']:.3f}, engine outside embree {cpu_split['outside_embree']:.3f}")
    pps_ns = nosplit["paths"] / nosplit["wall_s"]
    print(f"engine scalar without the first-hit split: {pps_ns / 1e6:.3f} M paths/s, "
          f"{nosplit['segments'] / nosplit['paths']:.3f} segments/path")
    print(f"embree alone on the same batches: {emb_seg_s / 1e6:.2f} M segments/s -> ratio {seg_s / emb_seg_s:.2f} "
          f"(CPU-time ratio {cpu_emb / scal['cpu_s']:.2f}: engine CPU {scal['cpu_s']:.2f} s, "
          f"embree CPU {cpu_emb:.2f} s)")
    print(f"minimal numpy+embree loop: {min_pps / 1e6:.3f} M paths/s ({min_spp:.2f} segments/path) -> "
          f"engine/minimal {pps_s / min_pps:.2f} (scalar), {pps_p / min_pps:.2f} (polarised)")
    print(f"build split {', '.join(f'{k} {v:.2f} s' for k, v in tracer.build_split_s.items())}; fit reuse: "
          f"with_heights {with_heights_s:.2f} s, update_heights (refit) "
          f"{'n/a' if update_s is None else f'{update_s:.2f} s'}")
    print(f"peak RSS {peak:.0f} MB, threads {a.threads}, ray kernels {pol['kernel']} (relief_bsdf.kernels; "
          "RELIEF_RAY_KERNEL=numpy forces numpy)")
    out = {"paths_per_s": pps_s, "paths_per_s_polarized": pps_p, "segments_per_path": scal["segments"] / scal["paths"],
           "segments_per_s": seg_s, "embree_segments_per_s": emb_seg_s, "ratio_to_embree": seg_s / emb_seg_s,
           "ratio_to_embree_cpu": cpu_emb / scal["cpu_s"], "paths_per_s_no_split": pps_ns,
           "minimal_loop_paths_per_s": min_pps, "ratio_to_minimal_no_split": pps_ns / min_pps,
           "ratio_to_minimal": pps_s / min_pps,
           "ratio_to_minimal_polarized": pps_p / min_pps, "polarized_cost_factor": pps_s / pps_p,
           "ratio_to_embree_polarized": ratio_wall_p, "ratio_to_embree_cpu_polarized": ratio_cpu_p,
           "polarized_pairs": pair_ratios, "polarized_cpu_s": cpu_split,
           "R": scal["R"], "T": scal["T"], "lost": scal["lost"], "rays": scal["paths"], "size": a.size,
           "threads": a.threads, "build_s": tracer.build_s, "build_split_s": tracer.build_split_s,
           "direct_buffers": tracer.direct_buffers, "with_heights_s": with_heights_s, "update_heights_s": update_s,
           "peak_rss_mb": peak, "ray_kernel": pol["kernel"]}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    from measure import bench
    sys.exit(bench("bench_ray", main))
