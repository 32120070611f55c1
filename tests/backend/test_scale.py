"""map_tasks on a Dask LocalCluster (2 single-threaded worker processes): same numbers as the
local backends, context shipped once per worker, progress across the cluster, lost workers,
failed tasks, checkpoints and resume."""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")  # a runtime dependency: always installed

from relief_bsdf import parallel  # noqa: E402
from relief_bsdf.cluster import synthetic_task  # noqa: E402

pytestmark = pytest.mark.slow
N = 16
TASKS = [(k,) for k in range(N)]


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=40)
    c = distributed.Client(cluster)
    try:
        with parallel.parallel_settings(dask=c):
            yield c
    finally:
        c.close()
        cluster.close()


def _ctx(tmp_path: Path | None = None, **extra) -> dict:
    ctx = {"seed": 11, "size": 32, "work": 3}
    if tmp_path is not None:
        (tmp_path / "log").mkdir(exist_ok=True)
        ctx["log_dir"] = str(tmp_path / "log")
    ctx.update(extra)
    return ctx


def _executions(ctx: dict) -> list[int]:
    return sorted(int(p.name.split("-")[0]) for p in Path(ctx["log_dir"]).iterdir())


def _same(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))


def _reference():
    return parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial")


def test_dask_gives_the_same_numbers_as_local_backends(client, tmp_path):
    ctx = _ctx(tmp_path)
    seen = []
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, progress=lambda d, n, w: seen.append(d))
    assert parallel.last_run()["backend"] == "dask"
    assert _same(out, _reference())
    assert _same(out, parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="processes", workers=2))
    assert seen == list(range(1, N + 1))
    # the work really ran on the cluster's worker processes, not here
    pids = {int(p.read_text()) for p in Path(ctx["log_dir"]).iterdir()}
    worker_pids = set(client.run(os.getpid).values())
    assert pids <= worker_pids and os.getpid() not in pids


def _probe(context, task):
    """Keep every context object a worker is handed alive, and report its identity."""
    w = distributed.get_worker()
    held = w.__dict__.setdefault("_relief_probe", [])
    held.append(context)
    return os.getpid(), id(context), float(context["payload"][task])


def test_context_is_shipped_once_per_worker(client):
    import cloudpickle
    import sys

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        payload = np.arange(200_000, dtype=float)              # 1.6 MB
        out = parallel.map_tasks(_probe, list(range(40)), {"payload": payload})
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert [v for _, _, v in out] == list(range(40))
    per_worker: dict[int, set] = {}
    for pid, ident, _ in out:
        per_worker.setdefault(pid, set()).add(ident)
    # one deserialised context object per worker, however many tasks it ran
    assert all(len(ids) == 1 for ids in per_worker.values())
    assert sum(1 for pid, _, _ in out if pid in per_worker) == 40


def test_lost_worker_mid_run_gives_a_complete_identical_result(client, tmp_path):
    ctx = _ctx(tmp_path, sleep_s=0.15)
    pids = client.run(os.getpid)                              # worker address -> process id
    killed = []

    def progress(done, total, what):
        if done == 3 and not killed:
            victim = sorted(pids)[0]
            killed.append(victim)
            os.kill(pids[victim], signal.SIGKILL)             # the worker vanishes mid-task

    seen = []
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, progress=lambda d, n, w: (seen.append(d), progress(d, n, w)))
    assert killed and seen[-1] == N
    assert _same(out, _reference())
    # the victim really left the cluster (its nanny starts a fresh worker under a new address)
    assert set(_executions(ctx)) == set(range(N))
    assert killed[0] not in set(client.scheduler_info()["workers"])
    client.wait_for_workers(2, timeout=60)


def test_task_that_kills_its_worker_is_rescheduled(client, tmp_path):
    ctx = _ctx(tmp_path, crash_file=str(tmp_path / "crashed"), crash_at=5)
    out = parallel.map_tasks(synthetic_task, TASKS, ctx)
    assert (tmp_path / "crashed").exists()
    assert _same(out, _reference())
    assert _executions(ctx).count(5) == 2
    client.wait_for_workers(2, timeout=60)


def test_failed_tasks_are_retried_then_reported(client, tmp_path):
    poison = tmp_path / "poison"
    poison.touch()
    ctx = _ctx(tmp_path, poison_file=str(poison), poison_from=N - 1)
    with pytest.raises(RuntimeError, match=f"poisoned task {N - 1}"):
        parallel.map_tasks(synthetic_task, TASKS, ctx, retries=2)
    assert _executions(ctx).count(N - 1) == 3                 # first try + 2 retries


def test_checkpointed_dask_run_resumes_after_failure(client, tmp_path):
    ck = tmp_path / "ck"
    poison = tmp_path / "poison"
    poison.touch()
    ctx = _ctx(tmp_path, poison_file=str(poison), poison_from=10)
    with pytest.raises(RuntimeError, match="poisoned task"):
        parallel.map_tasks(synthetic_task, TASKS, ctx, retries=0, checkpoint_dir=ck)
    keys = parallel.task_keys(synthetic_task, TASKS, ctx)
    saved = {k for k in range(N) if (ck / f"{keys[k]}.pkl.z").exists()}
    assert saved <= set(range(10))
    poison.unlink()
    for p in Path(ctx["log_dir"]).iterdir():
        p.unlink()
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, checkpoint_dir=ck)
    assert parallel.last_run()["loaded"] == len(saved)
    assert set(_executions(ctx)) == set(range(N)) - saved     # nothing finished ran twice
    assert _same(out, _reference())
