"""The one place that decides where independent tasks run: `map_tasks`.

Independent tasks are things like (wavelength, incidence, side) of a reconstruction,
candidate effects of a diagnosis, or rows of a plate simulation.  A task is a pure
function `fn(context, task) -> result`, where `context` is the large shared input
(a relief, its mesh, a material) shipped to each worker *once*, and `task` is small.

Where they run is a `ParallelSettings` value (parallel/settings.py), passed in:
`map_tasks(..., settings=s)`, or put in force for a block with
`with parallel_settings(s):` (the CLI's `main()` does this with the command's
`--dask/--workers/--checkpoint-dir/--retries`, so calls deep inside the methods see the
user's flags without every function carrying a settings argument).  The block's value is
a `contextvars.ContextVar`: scoped to the block and to the thread (or asyncio task) that
opened it, never a process-wide global; outside any block the documented default
`DEFAULT_SETTINGS` applies (the environment decides, see settings.py).  Keyword
overrides of one call (`backend=`, `workers=`, `checkpoint_dir=`, `retries=`; None = as
in force) win over both.

Backends:
- "serial": in this process (one task, debugging, and always inside a worker, so a
  task that itself calls `map_tasks` never nests pools).  A call may let its tasks run
  here on up to `threads` threads at once (`map_tasks(..., threads=N)`, never inside a
  worker): for tasks whose heavy work releases the GIL (Embree, numpy on big arrays),
  e.g. a ray table's many one-chunk incidences; `in_task_thread()` tells a task it runs
  on such a thread (so it does not spread its own work over threads again).
- "processes" (default): local worker processes, one per core, no setup; the context
  is sent once per worker through the pool initializer (parallel/worker.py).  A worker
  that dies (segfault, out-of-memory kill) breaks the pool: finished results are kept,
  the unfinished tasks run again on a fresh pool up to `retries` times, then a
  `WorkerCrashed` error names them.  Workers ignore SIGINT; Ctrl-C in the parent
  terminates them and re-raises.
- "dask": a `distributed` cluster (settings `dask=`, the CLI flag
  `--dask tcp://HOST:PORT|local`, or `RELIEF_DASK_SCHEDULER`).  The context is scattered
  to every worker once, tasks are submitted with `retries=`, progress counts tasks
  completed across the cluster.  Dask specifics live in `cluster.py`.

Checkpoints: with a `checkpoint_dir` every finished task's result is written atomically to
`DIR/<label>-<sha256 of (fn, context, task, code version)>.npz` as soon as it arrives, as
*data* (`relief_bsdf.io.checkpoint`: a numpy archive read with allow_pickle=False, no object
is ever unpickled, so a file planted in a shared folder cannot run code); a rerun with the
same function, context, task and code loads it instead of computing, so a killed run resumes
where it stopped.  The full key digest is stored inside the file and compared on load: a
checkpoint renamed or copied from another run is ignored (one note on stderr per run), as is
a damaged one.  Old pickled checkpoints (`*.pkl.z`) are never opened.  Changing the context
(relief, material, seed, sampling) or the task changes the key.  A result that is not data
(an object) is not checkpointed (one note).  The checkpoint folder in force is for the
top-level run: a nested call inside a worker only uses an explicit one.

Results come back in task order whatever ran them, and every task draws its random
numbers from `task_rng(seed, *key)`, so the same inputs and seed give the same
output on any backend, any number of workers, and across a resume.
"""
from __future__ import annotations

import argparse
import contextlib
import contextvars
import hashlib
import multiprocessing
import multiprocessing.context
import os
import pickle
import sys
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from relief_bsdf.errors import InputError
from relief_bsdf.parallel import cluster
from relief_bsdf.parallel.blas import workers_one_blas_thread
from relief_bsdf.parallel.memory import small_pages
from relief_bsdf.parallel.settings import (DEFAULT_SETTINGS, ParallelSettings, check_dask_spec, group_size,
                                           settings_from_args)
from relief_bsdf.parallel.worker import in_worker, init_worker, run_in_worker
from relief_bsdf.progress import Progress, silent


class WorkerCrashed(RuntimeError):
    """A local worker process died (not a Python exception in a task) more often than allowed."""


@dataclass
class RunStats:
    """Counts of one `map_tasks` call: backend used, total tasks, loaded from checkpoints, computed,
    and the threads of this process the serial backend ran them on (1: one at a time)."""

    backend: str
    total: int
    loaded: int = 0
    computed: int = 0
    threads: int = 1

    def as_dict(self) -> dict[str, Any]:
        return {"backend": self.backend, "total": self.total, "loaded": self.loaded, "computed": self.computed,
                "threads": self.threads}


