"""Progress reporting (progress.py): terminal bar on a TTY, plain log lines elsewhere."""
import io
import re

import numpy as np
import pytest

from relief_bsdf.progress import LineProgress, TerminalBar

LINE = re.compile(r"^(?P<label>[^:]+): (?P<done>\d+)/(?P<total>\d+) \((?P<pct>\d+) %\) elapsed (?P<t>\d+)s")


class TTY(io.StringIO):
    def isatty(self):
        return True


class Clock:
    def __init__(self, step_s):
        self.t, self.step_s = 0.0, step_s

    def __call__(self):
        self.t += self.step_s
        return self.t


def _lines(stream):
    text = stream.getvalue()
    assert "\r" not in text and text.endswith("\n")
    return text.splitlines()


def test_terminal_bar_off_a_tty_writes_one_line_per_ten_percent():
    s = io.StringIO()                     # not a terminal: a log file, a CI capture
    bar = TerminalBar("fit", stream=s)
    for k in range(1001):
        bar(k, 1000, f"task {k}")
    lines = _lines(s)
    assert len(lines) == 11               # 0 %, 10 %, ..., 100 %
    got = [LINE.match(x) for x in lines]
    assert all(m and m["label"] == "fit" and m["total"] == "1000" for m in got)
    assert [int(m["done"]) for m in got] == list(range(0, 1001, 100))
    assert [int(m["pct"]) for m in got] == list(range(0, 101, 10))
    assert lines[-1].endswith("- task 1000") and "eta" not in lines[-1]
    assert "eta" in lines[5]


def test_uneven_counts_still_step_and_completion_is_written_once():
    s = io.StringIO()
    p = LineProgress("render", s)
    for k in (0, 1, 2, 3, 3, 3):          # three tasks: 0, 33, 66, 100 %; repeated completion ignored
        p(k, 3)
    assert [int(LINE.match(x)["done"]) for x in _lines(s)] == [0, 1, 2, 3]


def test_heartbeat_after_interval_without_a_line():
    # 1000 tasks, 7 s each: with a 30 s interval a line comes every 5th task (35 s) besides the 10 % steps
    s = io.StringIO()
    p = LineProgress("diagnose", s, interval_s=30.0, clock=Clock(7.0))
    for k in range(1, 101):
        p(k, 1000)
    done = [int(LINE.match(x)["done"]) for x in _lines(s)]
    assert done[0] == 1 and done[-1] == 100                      # the first line, then the 10 % step
    gaps = np.diff(done)
    assert np.all(gaps >= 4) and np.all(gaps <= 5)              # never more often than every 30 s
    times = [int(LINE.match(x)["t"]) for x in _lines(s)]
    assert np.all(np.diff(times) >= 28)


def test_the_first_forced_heartbeat_is_written_only_before_any_progress_line():
    """keep_alive's first heartbeat (forced, after one second) shows a silent job alive; once the job
    has written a progress line (here its 100 % line) it is not written: a "working" line after the
    completion line would read as more work (the CLI test saw it under load)."""
    s = io.StringIO()
    p = LineProgress("x", s, interval_s=30.0, clock=Clock(0.5))
    p.beat(force=True)
    assert len(_lines(s)) == 1 and _lines(s)[0].startswith("x: working, elapsed ")
    s2 = io.StringIO()
    q = LineProgress("y", s2, interval_s=30.0, clock=Clock(0.5))
    q(9, 9)
    q.beat(force=True)
    assert len(_lines(s2)) == 1 and LINE.match(_lines(s2)[0])["pct"] == "100"


def test_fast_work_gets_no_heartbeat_and_a_new_total_starts_a_new_sequence():
    s = io.StringIO()
    p = LineProgress("x", s, interval_s=30.0, clock=Clock(0.001))
    for k in range(0, 51):
        p(k, 50)
    for k in range(0, 5):                 # a second phase with its own count
        p(k, 4, "phase 2")
    lines = _lines(s)
    assert len(lines) == 11 + 5
    assert lines[11].startswith("x: 0/4 (0 %)") and lines[-1].startswith("x: 4/4 (100 %)")


def test_terminal_bar_on_a_tty_keeps_the_redrawn_bar():
    s = TTY()
    bar = TerminalBar("reconstruct", stream=s)
    for k in range(11):
        bar(k, 10)
    out = s.getvalue()
    assert out.startswith("\rreconstruct [") and out.endswith("\n") and out.count("\n") == 1


def test_silence_off_a_tty_on_request_and_bad_step():
    s = io.StringIO()
    bar = TerminalBar("fit", stream=s, lines=False)
    bar(5, 10)
    bar(10, 10)
    assert s.getvalue() == ""
    with pytest.raises(ValueError, match="step"):
        LineProgress("x", s, step=0.0)


def test_cli_progress_in_a_captured_stderr_is_line_based(tmp_path, capsys):
    from relief_bsdf.cli import main
    rng = np.random.default_rng(0)
    h = rng.normal(size=(32, 32)) * 0.05e-6
    relief = tmp_path / "r.npz"
    np.savez(relief, heights=h, dx=1e-6, dy=1e-6)
    rc = main(["reconstruct", str(relief), "--method", "microfacet", "--n", "1.5", "--theta-i-deg", "0,20,40",
               "--theta-step-deg", "15", "--phi-step-deg", "45", "-o", str(tmp_path / "t.h5")])
    err = capsys.readouterr().err
    assert rc == 0
    assert "\r" not in err
    lines = [x for x in err.splitlines() if x.startswith("reconstruct microfacet:")]
    assert lines and LINE.match(lines[-1]) and "(100 %)" in lines[-1]
