"""Where the add-on's files live, and which path strings end up in the .blend.

- A saved .blend: `//name` means beside the .blend (Blender's own convention); tables,
  results and renders go there.
- An unsaved .blend: `//name` resolves into the per-user cache folder (`prefs.per_user_cache`,
  documented there; never the system's temporary folder).  The scene keeps the `//name`
  string, never the cache path, so nothing machine- or session-specific is saved into the
  .blend.  When the file is then saved, `copy_cached_beside_blend` (a save handler) copies
  the files the scene names from the cache to beside the .blend, where `//name` now points.
- The lookup images of baked node groups are packed into the .blend (bake_nodes.lut_image),
  so a saved file renders without its tables.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import bpy
from bpy.app.handlers import persistent

from .prefs import per_user_cache

# scene.relief properties holding "//" paths that the save handler carries beside the .blend
PATH_PROPS = ("table_path", "output_dir", "fit_dir", "render_path")


def resolve(p: str) -> Path:
    """Blender path -> file system path (`//` = beside the .blend, or the per-user cache)."""
    if p.startswith("//") and not bpy.data.filepath:
        return per_user_cache() / p[2:]
    return Path(bpy.path.abspath(p))


def stored(path) -> str:
    """The string to keep in the .blend for `path`: `//relative` inside the cache or beside the
    .blend, else the absolute path the user chose."""
    path = Path(path).resolve()
    cache = per_user_cache().resolve()
    if path == cache or cache in path.parents:
        return "//" + path.relative_to(cache).as_posix()
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(str(path))
        except ValueError:                         # another drive (Windows)
            pass
    return str(path)


def _copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        tmp = dst.with_name(dst.name + ".part")
        shutil.copy2(src, tmp)
        tmp.replace(dst)


@persistent
def copy_cached_beside_blend(*_args) -> None:
    """Save handler: the `//` files an unsaved session wrote to the cache, copied beside the
    newly saved .blend (existing files there are left alone)."""
    if not bpy.data.filepath:
        return
    cache = per_user_cache()
    blend_dir = Path(bpy.data.filepath).parent
    for scene in bpy.data.scenes:
        s = getattr(scene, "relief", None)
        if s is None:
            continue
        values = [getattr(s, k, "") for k in PATH_PROPS]
        values += [g.get("relief_table", "") for g in bpy.data.node_groups]
        for v in values:
            if not isinstance(v, str) or not v.startswith("//"):
                continue
            rel = v[2:].rstrip("/\\")
            src, dst = cache / rel, blend_dir / rel
            if rel and src.exists() and not dst.exists():
                _copy(src, dst)


def register():
    if copy_cached_beside_blend not in bpy.app.handlers.save_post:
        bpy.app.handlers.save_post.append(copy_cached_beside_blend)


def unregister():
    if copy_cached_beside_blend in bpy.app.handlers.save_post:
        bpy.app.handlers.save_post.remove(copy_cached_beside_blend)
