"""The one place that decides where independent tasks run.

Independent tasks are things like (wavelength, incidence, side) of a reconstruction,
candidate effects of a diagnosis, or rows of a plate simulation.  A task is a pure
function `fn(context, task) -> result`, where `context` is the large shared input
(a relief, its mesh, a material) shipped to each worker *once*, and `task` is small.

Backends (chosen per call by `backend=`, else by `configure` / the environment):
- "serial": in this process (one task, debugging, and always inside a worker, so a
  task that itself calls `map_tasks` never nests pools).
- "processes" (default): local worker processes, one per core, no setup; the context
  is sent once per worker through the pool initializer.  A worker that dies (segfault,
  out-of-memory kill) breaks the pool: finished results are kept, the unfinished tasks
  run again on a fresh pool up to `retries` times, then a `WorkerCrashed` error names
  them.  Workers ignore SIGINT; Ctrl-C in the parent terminates them and re-raises.
- "dask": a `distributed` cluster, selected by `configure(dask=...)`, the CLI flag
  `--dask tcp://HOST:PORT|local` (`add_parallel_args`) or `RELIEF_DASK_SCHEDULER`.
  The context is scattered to every worker once (`client.scatter(broadcast=True)`),
  tasks are submitted with `retries=` (a task that raised runs again; a task lost with
  its worker is rescheduled by the scheduler), progress counts tasks completed across
  the cluster (`distributed.as_completed`).  Dask specifics live in `cluster.py`.

Checkpoints: with `checkpoint_dir=` (or `configure(checkpoint_dir=...)`, CLI
`--checkpoint-dir`) every finished task's result is written atomically to
`DIR/<label>-<sha256 of (fn, context, task)>.pkl.z` as soon as it arrives; a rerun with
the same function, context and task loads it instead of computing, so a killed run
resumes where it stopped.  Changing the context (relief, material, seed, sampling) or
the task changes the key, so a stale checkpoint is never reused.

Results come back in task order whatever ran them, and every task draws its random
numbers from `task_rng(seed, *key)`, so the same inputs and seed give the same
output on any backend, any number of workers, and across a resume.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import multiprocessing
import multiprocessing.context
import os
import pickle
import signal
import threading
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from relief_bsdf.io.atomic import write_bytes_atomic
from relief_bsdf.errors import InputError
from relief_bsdf.progress import Progress, silent

_CONTEXT: dict[int, Any] = {}
_IN_WORKER = False                 # this whole process is a worker (local pool)
_LOCAL = threading.local()         # this thread runs a task (a Dask worker thread, maybe in-process)


class WorkerCrashed(RuntimeError):
    """A local worker process died (not a Python exception in a task) more often than allowed."""


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


def forget_worker_cached(key: Any) -> None:
    """Drop one `worker_cached` object from this process (e.g. a BVH built for a serial run)."""
    _WORKER_CACHE.pop(key, None)


def default_workers() -> int:
    """Worker count: RELIEF_WORKERS if set, else every core."""
    env = os.environ.get("RELIEF_WORKERS")
    if env:
        return max(1, int(env))
    return max(1, os.cpu_count() or 1)


def in_worker() -> bool:
    """True inside a task running on a worker (local process or Dask worker)."""
    return _IN_WORKER or getattr(_LOCAL, "in_task", False)


@contextlib.contextmanager
def running_task() -> Iterator[None]:
    """Mark this thread as running a task (nested map_tasks calls then run serially)."""
    old = getattr(_LOCAL, "in_task", False)
    _LOCAL.in_task = True
    try:
        yield
    finally:
        _LOCAL.in_task = old


# ---------------------------------------------------------------------------------------------
# configuration: where tasks run

@dataclass(frozen=True)
class Settings:
    """Process-wide defaults for `map_tasks` (set by `configure`, the CLI or Blender).

    dask: None (local processes), "local" (a LocalCluster started on first use),
          "tcp://HOST:PORT" (an existing scheduler), or a `distributed.Client`.
    workers: local worker count (processes or LocalCluster); None = every core.
    checkpoint_dir: folder for per-task checkpoints; None = no checkpoints.
    retries: how often a failed task (or, locally, a crashed pool) is run again.
    """

    dask: Any = None
    workers: int | None = None
    checkpoint_dir: str | None = None
    retries: int = 2


_SETTINGS = Settings()
_UNSET = object()


def settings() -> Settings:
    """The current process-wide settings."""
    return _SETTINGS


def _check_dask_spec(dask: Any) -> Any:
    if dask is None or not isinstance(dask, str):
        return dask
    spec = dask.strip()
    if spec == "local" or "://" in spec:
        return spec
    if ":" in spec and spec.rsplit(":", 1)[1].isdigit():
        return "tcp://" + spec
    raise InputError("--dask", f"expected 'local' or a scheduler address such as tcp://HOST:8786, got {dask!r}")


def configure(*, dask: Any = _UNSET, workers: Any = _UNSET, checkpoint_dir: Any = _UNSET,
              retries: Any = _UNSET) -> Settings:
    """Set where `map_tasks` runs from now on; returns the previous settings.

    Only the given keywords change.  `dask="local"` starts a LocalCluster lazily on the
    first `map_tasks` call; `dask="tcp://HOST:PORT"` connects to that scheduler.
    """
    global _SETTINGS
    old = _SETTINGS
    changes: dict[str, Any] = {}
    if dask is not _UNSET:
        changes["dask"] = _check_dask_spec(dask)
    if workers is not _UNSET:
        if workers is not None and int(workers) < 1:
            raise InputError("--workers", f"need at least 1 worker, got {workers}")
        changes["workers"] = None if workers is None else int(workers)
    if checkpoint_dir is not _UNSET:
        changes["checkpoint_dir"] = None if checkpoint_dir is None else str(checkpoint_dir)
    if retries is not _UNSET:
        if int(retries) < 0:
            raise InputError("--retries", f"retries must be >= 0, got {retries}")
        changes["retries"] = int(retries)
    _SETTINGS = replace(old, **changes)
    return old


@contextlib.contextmanager
def parallel_settings(**kwargs: Any) -> Iterator[Settings]:
    """`configure(**kwargs)` for the duration of a `with` block; a LocalCluster started
    inside the block is closed at its end and the previous settings come back."""
    global _SETTINGS
    from relief_bsdf.parallel import cluster

    before = set(cluster.open_clients())
    old = configure(**kwargs)
    try:
        yield _SETTINGS
    finally:
        _SETTINGS = old
        for spec in set(cluster.open_clients()) - before:
            cluster.close_client(spec)


def add_parallel_args(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add `--dask`, `--workers`, `--checkpoint-dir`, `--retries` to a subcommand's parser
    (those it does not define already).

    Use with `apply_parallel_args(args)` (or `with parallel_from_args(args):`) in `run`.
    """
    have = set(getattr(parser, "_option_string_actions", {}))   # a subcommand's own --workers stays its own
    g = parser.add_argument_group("where the work runs")
    if "--dask" not in have:
        g.add_argument("--dask", metavar="ADDRESS|local", default=None,
                       help="run tasks on a Dask cluster: tcp://HOST:PORT of a running scheduler, or 'local' "
                            "to start a LocalCluster (default: local processes, or $RELIEF_DASK_SCHEDULER)")
    if "--workers" not in have:
        g.add_argument("--workers", type=int, default=None, metavar="N",
                       help="local worker processes (default: every core, or $RELIEF_WORKERS)")
    if "--checkpoint-dir" not in have:
        g.add_argument("--checkpoint-dir", default=None, metavar="DIR",
                       help="save each finished task here; a rerun with the same inputs resumes from it")
    if "--retries" not in have:
        g.add_argument("--retries", type=int, default=None, metavar="K",
                       help="run a failed or lost task again up to K times (default 2)")
    return parser


