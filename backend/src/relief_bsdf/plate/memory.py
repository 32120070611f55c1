"""The one owner of what the forward model keeps between evaluations: `ForwardMemory`.

Everything the plate engine would otherwise derive again (boundary tables, plate solvers with their
factorised operators, relief tracers, photon samplers, slab operators, detector weights, phase
functions) lives in ONE object, keyed by content, held to ONE byte budget:

- `get(key, make, kind)`: the held value, else `make()` put under `key`; while the held bytes exceed
  the budget, entries go by GreedyDual-Size (Cao & Irani 1997): each entry's priority is the
  clock at its last use plus the seconds it took to make per GB it holds, the lowest goes first and
  the clock moves up to it, so what was used long ago goes first unless it is dear to make for its
  size (a ray-traced sector table stays over a detector's weights made in a blink); the newest entry
  always stays, so a single object larger than the budget is still computed, used and dropped at the
  next put: the job degrades to recomputing instead of growing;
- bytes are the arrays an entry reaches (numpy arrays in its attributes, dicts, lists, tuples;
  each array's buffer counted once per entry; `memory_bytes()` where an object knows better, e.g.
  a tracer's BVH); a solver that grows while it solves is measured again (`refresh`);
- `report()`: budget, held and peak bytes per kind, hits, misses, evictions (the benchmarks and
  the diagnosis's JSON print it).

Which owner is in force: the job makes one and activates it for its block (`with memory.active():`,
a context variable: scoped to the block and its thread); code below asks `current_memory()`.
Outside any job, the process's own owner (`parallel.worker.process_object`, the one place that
keeps per-process state: a pool worker's owner must outlive a task), with the budget the job gave
its workers (`parallel.worker.worker_memory_bytes`) or `DEFAULT_BUDGET_BYTES`.

The values are pure functions of their keys: evicting one changes no number, only the time.
"""
from __future__ import annotations

import contextlib
import contextvars
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.parallel import current_settings
from relief_bsdf.parallel.worker import process_object, worker_memory_bytes

KINDS = ("table", "solver", "tracer", "sampler", "slab", "detector", "phase", "other")
DEFAULT_BUDGET_BYTES = 1.5e9     # one process's held bytes when no job says otherwise (RELIEF_MEMORY_GB: the job's)
MEMORY_ENV = "RELIEF_MEMORY_GB"  # a job's total memory (every process together), GB


class MissingTable(BaseException):
    """A value this process does not hold was asked for inside `ForwardMemory.held_only` (a BaseException:
    no `except Exception` on the way may take it for a failed derivation and fall back to other physics)."""


_HELD_ONLY: contextvars.ContextVar = contextvars.ContextVar("relief_held_only", default=False)
_ACTIVE: contextvars.ContextVar = contextvars.ContextVar("relief_forward_memory", default=None)


def deep_nbytes(value: Any, seen: set | None = None, depth: int = 0) -> int:
    """Bytes of the numpy buffers `value` reaches (attributes, dict values, list / tuple items, to depth 8),
    each buffer once; an object's own `memory_bytes()` where it has one."""
    seen = set() if seen is None else seen
    if depth > 8 or value is None or isinstance(value, (str, bytes, int, float, bool, complex)):
        return 0
    if isinstance(value, np.ndarray):
        base = value
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) in seen:
            return 0
        seen.add(id(base))
        return int(base.nbytes)
    if id(value) in seen:
        return 0
    seen.add(id(value))
    own = getattr(value, "memory_bytes", None)
    if callable(own) and not isinstance(value, type):
        return int(own())
    if isinstance(value, dict):
        return sum(deep_nbytes(v, seen, depth + 1) for v in value.values())
    if isinstance(value, (list, tuple, set, frozenset)):
        return sum(deep_nbytes(v, seen, depth + 1) for v in value)
    d = getattr(value, "__dict__", None)
    if isinstance(d, dict):
        return sum(deep_nbytes(v, seen, depth + 1) for v in d.values())
    slots = getattr(type(value), "__slots__", ())
    return sum(deep_nbytes(getattr(value, s, None), seen, depth + 1) for s in slots if isinstance(s, str))


