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


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc to list a session")
def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    """SIGTERM (a job scheduler's time limit): one line, exit 143, checkpoints kept, nothing half-written,
    no process of the run left."""
    ck = tmp_path / "ck"
    script = textwrap.dedent(f"""
        import sys
        import relief_bsdf.cli as cli
        import relief_bsdf.cli.cmd_info as cmd_info
        import relief_bsdf.parallel as parallel
        from relief_bsdf.parallel.cluster import synthetic_task

        def long_command(args):
            ctx = {{"seed": 1, "size": 8, "work": 1, "sleep_s": 0.4}}
            parallel.map_tasks(synthetic_task, [(k,) for k in range(40)], ctx, backend="processes", workers=2,
                               checkpoint_dir={str(ck)!r})
            return 0

        if __name__ == "__main__":
            cmd_info.run = long_command          # `relief info` stands in for any long command
            sys.exit(cli.main(["info", "x"]))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True, stderr=subprocess.PIPE,
                            text=True)
    sid = proc.pid
    try:
        assert _wait_for(lambda: len(list(ck.glob("[!.]*.npz"))) >= 2, 60), "the run never checkpointed"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode == 143, err
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and "terminated" in lines[0], err
        kept = list(ck.glob("[!.]*.npz"))
        assert 2 <= len(kept) < 40
        assert not [p for p in ck.iterdir() if ".part" in p.name]
        assert _wait_for(lambda: not _session_members(sid), 8), f"left behind: {_session_members(sid)}"
    finally:
        for pid in _session_members(sid):
            os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
