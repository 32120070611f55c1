"""Scale-out benchmark: the same fixed request on a Dask LocalCluster of 1 and 2 workers.

What it measures (all in one run, so machine noise hits every figure alike):
- `serial_s`: the request computed in this process, one task after another: the raw
  compute limit (no scheduling at all); `per_task_cost_s` = serial_s / tasks.
- `dask_1_s`, `dask_2_s`: the request through `parallel.map_tasks` on a LocalCluster of
  1 and 2 single-threaded worker processes (started before timing; the time includes
  scattering the context, scheduling, result transfer).  `speedup` = dask_1_s / dask_2_s.
- `processes_2_s`: the default local backend with 2 worker processes, for comparison.
- `overhead_per_task_s`: trivial tasks (return their argument) through the same Dask path
  on the 2-worker cluster, one Dask task each (RELIEF_TASK_GROUP=1), wall time / tasks: what
  each task costs beyond its own work (`overhead_per_task_batched_s`: with map_tasks'
  automatic grouping, what a user actually pays; `overhead_per_task_processes_s`: the
  default local backend).
- `cores_busy_*`: CPU seconds of the working processes / wall time: how many cores the run
  really got (on a machine shared with other programs, fewer than its workers).

Workload: by default the documented synthetic task `cluster.synthetic_task` (a seeded
random matrix-vector recurrence, `--size`, `--work` rounds; deterministic cost, no physics).
With `--method normals|microfacet` the request is a real reconstruction of a small synthetic
Gaussian relief (1 um pitch, 0.5 um rms, 10 um correlation) through `methods.reconstruct`,
whose tasks go through map_tasks (`ray` traces in threads inside one process for now, and
`kirchhoff` needs a finer pitch than this relief has).

Last line: one JSON object with at least `speedup`, `workers`, `overhead_per_task_s`.
Run: `.venv/bin/python benchmarks/bench_scale.py [--tasks 48] [--method NAME]`.
"""
from __future__ import annotations

import sys

import argparse
import contextlib
import logging
import json
import os
import platform
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")        # one thread per worker, here too
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _synthetic(args):
    from relief_bsdf.parallel.cluster import synthetic_task

    ctx = {"seed": 1, "size": args.size, "work": args.work}
    tasks = [(k,) for k in range(args.tasks)]

    def run(backend=None, workers=None):
        from relief_bsdf import parallel
        return parallel.map_tasks(synthetic_task, tasks, ctx, backend=backend, workers=workers, label="bench")

    return run, len(tasks), {"workload": "synthetic", "size": args.size, "work_rounds": args.work}


@contextlib.contextmanager
def _env(name, value):
    """Set (or with None, unset) an environment variable inside the block."""
    old = os.environ.get(name)
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def _backend_env(name):
    """Force the backend of every map_tasks call inside (methods call it without backend=)."""
    return _env("RELIEF_BACKEND", name)


def _gaussian_relief(n, pitch_m, rms_m, corr_m, seed):
    """Periodic Gaussian relief: white noise filtered to the spectrum of s^2 exp(-r^2/L^2)."""
    import numpy as np

    from relief_bsdf.parallel import task_rng
    from relief_bsdf.surface.relief import Relief

    f = np.fft.fftfreq(n, pitch_m)
    fx, fy = np.meshgrid(f, f)
    amp = np.exp(-(np.pi * corr_m) ** 2 * (fx ** 2 + fy ** 2) / 2)
    z = np.fft.ifft2(np.fft.fft2(task_rng(seed, 0).standard_normal((n, n))) * amp).real
    z *= rms_m / z.std()
    return Relief(heights_m=z, dx_m=pitch_m, dy_m=pitch_m, periodic=True, source="bench_scale gaussian")


def _method(args):
    import numpy as np

    from relief_bsdf import parallel
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.methods.request import Request

    relief = _gaussian_relief(args.relief_size, 1e-6, 0.5e-6, 10e-6, seed=1)
    material = Material(inside=ConstantIndex(1.5))
    req = Request(wavelengths_nm=tuple(np.linspace(450, 650, args.wavelengths)),
                  theta_i_deg=tuple(np.linspace(0, 80, args.thetas)), phi_i_deg=(0.0, 90.0),
                  samples=args.samples, seed=1)
    n = len(req.wavelengths_nm) * len(req.theta_i_deg) * len(req.phi_i_deg)

    def run(backend=None, workers=None):
        with _backend_env(backend), parallel.parallel_settings(workers=workers):
            return reconstruct(relief, material, req, args.method)

    return run, n, {"workload": f"method:{args.method}", "relief_size": args.relief_size, "samples": args.samples}


def _process_cpu_s() -> float:
    """CPU seconds used so far by the calling process (runs on each Dask worker)."""
    t = os.times()
    return t.user + t.system