# the settings in force in this thread / asyncio task (see the module doc), and the last run's counts
_IN_FORCE: contextvars.ContextVar[ParallelSettings] = contextvars.ContextVar("relief_parallel_settings",
                                                                             default=DEFAULT_SETTINGS)
_LAST_RUN: contextvars.ContextVar[dict | None] = contextvars.ContextVar("relief_parallel_last_run", default=None)


def current_settings() -> ParallelSettings:
    """The settings in force here (the innermost `parallel_settings` block, else `DEFAULT_SETTINGS`)."""
    return _IN_FORCE.get()


@contextlib.contextmanager
def parallel_settings(settings: ParallelSettings | None = None, **changes: Any) -> Iterator[ParallelSettings]:
    """Put `settings` (default: those in force), with `changes` (fields of `ParallelSettings`;
    None clears a field) applied, in force for a `with` block; yields them.

    A LocalCluster started inside the block is closed at its end, and the previous settings
    come back (also on error or Ctrl-C).
    """
    new = replace(settings if settings is not None else current_settings(), **changes)
    before = set(cluster.open_clients())
    token = _IN_FORCE.set(new)
    try:
        yield new
    finally:
        _IN_FORCE.reset(token)
        for spec in set(cluster.open_clients()) - before:
            cluster.close_client(spec)


def parallel_from_args(args: argparse.Namespace):
    """Context manager: the flags of `add_parallel_args` in force inside the block."""
    return parallel_settings(settings_from_args(args, current_settings()))


def apply_parallel_args(args: argparse.Namespace) -> ParallelSettings:
    """Check the flags of `add_parallel_args` and return the settings they give.

    Changes nothing: `relief`'s `main()` already runs every command inside
    `parallel_from_args(args)`.  (Kept for the subcommands that still call it.)
    """
    return settings_from_args(args, current_settings())


def resolve_backend(backend: str | None = None, settings: ParallelSettings | None = None) -> str:
    """Which backend a `map_tasks` call with this `backend=` argument uses now."""
    if in_worker():
        return "serial"
    s = settings if settings is not None else current_settings()
    if backend or s.backend:
        return backend or s.backend
    env = os.environ.get("RELIEF_BACKEND")
    if env:
        return env
    if s.dask is not None or os.environ.get("RELIEF_DASK_SCHEDULER"):
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


def _task_digests(fn: Callable, tasks: Sequence[Any], context: Any) -> list[str]:
    """Full SHA-256 (hex) of (fn, context, task, code version) per task: what a checkpoint is keyed by.
    (Pickling here only *hashes* the task; nothing is ever unpickled.)"""
    from relief_bsdf.io.checkpoint import code_version

    fn_name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
    base = hashlib.sha256(fn_name.encode() + b"\0" + _digest_context(context).encode() + b"\0"
                          + code_version().encode())
    out = []
    for t in tasks:
        h = base.copy()
        h.update(pickle.dumps(t, protocol=4))
        out.append(h.hexdigest())
    return out


def _safe_label(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in label)[:40] or "task"


def task_keys(fn: Callable, tasks: Sequence[Any], context: Any, label: str = "task") -> list[str]:
    """Stable checkpoint names: `<label>-<sha256(fn, context, task, code version)>` (first 32 hex digits)."""
    safe = _safe_label(label)
    return [f"{safe}-{d[:32]}" for d in _task_digests(fn, tasks, context)]


class _TaskCheckpoints:
    """The per-task checkpoints of one `map_tasks` call in a folder (data only, keyed, validated)."""

    def __init__(self, ckdir: Path, fn: Callable, tasks: list, context: Any, label: str):
        from relief_bsdf.io.checkpoint import CheckpointStore

        self.ckdir = ckdir
        self.ignored: list[str] = []
        safe = _safe_label(label)
        self.stores = [CheckpointStore(ckdir / f"{safe}-{d[:32]}.npz", {"task": d}, note=self.ignored.append)
                       for d in _task_digests(fn, tasks, context)]
        self.saving = True
        self.legacy = sorted(p.name for p in ckdir.glob(f"{safe}-*.pkl.z"))

    def load(self, i: int) -> tuple[bool, Any]:
        data = self.stores[i].load()
        if "result" not in data:
            return False, None
        return True, data["result"]

    def save(self, i: int, result: Any) -> None:
        if not self.saving:
            return
        try:
            self.stores[i].save({"result": result})
        except TypeError as e:
            self.saving = False
            _note(f"tasks' results are not checkpointed in {self.ckdir} ({e})")

    def report(self) -> None:
        """One line for the checkpoints this call ignored (stale, foreign or damaged), one for old pickles."""
        if self.ignored:
            _note(f"ignored {len(self.ignored)} checkpoint(s) in {self.ckdir} that do not belong to this run or "
                  f"are damaged (first: {self.ignored[0].removeprefix('ignored checkpoint ')[:160]})")
        if self.legacy:
            _note(f"{len(self.legacy)} old pickled checkpoint(s) (*.pkl.z) in {self.ckdir} were not opened "
                  "(pickles can run code); delete them")


