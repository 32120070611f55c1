"""map_tasks on a Dask LocalCluster (2 single-threaded worker processes): same numbers as the
local backends, context shipped once per worker, progress across the cluster, lost workers,
failed tasks, checkpoints and resume."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

import distributed  # noqa: E402,F401  (a runtime dependency: a missing one must fail, not skip)

import relief_bsdf.parallel as parallel  # noqa: E402
from relief_bsdf.parallel.cluster import synthetic_task  # noqa: E402

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
    return sorted(int(p.name.split("-")[0]) for p in Path(ctx["log_dir"]).iterdir() if p.name[0].isdigit())


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
    pids = {int(p.read_text()) for p in Path(ctx["log_dir"]).iterdir() if p.name[0].isdigit()}
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
    saved = {k for k in range(N) if (ck / f"{keys[k]}.npz").exists()}
    assert saved <= set(range(10))
    poison.unlink()
    for p in Path(ctx["log_dir"]).iterdir():
        p.unlink()
    out = parallel.map_tasks(synthetic_task, TASKS, ctx, checkpoint_dir=ck)
    assert parallel.last_run()["loaded"] == len(saved)
    assert set(_executions(ctx)) == set(range(N)) - saved     # nothing finished ran twice
    assert _same(out, _reference())


def _toy_incidence(ctx, task):
    """A smooth stand-in lobe for one (wavelength, theta_i, phi_i): values decay away from the
    specular direction, scaled by wavelength; seeded noise so every cell depends on the seed."""
    iw, ii, ip = task
    th = ctx["theta_s"][:, None]
    ph = ctx["phi_s"][None, :]
    lobe = np.exp(-((th - ctx["theta_i"][ii]) / 15.0) ** 2) * (1 + np.cos(np.radians(ph - ctx["phi_i"][ip] - 180)))
    noise = parallel.task_rng(ctx["seed"], iw, ii, ip).random(lobe.shape) * 1e-3
    r = (lobe + noise) * ctx["wavelength"][iw] / 550.0
    return np.stack([r, 0.5 * r])


def test_spectral_anisotropic_request_as_one_chunked_table(client, tmp_path):
    """31 wavelengths x 18 theta_i x 12 phi_i (6696 tasks) on the cluster, one BsdfTable, one HDF5
    file chunked per incidence and compressed; every cell back where its task put it."""
    import cloudpickle
    import sys

    from relief_bsdf.bsdf.table import BsdfTable
    from relief_bsdf.io.hdf5 import load_tables, save_tables

    te, pe = np.linspace(0, 90, 19), np.arange(-5.0, 360.0, 10.0)
    ctx = {"seed": 5, "wavelength": np.linspace(400, 700, 31), "theta_i": np.arange(0, 90, 5.0),
           "phi_i": np.arange(0, 360, 30.0), "theta_s": 0.5 * (te[1:] + te[:-1]), "phi_s": 0.5 * (pe[1:] + pe[:-1])}
    W, I, P = 31, 18, 12
    tasks = [(iw, ii, ip) for iw in range(W) for ii in range(I) for ip in range(P)]
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    seen = []
    try:
        res = parallel.map_tasks(_toy_incidence, tasks, ctx, label="toy", progress=lambda d, n, w: seen.append(d))
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert parallel.last_run()["backend"] == "dask" and seen[-1] == len(tasks)
    values = np.stack(res).reshape(W, I, P, 2, len(te) - 1, len(pe) - 1)
    table = BsdfTable(ctx["wavelength"], ctx["theta_i"], ctx["phi_i"], te, pe, values, method="toy")
    path = save_tables(tmp_path / "big.h5", [table])
    import h5py

    with h5py.File(path) as f:
        d = f["outside/values_per_sr"]
        assert d.shape == (W, I, P, 2, 18, 36)
        assert d.chunks == (1, 1, 1, 2, 18, 36)            # one chunk per incidence: eval reads one
        assert d.compression == "gzip" and d.shuffle
    # the smooth lobes compress: the file is well under the raw float32 size
    assert path.stat().st_size < 0.6 * values.size * 4
    back = load_tables(path)[0]
    k = 4321
    iw, ii, ip = tasks[k]
    assert np.allclose(back.values_per_sr[iw, ii, ip], _toy_incidence(ctx, tasks[k]).astype(np.float32))
    assert np.allclose(back.values_per_sr, values.astype(np.float32))


def test_monte_carlo_method_identical_on_dask_and_locally(client):
    """A real seeded Monte-Carlo method (normals) gives bit-identical tables on the cluster,
    on local processes and in this process."""
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.methods.request import Request
    from relief_bsdf.surface.synth import random_relief

    relief = random_relief(64, 1e-6, 0.4e-6, 8e-6, seed=2)
    req = Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0, 40.0, 70.0), phi_i_deg=(0.0, 90.0),
                  incident_from=("outside", "inside"), samples=4000, seed=9,
                  theta_s_edges_deg=tuple(np.linspace(0, 90, 19)), phi_s_edges_deg=tuple(np.arange(-15.0, 360, 30)))
    mat = Material(inside=ConstantIndex(1.5))
    on_dask = reconstruct(relief, mat, req, "normals")
    assert parallel.last_run()["backend"] == "dask" and parallel.last_run()["total"] == 24
    with parallel.parallel_settings(dask=None, workers=2):  # two worker processes, whatever RELIEF_WORKERS says
        local = reconstruct(relief, mat, req, "normals")
        assert parallel.last_run()["backend"] == "processes"
    os.environ["RELIEF_BACKEND"] = "serial"
    try:
        serial = reconstruct(relief, mat, req, "normals")
    finally:
        del os.environ["RELIEF_BACKEND"]
    for a, b, c in zip(on_dask, local, serial):
        assert a.values_per_sr.any()
        assert np.array_equal(a.values_per_sr, b.values_per_sr) and np.array_equal(a.values_per_sr, c.values_per_sr)
        assert np.array_equal(a.specular_R, c.specular_R) and np.array_equal(a.lost, c.lost)


def test_cli_reconstruct_on_a_local_dask_cluster_matches_default(tmp_path):
    import subprocess
    import sys

    from relief_bsdf.io.hdf5 import load_tables
    from relief_bsdf.surface.synth import random_relief

    r = random_relief(64, 1e-6, 0.4e-6, 8e-6, seed=4)
    np.savez(tmp_path / "r.npz", heights=r.heights_m, dx=r.dx_m, dy=r.dy_m)
    relief_cli = [sys.executable, "-m", "relief_bsdf.cli", "reconstruct", str(tmp_path / "r.npz"),
                  "--method", "normals", "--n", "1.5", "--wavelengths-nm", "500,600", "--theta-i-deg", "0,40", "--phi-i-deg", "0,90",
                  "--samples", "3000", "--theta-step-deg", "5", "--phi-step-deg", "30", "--seed", "3"]
    env = {k: v for k, v in os.environ.items() if k not in ("RELIEF_DASK_SCHEDULER", "RELIEF_BACKEND")}
    a = subprocess.run(relief_cli + ["-o", str(tmp_path / "a.h5")], capture_output=True, text=True, env=env)
    assert a.returncode == 0, a.stderr
    b = subprocess.run(relief_cli + ["--dask", "local", "--workers", "2", "--checkpoint-dir", str(tmp_path / "ck"),
                                     "-o", str(tmp_path / "b.h5")], capture_output=True, text=True, env=env)
    assert b.returncode == 0, b.stderr
    ta, tb = load_tables(tmp_path / "a.h5")[0], load_tables(tmp_path / "b.h5")[0]
    assert ta.values_per_sr.any() and np.array_equal(ta.values_per_sr, tb.values_per_sr)
    assert len(list((tmp_path / "ck").glob("normals-*.npz"))) == 2 * 2 * 2
    bad = subprocess.run(relief_cli + ["--dask", "nowhere", "-o", str(tmp_path / "c.h5")], capture_output=True,
                         text=True, env=env)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--dask" in bad.stderr


def test_workers_with_another_relief_version_are_refused(client, monkeypatch):
    from relief_bsdf.parallel import cluster
    from relief_bsdf.errors import InputError

    cluster.check_workers(client)                             # same installation: accepted
    monkeypatch.setattr("relief_bsdf.__version__", "0.0.0-other")
    with pytest.raises(InputError, match=r"--dask: 2 of 2 Dask workers do not run relief_bsdf 0.0.0-other"):
        cluster.check_workers(client)


def test_in_process_threaded_cluster_leaves_the_client_process_usable():
    """With a threads-only cluster the tasks run in this process: the 'inside a task' mark
    must stay on the worker thread, so later calls here still use the pool they ask for."""
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as lc, \
            distributed.Client(lc, set_as_default=False) as c:
        with parallel.parallel_settings(dask=c):
            out = parallel.map_tasks(_nested_backend, [0, 1, 2, 3], None)
    assert out == ["serial"] * 4
    assert not parallel.in_worker()
    assert parallel.resolve_backend("processes") == "processes"


def _nested_backend(context, task):
    return parallel.resolve_backend("processes")


def test_cancel_from_progress_cancels_the_cluster_work(client, tmp_path):
    from relief_bsdf.progress import Cancelled

    ctx = _ctx(tmp_path, sleep_s=0.3)
    tasks = [(k,) for k in range(40)]

    def progress(done, total, what):
        if done == 2:
            raise Cancelled()

    with pytest.raises(Cancelled):
        parallel.map_tasks(synthetic_task, tasks, ctx, progress=progress)
    time.sleep(1.0)
    ran = len(_executions(ctx))
    assert ran < 12                                          # the other 28+ tasks never started
    assert not any(client.processing().values())


def test_ctrl_c_on_a_local_dask_run_exits_cleanly(tmp_path):
    """Ctrl-C in a terminal (SIGINT to the process group) during `--dask local`: exit code 130,
    one line on stderr, no worker process left behind."""
    import subprocess
    import sys

    import psutil

    from relief_bsdf.surface.synth import random_relief

    r = random_relief(64, 1e-6, 0.4e-6, 8e-6, seed=4)
    np.savez(tmp_path / "r.npz", heights=r.heights_m, dx=r.dx_m, dy=r.dy_m)
    cmd = [sys.executable, "-m", "relief_bsdf.cli", "reconstruct", str(tmp_path / "r.npz"), "--method", "normals",
           "--n", "1.5", "--wavelengths-nm", ",".join(str(400 + 10 * i) for i in range(31)), "--theta-i-deg", "0,30,60",
           "--samples", "200000", "--theta-step-deg", "5", "--phi-step-deg", "30", "--dask", "local", "--workers", "2",
           "-o", str(tmp_path / "t.h5")]
    env = {k: v for k, v in os.environ.items() if k not in ("RELIEF_DASK_SCHEDULER", "RELIEF_BACKEND")}
    # a runner started in the background (`cmd &` in a script) hands SIGINT down ignored: give the child
    # the default disposition, as a terminal would
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    import threading
    lines: list = []
    reader = threading.Thread(target=lambda: lines.extend(iter(p.stderr.readline, "")), daemon=True)
    try:
        reader.start()
        t0 = time.monotonic()
        # the cluster ignores Ctrl-C while its workers start (cluster.py); a first progress line with a task
        # count on stderr (stderr is not a terminal: plain log lines; the heartbeat's "working" line comes
        # before the cluster is up) means it is up and tasks are under way
        while not any(ln.startswith("reconstruct normals:") and "/" in ln for ln in list(lines)):
            assert p.poll() is None and time.monotonic() - t0 < 60, lines
            time.sleep(0.05)
        kids = [c.pid for c in psutil.Process(p.pid).children(recursive=True)]
        assert len(kids) >= 2
        os.killpg(p.pid, signal.SIGINT)
        p.wait(timeout=60)
        reader.join(10)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    err = "".join(lines)
    assert p.returncode == 130, err
    # progress lines, then exactly one line for the interruption, no traceback
    *progress, last = err.strip().splitlines()
    assert last == "relief reconstruct: interrupted", err
    assert progress and all(ln.startswith("reconstruct normals:") for ln in progress), err
    assert "Traceback" not in err
    time.sleep(1.0)
    alive = [k for k in kids if psutil.pid_exists(k) and psutil.Process(k).status() != psutil.STATUS_ZOMBIE]
    assert alive == []
