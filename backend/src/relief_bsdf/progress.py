"""Progress reporting for long work: one callable type, a terminal bar, and a silent default.

Backend functions take `progress: Progress | None`; they call `progress(done, total, what)`
with counts of finished independent tasks (incidences, wavelengths, candidates, ...).
Front ends (CLI, Blender worker thread) pass their own callable; raising `Cancelled`
from it stops the work cleanly at the next task boundary.
"""
from __future__ import annotations

import sys
import time
from typing import Callable, Optional

Progress = Callable[[int, int, str], None]


class Cancelled(Exception):
    """Raised from a progress callback to stop long work (e.g. the Blender Esc key)."""


def silent(done: int, total: int, what: str = "") -> None:
    """A progress callback that does nothing."""


class TerminalBar:
    """A one-line progress bar on stderr (only when it is a terminal, or when forced)."""

    def __init__(self, label: str, stream=None, force: bool = False, width: int = 30):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = force or getattr(self.stream, "isatty", lambda: False)()
        self.width = width
        self.t0 = time.monotonic()
        self._last = 0.0

    def __call__(self, done: int, total: int, what: str = "") -> None:
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


def fraction_callback(progress: Optional[Progress], offset: int, total: int) -> Progress:
    """Map a sub-task's own (done, total) onto a slice [offset, offset+1) of a parent count."""
    progress = progress or silent

    def cb(done: int, sub_total: int, what: str = "") -> None:
        progress(offset + (done >= sub_total), total, what)

    return cb
