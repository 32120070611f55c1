"""parallel.map_tasks on the local backends: determinism, progress, checkpoints and resume,
worker crashes, Ctrl-C, and the command-line flags (Dask itself: test_scale.py)."""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

import relief_bsdf.parallel as parallel
from relief_bsdf.parallel.cluster import synthetic_task
from relief_bsdf.errors import InputError

N = 12


def _ctx(tmp_path: Path | None = None, **extra) -> dict:
    ctx = {"seed": 7, "size": 32, "work": 3}
    if tmp_path is not None:
        log = tmp_path / "log"
        log.mkdir(exist_ok=True)
        ctx["log_dir"] = str(log)
    ctx.update(extra)
    return ctx


def _executions(ctx: dict) -> list[int]:
    return sorted(int(p.name.split("-")[0]) for p in Path(ctx["log_dir"]).iterdir() if p.name[0].isdigit())


def _clear_log(ctx: dict) -> None:
    for p in Path(ctx["log_dir"]).iterdir():
        p.unlink()


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))


TASKS = [(k,) for k in range(N)]


def test_task_rng_is_reproducible_and_independent():
    a = parallel.task_rng(3, 1, 2).standard_normal(1000)
    b = parallel.task_rng(3, 1, 2).standard_normal(1000)
    c = parallel.task_rng(3, 2, 1).standard_normal(1000)
    d = parallel.task_rng(4, 1, 2).standard_normal(1000)
    assert np.array_equal(a, b)
    # independent streams: correlation of 1000 normal pairs is ~N(0, 1/sqrt(1000))
    assert abs(np.corrcoef(a, c)[0, 1]) < 0.15
    assert abs(np.corrcoef(a, d)[0, 1]) < 0.15


def test_processes_equal_serial_in_task_order_with_progress():
    ref = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial")
    seen = []
    out = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="processes", workers=2,
                             progress=lambda d, n, w: seen.append((d, n)))
    assert _same(ref, out)
    # results differ between tasks (each has its own stream)
    assert not np.array_equal(ref[0], ref[1])
    assert [d for d, _ in seen] == list(range(1, N + 1)) and all(n == N for _, n in seen)
    assert parallel.last_run()["backend"] == "processes"


def test_nested_map_tasks_runs_serially_inside_a_worker():
    out = parallel.map_tasks(_nested, [0, 1, 2], None, backend="processes", workers=2)
    assert out == [("serial", 0), ("serial", 1), ("serial", 2)]


def _nested(context, task):
    inner = parallel.map_tasks(_identity, [task], None, backend="processes", workers=2)
    return parallel.resolve_backend("processes"), inner[0]


def _identity(context, task):
    return task


def test_checkpoints_resume_after_a_failed_run(tmp_path):
    ck = tmp_path / "ck"
    poison = tmp_path / "poison"
    poison.touch()
    ctx = _ctx(tmp_path, poison_file=str(poison), poison_from=5)
    clean = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial")
    # serial: tasks 0..4 finish and are checkpointed, task 5 raises and ends the run
    with pytest.raises(RuntimeError, match="poisoned task 5"):
        parallel.map_tasks(synthetic_task, TASKS, ctx, backend="serial", checkpoint_dir=ck)
    assert _executions(ctx) == [0, 1, 2, 3, 4, 5]
    assert len(list(ck.glob("[!.]*.npz"))) == 5
    poison.unlink()
    _clear_log(ctx)
    seen = []
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2, checkpoint_dir=ck,
                             progress=lambda d, n, w: seen.append(d))
    assert _same(out, clean)
    assert _executions(ctx) == list(range(5, N))           # only the unfinished ones ran
    assert parallel.last_run() == {"backend": "processes", "total": N, "loaded": 5, "computed": N - 5,
                                  "threads": 1}
    assert seen[0] == 5 and seen[-1] == N
    # a third run computes nothing
    _clear_log(ctx)
    again = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2, checkpoint_dir=ck)
    assert _same(again, clean) and _executions(ctx) == []


