"""Parallel execution: where independent tasks run (serial, local processes, a Dask cluster).

    map_tasks(fn, tasks, context, settings=ParallelSettings(...), progress=...) -> results in task order

- `settings.py`: `ParallelSettings` (backend, dask, workers, checkpoint_dir, retries) with its
  documented default `DEFAULT_SETTINGS` (the environment decides), the CLI flags
  (`add_parallel_args`, `settings_from_args`) and task batching (`group_size`);
- `tasks.py`: `map_tasks` (local runners, checkpoints and resume), `parallel_settings(...)`
  (settings in force for a `with` block, scoped by a ContextVar, never a global),
  `kept_workers(context)` (one pool of worker processes for a block's calls on that context);
- `cluster.py`: the Dask client and the cluster runner (imports settings and worker only);
- `worker.py`: the task side: `task_rng`, `worker_cached`, `in_worker` (the only per-process
  state, kept there and documented why).

Imports point one way: (settings, worker) <- cluster <- tasks <- this face; at import time the
package needs only `errors`, `progress`, `seeds` and `io.atomic`; `task_rng` is `relief_bsdf.seeds`'
(the one scheme, which `surface` draws from without importing this package).
"""
from relief_bsdf.parallel.settings import (DEFAULT_SETTINGS, ParallelSettings, add_parallel_args, default_workers,
                                           group_size, settings_from_args)
from relief_bsdf.parallel.tasks import (RunStats, WorkerCrashed, apply_parallel_args, current_settings,
                                        has_kept_workers, in_task_thread, kept_workers, last_run, map_tasks,
                                        parallel_from_args, parallel_settings, resolve_backend, task_keys)
from relief_bsdf.parallel.worker import forget_worker_cached, in_worker, task_rng, worker_cached

__all__ = ["DEFAULT_SETTINGS", "ParallelSettings", "RunStats", "WorkerCrashed", "add_parallel_args",
           "apply_parallel_args", "current_settings", "default_workers", "forget_worker_cached", "group_size",
           "has_kept_workers", "in_task_thread", "in_worker", "kept_workers", "last_run", "map_tasks",
           "parallel_from_args", "parallel_settings", "resolve_backend", "settings_from_args", "task_keys", "task_rng",
           "worker_cached"]
