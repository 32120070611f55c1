"""Fixtures for the Blender tests (bpy module in this process; one fresh empty file per test)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))   # `relief_addon` importable as a package (as in scenes/render_plate.py)

import bpy  # noqa: E402  (after the path set-up; bmesh must come after bpy)


def pytest_collection_modifyitems(items):
    for it in items:
        if "tests/blender" in str(it.fspath).replace("\\", "/"):
            it.add_marker(pytest.mark.blender)


@pytest.fixture
def clean_bpy():
    """Factory settings, empty file; the add-on is not registered."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy


@pytest.fixture
def addon(clean_bpy):
    """The add-on registered for one test, unregistered afterwards."""
    import relief_addon
    relief_addon.register()
    try:
        yield relief_addon
    finally:
        relief_addon.unregister()
