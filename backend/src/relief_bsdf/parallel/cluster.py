"""Dask specifics behind `parallel.map_tasks` (`distributed` is imported only when a cluster is used).

Depends on `parallel.settings` and `parallel.worker`, never on `parallel.tasks` (which
imports this module): no import cycle.

- `get_client(spec, workers)`: "local" starts a `distributed.LocalCluster` (one
  single-threaded worker process per core, or `workers`) bound to 127.0.0.1, its dashboard
  included (reachable from this machine only), "tcp://HOST:PORT" connects to a
  running scheduler; clients are cached per spec for the life of the process and closed
  at exit (or by `close_client`).
- `run_on_client(client, fn, context, items, retries, label)`: scatters the context to
  every worker once and yields (index, result) as tasks complete anywhere on the cluster.
- `synthetic_task`: a documented, deterministic stand-in workload for tests and the
  scale benchmark (no physics).

Fault model (distributed's own): a task that raises is resubmitted up to `retries` times;
a task whose worker dies is rescheduled on another worker by the scheduler (up to
`distributed.scheduler.allowed-failures` deaths, default 3, then `KilledWorker`); the
scattered context has a replica on every worker, so losing one worker loses no input,
and finished results are already in the caller's hands (and checkpoints).
"""
from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import threading
import time
import uuid
from typing import Any, Callable, Iterator

import numpy as np

from relief_bsdf.errors import InputError
from relief_bsdf.parallel.settings import default_workers, group_size
from relief_bsdf.parallel.worker import run_marked, task_rng

_CLIENTS: dict[str, Any] = {}


def open_clients() -> list[str]:
    """Specs of the clients this process holds open."""
    return list(_CLIENTS)


