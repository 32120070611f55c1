"""Backend work started from Blender: worker processes that never re-run the user's script.

Why.  The backend's local worker pool (`relief_bsdf.parallel`) starts its processes with
multiprocessing's "forkserver" (or "spawn") method.  Both hand each new worker the parent's
`__main__` (`multiprocessing.spawn.get_preparation_data`): its module name, or else its file,
which the worker then *executes* as `__mp_main__` before it takes a task.  Inside Blender
`__main__` is the user's script (`blender --background --python script.py`, a Text editor
script, a script run with the bpy module): the worker re-runs it, `import bpy` fails there
(Blender's bundled Python has no bpy outside Blender; the bpy module cannot load in a forked
child) and every worker dies before its first task.  The usual remedy, an
`if __name__ == "__main__":` guard, is something a Blender user cannot be expected to know.

What.  While the add-on runs backend work, `clean_main()` puts a bare stand-in module (no
file, no spec) in `sys.modules["__main__"]`.  The workers then start from the project's own
code only: the pool's entry point `relief_bsdf.parallel.worker.init_worker` and the task
functions, both imported by module name.  The user's script keeps running unchanged (its
frame holds its own globals; nothing looks it up through `sys.modules` while the operator
runs), and the real `__main__` is put back afterwards, also on error.

`backend_settings()` is the `ParallelSettings` the add-on's preferences ask for (worker
count; 0 = every core), put in force around the work with `running_backend()`.
"""
from __future__ import annotations

import contextlib
import sys
import threading
import types
from typing import Iterator

_SWAP_LOCK = threading.Lock()
_DEPTH = [0]
_SAVED: list = []


@contextlib.contextmanager
def clean_main() -> Iterator[None]:
    """`sys.modules["__main__"]` is a bare module for the duration of the block (see module doc).

    Re-entrant and thread-safe: nested or concurrent blocks share one stand-in, and the real
    module comes back when the last block ends.
    """
    with _SWAP_LOCK:
        if _DEPTH[0] == 0:
            _SAVED.append(sys.modules.get("__main__"))
            stand_in = types.ModuleType("__main__", "stand-in while relief_addon runs worker processes")
            stand_in.__spec__ = None
            sys.modules["__main__"] = stand_in
        _DEPTH[0] += 1
    try:
        yield
    finally:
        with _SWAP_LOCK:
            _DEPTH[0] -= 1
            if _DEPTH[0] == 0:
                real = _SAVED.pop()
                if real is not None:
                    sys.modules["__main__"] = real
                else:                                   # pragma: no cover - no __main__ before
                    sys.modules.pop("__main__", None)


def backend_settings(workers: int = 0):
    """The `ParallelSettings` for `workers` local worker processes (0 = as the backend decides:
    $RELIEF_WORKERS or every core)."""
    from relief_bsdf.parallel import current_settings
    return current_settings().updated(workers=int(workers) if workers and workers > 0 else None)


@contextlib.contextmanager
def running_backend(workers: int = 0) -> Iterator[None]:
    """Clean `__main__` and the preferences' worker count in force, for one piece of backend work."""
    from relief_bsdf.parallel import parallel_settings
    with clean_main(), parallel_settings(backend_settings(workers)):
        yield