@dataclass
class _Entry:
    kind: str
    value: Any
    nbytes: int
    cost_s: float = 0.0          # seconds it took to make (what evicting it costs the job)
    priority: float = 0.0        # GreedyDual-Size: clock at last use + cost per GB held


def _cost_of(value: Any) -> float:
    """What a value handed in from elsewhere cost to make, where it says (a table's metadata `timing_s`)."""
    meta = getattr(value, "metadata", None)
    t = meta.get("timing_s") if isinstance(meta, dict) else None
    if isinstance(t, dict):                   # a ray table's phases and their "total"
        t = t.get("total", sum(v for v in t.values() if isinstance(v, (int, float))))
    return float(t) if isinstance(t, (int, float)) and t > 0 else 0.0


class ForwardMemory:
    """A byte-budgeted store of the forward model's derived objects, GreedyDual-Size eviction (module doc)."""

    def __init__(self, budget_bytes: float = DEFAULT_BUDGET_BYTES, maxsize: int = 400):
        self.budget_bytes = float(budget_bytes)
        self.maxsize = int(maxsize)
        self._d: "OrderedDict[tuple, _Entry]" = OrderedDict()
        self._total = 0
        self._recorders: list[set] = []
        self.hits = self.misses = self.evictions = 0
        self.peak_bytes = 0
        self._clock = 0.0                # GreedyDual-Size's inflation value
        self._lock = threading.RLock()   # threads of one job share the owner (a value is made outside it)

    # -- the store
    def get(self, key: tuple, make: Callable[[], Any], kind: str = "table") -> Any:
        """The value held under `key`, else `make()` (put under `key`)."""
        with self._lock:
            if kind == "table":
                for used in self._recorders:
                    used.add(key)
            e = self._d.get(key)
            if e is not None:
                self._use(key, e)
                self.hits += 1
                return e.value
            if _HELD_ONLY.get():
                raise MissingTable(key)
            self.misses += 1
        t0 = time.perf_counter()
        v = make()
        self.put(key, v, kind, cost_s=time.perf_counter() - t0)
        return v

    def _use(self, key: tuple, e: _Entry) -> None:
        self._d.move_to_end(key)
        e.priority = self._clock + e.cost_s / max(e.nbytes / 1e9, 1e-3)

    def peek(self, key: tuple) -> Any:
        """The value held under `key` or None (no derivation, no recency change)."""
        with self._lock:
            e = self._d.get(key)
            return None if e is None else e.value

    def put(self, key: tuple, value: Any, kind: str = "table", cost_s: float | None = None) -> None:
        """Hold `value` under `key` (newest), then evict to the budget.  `cost_s`: the seconds it took to
        make (None: what the value says, e.g. a table's `timing_s`, else 0)."""
        with self._lock:
            old = self._d.pop(key, None)
            if old is not None:
                self._total -= old.nbytes
            e = _Entry(kind if kind in KINDS else "other", value, deep_nbytes(value),
                       _cost_of(value) if cost_s is None else float(cost_s))
            self._d[key] = e
            self._total += e.nbytes
            self._use(key, e)
            self._evict()

    def refresh(self, key: tuple | None, cost_s: float = 0.0) -> None:
        """Measure an entry again (a solver's operators are made while it solves), add `cost_s` to what it
        cost, and evict to the budget (None: evict only, e.g. after the budget changed)."""
        with self._lock:
            e = self._d.get(key) if key is not None else None
            if e is None:
                self._evict()
                return
            self._total -= e.nbytes
            e.nbytes = deep_nbytes(e.value)
            e.cost_s += float(cost_s)
            self._total += e.nbytes
            self._use(key, e)
            self._evict()

    def discard(self, key: tuple) -> None:
        with self._lock:
            e = self._d.pop(key, None)
            if e is not None:
                self._total -= e.nbytes

    def _evict(self) -> None:
        """GreedyDual-Size down to the budget and the entry count (module doc); never the newest entry."""
        self.peak_bytes = max(self.peak_bytes, self._total)
        while len(self._d) > 1 and (len(self._d) > self.maxsize or self._total > self.budget_bytes):
            newest = next(reversed(self._d))
            key = min((k for k in self._d if k != newest), key=lambda k: self._d[k].priority)   # ties: least recent
            e = self._d.pop(key)
            self._clock = max(self._clock, e.priority)
            self._total -= e.nbytes
            self.evictions += 1

    def entries(self, kind: str) -> list[tuple[tuple, Any]]:
        """(key, value) of the entries of `kind`, least recently used first."""
        with self._lock:
            return [(k, e.value) for k, e in self._d.items() if e.kind == kind]

    def values(self, kind: str) -> list:
        """The values of the entries of `kind`, least recently used first."""
        with self._lock:
            return [e.value for e in self._d.values() if e.kind == kind]

    def drop(self, kind: str) -> None:
        """Discard every entry of `kind`."""
        with self._lock:
            for k in [k for k, e in self._d.items() if e.kind == kind]:
                self.discard(k)

    def key_of(self, value: Any) -> tuple | None:
        """The key `value` (the object itself) is held under, or None."""
        with self._lock:
            for k, e in self._d.items():
                if e.value is value:
                    return k
            return None

    def cost_of(self, key: tuple) -> float:
        """The seconds the entry under `key` took to make (0 when not held)."""
        with self._lock:
            e = self._d.get(key)
            return 0.0 if e is None else e.cost_s

    def note_used(self, keys: Any) -> None:
        """Count `keys` as asked for (`recording` blocks see them; held ones are touched) without a `get`:
        a value made from them was found held (`plate.deterministic.held_for_request`)."""
        with self._lock:
            for k in keys:
                for used in self._recorders:
                    used.add(k)
                if k in self._d:
                    self._use(k, self._d[k])

    def touch(self, key: tuple) -> None:
        with self._lock:
            e = self._d.get(key)
            if e is not None:
                self._use(key, e)

    def clear(self) -> None:
        with self._lock:
            self._d.clear()
            self._total = 0

    def __contains__(self, key: tuple) -> bool:
        return key in self._d

    def __len__(self) -> int:
        return len(self._d)

    @property
    def held_bytes(self) -> int:
        return self._total

    # -- what a diagnosis asks of it
    @contextlib.contextmanager
    def held_only(self) -> Iterator[None]:
        """Inside the block (this thread's context only) a value that is not held is not derived: `get`
        raises MissingTable instead, so a caller can hand the work to a process that will derive it."""
        token = _HELD_ONLY.set(True)
        try:
            yield
        finally:
            _HELD_ONLY.reset(token)

    @contextlib.contextmanager
    def recording(self) -> Iterator[set]:
        """Collect the keys of every table asked for inside the block (a set, filled as they come)."""
        used: set = set()
        self._recorders.append(used)
        try:
            yield used
        finally:      # by identity: nested blocks may hold equal sets (list.remove compares by value)
            self._recorders[:] = [r for r in self._recorders if r is not used]

    def tables(self, keys: Any) -> dict:
        """{key: table} of those of `keys` still held whose value is a BsdfTable (data that can travel to a
        worker process).  One read per key: another thread may put or evict meanwhile."""
        with self._lock:
            out = {}
            for k in keys:
                e = self._d.get(k)
                if e is not None and isinstance(e.value, BsdfTable):
                    out[k] = e.value
            return out

    def worth_sending(self, tables: dict) -> bool:
        """Whether tables are small enough to be sent to this process and held: at most a sixth of the
        budget (a step's screens must not evict one another; larger ones are derived where needed)."""
        return sum(deep_nbytes(t) for t in tables.values()) <= self.budget_bytes / 6

    def holds(self, keys: Any) -> bool:
        """Whether every one of `keys` is held (False for None or no keys)."""
        with self._lock:
            return bool(keys) and all(k in self._d for k in keys)

    # -- reporting
    def report(self) -> dict:
        """{"budget_bytes", "held_bytes", "peak_held_bytes", "hits", "misses", "evictions",
        "by_kind": {kind: {"entries", "bytes"}}}."""
        with self._lock:
            by: dict = {}
            for e in self._d.values():
                k = by.setdefault(e.kind, {"entries": 0, "bytes": 0})
                k["entries"] += 1
                k["bytes"] += e.nbytes
            return {"budget_bytes": int(self.budget_bytes), "held_bytes": int(self._total),
                    "peak_held_bytes": int(self.peak_bytes), "hits": self.hits, "misses": self.misses,
                    "evictions": self.evictions, "by_kind": by}

    # -- scope
    @contextlib.contextmanager
    def active(self) -> Iterator["ForwardMemory"]:
        """Make this the owner `current_memory()` returns inside the block (this thread's context)."""
        token = _ACTIVE.set(self)
        try:
            yield self
        finally:
            _ACTIVE.reset(token)


