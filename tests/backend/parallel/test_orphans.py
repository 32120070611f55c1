"""No process of a run outlives it: kill -9 of the run leaves no worker, fork server or resource tracker."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest


def _session_members(sid: int) -> list[int]:
    """Live (non-zombie) processes of session `sid` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_bytes()
        except OSError:
            continue
        fields = stat.rsplit(b")", 1)[1].split()
        state, session = fields[0], int(fields[3])
        if session == sid and state not in (b"Z", b"X"):
            out.append(int(d.name))
    return out


def _wait_for(cond, timeout_s: float) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():
            return True
        time.sleep(0.1)
    return cond()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc to list a session")
def test_kill_9_of_the_run_leaves_no_process(tmp_path):
    started = tmp_path / "started"
    script = textwrap.dedent(f"""
        import os, time
        import relief_bsdf.parallel as parallel
        from relief_bsdf.parallel.cluster import synthetic_task
        if __name__ == "__main__":
            ctx = {{"seed": 1, "size": 8, "work": 1, "sleep_s": 30.0, "log_dir": {str(tmp_path)!r}}}
            parallel.map_tasks(synthetic_task, [(k,) for k in range(8)], ctx, backend="processes", workers=2)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    sid = proc.pid
    try:
        # both workers are running a task (each wrote its log file): the pool, fork server and tracker exist
        assert _wait_for(lambda: len([p for p in tmp_path.iterdir() if p.name[0].isdigit()]) >= 2, 60), \
            "the workers never started"
        members = _session_members(sid)
        assert len(members) >= 4, f"expected run, fork server, tracker and 2 workers, found {members}"
        proc.send_signal(signal.SIGKILL)           # only the run itself, not its process group
        proc.wait(10)
        assert _wait_for(lambda: not _session_members(sid), 8), \
            f"processes of the killed run still alive: {_session_members(sid)}"
    finally:
        for pid in _session_members(sid):
            os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