def test_checkpoint_keys_change_with_context_task_and_function(tmp_path):
    base = parallel.task_keys(synthetic_task, TASKS, _ctx())
    assert len(set(base)) == N
    assert base == parallel.task_keys(synthetic_task, TASKS, _ctx())
    assert set(base).isdisjoint(parallel.task_keys(synthetic_task, TASKS, _ctx(seed=8)))
    assert set(base).isdisjoint(parallel.task_keys(_identity, TASKS, _ctx()))
    assert set(base).isdisjoint(parallel.task_keys(synthetic_task, [(k, 0) for k in range(N)], _ctx()))


def test_damaged_checkpoint_is_recomputed(tmp_path):
    ck = tmp_path / "ck"
    ref = parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), backend="serial", checkpoint_dir=ck)
    victim = ck / (parallel.task_keys(synthetic_task, TASKS[:3], _ctx())[1] + ".npz")
    victim.write_bytes(b"not a checkpoint")
    out = parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), backend="serial", checkpoint_dir=ck)
    assert _same(out, ref)
    assert parallel.last_run()["computed"] == 1


@pytest.mark.slow
def test_killed_run_resumes_from_checkpoints(tmp_path):
    """SIGKILL the whole run (driver and workers) part-way, then resume in this process."""
    ck = tmp_path / "ck"
    ctx = _ctx(tmp_path, sleep_s=0.25)
    script = textwrap.dedent(f"""
        import relief_bsdf.parallel as parallel
        from relief_bsdf.parallel.cluster import synthetic_task
        if __name__ == "__main__":
            parallel.map_tasks(synthetic_task, {TASKS!r}, {ctx!r}, backend="processes", workers=2,
                               checkpoint_dir={str(ck)!r})
    """)
    # the default SIGINT disposition even when this runner was started in the background (SIGINT ignored)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        t0 = time.monotonic()
        while len(list(ck.glob("[!.]*.npz"))) < 4:
            assert time.monotonic() - t0 < 60, "the run never checkpointed"
            assert proc.poll() is None, "the run ended before it was killed"
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    finished = len(list(ck.glob("[!.]*.npz")))
    assert 4 <= finished < N
    _clear_log(ctx)
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="serial", checkpoint_dir=ck)
    assert parallel.last_run()["loaded"] == finished
    assert len(_executions(ctx)) == N - finished
    assert _same(out, parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial"))


def test_crashed_worker_is_replaced_and_its_tasks_rerun(tmp_path):
    ctx = _ctx(tmp_path, crash_file=str(tmp_path / "crashed"), crash_at=4)
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2)
    assert (tmp_path / "crashed").exists()                   # the worker really died once
    assert _same(out, parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial"))


def test_worker_that_always_crashes_gives_a_clear_error(tmp_path):
    ctx = _ctx(tmp_path, crash_file=str(tmp_path / "crashed"), crash_at=4, crash_always=True)
    with pytest.raises(parallel.WorkerCrashed, match=r"died abruptly .* indices \[.*4"):
        parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2, retries=1)
    # every task was attempted at most twice (1 retry), and task 4 exactly twice
    ex = _executions(ctx)
    assert ex.count(4) == 2 and max(ex.count(k) for k in range(N)) <= 2


