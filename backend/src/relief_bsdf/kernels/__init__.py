"""Optional compiled kernels of the ray method's hottest numpy steps, with the numpy code as fallback.

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
(methods.ray.method).  Each does the same
float32 / float64 operations in the same order as the numpy code it replaces (beside its caller,
which stays the reference and the fallback), so the tables are bit for bit the same
(tests/backend/methods/test_ray_kernels.py); the C is built without fused multiply-adds
(-ffp-contract=off) and with flags that change no value (backend/setup.py).  Memory access decides
their speed as much as arithmetic: arrays they read or write row by row are padded
(`methods.ray.exits.padded_rows`: power-of-two chunk lengths otherwise put the rows in one cache set)
and the division-heavy facet loop is written to vectorise.

Selection: `active()` is the compiled module, or None for numpy.  The compiled module is used when it
was built (`backend/setup.py`: an optional extension, built by `pip install -e backend`; a pure-Python
install, e.g. the Blender extension's wheel with RELIEF_PURE_PYTHON=1, has none); the environment
variable RELIEF_RAY_KERNEL=numpy (read at import) forces numpy; `select(name)` switches (tests).
`name()` is what runs: "cython" or "numpy" (ray table metadata, bench_ray.py).
"""
from __future__ import annotations

import os

try:
    from relief_bsdf.kernels import _compiled
except ImportError:                      # not built (no compiler, pure-Python wheel): numpy
    _compiled = None

ENV = "RELIEF_RAY_KERNEL"
_active = None if os.environ.get(ENV, "").strip().lower() == "numpy" else _compiled


def available() -> bool:
    """True when the compiled kernels were built and import."""
    return _compiled is not None


def active():
    """The compiled kernel module in use, or None: the callers' numpy code runs."""
    return _active


def built():
    """The compiled kernel module whether selected or not (None when not built): for data that only the
    compiled kernels write and only they can read back (`methods.ray.exits.Exits.compact`)."""
    return _compiled


def name() -> str:
    """"cython" when the compiled kernels run, else "numpy"."""
    return "numpy" if _active is None else "cython"


def select(kernel: str) -> str:
    """Use "cython" (RuntimeError when not built) or "numpy" from now on; the previous name."""
    global _active
    prev = name()
    if kernel == "numpy":
        _active = None
    elif kernel == "cython":
        if _compiled is None:
            raise RuntimeError("the compiled ray kernels are not built (pip install -e backend with a C compiler)")
        _active = _compiled
    else:
        raise ValueError(f"unknown kernel {kernel!r} (cython or numpy)")
    return prev
