"""Suite-wide hooks: the `shared_data` marker, and the cores shared out between test processes.

A test that reads `../shared` beside the checkout (the file contract `formats.md`, the measured
BSDF files, the validation set: data without a licence to redistribute, kept outside the
repository) carries `@pytest.mark.shared_data`.  Where `../shared` is absent (a clone on its own)
those tests are deselected and the run ends with one line naming them; where it is present (CI,
the development machines) they run like every other test.  The instrument files the readers are
tested on live in the repository (tests/data/topography, SOURCE.md).

The cores are shared out, not oversubscribed: under pytest-xdist (`make test`, `make test-fast`:
`-n 2`) every test process already holds one core, so each gets RELIEF_WORKERS = cores / test
processes (1 on two cores) unless the environment sets it: a `map_tasks` call with the default
settings then runs its tasks in the test's own process (the serial backend, the same numbers by the
per-task seeds, `parallel.tasks`) instead of starting a pool of worker processes that compete with
the other test process for the same cores.  The tests of the pool itself name their backend and
worker count (tests/backend/parallel, the diagnosis's kept workers), so every path is still run.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
_LEFT_OUT = pytest.StashKey[list]()


def _share_the_cores() -> None:
    """RELIEF_WORKERS = cores / xdist processes (at least 1) for a test process under xdist, unless set."""
    n = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if n and "RELIEF_WORKERS" not in os.environ:
        os.environ["RELIEF_WORKERS"] = str(max(1, (os.cpu_count() or 1) // max(1, int(n))))


_share_the_cores()        # at import: before any test starts a worker pool or the fork server


def pytest_collection_modifyitems(config, items):
    if SHARED.is_dir():
        return
    left = [it for it in items if it.get_closest_marker("shared_data") is not None]
    if left:
        items[:] = [it for it in items if it.get_closest_marker("shared_data") is None]
        config.hook.pytest_deselected(items=left)
        config.stash[_LEFT_OUT] = [it.nodeid for it in left]


def pytest_sessionfinish(session):
    """Under pytest-xdist each worker collects and deselects; it hands its list to the controller."""
    out = getattr(session.config, "workeroutput", None)
    if out is not None:
        out["shared_data_left_out"] = session.config.stash.get(_LEFT_OUT, [])


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    left = getattr(node, "workeroutput", {}).get("shared_data_left_out", [])
    if left:
        node.config.stash[_LEFT_OUT] = sorted(set(node.config.stash.get(_LEFT_OUT, [])) | set(left))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    left = config.stash.get(_LEFT_OUT, [])
    if left:
        terminalreporter.write_line(f"shared_data: {len(left)} tests left out because {SHARED} is absent: "
                                    + ", ".join(left))