def _note(message: str) -> None:
    print(f"relief: note: {message}", file=sys.stderr)


# ---------------------------------------------------------------------------------------------
# runners: each yields (task index, result) as tasks complete

def _run_serial(fn: Callable, context: Any, items: list[tuple[int, Any]], settings: ParallelSettings,
                label: str) -> Iterator[tuple[int, Any]]:
    for i, t in items:
        yield i, fn(context, t)


_IN_TASK_THREAD: contextvars.ContextVar[bool] = contextvars.ContextVar("relief_in_task_thread", default=False)


def in_task_thread() -> bool:
    """True inside a task that `map_tasks(..., threads=N)` runs on one of N threads of this process."""
    return _IN_TASK_THREAD.get()


def _call_in_task_thread(fn: Callable, context: Any, task: Any) -> Any:
    _IN_TASK_THREAD.set(True)
    return fn(context, task)


def _run_threads(fn: Callable, context: Any, items: list[tuple[int, Any]], threads: int) -> Iterator[tuple[int, Any]]:
    """The serial backend on `threads` threads of this process: results in completion order.

    Each task runs in a copy of the caller's context (the settings in force travel with it), with
    `in_task_thread()` True.  A failing task raises here; the tasks not yet started are cancelled
    and the running ones finish before the error propagates (no thread is left tracing)."""
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="relief-task")
    try:
        futures = {pool.submit(contextvars.copy_context().run, _call_in_task_thread, fn, context, t): i
                   for i, t in items}
        for f in as_completed(futures):
            yield futures[f], f.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


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
    `RELIEF_START_METHOD` overrides it (e.g. "spawn").  The workers compute: no huge-page advice for
    their arrays (`parallel.memory`) and one BLAS thread each (`parallel.blas`); set here, before the
    fork server or a spawned worker starts and imports numpy, so they inherit it.
    """
    small_pages()
    workers_one_blas_thread()
    method = os.environ.get("RELIEF_START_METHOD", "forkserver")
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload([__name__])
    return ctx


def _pool_round(pool: ProcessPoolExecutor, fn: Callable, token: int, pending: dict[int, Any], workers: int):
    """Run the pending tasks on one pool, yielding (index, result) and removing them from
    `pending` as they arrive; the generator's return value says whether the pool broke."""
    todo = list(pending.items())
    b = group_size(len(todo), workers)
    groups = [todo[k:k + b] for k in range(0, len(todo), b)]
    futs = {}
    broken = False
    try:
        for g in groups:
            futs[pool.submit(run_in_worker, fn, token, [t for _, t in g])] = [i for i, _ in g]
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
    return broken


@dataclass(eq=False)
class _KeptPool:
    """The local worker pool of a `kept_workers` block: its context, and the pool once started."""

    context: Any
    pool: ProcessPoolExecutor | None = None
    workers: int = 0


_KEPT: contextvars.ContextVar[_KeptPool | None] = contextvars.ContextVar("relief_kept_pool", default=None)


@contextlib.contextmanager
def kept_workers(context: Any) -> Iterator[None]:
    """Inside the block, `map_tasks` calls on the local processes backend whose context is `context`
    (the same object) run on one pool of worker processes, started by the first such call and
    stopped at the block's end (also on error or Ctrl-C).

    The workers receive the context once, and whatever a task leaves in its worker process (a
    table cache, a memo of evaluations, a factorised solver, `worker_cached` objects) is there
    for the next call's tasks: a stepwise diagnosis's rounds run on workers that keep the tables
    and solvers of the rounds before instead of starting bare each round.  Results do not change:
    a task must give the same result whatever ran before it in its process (the caches hold
    data that is a pure function of its key).  A call with another context or another backend runs
    as outside the block; one with another number of workers restarts the kept pool with that many;
    a worker that dies breaks the kept pool and the call continues on fresh pools as usual
    (`retries`).  Blocks do not nest (the inner
    one wins for its context)."""
    kept = _KeptPool(context)
    token = _KEPT.set(kept)
    clean = False
    try:
        yield
        clean = True
    finally:
        _KEPT.reset(token)
        if kept.pool is not None:
            _stop_pool(kept.pool, kill=not clean)
            kept.pool = None