@pytest.mark.slow
def test_ctrl_c_stops_workers_cleanly(tmp_path):
    ctx = _ctx(tmp_path, sleep_s=30.0)
    script = textwrap.dedent(f"""
        import sys
        import relief_bsdf.parallel as parallel
        from relief_bsdf.parallel.cluster import synthetic_task
        if __name__ == "__main__":
            try:
                parallel.map_tasks(synthetic_task, {TASKS!r}, {ctx!r}, backend="processes", workers=2)
            except KeyboardInterrupt:
                sys.exit(130)
    """)
    # the default SIGINT disposition even when this runner was started in the background (SIGINT ignored)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        t0 = time.monotonic()
        while len(_executions(ctx)) < 2:
            assert time.monotonic() - t0 < 60 and proc.poll() is None
            time.sleep(0.02)
        worker_pids = {int(p.read_text()) for p in Path(ctx["log_dir"]).iterdir() if p.name[0].isdigit()}
        t1 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)                     # like Ctrl-C in a terminal
        assert proc.wait(15) == 130
        assert time.monotonic() - t1 < 10                      # not after the 30 s tasks
        time.sleep(0.2)
        alive = [p for p in worker_pids if psutil.pid_exists(p)
                 and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
        assert alive == []
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def test_cli_flags_configure_where_tasks_run(tmp_path, monkeypatch):
    monkeypatch.delenv("RELIEF_DASK_SCHEDULER", raising=False)
    monkeypatch.delenv("RELIEF_BACKEND", raising=False)
    p = parallel.add_parallel_args(argparse.ArgumentParser())
    args = p.parse_args(["--dask", "scheduler.example:8786", "--workers", "3",
                         "--checkpoint-dir", str(tmp_path), "--retries", "5"])
    assert parallel.resolve_backend() == "processes"
    with parallel.parallel_from_args(args) as s:
        assert s.dask == "tcp://scheduler.example:8786"
        assert (s.workers, s.checkpoint_dir, s.retries) == (3, str(tmp_path), 5)
        assert parallel.resolve_backend() == "dask"
        assert parallel.resolve_backend("serial") == "serial"
    assert parallel.current_settings() == parallel.ParallelSettings()
    assert parallel.resolve_backend() == "processes"
    monkeypatch.setenv("RELIEF_DASK_SCHEDULER", "tcp://elsewhere:8786")
    assert parallel.resolve_backend() == "dask"
    for bad in (["--dask", "nowhere"], ["--workers", "0"], ["--retries", "-1"]):
        with pytest.raises(InputError):
            parallel.apply_parallel_args(p.parse_args(bad))
    assert parallel.current_settings() == parallel.ParallelSettings()


def test_unreachable_scheduler_is_an_input_error(monkeypatch):
    monkeypatch.setenv("RELIEF_DASK_TIMEOUT_S", "1")
    with parallel.parallel_settings(dask="tcp://127.0.0.1:9"):
        with pytest.raises(InputError, match="--dask.*cannot reach"):
            parallel.map_tasks(synthetic_task, TASKS, _ctx())


def test_grouped_tasks_checkpoint_and_resume_one_by_one(tmp_path, monkeypatch):
    monkeypatch.setenv("RELIEF_TASK_GROUP", "5")
    assert parallel.group_size(1000, 2) == 5
    monkeypatch.delenv("RELIEF_TASK_GROUP")
    assert parallel.group_size(12, 2) == 1 and parallel.group_size(100_000, 2) == 32
    assert parallel.group_size(3200, 100) == 2
    monkeypatch.setenv("RELIEF_TASK_GROUP", "5")
    ck = tmp_path / "ck"
    poison = tmp_path / "poison"
    poison.touch()
    ctx = _ctx(tmp_path, poison_file=str(poison), poison_from=N - 1)
    with pytest.raises(RuntimeError, match="poisoned"):
        parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2, checkpoint_dir=ck)
    saved = len(list(ck.glob("[!.]*.npz")))
    assert saved <= N - 2                                    # the group holding task N-1 never returned
    poison.unlink()
    seen = []
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2, checkpoint_dir=ck,
                             progress=lambda d, n, w: seen.append(d))
    assert _same(out, parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial"))
    assert len(list(ck.glob("[!.]*.npz"))) == N
    assert seen[-1] == N and seen == sorted(seen)


def test_cancel_from_progress_stops_the_pool_at_once(tmp_path):
    from relief_bsdf.progress import Cancelled

    ctx = _ctx(tmp_path, sleep_s=0.5)
    tasks = [(k,) for k in range(40)]                       # 10 s of work on 2 workers

    def progress(done, total, what):
        if done == 2:
            raise Cancelled()

    t0 = time.monotonic()
    with pytest.raises(Cancelled):
        parallel.map_tasks(synthetic_task, tasks, ctx, backend="processes", workers=2, progress=progress)
    assert time.monotonic() - t0 < 5
    time.sleep(0.6)
    ran = len(_executions(ctx))
    time.sleep(1.0)
    assert len(_executions(ctx)) == ran and ran < 10          # nothing runs on after the cancel


def test_parallel_flags_keep_a_subcommands_own_workers_flag():
    p = argparse.ArgumentParser()
    p.add_argument("--workers", type=int, default=None, help="the subcommand's own")
    parallel.add_parallel_args(p)
    args = p.parse_args(["--workers", "3", "--dask", "local"])
    assert args.workers == 3 and args.dask == "local" and args.checkpoint_dir is None


def test_on_result_streams_results_into_the_callers_array(tmp_path):
    ref = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial")
    table = np.full((N, 32), np.nan, np.float32)
    order = []

    def put(i, r):
        table[i] = r
        order.append(i)

    ck = tmp_path / "ck"
    parallel.map_tasks(synthetic_task, TASKS[:5], _ctx(), backend="serial", checkpoint_dir=ck)
    out = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="processes", workers=2, checkpoint_dir=ck,
                             on_result=put)
    assert out == [None] * N                                  # nothing kept beyond the caller's array
    assert sorted(order) == list(range(N))
    assert np.array_equal(table, np.stack(ref).astype(np.float32))
    assert parallel.last_run()["loaded"] == 5


