"""The interactive path of long operators: worker thread, progress, Esc cancels, errors become reports.

There is no event loop in the bpy module, so the window manager and events are stand-ins;
the JobOperator code under test is the add-on's own.
"""
from __future__ import annotations

import time
from types import SimpleNamespace

from relief_addon.jobs import JobOperator


class FakeWM:
    def __init__(self):
        self.updates, self.began, self.ended, self.timers, self.handlers = [], 0, 0, [], []

    def progress_begin(self, a, b):
        self.began += 1

    def progress_update(self, v):
        self.updates.append(v)

    def progress_end(self):
        self.ended += 1

    def event_timer_add(self, dt, window=None):
        self.timers.append(dt)
        return object()

    def event_timer_remove(self, t):
        self.timers.pop()

    def modal_handler_add(self, op):
        self.handlers.append(op)


def _context():
    return SimpleNamespace(window=object(), window_manager=FakeWM(), scene=SimpleNamespace(relief=SimpleNamespace(
        job_status="")), workspace=None, screen=None)


class Job(JobOperator):
    bl_idname = "relief.test_job"
    job_label = "Test"

    def __init__(self, mode):
        self.mode, self.reports, self.finished_with = mode, [], None

    def report(self, kind, text):
        self.reports.append((set(kind), text))

    def prepare(self, context):
        return self.mode

    @staticmethod
    def work(mode, progress):
        from relief_bsdf.errors import InputError
        for k in range(200 if mode == "slow" else 4):
            if mode == "error" and k == 2:
                raise InputError("sample.toml", "bad key")
            progress(k, 4, f"step {k}")
            time.sleep(0.01)
        return 42

    def finish(self, context, result):
        self.finished_with = result


def _drive(op, ctx, esc_after=None, timeout=20.0):
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < timeout:
        ev = SimpleNamespace(type="ESC", value="PRESS") if esc_after is not None and n == esc_after else \
            SimpleNamespace(type="TIMER", value="NOTHING")
        res = op.modal(ctx, ev)
        n += 1
        if res & {"FINISHED", "CANCELLED"}:
            return res
        time.sleep(0.02)
    raise AssertionError("job did not end")


def test_threaded_job_reports_progress_and_finishes_on_main_thread():
    ctx = _context()
    op = Job("ok")
    assert op.invoke_threaded(ctx) == {"RUNNING_MODAL"}
    assert ctx.window_manager.handlers == [op] and ctx.window_manager.began == 1
    assert _drive(op, ctx) == {"FINISHED"}
    assert op.finished_with == 42
    assert ctx.window_manager.ended == 1 and ctx.window_manager.timers == []
    assert all(0 <= u <= 1000 for u in ctx.window_manager.updates)
    assert ctx.scene.relief.job_status == "Test: done"


def test_escape_cancels_at_the_next_task_boundary():
    ctx = _context()
    op = Job("slow")
    op.invoke_threaded(ctx)
    assert _drive(op, ctx, esc_after=3) == {"CANCELLED"}
    assert op.finished_with is None
    assert any("WARNING" in k and "cancelled" in t for k, t in op.reports)
    assert not op._thread.is_alive() and ctx.window_manager.ended == 1


class StagedJob(Job):
    """A job like the backend's: it checks its CancelToken between stages and reports no progress."""

    @staticmethod
    def work(mode, progress, cancel=None):
        for k in range(200):
            cancel.check(f"stage {k}")
            time.sleep(0.01)
        return 42


def test_escape_reaches_the_jobs_cancel_token_between_stages():
    ctx = _context()
    op = StagedJob("slow")
    op.invoke_threaded(ctx)
    assert _drive(op, ctx, esc_after=3) == {"CANCELLED"}
    assert op.finished_with is None
    assert any("WARNING" in k and "cancelled" in t for k, t in op.reports)


def test_backend_error_becomes_one_line_report():
    ctx = _context()
    op = Job("error")
    op.invoke_threaded(ctx)
    assert _drive(op, ctx) == {"CANCELLED"}
    kinds, text = op.reports[-1]
    assert "ERROR" in kinds and text == "Test: sample.toml: bad key"


def test_execute_runs_synchronously_and_reports_errors():
    ctx = _context()
    assert Job("ok").execute(ctx) == {"FINISHED"}
    op = Job("error")
    assert op.execute(ctx) == {"CANCELLED"}
    assert op.reports[-1][1] == "Test: sample.toml: bad key"


def test_execute_logs_progress_lines_off_a_terminal(capsys):
    # background batches (blender --background) have no status bar: the work's progress goes to stderr
    assert Job("ok").execute(_context()) == {"FINISHED"}
    err = capsys.readouterr().err
    assert "Test" in err and "\r" not in err
    assert any(line.strip() and "/" in line for line in err.splitlines())