def has_kept_workers(context: Any, workers: int | None = None) -> bool:
    """Would a `map_tasks` call here on `context` (with this `workers=`) run on the worker processes of
    a `kept_workers(context)` block?  (Then sending it a few small tasks costs no pool start.)"""
    kept = _KEPT.get()
    if kept is None or kept.context is not context or in_worker():
        return False
    s = _call_settings({"workers": workers})
    return resolve_backend(None, s) == "processes" and s.worker_count() > 1


def _new_pool(token: int, context: Any, workers: int, memory_bytes: float | None = None) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(max_workers=workers, initializer=init_worker,
                               initargs=(token, context, os.getpid(), memory_bytes), mp_context=_pool_context())


def _run_processes(fn: Callable, context: Any, items: list[tuple[int, Any]], settings: ParallelSettings,
                   label: str) -> Iterator[tuple[int, Any]]:
    token = id(context)
    pending = dict(items)
    workers = settings.worker_count()
    restarts = 0
    exit_codes: set[int] = set()
    kept = _KEPT.get()
    if kept is not None and kept.context is not context:
        kept = None
    while pending:
        if kept is not None and kept.pool is not None and kept.workers != workers:   # another worker count
            _stop_pool(kept.pool, kill=False)
            kept.pool = None
        if kept is not None and kept.pool is None:
            kept.pool, kept.workers = _new_pool(token, context, workers, settings.worker_memory_bytes), workers
        pool = kept.pool if kept is not None else _new_pool(token, context, max(1, min(workers, len(pending))),
                                                            settings.worker_memory_bytes)
        clean = False
        try:
            broken = yield from _pool_round(pool, fn, token, pending, workers)
            clean = not broken
        finally:
            procs = list((getattr(pool, "_processes", None) or {}).values())
            if kept is None or not clean:
                _stop_pool(pool, kill=not clean)
                if kept is not None:
                    kept.pool = None
        if broken:
            exit_codes |= {p.exitcode for p in procs if p.exitcode not in (None, 0, -15)}  # -15: the pool's stop
            restarts += 1
            if restarts > settings.retries:
                raise _crashed(restarts, pending, label, settings, exit_codes)


def _exit_cause(code: int) -> str:
    """What a worker's exit code says about why it died."""
    if code > 0:
        return (f"exit status {code}: a Python error before or between tasks, e.g. while the worker started "
                "(its traceback is on stderr / the console)")
    import signal
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = f"signal {-code}"
    hint = {"SIGKILL": "usually the out-of-memory killer", "SIGSEGV": "a crash in native code",
            "SIGBUS": "a crash in native code", "SIGABRT": "a native library aborted"}.get(name, "killed")
    return f"{name} ({hint})"


def _crashed(restarts: int, pending: dict[int, Any], label: str, settings: ParallelSettings,
             exit_codes: set[int] = frozenset()) -> WorkerCrashed:
    shown = sorted(pending)[:8]
    more = "" if len(pending) <= 8 else f" (+{len(pending) - 8} more)"
    causes = "; ".join(_exit_cause(c) for c in sorted(exit_codes)) or "exit code not known"
    memory = -9 in exit_codes or not exit_codes
    return WorkerCrashed(
        f"a worker process died abruptly {restarts} times while running {label} tasks ({causes}); "
        f"{len(pending)} unfinished, indices {shown}{more}; finished ones were kept"
        + (" in the checkpoint folder" if settings.checkpoint_dir else "")
        + (". Try fewer workers (--workers) or a smaller request." if memory else "."))


def _run_dask(fn: Callable, context: Any, items: list[tuple[int, Any]], settings: ParallelSettings,
              label: str) -> Iterator[tuple[int, Any]]:
    spec = settings.dask
    if spec is None and os.environ.get("RELIEF_DASK_SCHEDULER"):
        # the environment redirects the work to another machine: say so, never silently
        spec = check_dask_spec(os.environ["RELIEF_DASK_SCHEDULER"], "$RELIEF_DASK_SCHEDULER")
        if spec not in _ENV_NOTED:
            _ENV_NOTED.add(spec)
            _note(f"tasks run on the Dask scheduler {spec} named by $RELIEF_DASK_SCHEDULER")
    client = cluster.get_client(spec or "local", workers=settings.workers)
    yield from cluster.run_on_client(client, fn, context, items, retries=settings.retries, label=label)


