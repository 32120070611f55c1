"""The one place that decides where independent tasks run.

Independent tasks are things like (wavelength, incidence, side) of a reconstruction,
candidate effects of a diagnosis, or rows of a plate simulation.  A task is a pure
function `fn(context, task) -> result`, where `context` is the large shared input
(a relief, its mesh, a material) shipped to each worker *once*, and `task` is small.

Backends:
- "serial": in this process (used for one task, for debugging and inside workers).
- "processes" (default): local worker processes, one per core; the context is sent
  once per worker through the pool initializer.
- Dask (issue 8): selected by `--dask ADDRESS|local` or RELIEF_DASK_SCHEDULER.

Results come back in task order whatever ran them, and every task draws its random
numbers from `task_rng(seed, *key)`, so the same inputs and seed give the same
output on any backend and any number of workers.
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Sequence

import numpy as np

from .progress import Progress, silent

_CONTEXT: dict[int, Any] = {}


def task_rng(seed: int, *key: int) -> np.random.Generator:
    """Random generator for one task, derived from the run's seed and the task's integer key."""
    ints = [int(seed) & 0xFFFFFFFF] + [int(k) & 0xFFFFFFFF for k in key]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(ints)))


_WORKER_CACHE: dict[Any, Any] = {}


def worker_cached(key: Any, build: Callable[[], Any]) -> Any:
    """Build an expensive per-context object (a BVH, an FFT plan) once per worker process.

    Tasks call `worker_cached(("bvh", relief_digest), lambda: Tracer(relief))`; the object
    lives for the life of the worker, so it is built once per worker, not once per task.
    """
    if key not in _WORKER_CACHE:
        if len(_WORKER_CACHE) > 8:
            _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = build()
    return _WORKER_CACHE[key]


def default_workers() -> int:
    """Worker count: RELIEF_WORKERS if set, else every core."""
    env = os.environ.get("RELIEF_WORKERS")
    if env:
        return max(1, int(env))
    return max(1, os.cpu_count() or 1)


def _init_worker(token: int, context: Any) -> None:
    _CONTEXT[token] = context
    # numerical libraries inside a worker use one thread each: the pool already fills the cores
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def _run_in_worker(fn: Callable, token: int, task: Any) -> Any:
    return fn(_CONTEXT[token], task)


def map_tasks(fn: Callable[[Any, Any], Any], tasks: Sequence[Any], context: Any = None, *,
              progress: Progress | None = None, label: str = "task", backend: str | None = None,
              workers: int | None = None) -> list:
    """Run `fn(context, task)` for every task and return the results in task order.

    `fn` must be a module-level function (picklable).  Progress is reported as tasks
    complete, across all workers.
    """
    progress = progress or silent
    tasks = list(tasks)
    n = len(tasks)
    backend = backend or os.environ.get("RELIEF_BACKEND", "processes")
    workers = workers or default_workers()
    if n == 0:
        return []
    if backend == "serial" or workers == 1 or n == 1:
        out = []
        for k, t in enumerate(tasks):
            out.append(fn(context, t))
            progress(k + 1, n, label)
        return out
    if backend != "processes":
        raise ValueError(f"unknown backend {backend!r}")
    token = id(context)
    results: list = [None] * n
    with ProcessPoolExecutor(max_workers=min(workers, n), initializer=_init_worker,
                             initargs=(token, context)) as pool:
        futs = {pool.submit(_run_in_worker, fn, token, t): k for k, t in enumerate(tasks)}
        done = 0
        for f in as_completed(futs):
            results[futs[f]] = f.result()
            done += 1
            progress(done, n, label)
    return results
