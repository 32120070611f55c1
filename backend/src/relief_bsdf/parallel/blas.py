"""BLAS threads of the processes that compute: one each where processes share the cores.

numpy and scipy (pinned wheels) each carry an OpenBLAS that starts one thread per core, and an
OpenBLAS thread waiting for its share of a call spins on its core instead of sleeping.  A pool
worker is one of as many processes as there are cores, so a BLAS call made with every core's
thread there competes with the other workers' work and with the process that started them, and
the waiting threads burn the time the others need.  Measured on a diagnosis case on the 2-core
machine (docs/decisions/007): the slab operators of a volume-scattering screen, 24 `numpy.linalg.solve`
calls of 0.004 s each alone, took 10.3 s in the main process while the two workers computed
(0.43 s a call: 100x); the workers' own BLAS ran on two threads each as well (the `OMP_NUM_THREADS`
a worker set for itself came after numpy had started its OpenBLAS).  Alone on the machine a second
BLAS thread buys little (a bulk-absorption evaluation 0.48-0.65 s against 0.72-0.76 s with one: the
loop's LU factors), so a process that runs by itself keeps its threads.

- `blas_single_thread()`: this process's BLAS on one thread for a `with` block (the plate's small
  solves; an evaluation made here beside working pool workers);
- `workers_one_blas_thread()`: processes started from here (the fork server and the workers it
  forks, a spawned worker) load their BLAS with one thread (environment variables, before they
  start; a user's own setting wins); a pool worker's initializer also limits its own BLAS
  (`parallel.worker.init_worker`), in case its BLAS was loaded before the variables were set.
"""
from __future__ import annotations

import contextlib
import os

BLAS_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")   # BLAS only: not every OpenMP program started here


def blas_single_thread():
    """Context manager: BLAS on one thread in this process for the block (module doc)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - pinned in requirements/runtime.txt
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def workers_one_blas_thread() -> None:
    """Processes started from here load their BLAS with one thread (module doc); idempotent."""
    for name in BLAS_THREAD_ENV:
        os.environ.setdefault(name, "1")