def _args_settings(args: argparse.Namespace) -> dict[str, Any]:
    kw: dict[str, Any] = {}
    if getattr(args, "dask", None) is not None:
        kw["dask"] = args.dask
    if getattr(args, "workers", None) is not None:
        kw["workers"] = args.workers
    if getattr(args, "checkpoint_dir", None) is not None:
        kw["checkpoint_dir"] = args.checkpoint_dir
    if getattr(args, "retries", None) is not None:
        kw["retries"] = args.retries
    return kw


def apply_parallel_args(args: argparse.Namespace) -> Settings:
    """Configure from the flags of `add_parallel_args` for the rest of the process
    (a LocalCluster it starts is closed at exit)."""
    configure(**_args_settings(args))
    return _SETTINGS


def parallel_from_args(args: argparse.Namespace):
    """Context manager: the flags of `add_parallel_args` in force inside the block."""
    return parallel_settings(**_args_settings(args))


def resolve_backend(backend: str | None = None) -> str:
    """Which backend a `map_tasks` call with this `backend=` argument uses now."""
    if in_worker():
        return "serial"
    if backend:
        return backend
    env = os.environ.get("RELIEF_BACKEND")
    if env:
        return env
    if _SETTINGS.dask is not None or os.environ.get("RELIEF_DASK_SCHEDULER"):
        return "dask"
    return "processes"


