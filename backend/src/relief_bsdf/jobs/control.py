"""How a job is watched and stopped: progress (the project's `progress.Progress`) and a cancel token.

Every job takes `progress` (called with counts of finished independent tasks; `progress.silent`
when None) and `cancel` (a `CancelToken`, or None).  A job checks the token between its stages
(`CancelToken.check`), and the progress it passes down checks it at every task boundary
(`watched`), so a cancel takes effect at the next boundary, never inside a task: what was
finished stays finished (checkpoints, atomically written files), nothing is half-written.  A
cancelled job raises `progress.Cancelled`.  The Blender layer sets the token from Esc on its
worker thread; a script may set it from any thread.
"""
from __future__ import annotations

import threading

from relief_bsdf.progress import Cancelled, Progress, silent


class CancelToken:
    """A thread-safe flag that asks a running job to stop at its next stage or task boundary.

    `event`: an existing `threading.Event` to share (the Blender operator's Esc flag), else a new one.
    """

    def __init__(self, event: threading.Event | None = None):
        self._event = event if event is not None else threading.Event()

    def cancel(self) -> None:
        """Ask the job to stop (from any thread)."""
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def check(self, where: str = "") -> None:
        """Raise `progress.Cancelled` when the job was asked to stop (between stages)."""
        if self._event.is_set():
            raise Cancelled(f"cancelled{' before ' + where if where else ''}")


def check(cancel: CancelToken | None, where: str = "") -> None:
    """`cancel.check(where)`, nothing without a token."""
    if cancel is not None:
        cancel.check(where)


def watched(progress: Progress | None, cancel: CancelToken | None) -> Progress:
    """The progress a job passes down: `progress` (silent when None), checking `cancel` at every call
    (every finished task) first.  Without a token, `progress` itself (its `beat` kept for
    `progress.keep_alive`)."""
    progress = progress or silent
    if cancel is None:
        return progress

    def call(done: int, total: int, what: str = "") -> None:
        cancel.check()
        progress(done, total, what)

    beat = getattr(progress, "beat", None)
    if beat is not None:
        call.beat = beat            # type: ignore[attr-defined]
    return call
