"""Where a diagnosis's time goes: evaluations of the forward model and seconds, per stage of the search.

A diagnosis is a search over forward-model evaluations, and the evaluations are what costs: one of
the full forward model (the plate with the baseline's boundary tables, inside sector tables and the
Stokes loop, `forward.DiagnosisForward`) is a plate solve at least, and a new boundary table when an
effect changes the relief's geometry (a relief scale, a smoothing) or the incidence (a tilt); one of
the screening forward model (`DiagnosisForward.screening`: no inside sector tables, the
intensity-only loop) costs a fraction of that.  The profile counts both, per stage:

- ``baseline``: the baseline and its model sigma (the tables' Monte-Carlo draws);
- ``screens``: the linear screens of a step (two probes each, on the screening model); its seconds
  are the whole round's, which also runs the fits of candidates without parameters on the workers;
- ``candidate_fits``: a candidate's conditional fit (grid, Brent or Gauss-Newton, on the full model);
- ``null_restarts``: a fit that ended at its null value refitted from spread starts (`fitting._restart`);
- ``joint_refit``: the joint Gauss-Newton polish (and coordinate refit) of the named set;
- ``pair_starts``: the joint refit of a trading pair from the other start (`stepwise._pair_starts`);
- ``redundancy``: the drop test of a named effect (`stepwise._drop_redundant`);
- ``intervals``: the 68 % intervals (their Jacobian when the last polish left none, and the model
  draws at the optimum);
- ``method_check``: the baseline by another boundary method (interreflection, diffraction);
- ``search``: the rest of the search (the worker pool's start, the residual's signatures);
- ``report``: the baseline's residual located and, after the search, everything but the intervals
  (the residual's shapes, the report's words).

Seconds are wall-clock seconds of this process, exclusive (a stage nested in another, a null
restart inside a candidate's fit, is charged to itself only); evaluations that ran on worker
processes are counted in the stage of the task that asked for them.  The counts are exact, the
seconds depend on the machine's load.  diagnosis.json carries the profile as ``profile``.
"""
from __future__ import annotations

import contextlib
import contextvars
import time
from dataclasses import dataclass, field
from typing import Iterator

STAGES = ("baseline", "screens", "candidate_fits", "null_restarts", "joint_refit", "pair_starts", "redundancy",
          "intervals", "method_check", "search", "report")
KINDS = ("full", "screening")

_CURRENT: contextvars.ContextVar["Profile | None"] = contextvars.ContextVar("diagnosis_profile", default=None)


@dataclass
class Profile:
    """Evaluations (full / screening forward model) and exclusive wall seconds per stage."""

    stages: dict = field(default_factory=dict)
    _stack: list = field(default_factory=list, repr=False)     # [[stage, start time]] of the open stages

    def _entry(self, name: str) -> dict:
        return self.stages.setdefault(name, {"full": 0, "screening": 0, "seconds": 0.0})

    def current(self) -> str:
        return self._stack[-1][0] if self._stack else "other"

    def count(self, kind: str, k: int = 1, stage: str | None = None) -> None:
        self._entry(stage or self.current())[kind] += int(k)

    def merge(self, counts: dict) -> None:
        """Add evaluations counted elsewhere (a worker's task, `captured`): {stage: {full, screening}}."""
        for name, c in counts.items():
            e = self._entry(name)
            for kind in KINDS:
                e[kind] += int(c.get(kind, 0))

    def counts(self) -> dict:
        return {k: {kind: v[kind] for kind in KINDS} for k, v in self.stages.items() if v["full"] or v["screening"]}

    def enter(self, name: str) -> None:
        now = time.perf_counter()
        if self._stack:
            top = self._stack[-1]
            self._entry(top[0])["seconds"] += now - top[1]
        self._entry(name)
        self._stack.append([name, now])

    def leave(self) -> None:
        now = time.perf_counter()
        name, start = self._stack.pop()
        self._entry(name)["seconds"] += now - start
        if self._stack:
            self._stack[-1][1] = now

    def doc(self) -> dict:
        """diagnosis.json's `profile`: one entry per stage (the named stages in order, then any other)."""
        order = [s for s in STAGES if s in self.stages] + sorted(s for s in self.stages if s not in STAGES)
        rows = [{"stage": s, "full_evaluations": self.stages[s]["full"],
                 "screening_evaluations": self.stages[s]["screening"],
                 "seconds": round(self.stages[s]["seconds"], 3)} for s in order]
        return {"stages": rows,
                "full_evaluations": sum(r["full_evaluations"] for r in rows),
                "screening_evaluations": sum(r["screening_evaluations"] for r in rows),
                "seconds": round(sum(r["seconds"] for r in rows), 3),
                "note": ("evaluations of the full forward model (the baseline's tables, sectors and Stokes loop) and "
                         "of the screening one (no inside sector tables, intensity-only loop) per stage of the search; "
                         "seconds are this process's wall clock, each stage's own (nested stages apart); the screens' "
                         "seconds are their whole round, with the fits of candidates without parameters beside them")}


@contextlib.contextmanager
def profiling() -> Iterator[Profile]:
    """Count the evaluations and time the stages of everything inside the block (one diagnosis)."""
    p = Profile()
    token = _CURRENT.set(p)
    try:
        yield p
    finally:
        _CURRENT.reset(token)


@contextlib.contextmanager
def stage(name: str) -> Iterator[None]:
    """Charge the evaluations and seconds inside the block to `name` (nothing without a profile)."""
    p = _CURRENT.get()
    if p is None:
        yield
        return
    p.enter(name)
    try:
        yield
    finally:
        p.leave()


def captured() -> contextlib.AbstractContextManager[Profile]:
    """A fresh profile for one task (on a worker process or here), as `profiling`: its counts travel back
    with the task's result and are merged where the task was asked for (`Profile.merge`), so none is
    counted twice."""
    return profiling()


def merge(counts: dict | None) -> None:
    p = _CURRENT.get()
    if p is not None and counts:
        p.merge(counts)


def kind_of(grid) -> str:
    """"screening" for the screening forward model's grid (`DiagnosisForward.screening`: no inside sector
    tables where the baseline has them, or the intensity-only loop), else "full"."""
    from relief_bsdf.plate.grid import NO_SECTORS_DEG
    if grid is None:
        return "full"
    return "screening" if (not grid.stokes_loop or grid.sector_step_deg == NO_SECTORS_DEG) else "full"


def note_evaluations(grid, k: int = 1) -> None:
    """`k` evaluations of the forward model on `grid` in the current stage (nothing without a profile)."""
    p = _CURRENT.get()
    if p is not None and k:
        p.count(kind_of(grid), k)