# ---------------------------------------------------------------------------------------------
# checkpoints

def _digest_context(context: Any) -> str:
    digest = getattr(context, "digest", None)
    if callable(digest):
        return str(digest())
    try:
        blob = pickle.dumps(context, protocol=5)
    except Exception as e:  # noqa: BLE001 - report what cannot be checkpointed
        raise InputError("--checkpoint-dir", f"the task context cannot be checkpointed ({type(e).__name__}: {e})")
    return hashlib.sha256(blob).hexdigest()


def task_keys(fn: Callable, tasks: Sequence[Any], context: Any, label: str = "task") -> list[str]:
    """Stable checkpoint names: `<label>-<sha256(fn, context, task)>` (first 32 hex digits)."""
    fn_name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
    base = hashlib.sha256(fn_name.encode() + b"\0" + _digest_context(context).encode())
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in label)[:40] or "task"
    keys = []
    for t in tasks:
        h = base.copy()
        h.update(pickle.dumps(t, protocol=4))
        keys.append(f"{safe}-{h.hexdigest()[:32]}")
    return keys


def _ck_path(ckdir: Path, key: str) -> Path:
    return ckdir / f"{key}.pkl.z"


def _load_checkpoint(path: Path) -> tuple[bool, Any]:
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        return False, None
    try:
        return True, pickle.loads(zlib.decompress(blob))
    except Exception:  # noqa: BLE001 - a damaged checkpoint is recomputed, never trusted
        return False, None


def _save_checkpoint(path: Path, result: Any) -> None:
    write_bytes_atomic(path, zlib.compress(pickle.dumps(result, protocol=5), 1))


# ---------------------------------------------------------------------------------------------
# runners: each yields (task index, result) as tasks complete

def _run_serial(fn: Callable, context: Any, items: list[tuple[int, Any]], **_: Any) -> Iterator[tuple[int, Any]]:
    for i, t in items:
        yield i, fn(context, t)


def _init_worker(token: int, context: Any) -> None:
    global _IN_WORKER
    _CONTEXT[token] = context
    _IN_WORKER = True
    # Ctrl-C goes to the whole process group: the parent handles it and terminates us
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # numerical libraries inside a worker use one thread each: the pool already fills the cores
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def _run_in_worker(fn: Callable, token: int, batch: list) -> list:
    context = _CONTEXT[token]
    return [fn(context, task) for task in batch]