def job_memory_bytes(memory_gb: float | None = None) -> float:
    """A job's total memory (every process together): `memory_gb`, else the settings in force
    (`--memory-gb`, `parallel.ParallelSettings.memory_gb`), else $RELIEF_MEMORY_GB, else 3.5 GB."""
    if memory_gb is None:
        memory_gb = current_settings().memory_gb
    if memory_gb is None:
        env = os.environ.get(MEMORY_ENV)
        memory_gb = float(env) if env else 3.5
    if not memory_gb > 0:
        raise ValueError(f"memory budget must be > 0 GB, got {memory_gb}")
    return float(memory_gb) * 1e9


def _process_memory() -> ForwardMemory:
    return process_object("forward-memory", lambda: ForwardMemory(worker_memory_bytes() or DEFAULT_BUDGET_BYTES))


def current_memory() -> ForwardMemory:
    """The owner in force: the job's (`ForwardMemory.active`), else this process's own (module doc)."""
    m = _ACTIVE.get()
    return m if m is not None else _process_memory()


PROCESS_BASE_BYTES = 0.3e9   # an interpreter with numpy, scipy and Embree loaded, before any table (PSS)
TRANSIENT_SHARE = 1.0        # what one evaluation allocates while it builds, beyond what it keeps, per kept byte
#                              (a diagnosis of an exponential relief with inside sector tables: 1.4 GB beside an
#                              evaluation of 1.6 GB, i.e. ~0.9; decision record 011)


