"""Suite-wide hooks: the `shared_data` marker.

A test that reads `../shared` beside the checkout (the file contract `formats.md`, the measured
BSDF files, the validation set: data without a licence to redistribute, kept outside the
repository) carries `@pytest.mark.shared_data`.  Where `../shared` is absent (a clone on its own)
those tests are deselected and the run ends with one line naming them; where it is present (CI,
the development machines) they run like every other test.  The instrument files the readers are
tested on live in the repository (tests/data/topography, SOURCE.md).
"""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
_LEFT_OUT = pytest.StashKey[list]()


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