#: schedulers named by $RELIEF_DASK_SCHEDULER already announced in this process (one note each)
_ENV_NOTED: set[str] = set()

_RUNNERS = {"serial": _run_serial, "processes": _run_processes, "dask": _run_dask}


def _call_settings(overrides: dict[str, Any]) -> ParallelSettings:
    """The settings of one call: those in force (only the defaults inside a worker) plus its overrides."""
    base = DEFAULT_SETTINGS if in_worker() else current_settings()
    return base.updated(**overrides)


def _load_checkpoints(cks: _TaskCheckpoints, items: list[tuple[int, Any]],
                      deliver: Callable[[int, Any], None]) -> list:
    """Deliver the tasks found in checkpoints; return the items still to compute."""
    todo = []
    for i, t in items:
        ok, r = cks.load(i)
        if ok:
            deliver(i, r)
        else:
            todo.append((i, t))
    cks.report()
    return todo


def map_tasks(fn: Callable[[Any, Any], Any], tasks: Sequence[Any], context: Any = None, *,
              settings: ParallelSettings | None = None, progress: Progress | None = None, label: str = "task",
              on_result: Callable[[int, Any], None] | None = None, threads: int = 1, **overrides: Any) -> list:
    """Run `fn(context, task)` for every task and return the results in task order.

    `fn` must be a module-level function (picklable); `context` is shipped to each worker
    once.  `settings`: where to run (default: those in force, see the module doc);
    `overrides`: fields of `ParallelSettings` for this call only (`backend="serial"`,
    `workers=2`, `checkpoint_dir=...`, `retries=1`; None = as in force).  Progress is reported
    as tasks complete, across all workers (checkpointed tasks count as done at once).

    `on_result(index, result)`: called in this process as each result arrives (or is loaded
    from a checkpoint), in completion order; the returned list then holds None, so a big
    request can write each task's values straight into its table (float32) instead of
    keeping every task's result until the end.

    `threads`: where the tasks run in this process (the serial backend, not inside a worker),
    up to this many run at once on threads (module doc); the results are the same.
    """
    progress = progress or silent
    tasks = list(tasks)
    n = len(tasks)
    if n == 0:
        return []
    s = (settings.updated(**overrides) if settings is not None else _call_settings(overrides))
    backend = resolve_backend(None, s)
    if backend not in _RUNNERS:
        raise ValueError(f"unknown backend {backend!r}; choose from {', '.join(_RUNNERS)}")
    if backend == "processes" and (s.worker_count() == 1 or n == 1):
        backend = "serial"
    results: list = [None] * n
    stats = RunStats(backend, n)

    def deliver(i: int, r: Any) -> None:
        if on_result is None:
            results[i] = r
        else:
            on_result(i, r)

    items = list(enumerate(tasks))
    cks = _checkpoints(fn, tasks, context, label, s)
    try:
        if cks is not None:
            items = _load_checkpoints(cks, items, deliver)
            stats.loaded = n - len(items)
            if stats.loaded:
                progress(stats.loaded, n, f"{label} (resumed)")
        if items:
            if backend == "serial" and int(threads) > 1 and len(items) > 1 and not in_worker():
                stats.threads = min(int(threads), len(items))
                runner = _run_threads(fn, context, items, stats.threads)
            else:
                runner = _RUNNERS[backend](fn, context, items, s, label)
            with contextlib.closing(runner):
                for i, r in runner:
                    if cks is not None:
                        cks.save(i, r)
                    deliver(i, r)
                    del r
                    stats.computed += 1
                    progress(stats.loaded + stats.computed, n, label)
    finally:
        _LAST_RUN.set(stats.as_dict())
    return results


def _checkpoints(fn: Callable, tasks: list, context: Any, label: str, s: ParallelSettings) -> _TaskCheckpoints | None:
    if s.checkpoint_dir is None:
        return None
    ckdir = Path(s.checkpoint_dir)
    if ckdir.exists() and not ckdir.is_dir():
        raise InputError(ckdir, "--checkpoint-dir is a file, not a folder")
    try:
        ckdir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(ckdir, f"cannot create the checkpoint folder ({e.strerror or e})") from None
    return _TaskCheckpoints(ckdir, fn, tasks, context, label)


def last_run() -> dict[str, Any]:
    """Counts of the last `map_tasks` call made here (this thread / context): backend, total,
    loaded (from checkpoints) and computed tasks."""
    return dict(_LAST_RUN.get() or {})
