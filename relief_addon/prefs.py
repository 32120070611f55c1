"""Add-on preferences (Edit > Preferences > Add-ons > Relief BSDF): worker count, cache folder.

- Workers: local worker processes for reconstruction, simulation and fits (0 = every core,
  or $RELIEF_WORKERS when set).  Workers start from the add-on's own code, never from the
  user's script (see `workers.py`), so scripts need no `if __name__ == "__main__":` guard.
- Cache folder: where tables and results of an *unsaved* .blend go (a path starting with
  `//` means "beside the .blend", which does not exist yet).  Empty = the per-user default
  `per_user_cache()`: the extension's user folder
  (`bpy.utils.extension_path_user(__package__)`, e.g.
  `~/.config/blender/5.0/extensions/.user/user_default/relief_addon/cache` on Linux) when
  installed as an extension, else Blender's user data folder
  (`<user resources>/datafiles/relief_bsdf/cache`).  Paths in this folder are never stored
  in the .blend: a scene keeps its `//` path, and on save the tables it names are copied
  beside the .blend (`paths.py`).
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import bpy
from bpy.props import IntProperty, StringProperty

ADDON_ID = __package__            # "relief_addon", or "bl_ext.<repo>.relief_addon" when installed
_DEFAULTS = SimpleNamespace(workers=0, cache_dir="")


class ReliefPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    workers: IntProperty(name="Worker processes", default=0, min=0, soft_max=64,
                         description="Local worker processes for long jobs (0 = every core)")
    cache_dir: StringProperty(name="Cache folder", default="", subtype="DIR_PATH",
                              description="Tables and results of unsaved files (empty = the per-user default)")

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "workers")
        col.prop(self, "cache_dir")
        col.label(text=f"Default cache: {default_cache_dir()}", icon="INFO")


def get_prefs(context=None):
    """The add-on's preferences, or their defaults when it was registered without
    `addon_utils` (tests and scenes/render_plate.py call `relief_addon.register()` directly)."""
    context = context or bpy.context
    addons = getattr(getattr(context, "preferences", None), "addons", None)
    entry = addons.get(ADDON_ID) if addons is not None else None
    return entry.preferences if entry is not None and entry.preferences is not None else _DEFAULTS


def default_cache_dir() -> Path:
    """The documented per-user cache folder (see module doc); created on first use."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON_ID, path="cache", create=True))
    except (ValueError, AttributeError, RuntimeError):        # not installed as an extension
        return Path(bpy.utils.user_resource("DATAFILES", path="relief_bsdf/cache", create=True))


def per_user_cache(context=None) -> Path:
    """The cache folder in force: the preference when set, else `default_cache_dir()`."""
    p = get_prefs(context).cache_dir
    folder = Path(bpy.path.abspath(p)) if p else default_cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def register():
    bpy.utils.register_class(ReliefPreferences)


def unregister():
    bpy.utils.unregister_class(ReliefPreferences)
