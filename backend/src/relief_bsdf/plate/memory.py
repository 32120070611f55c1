"""The one owner of what the forward model keeps between evaluations: `ForwardMemory`.

Everything the plate engine would otherwise derive again (boundary tables, plate solvers with their
factorised operators, relief tracers, photon samplers, slab operators, detector weights, phase
functions) lives in ONE object, keyed by content, held to ONE byte budget:

- `get(key, make, kind)`: the held value, else `make()` put under `key`; before a value is put, and
  whenever the held bytes exceed the budget, entries go by GreedyDual-Size (Cao & Irani 1997): each
  entry's priority is the clock at its last use plus the seconds it took to make per GB it holds, the
  lowest goes first and the clock moves up to it, so what was used long ago goes first unless it is
  dear to make for its size (a ray-traced sector table stays over a detector's weights made in a
  blink); only an entry that frees a buffer goes (a table a held solver reads stays); a single object
  larger than the budget is still computed, used and dropped at the next put: the job degrades to
  recomputing instead of growing;
- `reserve(nbytes)`: evict so that what a computation is about to allocate beside the held entries
  fits too (a solver's round-trip system and factors, its sector kernels), before it is allocated;
- bytes are the numpy buffers the entries reach (attributes, dicts, lists, tuples; `memory_parts()`
  where an object names what it holds, `memory_bytes()` where it knows better, e.g. a tracer's BVH),
  each buffer counted ONCE over all entries (two solvers sharing their tables' part, a solver and the
  tables it reads); the buffers of evicted values still alive (a solver an evaluation is still using)
  are reported apart; a solver is measured again at every eviction;
- `report()`: budget, held (and evicted but alive) and peak bytes, per kind, hits, misses, evictions
  (the benchmarks and the diagnosis's JSON print it).

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
import weakref
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


def deep_buffers(value: Any, out: dict | None = None, seen: set | None = None, depth: int = 0) -> dict:
    """{buffer id: bytes} of the numpy buffers `value` reaches (attributes, dict values, list / tuple items,
    to depth 12; an object's `memory_parts()` instead of its attributes where it names what it holds; its
    `memory_bytes()` as one buffer of its own where it knows better, e.g. a tracer's BVH)."""
    out = {} if out is None else out
    seen = set() if seen is None else seen
    if depth > 12 or value is None or isinstance(value, (str, bytes, int, float, bool, complex)):
        return out
    if isinstance(value, np.ndarray):
        base = value
        while isinstance(base.base, np.ndarray):
            base = base.base
        out[id(base)] = int(base.nbytes)
        return out
    if id(value) in seen:
        return out
    seen.add(id(value))
    parts = getattr(value, "memory_parts", None)
    if callable(parts) and not isinstance(value, type):
        return deep_buffers(parts(), out, seen, depth + 1)
    own = getattr(value, "memory_bytes", None)
    if callable(own) and not isinstance(value, type):
        out[id(value)] = int(own())
        return out
    # snapshots (one C call each, atomic under the GIL): another thread may add to a held solver's dicts
    if isinstance(value, dict):
        items = list(value.values())
    elif isinstance(value, (list, tuple, set, frozenset)):
        items = list(value)
    else:
        d = getattr(value, "__dict__", None)
        slots = getattr(type(value), "__slots__", ())
        items = (list(d.values()) if isinstance(d, dict)
                 else [getattr(value, s, None) for s in slots if isinstance(s, str)])
    for v in items:
        deep_buffers(v, out, seen, depth + 1)
    return out


def deep_nbytes(value: Any, seen: set | None = None, depth: int = 0) -> int:
    """Bytes of the numpy buffers `value` reaches (`deep_buffers`), each buffer once (`seen`: ids already
    counted elsewhere, updated)."""
    seen = set() if seen is None else seen
    bufs = deep_buffers(value, None, seen, depth)
    total = sum(n for b, n in bufs.items() if b not in seen)
    seen.update(bufs)
    return total


@dataclass
class _Entry:
    kind: str
    value: Any
    buffers: dict                # {buffer id: bytes} it reaches (`deep_buffers`), measured at put / refresh
    cost_s: float = 0.0          # seconds it took to make (what evicting it costs the job)
    priority: float = 0.0        # GreedyDual-Size: clock at last use + cost per GB held

    @property
    def nbytes(self) -> int:
        return sum(self.buffers.values())


MUTABLE_KINDS = ("solver",)      # values that grow or shrink while held: measured again at every eviction


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
        self._ghost_bytes = 0
        self._ghosts: list = []          # (weak reference, buffers) of evicted values still alive (`_evict`)
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
        """Hold `value` under `key` (newest).  Before it is added, the other entries are evicted until the
        held bytes with it fit the budget (`_evict`); `cost_s`: the seconds it took to make (None: what the
        value says, e.g. a table's `timing_s`, else 0)."""
        with self._lock:
            old = self._d.pop(key, None)
            e = _Entry(kind if kind in KINDS else "other", value, deep_buffers(value),
                       _cost_of(value) if cost_s is None else float(cost_s))
            if old is not None:
                self._retire(old)
            self._evict(incoming=e.buffers)
            self._d[key] = e
            self._use(key, e)
            self._evict()

    def reserve(self, nbytes: float) -> None:
        """Evict until the held bytes and `nbytes` more fit the budget: what a computation is about to
        allocate beside what is held (a solver's round-trip system and its factors, `PlateSolver._operators`;
        its sector kernels), so that the owner gives the room back before the allocation, not after it.
        The newest entry stays (it is usually what is being computed from)."""
        with self._lock:
            self._evict(extra=float(nbytes))

    def refresh(self, key: tuple | None, cost_s: float = 0.0) -> None:
        """Measure an entry again (a solver's operators are made while it solves), add `cost_s` to what it
        cost, and evict to the budget (None: evict only, e.g. after the budget changed)."""
        with self._lock:
            e = self._d.get(key) if key is not None else None
            if e is None:
                self._evict()
                return
            e.buffers = deep_buffers(e.value)
            e.cost_s += float(cost_s)
            self._use(key, e)
            self._evict()

    def discard(self, key: tuple) -> None:
        with self._lock:
            e = self._d.pop(key, None)
            if e is not None:
                self._retire(e)
                self._evict()

    def _retire(self, e: _Entry) -> None:
        """An entry leaves the store: while something else still holds its value (a solver in use, a table
        a held solver reads), its buffers still count (`_evict`'s ghosts) until the value is freed."""
        try:
            self._ghosts.append((weakref.ref(e.value), e.buffers))
        except TypeError:                # no weak reference to it (a plain ndarray subclass, a tuple ...)
            pass

    def _union(self) -> tuple[dict, dict]:
        """({buffer id: [entries reaching it, bytes]} over the held entries and the live ghosts, the live
        ghosts' buffers), the mutable entries measured again (`MUTABLE_KINDS`)."""
        refs: dict = {}
        for k, e in self._d.items():
            if e.kind in MUTABLE_KINDS:
                e.buffers = deep_buffers(e.value)
            for b, n in e.buffers.items():
                r = refs.get(b)
                if r is None:
                    refs[b] = [1, n]
                else:
                    r[0] += 1
        self._ghosts = [(ref, bufs) for ref, bufs in self._ghosts if ref() is not None]
        ghost: dict = {}
        for _, bufs in self._ghosts:
            ghost.update(bufs)
        return refs, ghost

    def _evict(self, incoming: dict | None = None, extra: float = 0.0) -> None:
        """GreedyDual-Size down to the budget and the entry count (module doc); never the newest entry.
        The held bytes are those of the UNION of the buffers the entries reach (a buffer two solvers share,
        their tables' part, counts once), plus `incoming` (an entry about to be put) and `extra` bytes
        (`reserve`).  The buffers of evicted values still alive (a solver an evaluation still uses) are
        reported (`evicted_alive_bytes`), not evicted for: evicting more cannot free them, and the
        plan counts them among what an evaluation allocates beside the owner (`TRANSIENT_SHARE`)."""
        refs, ghost = self._union()
        held = {b: r[1] for b, r in refs.items()}
        pending = {b: n for b, n in (incoming or {}).items() if b not in held}

        def total() -> int:
            return sum(held.values()) + sum(n for b, n in pending.items() if b not in held)
        self._total = sum(held.values())
        self.peak_bytes = max(self.peak_bytes, self._total)
        keep = 0 if incoming is not None else 1          # before a put: every held entry may go
        t = total()
        while len(self._d) > keep and (len(self._d) + (incoming is not None) > self.maxsize
                                       or t + extra > self.budget_bytes):
            newest = next(reversed(self._d)) if keep else None
            # only an entry that frees something (a buffer no other entry reaches) is worth evicting: a table a
            # held solver reads stays (evicting it would free nothing and lose its key); over the entry count,
            # any entry
            over_count = len(self._d) + (incoming is not None) > self.maxsize
            frees = [k for k in self._d if k != newest
                     and (over_count or any(refs[b][0] == 1 for b in self._d[k].buffers if b in refs))]
            if not frees:
                break
            key = min(frees, key=lambda k: self._d[k].priority)   # ties: least recent
            e = self._d.pop(key)
            self._clock = max(self._clock, e.priority)
            for b in e.buffers:
                r = refs.get(b)
                if r is not None:
                    r[0] -= 1
                    if r[0] == 0:
                        del refs[b], held[b]
            self._retire(e)
            del e                        # the store's last reference: a value nothing else holds is freed now
            self.evictions += 1
            t = total()
        ghost = {}
        for ref, bufs in self._ghosts:
            if ref() is not None:
                ghost.update(bufs)
        self._ghost_bytes = sum(n for b, n in ghost.items() if b not in held)
        self._total = sum(held.values())

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
            self._ghosts.clear()
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
        """{"budget_bytes", "held_bytes" (the union of the entries' buffers), "evicted_alive_bytes" (those of
        evicted values still alive, beyond the held ones), "peak_held_bytes", "hits", "misses", "evictions", "by_kind": {kind:
        {"entries", "bytes"}}} (an entry's bytes: every buffer it reaches, shared ones in each)."""
        with self._lock:
            by: dict = {}
            for e in self._d.values():
                k = by.setdefault(e.kind, {"entries": 0, "bytes": 0})
                k["entries"] += 1
                k["bytes"] += e.nbytes
            return {"budget_bytes": int(self.budget_bytes), "held_bytes": int(self._total),
                    "evicted_alive_bytes": int(self._ghost_bytes),
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
TRANSIENT_SHARE = 1.0        # what one evaluation allocates OUTSIDE the owner while it builds (sources, Krylov
#                              vectors, rows, the ray engine's buffers), per byte one evaluation holds: the owner
#                              itself counts a solve's systems, factors and sector kernels before they are made
#                              (`reserve`); this counts what it evicted while still in use.  Measured on validation
#                              case 05 (one process, budget 1.5 GB, baseline then relief scale, stray light,
#                              absorption): peak RSS 2.24 GB = 0.3 base + 1.34 owner peak + 0.60 outside it, with
#                              one evaluation holding 0.67 GB: 0.9 (decision record 020)
POOL_SHARE = 1.5             # what each process of a pool (this one and every worker) holds beyond that, per byte one
#                              evaluation holds: the forward model with its baseline tables pickled for each worker and
#                              unpickled there, and each process's own screening solver.  Measured on validation case 09
#                              (Gaussian, ray; one evaluation 0.31 GB; 2 workers at 3.5 GB, budgets 0.555 GB each,
#                              planned
#                              1.17 GB per process): main 1.56 GB, workers 1.20 and 1.63 GB, 4.22 GB in all; the same
#                              diagnosis in one process 2.61 GB.  1.4 (main) and 1.6 (worker) evaluations beyond the
#                              one-process model


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
    `total_bytes` together.  Model of one process: PROCESS_BASE_BYTES + its budget (everything the owner
    counts: its entries and what a solve reserves before allocating it) +
    TRANSIENT_SHARE x `evaluation_bytes` (what one evaluation allocates outside the owner, per byte one
    evaluation of the forward model holds once made: its tables and solver, the owner's held bytes after
    the baseline), with a budget of at least one evaluation.  A pool of
    w >= 2 workers runs w + 1 processes (this one evaluates beside them, `diagnose.stepwise`), each holding
    POOL_SHARE x `evaluation_bytes` more (the forward model sent to the workers).  Where not
    even one process fits, this process alone with one evaluation's budget (`fits` False: the job
    will exceed the total; the caller says so)."""
    per = float(evaluation_bytes)
    for w in range(int(max_workers), 1, -1):
        budget = total_bytes / (w + 1) - PROCESS_BASE_BYTES - (TRANSIENT_SHARE + POOL_SHARE) * per
        if budget >= per:
            return MemoryPlan(total_bytes, per, w, budget, budget, True)
    budget = total_bytes - PROCESS_BASE_BYTES - TRANSIENT_SHARE * per
    return MemoryPlan(total_bytes, per, 1, max(budget, per), 0.0, budget >= per)