def test_settings_passed_in_win_and_the_block_stays_in_its_thread(monkeypatch):
    """Settings are values handed down: an explicit `settings=` wins over the block in force, a
    per-call keyword over both, and a `parallel_settings` block is invisible to other threads."""
    import threading
    monkeypatch.setenv("RELIEF_WORKERS", "2")      # the explicit settings' default worker count: a pool, not one

    explicit = parallel.ParallelSettings(backend="serial")
    with parallel.parallel_settings(backend="processes", workers=2) as s:
        assert s == parallel.current_settings() == parallel.ParallelSettings(backend="processes", workers=2)
        parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), settings=explicit)
        assert parallel.last_run()["backend"] == "serial"
        parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), settings=explicit, backend="processes")
        assert parallel.last_run()["backend"] == "processes"
        seen = []
        t = threading.Thread(target=lambda: seen.append(parallel.current_settings()))
        t.start()
        t.join()
        assert seen == [parallel.DEFAULT_SETTINGS]
    assert parallel.current_settings() == parallel.DEFAULT_SETTINGS
    with pytest.raises(InputError, match="--workers"):
        parallel.ParallelSettings(workers=0)


def test_parallel_modules_have_no_import_cycle():
    """settings and worker import nothing of `parallel`; cluster imports them, never tasks."""
    import ast
    import importlib.util

    def imports(mod):
        tree = ast.parse(Path(importlib.util.find_spec(mod).origin).read_text())
        return {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module} | \
            {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}

    par = "relief_bsdf.parallel"
    assert not {m for m in imports(f"{par}.settings") | imports(f"{par}.worker") if m.startswith(par)}
    assert {m for m in imports(f"{par}.cluster") if m.startswith(par)} == {f"{par}.settings", f"{par}.worker"}


def test_foreign_and_planted_checkpoints_are_never_trusted(tmp_path, capsys):
    """A checkpoint copied under another task's name is ignored (one note); a planted pickle is never opened."""
    import pickle
    import shutil

    ck = tmp_path / "ck"
    ref = parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), backend="serial", checkpoint_dir=ck)
    names = parallel.task_keys(synthetic_task, TASKS[:3], _ctx())
    shutil.copy(ck / f"{names[0]}.npz", ck / f"{names[1]}.npz")

    class Payload:
        def __reduce__(self):
            return (exec, (f"open({str(tmp_path / 'pwned')!r}, 'w').close()",))
    (ck / f"{names[2]}.pkl.z").write_bytes(pickle.dumps(Payload()))
    capsys.readouterr()
    out = parallel.map_tasks(synthetic_task, TASKS[:3], _ctx(), backend="serial", checkpoint_dir=ck)
    assert _same(out, ref) and parallel.last_run()["computed"] == 1
    assert not (tmp_path / "pwned").exists()
    notes = capsys.readouterr().err.strip().splitlines()
    assert len(notes) == 2 and "ignored 1 checkpoint" in notes[0] and "pkl.z" in notes[1]


