"""The task side of parallel execution: what runs inside a worker, and what a task may use.

A task is a module-level function `fn(context, task)`.  It may call

- `task_rng(seed, *key)`: its own random stream (same numbers on any backend; `relief_bsdf.seeds`);
- `worker_cached(key, build)`: an expensive object (a BVH, an FFT plan) built once per
  worker process and reused by every later task there;
- `in_worker()`: whether it runs as a task (a nested `map_tasks` then runs serially).

Why this module keeps module-level state (and nothing else in `parallel` does): a local
pool worker receives the shared context once, through the pool initializer
(`init_worker`), and the only place an initializer can leave something for the tasks that
follow in that *process* is module state of the worker process.  The same holds for the
per-worker cache, which must outlive a single task.  This state is per process and is
never read to decide *where* tasks run (that is `ParallelSettings`, passed in):

- `_CONTEXT`: shared context per pool token (set by `init_worker`, worker processes only);
- `_IN_WORKER`: this whole process is a local pool worker;
- `_LOCAL.in_task`: this thread runs a task (a Dask worker thread, maybe in-process);
- `_WORKER_CACHE`: the `worker_cached` objects (at most 9, then cleared);
- `_PROCESS_OBJECTS`: one object per name for the life of the process (`process_object`: the
  forward model's memory owner outside a job, `plate.memory`), never cleared;
- `_WORKER_MEMORY`: the byte budget the job gave its workers' memory owners (`init_worker`).
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from typing import Any, Callable, Iterator


from relief_bsdf.io.atomic import process_alive
from relief_bsdf.seeds import task_rng  # noqa: F401  (a task's random stream: the project's one scheme)

_CONTEXT: dict[int, Any] = {}
_IN_WORKER = False
_LOCAL = threading.local()
_WORKER_CACHE: dict[Any, Any] = {}
_CACHE_LIMIT = 8
_PROCESS_OBJECTS: dict[str, Any] = {}
_WORKER_MEMORY: list[float | None] = [None]


def worker_cached(key: Any, build: Callable[[], Any]) -> Any:
    """Build an expensive per-context object (a BVH, an FFT plan) once per worker process.

    Tasks call `worker_cached(("bvh", relief_digest), lambda: Tracer(relief))`; the object
    lives for the life of the worker, so it is built once per worker, not once per task.
    """
    if key not in _WORKER_CACHE:
        if len(_WORKER_CACHE) > _CACHE_LIMIT:
            _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = build()
    return _WORKER_CACHE[key]


def process_object(name: str, build: Callable[[], Any]) -> Any:
    """The process's one object called `name`, built on first use and kept for the life of the process."""
    if name not in _PROCESS_OBJECTS:
        _PROCESS_OBJECTS[name] = build()
    return _PROCESS_OBJECTS[name]


def worker_memory_bytes() -> float | None:
    """The byte budget the job gave this worker's forward-model memory (None outside a pool worker)."""
    return _WORKER_MEMORY[0]


def forget_worker_cached(key: Any) -> None:
    """Drop one `worker_cached` object from this process (e.g. a BVH built for a serial run)."""
    _WORKER_CACHE.pop(key, None)


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


def init_worker(token: int, context: Any, owner_pid: int | None = None, memory_bytes: float | None = None) -> None:
    """Initializer of a local pool worker: keep the context, ignore Ctrl-C, one thread per library,
    hold the forward model's memory to `memory_bytes` (the job's share for each worker), and exit
    when the run that owns the pool (`owner_pid`) is gone."""
    global _IN_WORKER
    _IN_WORKER = True
    _WORKER_MEMORY[0] = memory_bytes
    _CONTEXT[token] = context
    # Ctrl-C goes to the whole process group: the parent handles it and terminates us
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # numerical libraries inside a worker use one thread each: the pool already fills the cores
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _one_blas_thread_here()
    if owner_pid is not None:
        watch_owner(owner_pid)


def _one_blas_thread_here() -> None:
    """This worker's BLAS on one thread for the rest of its life: it may have been loaded (by the fork
    server's imports) before OMP_NUM_THREADS was set, and OpenBLAS's waiting threads spin
    (parallel.blas, which sets the variables before the fork server starts)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - pinned in requirements/runtime.txt
        return
    threadpool_limits(limits=1, user_api="blas")      # not restored: the limit stays with the process


def watch_owner(owner_pid: int, interval_s: float = 0.5) -> threading.Thread:
    """Exit this process (os._exit) once `owner_pid` is gone, whatever killed it (kill -9 included).

    Why polling: a pool worker's parent is the fork server, not the run, and the pipes it waits on
    are also held open by its sibling workers, so neither a parent-death signal nor end-of-file
    tells it that the run died.  Once the workers are gone, the fork server and multiprocessing's
    resource tracker see their last pipe close and exit too: no process of the run is left.
    """
    def watch() -> None:
        while process_alive(owner_pid):
            time.sleep(interval_s)
        os._exit(3)

    t = threading.Thread(target=watch, name="relief-owner-watch", daemon=True)
    t.start()
    return t


def run_in_worker(fn: Callable, token: int, batch: list) -> list:
    """Run one batch of tasks in a local pool worker against the context `init_worker` kept."""
    context = _CONTEXT[token]
    return [fn(context, task) for task in batch]


def run_marked(batch: list, fn: Callable, context: Any) -> list:
    """Run one batch of tasks on a Dask worker thread, marked as a task (nested calls run serially)."""
    with running_task():
        return [fn(context, task) for task in batch]
