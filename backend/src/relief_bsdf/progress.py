"""Progress reporting for long work: one callable type, a terminal bar, log lines, a silent default.

Backend functions take `progress: Progress | None`; they call `progress(done, total, what)`
with counts of finished independent tasks (incidences, wavelengths, candidates, ...).
Front ends (CLI, Blender worker thread) pass their own callable; raising `Cancelled`
from it stops the work cleanly at the next task boundary.

`TerminalBar` redraws one line with carriage returns when its stream is a terminal.
When it is not (CI logs, batch jobs, `blender --background`, output piped to a file)
it falls back to `LineProgress`: whole lines, no carriage returns, one per ~10 % of
the work or after `interval_s` seconds without a line, each with label, done/total
and elapsed time.
"""
from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, Optional

Progress = Callable[[int, int, str], None]


class Cancelled(Exception):
    """Raised from a progress callback to stop long work (e.g. the Blender Esc key)."""


def silent(done: int, total: int, what: str = "") -> None:
    """A progress callback that does nothing."""


def _is_tty(stream) -> bool:
    try:
        return bool(getattr(stream, "isatty", lambda: False)())
    except (ValueError, OSError):   # a closed or detached stream
        return False


class LineProgress:
    """Progress as plain log lines (no carriage returns), for streams that are not terminals.

    A line is written when the work crosses the next `step` fraction (default 10 %), when
    `interval_s` seconds passed since the last line and more tasks finished (a heartbeat for
    slow jobs with few tasks), and once at completion:
        ``<label>: <done>/<total> (<pct> %) elapsed <t>s[, eta <t>s][ - <what>]``
    A new count (a smaller `done` or another `total`) starts a new sequence, so one object
    can report several phases.  `clock` is injectable for tests.
    """

    def __init__(self, label: str, stream=None, step: float = 0.1, interval_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic):
        if not 0 < step <= 1:
            raise ValueError(f"LineProgress: step must be in (0, 1], got {step}")
        self.label = label
        self.stream = stream or sys.stderr
        self.step = step
        self.interval_s = interval_s
        self.clock = clock
        self.t0 = clock()
        self._lock = threading.Lock()
        self._what = ""
        self._wrote = False        # any line written (`beat`)
        self._reset(None)

    def _reset(self, total) -> None:
        self._total = total
        self._bucket = -1          # last step index written
        self._done = -1            # last count written
        self._t_line = self.clock()
        self._finished = False

    def __call__(self, done: int, total: int, what: str = "") -> None:
        with self._lock:
            self._line(done, total, what)

    def beat(self, force: bool = False) -> None:
        """A time-based line when nothing was written for `interval_s` (long work between task
        boundaries, e.g. one fit evaluation's tables): ``<label>: working, elapsed <t>s[ - <what>]``.
        `force` writes it now (the first line of a job), unless a line was already written: a job
        that reported progress has shown it is alive, and a "working" line after its 100 % line
        would read as more work (seen when a job's tables took just over `keep_alive`'s first second)."""
        with self._lock:
            now = self.clock()
            if force and self._wrote:
                return
            if not force and now - self._t_line < self.interval_s:
                return
            what = f" - {self._what}" if self._what else ""
            self.stream.write(f"{self.label}: working, elapsed {now - self.t0:.0f}s{what}\n")
            self.stream.flush()
            self._t_line, self._wrote = now, True

    def _line(self, done: int, total: int, what: str) -> None:
        self._what = " ".join(str(what).split())[:60]
        if total != self._total or done < self._done:
            self._reset(total)
        if self._finished:
            return
        now = self.clock()
        frac = min(done / total, 1.0) if total else 1.0
        bucket = int(frac / self.step + 1e-9)
        finished = done >= total
        due = bucket > self._bucket or finished or (now - self._t_line >= self.interval_s and done > self._done)
        if not due:
            return
        elapsed = now - self.t0
        eta = f", eta {elapsed * (1 - frac) / frac:.0f}s" if 0 < frac < 1 else ""
        what = " ".join(str(what).split())[:60]
        line = f"{self.label}: {done}/{total} ({100 * frac:.0f} %) elapsed {elapsed:.0f}s{eta}"
        self.stream.write(line + (f" - {what}" if what else "") + "\n")
        self.stream.flush()
        self._bucket, self._done, self._t_line, self._finished = bucket, done, now, finished
        self._wrote = True


class TerminalBar:
    """A one-line progress bar on stderr when it is a terminal (or when forced); otherwise
    log lines through `LineProgress` (`lines=False` restores silence off a terminal)."""

    def __init__(self, label: str, stream=None, force: bool = False, width: int = 30, lines: bool = True,
                 interval_s: float = 30.0):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = force or _is_tty(self.stream)
        self.width = width
        self.t0 = time.monotonic()
        self._last = 0.0
        self.lines = LineProgress(label, self.stream, interval_s=interval_s) if (lines and not self.enabled) else None

    def beat(self, force: bool = False) -> None:
        """Time-based heartbeat line (log mode only: a terminal bar redraws on every call)."""
        if self.lines is not None:
            self.lines.beat(force)

    def __call__(self, done: int, total: int, what: str = "") -> None:
        if self.lines is not None:
            self.lines(done, total, what)
            return
        now = time.monotonic()
        if not self.enabled or (now - self._last < 0.1 and done < total):
            return
        self._last = now
        frac = done / total if total else 1.0
        n = int(round(frac * self.width))
        eta = (now - self.t0) * (1 - frac) / frac if frac > 0 else float("nan")
        msg = f"\r{self.label} [{'#' * n}{'.' * (self.width - n)}] {done}/{total} {what[:30]:30s} eta {eta:5.0f}s"
        self.stream.write(msg)
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


@contextmanager
def keep_alive(progress: Optional[Progress], interval_s: float = 1.0, first_after_s: float = 1.0) -> Iterator[None]:
    """Run the block with a heartbeat: a first line once the work has lasted `first_after_s`
    (a job that fails at once prints only its error), then `progress.beat()` polled every
    `interval_s` seconds from a daemon thread (the progress object decides when a line is due:
    LineProgress after its own 30 s of silence), so a non-terminal log shows a long job alive
    from its first second.  Progress objects without `beat` are left as they are."""
    beat = getattr(progress, "beat", None)
    if beat is None:
        yield
        return
    stop = threading.Event()

    def run() -> None:
        if stop.wait(first_after_s):
            return
        beat(force=True)
        while not stop.wait(interval_s):
            beat()
    t = threading.Thread(target=run, name="relief-heartbeat", daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join(timeout=5.0)


def fraction_callback(progress: Optional[Progress], offset: int, total: int) -> Progress:
    """Map a sub-task's own (done, total) onto a slice [offset, offset+1) of a parent count."""
    progress = progress or silent

    def cb(done: int, sub_total: int, what: str = "") -> None:
        progress(offset + (done >= sub_total), total, what)

    return cb