@contextlib.contextmanager
def _sigint_ignored_by_children() -> Iterator[None]:
    """Start worker processes with SIGINT ignored (the disposition survives their exec), so
    Ctrl-C in a terminal reaches only this process, which cancels the work and closes the
    cluster cleanly instead of every worker printing a KeyboardInterrupt traceback.  (This
    process ignores Ctrl-C for the second or two the workers take to start.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def get_client(spec: Any, workers: int | None = None):
    """A `distributed.Client` for `spec` ("local", "tcp://HOST:PORT" or a Client), cached."""
    import distributed

    if isinstance(spec, distributed.Client):
        return spec
    if spec in _CLIENTS:
        client = _CLIENTS[spec]
        if client.status == "running":
            return client
        close_client(spec)
    if spec == "local":
        n = int(workers or default_workers())
        with _sigint_ignored_by_children():
            # everything on the loopback interface: the scheduler, its workers and the dashboard
            # (which is unauthenticated) are reachable from this machine only.  The workers' own log
            # lines are silenced below CRITICAL: what goes wrong in a task reaches this process as the
            # task's exception (retried, then raised: `run_on_client`); what a worker logs at ERROR is
            # the comm noise of a shutdown, e.g. a heartbeat that met the closed scheduler after Ctrl-C
            # (a traceback on the user's terminal, as test_scale's Ctrl-C test can show)
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                               host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                               silence_logs=logging.CRITICAL)
        client = distributed.Client(cluster)
    else:
        try:
            client = distributed.Client(spec, timeout=float(os.environ.get("RELIEF_DASK_TIMEOUT_S", "20")))
        except (OSError, TimeoutError) as e:
            raise InputError("--dask", f"cannot reach a Dask scheduler at {spec} ({type(e).__name__}: {e})") from None
        try:
            check_workers(client)
        except BaseException:
            client.close()
            raise
    _CLIENTS[spec] = client
    return client


def _worker_relief_version() -> str:
    try:
        import relief_bsdf
    except ImportError:
        return "missing"
    return getattr(relief_bsdf, "__version__", "unknown")


def check_workers(client, where: str = "--dask") -> None:
    """Refuse a cluster whose workers lack this relief_bsdf version: their results would
    differ (or the tasks fail to unpickle) far into a long run."""
    from relief_bsdf import __version__

    found = client.run(_worker_relief_version, on_error="return")
    bad = {w: v for w, v in found.items() if v != __version__}
    if bad:
        shown = ", ".join(f"{w}: {v if isinstance(v, str) else type(v).__name__}" for w, v in list(bad.items())[:4])
        raise InputError(where, f"{len(bad)} of {len(found)} Dask workers do not run relief_bsdf {__version__} "
                                f"({shown}); install the same version on every worker")


def close_client(spec: str) -> None:
    """Close a cached client (and the LocalCluster it started)."""
    client = _CLIENTS.pop(spec, None)
    if client is None:
        return
    cluster = getattr(client, "cluster", None) if spec == "local" else None
    with contextlib.suppress(Exception):
        client.close()
    if cluster is not None:
        with contextlib.suppress(Exception):
            cluster.close()


@atexit.register
def close_all() -> None:
    """Close every cached client (registered at exit)."""
    for spec in list(_CLIENTS):
        close_client(spec)


def run_on_client(client, fn: Callable, context: Any, items: list[tuple[int, Any]], *, retries: int = 2,
                  label: str = "task") -> Iterator[tuple[int, Any]]:
    """Run `fn(context, task)` for (index, task) items on the cluster; yield (index, result)
    in completion order.  The context travels to each worker once; consecutive tasks are
    grouped (`parallel.settings.group_size`); on exit (normal, error, Ctrl-C, or the consumer stopping) the
    unfinished futures are cancelled."""
    try:
        yield from _run_on_client(client, fn, context, items, retries=retries, label=label)
    except KeyboardInterrupt:
        # the operations cut short by Ctrl-C (a scatter, a gather) would each log an error from
        # the in-process scheduler; the user asked to stop: one line from the CLI is enough
        for name in ("distributed", "asyncio"):     # asyncio: "Task exception was never retrieved"
            logging.getLogger(name).setLevel(logging.CRITICAL)
        raise


def _run_on_client(client, fn: Callable, context: Any, items: list[tuple[int, Any]], *, retries: int,
                   label: str) -> Iterator[tuple[int, Any]]:
    import distributed

    # wrapped in a list: scatter would split a dict or list context into one future per item
    ctx = client.scatter([context], broadcast=True, hash=False)[0] if context is not None else None
    n_workers = len(client.scheduler_info().get("workers", {}))
    b = group_size(len(items), n_workers)
    groups = [items[k:k + b] for k in range(0, len(items), b)]
    tag = uuid.uuid4().hex[:8]
    keys = [f"{label}-{tag}-{g[0][0]}" + (f"+{len(g)}" if len(g) > 1 else "") for g in groups]
    index = {k: [i for i, _ in g] for k, g in zip(keys, groups)}
    futures = client.map(run_marked, [[t for _, t in g] for g in groups], key=keys, retries=int(retries), pure=False,
                         fn=fn, context=ctx)
    remaining = {f.key: f for f in futures}
    try:
        for f in distributed.as_completed(futures, loop=client.loop):
            try:
                rs = f.result()
            except distributed.KilledWorker as e:
                raise RuntimeError(f"{label} tasks {index[f.key]} killed their worker repeatedly on the Dask "
                                   f"cluster ({e}); the finished tasks were kept") from None
            remaining.pop(f.key, None)
            f.release()
            for i, r in zip(index[f.key], rs):
                yield i, r
    finally:
        if remaining:
            with contextlib.suppress(Exception):
                client.cancel(list(remaining.values()))
        if ctx is not None:
            with contextlib.suppress(Exception):
                ctx.release()


# ---------------------------------------------------------------------------------------------
# synthetic workload (tests and benchmarks)

def synthetic_task(context: dict, task: tuple) -> np.ndarray:
    """Deterministic stand-in for one reconstruction task (no physics).

    context: {"seed": int, "size": int, "work": int, optional "sleep_s": float,
    "log_dir": path (each execution writes a file "<index>-<random>" holding the
    worker's pid, so tests count executions and see where they ran),
    "poison_file": path (while it exists, tasks with index >= "poison_from" raise),
    "crash_file": path (the task whose index is "crash_at" kills its worker process
    the first time, creating the file so the rerun succeeds; every time with
    "crash_always")}.
    task: (index, ...): the index keys the random stream `task_rng(seed, index)`.

    Returns a (size,) float64 array: `work` rounds of a random matrix-vector product,
    so the cost per task is set by `size` and `work` and the result depends on every
    random number drawn: identical results prove identical seeds.
    """
    k = int(task[0])
    if context.get("log_dir"):
        name = f"{k}-{uuid.uuid4().hex}"
        part = os.path.join(context["log_dir"], "." + name)      # written whole, then named: never read half-written
        with open(part, "w") as f:
            f.write(str(os.getpid()))
        os.replace(part, os.path.join(context["log_dir"], name))
    if context.get("crash_file") is not None and k == int(context.get("crash_at", -1)):
        if context.get("crash_always") or not os.path.exists(context["crash_file"]):
            open(context["crash_file"], "w").close()
            os._exit(17)
    if context.get("poison_file") and k >= int(context.get("poison_from", 0)) \
            and os.path.exists(context["poison_file"]):
        raise RuntimeError(f"poisoned task {k}")
    if context.get("sleep_s"):
        time.sleep(float(context["sleep_s"]))
    rng = task_rng(int(context.get("seed", 0)), k)
    n = int(context.get("size", 64))
    x = rng.standard_normal(n)
    for _ in range(int(context.get("work", 1))):
        a = rng.standard_normal((n, n)) / np.sqrt(n)
        x = np.tanh(a @ x)
    return x


def trivial_task(context: Any, task: Any) -> Any:
    """Does nothing but return its task: measures the scheduling overhead per task."""
    return task
