"""Where independent tasks run: the `ParallelSettings` value, its command-line flags, batching.

A `ParallelSettings` is a plain frozen value.  It is *passed in*: `map_tasks(...,
settings=s)`, or put in force for a block with `parallel.parallel_settings(s)` (the
CLI's `main()` does that with the flags of `add_parallel_args`, so every `map_tasks` call
a command makes, however deep in the methods, runs where the user asked).  Nothing here
is process-wide mutable state.

Documented default (`DEFAULT_SETTINGS = ParallelSettings()`): every field None / 2, which
means "decide from the environment when the tasks start":

- backend:         $RELIEF_BACKEND, else "dask" when a scheduler is set (field `dask` or
                   $RELIEF_DASK_SCHEDULER), else "processes" (local worker processes);
- workers:         $RELIEF_WORKERS, else every core (`default_workers`);
- checkpoint_dir:  none (no checkpoints);
- retries:         2 (a failed Dask task / a crashed local pool runs again twice).

This module imports nothing else of the package but `errors`: the settings sit below
both the local runner (`tasks`) and the Dask side (`cluster`), which is what keeps the
two free of an import cycle.
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, replace
from typing import Any

from relief_bsdf.errors import InputError

BACKENDS = ("serial", "processes", "dask")


def default_workers() -> int:
    """Worker count: RELIEF_WORKERS if set, else every core."""
    env = os.environ.get("RELIEF_WORKERS")
    if env:
        return max(1, int(env))
    return max(1, os.cpu_count() or 1)


#: address schemes of a Dask scheduler (distributed's comms); "tls" for one reached across machines
DASK_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")


def check_dask_spec(dask: Any, where: str = "--dask") -> Any:
    """Normalise a scheduler spec: None, a Client, "local", "SCHEME://HOST:PORT" with a Dask comm
    scheme (tcp, tls, ucx, ws, wss; "HOST:PORT" gains tcp://).  Anything else is an InputError naming
    `where` (the flag or the environment variable it came from)."""
    if dask is None or not isinstance(dask, str):
        return dask
    spec = dask.strip()
    if spec == "local":
        return spec
    if "://" in spec:
        scheme, rest = spec.split("://", 1)
        if scheme.lower() not in DASK_SCHEMES:
            raise InputError(where, f"{dask!r}: {scheme}:// is not a Dask scheduler address; use "
                                    f"{' / '.join(s + '://HOST:PORT' for s in DASK_SCHEMES[:2])} or 'local'")
        host, _, port = rest.rstrip("/").rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536 or "/" in host:
            raise InputError(where, f"{dask!r}: expected {scheme}://HOST:PORT (e.g. {scheme}://node1:8786)")
        return f"{scheme.lower()}://{rest.rstrip('/')}"
    if ":" in spec and spec.rsplit(":", 1)[1].isdigit():
        return "tcp://" + spec
    raise InputError(where, f"expected 'local' or a scheduler address such as tcp://HOST:8786, got {dask!r}")


@dataclass(frozen=True)
class ParallelSettings:
    """Where `map_tasks` runs its tasks (see the module doc for the default of each field).

    backend: "serial", "processes", "dask" or None (from the environment / `dask`).
    dask: None (no cluster), "local" (a LocalCluster started on first use and closed with the
          `parallel_settings` block that started it), "tcp://HOST:PORT" (a running scheduler),
          or a `distributed.Client`.
    workers: local worker processes (or LocalCluster workers); None = $RELIEF_WORKERS or every core.
    checkpoint_dir: folder for per-task checkpoints; None = no checkpoints.
    retries: how often a failed task (or, locally, a crashed pool) is run again.
    worker_memory_bytes: the byte budget each local worker's forward-model memory owner holds
          (`plate.memory`; the job that starts the pool decides it from its total); None = that
          module's default.
    memory_gb: the memory a job may use, every process together (`--memory-gb`; None =
          $RELIEF_MEMORY_GB, else 3.5: `plate.memory.job_memory_bytes`).
    Values are checked on construction (an `InputError` naming the CLI flag).
    """

    backend: str | None = None
    dask: Any = None
    workers: int | None = None
    checkpoint_dir: str | None = None
    retries: int = 2
    worker_memory_bytes: float | None = None
    memory_gb: float | None = None

    def __post_init__(self) -> None:
        if self.backend is not None and self.backend not in BACKENDS:
            raise ValueError(f"unknown backend {self.backend!r}; choose from {', '.join(BACKENDS)}")
        object.__setattr__(self, "dask", check_dask_spec(self.dask))
        if self.workers is not None:
            if int(self.workers) < 1:
                raise InputError("--workers", f"need at least 1 worker, got {self.workers}")
            object.__setattr__(self, "workers", int(self.workers))
        if self.checkpoint_dir is not None:
            object.__setattr__(self, "checkpoint_dir", str(self.checkpoint_dir))
        if int(self.retries) < 0:
            raise InputError("--retries", f"retries must be >= 0, got {self.retries}")
        object.__setattr__(self, "retries", int(self.retries))
        if self.memory_gb is not None and not float(self.memory_gb) > 0:
            raise InputError("--memory-gb", f"the memory budget must be > 0 GB, got {self.memory_gb}")

    def updated(self, **changes: Any) -> "ParallelSettings":
        """A copy with the given fields changed; a change of None keeps the field as it is
        (callers pass their optional arguments straight through)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def worker_count(self) -> int:
        """The local worker count these settings give."""
        return self.workers or default_workers()


DEFAULT_SETTINGS = ParallelSettings()


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


# ---------------------------------------------------------------------------------------------
# command-line flags

def add_parallel_args(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add `--dask`, `--workers`, `--checkpoint-dir`, `--retries` to a subcommand's parser
    (those it does not define already).  `relief`'s `main()` turns them into the command's
    `ParallelSettings` (`settings_from_args`) and runs the command with them in force.
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
    if "--memory-gb" not in have:
        g.add_argument("--memory-gb", type=float, default=None, metavar="GB",
                       help="memory the job may use, every process together: what the forward model keeps and "
                            "how many workers run at once follow from it (default 3.5, or $RELIEF_MEMORY_GB)")
    return parser


def settings_from_args(args: argparse.Namespace, base: ParallelSettings = DEFAULT_SETTINGS) -> ParallelSettings:
    """`base` with the flags of `add_parallel_args` that were given (absent flags keep `base`'s)."""
    return base.updated(dask=getattr(args, "dask", None), workers=getattr(args, "workers", None),
                        checkpoint_dir=getattr(args, "checkpoint_dir", None), retries=getattr(args, "retries", None),
                        memory_gb=getattr(args, "memory_gb", None))
