"""Atomic file output: write to a temporary file beside the target, then rename.

A reader never sees a half-written file: either the old content or the new one.

- The temporary is ``.<stem>.<host>-<pid>.<random>.part<suffix>`` beside the target.  A run
  killed mid-write (kill -9, power loss) leaves it behind; the next write into that folder
  removes every such ``.part`` file whose writer (same host, that pid) no longer runs
  (`remove_stale_parts`), so a live concurrent writer's temporary is never touched.
- The finished file gets the mode an ordinary ``open(..., "w")`` would give it, 0666 less the
  umask (not the 0600 of ``mkstemp``).
- `check_output_file` / `check_output_dir` check an output path *before* any computation:
  a folder where a file is expected (or the reverse), a parent that is a file, a folder that
  cannot be written; each raises an `InputError` naming the path.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import socket
from pathlib import Path
from typing import Iterator

from relief_bsdf.errors import InputError

#: folders this process already swept of stale temporaries (a cache; deciding nothing else)
_SWEPT: set[Path] = set()
_PART = re.compile(r"^\..+\.(?P<host>[0-9a-f]{8})-(?P<pid>\d+)\.[0-9a-f]+\.part(\.[^.]*)?$")


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _umask() -> int:
    """The process umask, read without changing it where Linux allows (/proc), else set and restored."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def process_alive(pid: int) -> bool:
    """Whether process `pid` still runs (a zombie, dead but not yet reaped, counts as gone).  The one
    liveness check: stale `.part` files here, orphaned pool workers in parallel.worker."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rsplit(b")", 1)[1].split()[0]
        return state not in (b"Z", b"X")
    except (OSError, IndexError):
        return True


def remove_stale_parts(folder: str | Path) -> list[Path]:
    """Delete the `.part` temporaries in `folder` left by writers (of this host) that are gone."""
    folder = Path(folder)
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    host = _host_tag()
    try:
        names = [e.name for e in os.scandir(folder) if e.name.startswith(".") and ".part" in e.name]
    except OSError:
        return removed
    for name in names:
        m = _PART.match(name)
        if m is None or m["host"] != host or process_alive(int(m["pid"])):
            continue
        with contextlib.suppress(OSError):
            (folder / name).unlink()
            removed.append(folder / name)
    return removed


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; move it onto `target` on success.

    The temporary keeps the target's suffix so libraries that choose a format by
    extension (h5py, OpenImageIO, matplotlib) still do the right thing.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.parent.resolve() not in _SWEPT:           # once per folder and process: folders of
        _SWEPT.add(target.parent.resolve())              # thousands of checkpoints stay cheap to write
        remove_stale_parts(target.parent)
    suffix = target.suffix if suffix is None else suffix
    tmp_path = target.parent / f".{target.stem}.{_host_tag()}-{os.getpid()}.{secrets.token_hex(4)}.part{suffix}"
    fd = os.open(tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    os.close(fd)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())        # a library may have recreated it: set the mode last
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_text_atomic(target: str | Path, text: str, encoding: str = "utf-8") -> Path:
    """Write `text` to `target` atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(target)


def write_bytes_atomic(target: str | Path, data: bytes) -> Path:
    """Write `data` to `target` atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


# ---------------------------------------------------------------------------------------------
# output paths, checked before the work starts

def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_can_create_in(folder: Path, shown: Path) -> None:
    """The folder (or, if absent, its nearest existing ancestor) is a folder we can create files in."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise InputError(shown, f"cannot write here: {base} is a file, not a folder")
    probe = base / f".relief-write-probe.{os.getpid()}.{secrets.token_hex(4)}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as e:
        raise InputError(shown, f"cannot write in folder {base} ({e.strerror or e})") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        probe.unlink()


def check_output_file(path: str | Path) -> Path:
    """An output *file* path we will be able to write: not a folder, its folder existing and writable
    (a command that fails creates no folder)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder; expected an output file name")
    if path.exists() and not path.is_file():
        raise InputError(path, "exists and is not a regular file (a FIFO, socket or device?)")
    _check_can_create_in(path.parent, path)
    if not path.parent.exists():
        raise InputError(path, f"the folder {path.parent} does not exist; create it first (nothing was written)")
    remove_stale_parts(path.parent)
    return path


def check_output_dir(path: str | Path) -> Path:
    """An output *folder* path we will be able to write in: not a file, writable (created later)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, "is a file; expected an output folder")
    _check_can_create_in(path, path)
    remove_stale_parts(path)
    return path
