"""Optional compiled kernels of the ray method's hottest numpy steps, with their numpy twins as fallback.

What is compiled (`_compiled.pyx`, Cython: C loops over the rays with the GIL released, so the engine's
two threads overlap) and why: after the Embree queries, the ray engine's CPU time on polarised tables
goes to passes that numpy cannot fuse - the table builder's 16 weighted bincounts per chunk (one per
Mueller entry), the facets' Fresnel coefficients and frame rotations (a few dozen float32 temporaries
per bounce), the exit records and their Mueller columns, the slab distances of each query.  The
kernels: `bin_cells` / `add_at` (bsdf.builder; a cell's 16 Mueller sums four at a time in SSE2, exits
held compactly expanded in registers), `direction_parts` / `cells_of_angles` (the cell index around
numpy's arccos and arctan2), `near_direction` / `near_two_directions` (the specular prefilter),
`slab_far` / `slab_distances`, `subtile_index` (methods.ray.tracer), `facet_geometry`, `facet_event`
(with `facet_split_loop`: a first interaction's two branches' factors in the same pass), `split_rays`
(the first hits' sub-tiles tagged in the same pass), `split_weights`, `classify_misses`,
`exit_columns` (methods.ray.transport: a one-interaction path's exit held compactly, its 6 factors and
exit rotation), `expand_compact`, `gather_records` (methods.ray.exits), `beam_origins`
(methods.ray.method), `cells_of_edges` (methods.ray.cells: the cell of graded edges, searched).  Each does
the same
float32 / float64 operations in the same order as its numpy twin (`twins`, the same name and arguments:
the reference, and what runs without the compiled module), so the tables are bit for bit the same
(tests/backend/kernels: each kernel against its twin, and whole tables traced with either);
`cells_of_directions` and `cells_of_edges` (the cell index) alone compute otherwise: they settle the cells of
the directions farther than 2e-5 rad from every cell edge from their own float32 angles, and their twins use
numpy's arccos and arctan2 throughout: the same cells (decision records 014, 023); the C is built without fused
multiply-adds (-ffp-contract=off) and with flags that change no value (backend/setup.py).  Memory access decides
their speed as much as arithmetic: arrays they read or write row by row are padded
(`methods.ray.exits.padded_rows`: power-of-two chunk lengths otherwise put the rows in one cache set)
and the division-heavy facet loop is written to vectorise.

Dispatch: one rule, in one place.  `REGISTRY` maps each kernel's name to its compiled function and its
numpy twin; the one in use is bound to this module's attribute of that name, so callers call
`kernels.NAME(...)` and never choose.  The compiled kernels run when they were built (`backend/setup.py`:
an optional extension, built by `pip install -e backend`; a pure-Python install, e.g. the Blender
extension's wheel with RELIEF_PURE_PYTHON=1, has none) unless the environment variable
RELIEF_RAY_KERNEL=numpy (read at import) asks for the twins; `select(name)` switches (tests).  `name()` is
what runs: "cython" or "numpy" (ray table metadata, bench_ray.py).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

from relief_bsdf.kernels import twins

try:
    from relief_bsdf.kernels import _compiled
except ImportError:                      # not built (no compiler, pure-Python wheel): the numpy twins
    _compiled = None

ENV = "RELIEF_RAY_KERNEL"
NAMES = ("bin_cells", "add_at", "direction_parts", "cells_of_angles", "cells_of_directions", "cells_of_edges",
         "near_direction", "near_two_directions", "exit_columns", "expand_compact", "facet_event", "facet_geometry",
         "slab_distances", "slab_far", "classify_misses", "beam_origins", "subtile_index", "gather_records",
         "gather_rays", "split_rays", "split_weights")


@dataclass(frozen=True)
class Kernel:
    """One kernel: its compiled function (None when not built) and its numpy twin (the reference)."""

    name: str
    compiled: Callable | None
    twin: Callable


REGISTRY = {n: Kernel(n, None if _compiled is None else getattr(_compiled, n), getattr(twins, n)) for n in NAMES}
_name = "numpy"


def available() -> bool:
    """True when the compiled kernels were built and import."""
    return _compiled is not None


def name() -> str:
    """"cython" when the compiled kernels run, else "numpy"."""
    return _name


def select(kernel: str) -> str:
    """Use "cython" (RuntimeError when not built) or "numpy" (the twins) from now on, for every kernel; the
    previous name."""
    global _name
    if kernel not in ("cython", "numpy"):
        raise ValueError(f"unknown kernel {kernel!r} (cython or numpy)")
    if kernel == "cython" and _compiled is None:
        raise RuntimeError("the compiled ray kernels are not built (pip install -e backend with a C compiler)")
    prev, _name = _name, kernel
    for k in REGISTRY.values():
        globals()[k.name] = k.compiled if kernel == "cython" else k.twin
    return prev


select("numpy" if _compiled is None or os.environ.get(ENV, "").strip().lower() == "numpy" else "cython")
