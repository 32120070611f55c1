"""Memory pages of the processes that compute: this one and its pool workers.

numpy (>= 1.20) advises the kernel to back every array of 4 MB or more with transparent huge pages
(madvise MADV_HUGEPAGE).  Where the kernel's THP defrag policy is "madvise" (the default of many
Linux distributions, and of the 2-core machines this project is measured on), the first touch of
such an array compacts memory synchronously to find 2-MB pages and clears them.  The plate engine
allocates and frees large temporaries by the hundred per evaluation (tables interpolated to the
engine's incidences, Mueller kernels, the cone reading's gathers), so every evaluation pays it
again.  Measured on a diagnosis baseline (the relief's tables, one plate solve, the eight table
draws of the model sigma; `perf record`, docs/decisions/008): 32 % of the CPU time was the
kernel clearing huge pages (clear_page_erms under folio_zero_user), 11.0 s of system time in 25.2 s
of CPU, 17.4 s wall; without the advice 3.5 s of system time, 11.3 s wall.  The values are the same
bit for bit: the size of a page changes no number.  Where huge pages are cheap (defrag "defer" or
"never") the advice buys a few per cent of TLB misses at most for these array sizes.
"""
from __future__ import annotations

import functools
import os

HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"     # numpy's own switch, read at its import; a user's setting wins


def small_pages() -> bool:
    """Turn numpy's huge-page advice off in this process (module doc), unless the user set
    NUMPY_MADVISE_HUGEPAGE; returns whether it was on.  Idempotent, cheap; call before heavy work."""
    if HUGEPAGE_ENV in os.environ:
        return False
    try:
        from numpy.core.multiarray import _set_madvise_hugepage
    except ImportError:             # a numpy without the switch: nothing to turn off
        return False
    os.environ[HUGEPAGE_ENV] = "0"  # processes started from here (the fork server, a CLI child) inherit it
    return bool(_set_madvise_hugepage(False))


def trim_heap(collect: bool = True) -> bool:
    """Collect garbage (`collect`) and hand the heap's free memory back to the system (glibc `malloc_trim`:
    the free pages of every arena, not only the heaps' tops); returns whether the allocator was asked.
    glibc keeps freed blocks for reuse (the ray engine asks it to keep more, `keep_freed_heap`: one arena
    per tracing thread), so a process that freed its tables or a solve's temporaries (a memory owner
    evicted down to a smaller budget, a job's stage done, one evaluation of the forward model done)
    still holds their pages: they count in the job's peak while the next stage, evaluation or pool
    worker allocates its own.  Without garbage to collect it costs about a millisecond plus the pages
    it returns.  The values computed afterwards are unchanged."""
    import gc
    if collect:
        gc.collect()
    trim = _malloc_trim()
    if trim is None:                        # not glibc: the memory stays with the process, nothing else changes
        return False
    trim(0)
    return True


@functools.cache
def _malloc_trim():
    """glibc's `malloc_trim`, looked up once per process (trim_heap runs after every plate evaluation),
    or None where the C library has none."""
    import ctypes
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