def group_size(n_tasks: int, n_workers: int) -> int:
    """Tasks sent to a worker as one unit: 1 unless there are many more tasks than workers.

    Each unit costs a round trip (~0.1 ms locally, 1-3 ms on Dask; bench_scale.py); grouping
    consecutive tasks amortises it while keeping at least 16 units per worker, so the idle
    tail at the end of a run stays a few percent of it, and at most 32 tasks per unit, so
    progress, checkpoints and the work lost with a worker stay fine-grained.
    `RELIEF_TASK_GROUP` overrides it.
    """
    env = os.environ.get("RELIEF_TASK_GROUP")
    if env:
        return max(1, int(env))
    return int(min(32, max(1, n_tasks // (16 * max(1, n_workers)))))


def _stop_pool(pool: ProcessPoolExecutor, kill: bool) -> None:
    if not kill:
        pool.shutdown(wait=True)
        return
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(timeout=5)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)


def _pool_context() -> multiprocessing.context.BaseContext:
    """Start method of the local worker pool: "forkserver", never plain "fork".

    Forking a process that already runs native thread pools (Embree's task threads after a
    BVH build in this process, OpenBLAS, a Dask client's event loop) copies their locks but
    not their threads, and the child can hang forever in its first call into that library
    (seen: a worker stuck creating its Embree device).  The fork server is a fresh interpreter
    that imports this module once and forks workers from that clean state, so starting a
    worker stays cheap.  Like "spawn", it needs `if __name__ == "__main__":` in user scripts.
    `RELIEF_START_METHOD` overrides it (e.g. "spawn").
    """
    method = os.environ.get("RELIEF_START_METHOD", "forkserver")
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload([__name__])
    return ctx


def _run_processes(fn: Callable, context: Any, items: list[tuple[int, Any]], *, workers: int, retries: int,
                   label: str, **_: Any) -> Iterator[tuple[int, Any]]:
    token = id(context)
    pending = dict(items)
    restarts = 0
    while pending:
        pool = ProcessPoolExecutor(max_workers=max(1, min(workers, len(pending))), initializer=_init_worker,
                                   initargs=(token, context), mp_context=_pool_context())
        clean = False
        broken = False
        try:
            todo = list(pending.items())
            b = group_size(len(todo), workers)
            groups = [todo[k:k + b] for k in range(0, len(todo), b)]
            futs = {}
            try:
                for g in groups:
                    futs[pool.submit(_run_in_worker, fn, token, [t for _, t in g])] = [i for i, _ in g]
            except BrokenProcessPool:          # a worker died while tasks were still being handed out
                broken = True
            if not broken:
                for f in as_completed(futs):
                    try:
                        rs = f.result()
                    except BrokenProcessPool:
                        broken = True
                        break
                    for i, r in zip(futs[f], rs):
                        del pending[i]
                        yield i, r
            if broken:                         # keep whatever else finished before the pool broke
                for f, idx in futs.items():
                    if f.done() and not f.cancelled() and f.exception() is None and idx[0] in pending:
                        for i, r in zip(idx, f.result()):
                            del pending[i]
                            yield i, r
            clean = not broken
        finally:
            _stop_pool(pool, kill=not clean)
        if broken:
            restarts += 1
            if restarts > retries:
                shown = sorted(pending)[:8]
                more = "" if len(pending) <= 8 else f" (+{len(pending) - 8} more)"
                raise WorkerCrashed(
                    f"a worker process died abruptly (crash or out-of-memory kill) {restarts} times while running "
                    f"{label} tasks; {len(pending)} unfinished, indices {shown}{more}; finished ones were kept"
                    + (" in the checkpoint folder" if _SETTINGS.checkpoint_dir else "")
                    + ". Try fewer workers (--workers) or a smaller request.")


def _run_dask(fn: Callable, context: Any, items: list[tuple[int, Any]], *, workers: int | None, retries: int,
              label: str, **_: Any) -> Iterator[tuple[int, Any]]:
    from relief_bsdf.parallel import cluster

    spec = _SETTINGS.dask if _SETTINGS.dask is not None else os.environ.get("RELIEF_DASK_SCHEDULER")
    client = cluster.get_client(_check_dask_spec(spec) or "local", workers=workers or _SETTINGS.workers)
    yield from cluster.run_on_client(client, fn, context, items, retries=retries, label=label)


_RUNNERS = {"serial": _run_serial, "processes": _run_processes, "dask": _run_dask}


def map_tasks(fn: Callable[[Any, Any], Any], tasks: Sequence[Any], context: Any = None, *,
              progress: Progress | None = None, label: str = "task", backend: str | None = None,
              workers: int | None = None, checkpoint_dir: str | os.PathLike | None = None,
              retries: int | None = None, on_result: Callable[[int, Any], None] | None = None) -> list:
    """Run `fn(context, task)` for every task and return the results in task order.

    `fn` must be a module-level function (picklable); `context` is shipped to each worker
    once.  Progress is reported as tasks complete, across all workers (checkpointed tasks
    count as done at once).  `backend`: "serial", "processes" or "dask" (default: as
    configured, see the module doc).  `checkpoint_dir` (default: as configured) saves each
    result as it arrives and reuses saved ones.  `retries` (default 2): how often a failed
    (dask) or crashed (processes) task is run again.

    `on_result(index, result)`: called in this process as each result arrives (or is loaded
    from a checkpoint), in completion order; the returned list then holds None, so a big
    request can write each task's values straight into its table (float32) instead of
    keeping every task's result until the end.
    """
    progress = progress or silent
    tasks = list(tasks)
    n = len(tasks)
    if n == 0:
        return []
    backend = resolve_backend(backend)
    if backend not in _RUNNERS:
        raise ValueError(f"unknown backend {backend!r}; choose from {', '.join(_RUNNERS)}")
    retries = _SETTINGS.retries if retries is None else int(retries)
    nworkers = workers or _SETTINGS.workers or default_workers()
    if backend == "processes" and (nworkers == 1 or n == 1):
        backend = "serial"

    # the configured checkpoint folder is for the top-level run; a nested call only uses an explicit one
    ckdir = checkpoint_dir if checkpoint_dir is not None or in_worker() else _SETTINGS.checkpoint_dir
    results: list = [None] * n
    items = list(enumerate(tasks))
    paths: list[Path] | None = None
    stats = {"backend": backend, "total": n, "loaded": 0, "computed": 0}
    if ckdir is not None:
        ckdir = Path(ckdir)
        ckdir.mkdir(parents=True, exist_ok=True)
        paths = [_ck_path(ckdir, k) for k in task_keys(fn, tasks, context, label)]
        todo = []
        for i, t in items:
            ok, r = _load_checkpoint(paths[i])
            if ok:
                if on_result is None:
                    results[i] = r
                else:
                    on_result(i, r)
                stats["loaded"] += 1
            else:
                todo.append((i, t))
        items = todo
        if stats["loaded"]:
            progress(stats["loaded"], n, f"{label} (resumed)")
    try:
        if items:
            runner = _RUNNERS[backend](fn, context, items, workers=workers if backend == "dask" else nworkers,
                                       retries=retries, label=label)
            with contextlib.closing(runner):
                for i, r in runner:
                    if paths is not None:
                        _save_checkpoint(paths[i], r)
                    if on_result is None:
                        results[i] = r
                    else:
                        on_result(i, r)
                    del r
                    stats["computed"] += 1
                    progress(stats["loaded"] + stats["computed"], n, label)
    finally:
        _LAST_RUN.clear()
        _LAST_RUN.update(stats)
    return results


_LAST_RUN: dict[str, Any] = {}


def last_run() -> dict[str, Any]:
    """Counts of the last `map_tasks` call in this process: backend, total, loaded (from
    checkpoints) and computed tasks."""
    return dict(_LAST_RUN)