@dataclass(frozen=True)
class MemoryPlan:
    """How a job spreads its memory: `workers` processes of the local pool (1: this process alone) and
    the byte budget of this process's owner and of each worker's (`plan_processes`)."""

    total_bytes: float
    evaluation_bytes: float
    workers: int
    main_budget_bytes: float
    worker_budget_bytes: float
    fits: bool

    def describe(self) -> dict:
        gb = 1e-9
        return {"total_gb": round(self.total_bytes * gb, 3), "evaluation_gb": round(self.evaluation_bytes * gb, 3),
                "workers": self.workers, "main_budget_gb": round(self.main_budget_bytes * gb, 3),
                "worker_budget_gb": round(self.worker_budget_bytes * gb, 3), "fits": self.fits}


def plan_processes(total_bytes: float, evaluation_bytes: float, max_workers: int) -> MemoryPlan:
    """The most pool workers (`max_workers` at most, else 1 = this process alone) whose processes fit
    `total_bytes` together.  Model of one process: PROCESS_BASE_BYTES + its budget + TRANSIENT_SHARE x
    `evaluation_bytes` (what one evaluation of the forward model holds once made: its tables and solver,
    the owner's held bytes after the baseline), with a budget of at least one evaluation.  A pool of
    w >= 2 workers runs w + 1 processes (this one evaluates beside them, `diagnose.stepwise`).  Where not
    even one process fits, this process alone with one evaluation's budget (`fits` False: the job
    will exceed the total; the caller says so)."""
    per = float(evaluation_bytes)
    for w in range(int(max_workers), 1, -1):
        budget = total_bytes / (w + 1) - PROCESS_BASE_BYTES - TRANSIENT_SHARE * per
        if budget >= per:
            return MemoryPlan(total_bytes, per, w, budget, budget, True)
    budget = total_bytes - PROCESS_BASE_BYTES - TRANSIENT_SHARE * per
    return MemoryPlan(total_bytes, per, 1, max(budget, per), 0.0, budget >= per)
