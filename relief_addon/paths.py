"""Where the add-on's files live, and which path strings end up in the .blend.

- A saved .blend: `//name` means beside the .blend (Blender's own convention); tables,
  results and renders go there.
- An unsaved .blend: `//name` resolves into the per-user cache folder (`prefs.per_user_cache`,
  documented there; never the system's temporary folder).  The scene keeps the `//name`
  string, never the cache path, so nothing machine- or session-specific is saved into the
  .blend.  The cache is shared by every unsaved session, so a table written there is named by
  its content (`content_named`: `relief_table-<12 hex digits of its SHA-256>.h5`): two sessions
  never overwrite each other's table, and a name always means the same bytes.  When the file is
  then saved, `copy_cached_beside_blend` (a save handler) copies the files the scene names from
  the cache to beside the .blend, where `//name` now points, replacing a different file of the
  same name there (never keeping a stale one).
- A job's output folder (simulate, fit, diagnose) in an unsaved session would be shared the
  same way, and its files are not content-named (fit.json, report.html): `session_output`
  gives each unsaved session its own folder, `<job>-<session tag>` (a random tag drawn once per
  Blender process), so two unsaved sessions never write into each other's results.
- The lookup images of baked node groups are packed into the .blend (bake_nodes.lut_image),
  so a saved file renders without its tables.
"""
from __future__ import annotations

import filecmp
import hashlib
import re
import shutil
import uuid
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


_SESSION_TAG = uuid.uuid4().hex[:8]


def session_output(folder) -> Path:
    """`folder` for a job's outputs; in the per-user cache (an unsaved session) the session's own
    `<name>-<tag>` beside it (module doc)."""
    folder = Path(folder)
    return folder.with_name(f"{folder.name}-{_SESSION_TAG}") if in_cache(folder) else folder


def in_cache(path) -> bool:
    """Whether `path` lies in the per-user cache (where unsaved sessions write; main thread)."""
    cache = per_user_cache().resolve()
    path = Path(path).resolve()
    return path == cache or cache in path.parents


_DIGEST = re.compile(r"-[0-9a-f]{12}$")


def scratch_name(path) -> Path:
    """A name in `path`'s folder no other writer uses (this process, a random id), same suffix: write
    there, then `content_named`."""
    path = Path(path)
    stem = _DIGEST.sub("", path.stem)
    return path.with_name(f"{stem}.writing-{uuid.uuid4().hex[:12]}{path.suffix}")


def content_named(path) -> Path:
    """Rename the file `path` to `<stem>-<first 12 hex digits of its SHA-256><suffix>` in its folder
    (an earlier digest or `.writing-...` part of the stem dropped) and return the new path.  Equal
    names then mean equal bytes, so sessions sharing the cache cannot overwrite each other's files
    (replacing an equal file is harmless).  File operations only: safe on a worker thread."""
    path = Path(path)
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    stem = _DIGEST.sub("", path.stem.split(".writing-")[0])
    dst = path.with_name(f"{stem}-{h.hexdigest()[:12]}{path.suffix}")
    path.replace(dst)
    return dst


def _same(src: Path, dst: Path) -> bool:
    if src.is_dir() or dst.is_dir():
        return False                              # folders: merged file by file below
    return dst.is_file() and filecmp.cmp(src, dst, shallow=False)


def _copy(src: Path, dst: Path) -> None:
    """Copy a file (atomically) or a folder (merged: its files replace those of the same name)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst, dirs_exist_ok=True)
    else:
        tmp = dst.with_name(dst.name + ".part")
        shutil.copy2(src, tmp)
        tmp.replace(dst)


_SAVING_UNSAVED = {"value": False}


@persistent
def note_unsaved_before_save(*_args) -> None:
    """Save-pre handler: whether the file being saved was unsaved (its `//` files are in the cache)."""
    _SAVING_UNSAVED["value"] = not bpy.data.filepath


@persistent
def copy_cached_beside_blend(*_args) -> None:
    """Save handler: when an unsaved session is saved, the `//` files it wrote to the cache are
    copied beside the newly saved .blend, replacing a different file of the same name there (a
    stale table from an earlier session).  Later saves copy nothing: `//` then already means the
    .blend's folder, where the session writes."""
    was_unsaved, _SAVING_UNSAVED["value"] = _SAVING_UNSAVED["value"], False
    if not bpy.data.filepath or not was_unsaved:
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
            if rel and src.exists() and not _same(src, dst):
                _copy(src, dst)


def register():
    if note_unsaved_before_save not in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.append(note_unsaved_before_save)
    if copy_cached_beside_blend not in bpy.app.handlers.save_post:
        bpy.app.handlers.save_post.append(copy_cached_beside_blend)


def unregister():
    if note_unsaved_before_save in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(note_unsaved_before_save)
    if copy_cached_beside_blend in bpy.app.handlers.save_post:
        bpy.app.handlers.save_post.remove(copy_cached_beside_blend)