def _measure(fn, cpu_probe):
    """(wall seconds, CPU seconds of the processes doing the work) of one call."""
    c0 = cpu_probe()
    t0 = time.perf_counter()
    fn()
    wall = time.perf_counter() - t0
    return wall, cpu_probe() - c0


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", type=int, default=48)
    p.add_argument("--size", type=int, default=256, help="synthetic: vector length")
    p.add_argument("--work", type=int, default=40, help="synthetic: rounds per task")
    p.add_argument("--trivial", type=int, default=400, help="trivial tasks for the overhead figure")
    p.add_argument("--method", default=None, help="use a real method's tasks instead of the synthetic workload")
    p.add_argument("--relief-size", type=int, default=128)
    p.add_argument("--samples", type=int, default=20000)
    p.add_argument("--wavelengths", type=int, default=4)
    p.add_argument("--thetas", type=int, default=6)
    p.add_argument("--repeat", type=int, default=3, help="best of this many interleaved timings")
    args = p.parse_args(argv)

    import distributed

    logging.getLogger("distributed").setLevel(logging.ERROR)

    from relief_bsdf import parallel
    from relief_bsdf.parallel.cluster import trivial_task

    run, n_tasks, info = (_method if args.method else _synthetic)(args)

    triv = list(range(args.trivial))
    clusters, clients = {}, {}

    def local_cpu():
        t = os.times()
        return t.user + t.system + t.children_user + t.children_system

    def cluster_cpu(nw):
        return lambda: local_cpu() + sum(clients[nw].run(_process_cpu_s).values())

    try:
        for nw in (1, 2):
            clusters[nw] = distributed.LocalCluster(n_workers=nw, threads_per_worker=1, processes=True,
                                                    dashboard_address=":0", silence_logs=40)
            clients[nw] = distributed.Client(clusters[nw], set_as_default=False)
            with parallel.parallel_settings(dask=clients[nw]):
                run()                                       # warm-up: imports and caches in the workers
        # interleaved rounds: load from other processes on the machine hits every variant alike
        times: dict = {k: [] for k in ("serial", "processes", 1, 2, "trivial", "trivial_batched", "trivial_processes")}
        for _ in range(args.repeat):
            times["serial"].append(_measure(lambda: run(backend="serial"), local_cpu))
            for nw in (1, 2):
                with parallel.parallel_settings(dask=clients[nw]):
                    times[nw].append(_measure(run, cluster_cpu(nw)))
            times["processes"].append(_measure(lambda: run(backend="processes", workers=2), local_cpu))
            with parallel.parallel_settings(dask=clients[2]):
                with _env("RELIEF_TASK_GROUP", "1"):               # one Dask task per task: raw overhead
                    times["trivial"].append(_measure(
                        lambda: parallel.map_tasks(trivial_task, triv, None, label="trivial"), cluster_cpu(2)))
                times["trivial_batched"].append(_measure(      # map_tasks' automatic grouping
                    lambda: parallel.map_tasks(trivial_task, triv, None, label="trivial"), cluster_cpu(2)))
            times["trivial_processes"].append(_measure(
                lambda: parallel.map_tasks(trivial_task, triv, None, backend="processes", workers=2), local_cpu))
    finally:
        for nw in clients:
            clients[nw].close()
            clusters[nw].close()
    best = {k: min(v) for k, v in times.items()}           # fastest wall time and its CPU seconds
    wall = {k: v[0] for k, v in best.items()}
    cpu = {k: v[1] for k, v in best.items()}
    load = os.getloadavg()[0]

    result = {
        **info,
        "tasks": n_tasks,
        "workers": 2,
        "serial_s": round(wall["serial"], 4),
        "per_task_cost_s": round(wall["serial"] / n_tasks, 5),
        "per_task_cpu_s": round(cpu["serial"] / n_tasks, 5),
        "dask_1_s": round(wall[1], 4),
        "dask_2_s": round(wall[2], 4),
        "speedup": round(wall[1] / wall[2], 3),
        "efficiency_2": round(wall[1] / wall[2] / 2, 3),
        "cores_busy_dask_1": round(cpu[1] / wall[1], 2),
        "cores_busy_dask_2": round(cpu[2] / wall[2], 2),
        "processes_2_s": round(wall["processes"], 4),
        "speedup_processes_vs_serial": round(wall["serial"] / wall["processes"], 3),
        "cores_busy_processes_2": round(cpu["processes"] / wall["processes"], 2),
        "overhead_per_task_s": round(wall["trivial"] / len(triv), 6),
        "overhead_cpu_per_task_s": round(cpu["trivial"] / len(triv), 6),
        "overhead_per_task_batched_s": round(wall["trivial_batched"] / len(triv), 6),
        "overhead_per_task_processes_s": round(wall["trivial_processes"] / len(triv), 6),
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(load, 2),
        "python": platform.python_version(),
        "dask": distributed.__version__,
    }
    print(f"{n_tasks} tasks of {info['workload']}: serial {wall['serial']:.3f} s "
          f"({wall['serial'] / n_tasks * 1e3:.2f} ms/task wall, {cpu['serial'] / n_tasks * 1e3:.2f} ms/task CPU)")
    print(f"Dask LocalCluster: 1 worker {wall[1]:.3f} s, 2 workers {wall[2]:.3f} s, speed-up {wall[1] / wall[2]:.2f} "
          f"(cores kept busy: {cpu[1] / wall[1]:.2f} vs {cpu[2] / wall[2]:.2f})")
    print(f"local processes (2): {wall['processes']:.3f} s, speed-up vs serial "
          f"{wall['serial'] / wall['processes']:.2f} (cores busy {cpu['processes'] / wall['processes']:.2f})")
    print(f"overhead per trivial task: Dask {wall['trivial'] / len(triv) * 1e3:.2f} ms wall "
          f"({cpu['trivial'] / len(triv) * 1e3:.2f} ms CPU), grouped by map_tasks "
          f"{wall['trivial_batched'] / len(triv) * 1e3:.3f} ms, local processes "
          f"{wall['trivial_processes'] / len(triv) * 1e3:.3f} ms")
    if load > (os.cpu_count() or 1):
        print(f"note: load average {load:.1f} on {os.cpu_count()} cores: other processes took CPU, so the wall-time "
              "speed-ups understate what idle cores give; 'cores_busy' says how many cores the run actually got")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    from measure import bench
    sys.exit(bench("bench_scale", lambda argv: (main(argv), 0)[1]))
