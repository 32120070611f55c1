"""CPU time of the `ray` engine's numpy side alone, against Embree's, on one thread.

Runs one `ray.reconstruct_with` (the issue-3 scene: Gaussian relief, rms slope magnitude 0.3,
n = 1.5, beam at 30 degrees) recording every Embree result, then replays the same computation
with the recorded results (no Embree) and reports the calling thread's CPU seconds: numpy
ns per segment and numpy / Embree.  Less sensitive to a shared machine than wall-clock
figures (thread CPU time, best of --repeat).  engine/embree ~ embree / (embree + numpy) is the
ratio `bench_ray.py` reaches when nothing else costs CPU.  The numpy side runs the compiled
kernels when built (`relief_bsdf.kernels`; RELIEF_RAY_KERNEL=numpy for numpy alone).

    .venv/bin/python benchmarks/profile_ray_numpy.py [--size 1024] [--rays 1048576] [--polarized] [--profile] [--repeat 5]
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time

import numpy as np

from relief_bsdf.methods import ray
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--rays", type=int, default=1 << 20)
    ap.add_argument("--polarized", action="store_true")
    ap.add_argument("--profile", action="store_true", help="cProfile one replay")
    ap.add_argument("--repeat", type=int, default=5, help="replays timed (best and median reported)")
    ap.add_argument("--no-tile", dest="no_tile", action="store_true", help="Monte-Carlo sigma only (no sub-tile groups)")
    a = ap.parse_args(argv)
    L = 8e-6
    relief = random_relief(a.size, 1e-6, 0.3 * L / 2, L, seed=7)
    tracer = ray.ReliefTracer(relief, threads=1)
    mat = Material(ConstantIndex(1.5))
    req = Request(theta_i_deg=(30.0,), samples=a.rays, seed=3, options={"polarized": a.polarized, "threads": 1, **({"tile_uncertainty": False} if a.no_tile else {})})
    real = tracer.scene
    log: list = []

    class Record:
        def run(self, o, k, dists=None, output=1):
            t = time.thread_time()
            r = real.run(o, k, dists=dists, output=output)
            log.append((r, time.thread_time() - t))
            return r

    class Replay:
        def __init__(self):
            self.i = 0

        def run(self, o, k, dists=None, output=1):
            self.i += 1
            return log[self.i - 1][0]

    tracer.scene = Record()
    ref = ray.reconstruct_with(tracer, relief, mat, req)[0]
    emb = sum(x[1] for x in log)
    times = []
    for _ in range(max(1, a.repeat)):
        tracer.scene = Replay()
        t = time.thread_time()
        tab = ray.reconstruct_with(tracer, relief, mat, req)[0]
        times.append(time.thread_time() - t)
    best = min(times)
    assert np.array_equal(ref.values_per_sr, tab.values_per_sr)      # the replay is the same computation
    segs = ref.metadata["tasks"][0]["segments"]
    print(f"{'polarised' if a.polarized else 'scalar'} ({tab.metadata['ray_kernel']} kernels): embree CPU {emb:.3f} s, "
          f"numpy CPU {best:.3f} s (median of {len(times)} {float(np.median(times)):.3f} s) "
          f"({best / segs * 1e9:.0f} ns/segment), numpy/embree {best / emb:.2f}, "
          f"engine/embree ~ {emb / (emb + best):.2f}")
    if a.profile:
        tracer.scene = Replay()
        pr = cProfile.Profile()
        pr.enable()
        ray.reconstruct_with(tracer, relief, mat, req)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(15)
    return 0


if __name__ == "__main__":
    sys.exit(main())