def _thread_probe(ctx, task):
    """A task that reports where it ran; task -1 fails (after the others had a chance to start)."""
    import threading
    (k,) = task
    if k == -1:
        time.sleep(0.05)
        raise ValueError("task -1 fails")
    time.sleep(0.02)
    return (k * k, parallel.in_task_thread(), threading.get_ident(), parallel.current_settings().retries)


def test_serial_tasks_on_threads_give_the_same_results_in_task_order_and_errors_propagate():
    """`map_tasks(..., threads=N)` on the serial backend: the tasks run on N threads of this process
    (they say so through `in_task_thread`, and more than one thread served them), results come back
    in task order, equal to the plain serial run, the settings in force reach the tasks, and a failing
    task's error reaches the caller."""
    plain = parallel.map_tasks(_thread_probe, TASKS, None, backend="serial")
    with parallel.parallel_settings(retries=5):
        seen = []
        threaded = parallel.map_tasks(_thread_probe, TASKS, None, backend="serial", threads=2,
                                      progress=lambda d, n, w: seen.append(d))
    assert [r[0] for r in threaded] == [r[0] for r in plain] == [k * k for k in range(N)]
    assert not any(r[1] for r in plain) and all(r[1] for r in threaded)
    assert len({r[2] for r in threaded}) == 2
    assert all(r[3] == 5 for r in threaded)
    assert seen == list(range(1, N + 1))
    assert parallel.last_run()["threads"] == 2
    assert not parallel.in_task_thread()
    with pytest.raises(ValueError, match="task -1 fails"):
        parallel.map_tasks(_thread_probe, TASKS[:4] + [(-1,)], None, backend="serial", threads=2)
    # processes and workers are untouched by `threads` (they use their own processes)
    out = parallel.map_tasks(_thread_probe, TASKS[:4], None, backend="processes", workers=2, threads=2)
    assert [r[0] for r in out] == [0, 1, 4, 9] and not any(r[1] for r in out)


def _pid_and_calls(ctx, task):
    """(this process's id, how many tasks this process ran before this one)."""
    from relief_bsdf.parallel import worker
    state = worker.worker_cached(("test kept pool", "calls"), lambda: [0])
    state[0] += 1
    time.sleep(0.05)                       # let both workers take tasks
    return os.getpid(), state[0] - 1


def test_kept_workers_run_every_call_of_the_block_on_the_same_processes_then_stop_them():
    ctx = {"what": "kept"}
    with parallel.kept_workers(ctx):
        first = parallel.map_tasks(_pid_and_calls, range(8), ctx, backend="processes", workers=2)
        second = parallel.map_tasks(_pid_and_calls, range(8), ctx, backend="processes", workers=2)
        other = parallel.map_tasks(_pid_and_calls, range(8), {"what": "other"}, backend="processes", workers=2)
    pids = {p for p, _ in first}
    assert len(pids) == 2 and {p for p, _ in second} == pids         # the same two processes
    assert min(c for _, c in second) >= 1                             # which kept what the first call left
    assert not pids & {p for p, _ in other}                           # another context: a pool of its own
    assert min(c for _, c in other) == 0                              # ... started bare
    time.sleep(0.5)
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in pids)
    after = parallel.map_tasks(_pid_and_calls, range(8), ctx, backend="processes", workers=2)
    assert not pids & {p for p, _ in after}                           # outside the block: a fresh pool


def test_a_crash_in_a_kept_pool_reruns_its_tasks_on_a_fresh_one(tmp_path):
    ctx = _ctx(tmp_path, crash_file=str(tmp_path / "crashed"), crash_at=4)
    with parallel.kept_workers(ctx):
        out = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2)
        again = parallel.map_tasks(synthetic_task, TASKS, ctx, backend="processes", workers=2)
    assert (tmp_path / "crashed").exists()
    expected = parallel.map_tasks(synthetic_task, TASKS, _ctx(), backend="serial")
    assert _same(out, expected) and _same(again, expected)
