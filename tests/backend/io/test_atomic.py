"""Atomic writes: umask honoured, stale temporaries of dead writers swept, live ones kept; output checks."""
from __future__ import annotations

import os
import stat

import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.io.atomic import (_host_tag, atomic_path, check_output_dir, check_output_file, remove_stale_parts,
                                   write_text_atomic)


def test_mode_follows_the_umask(tmp_path):
    for mask, mode in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
        old = os.umask(mask)
        try:
            p = write_text_atomic(tmp_path / f"f{mask:o}.txt", "x")
        finally:
            os.umask(old)
        assert stat.S_IMODE(p.stat().st_mode) == mode


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "t.h5") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_only_temporaries_of_dead_writers_are_removed(tmp_path):
    dead = tmp_path / f".t.{_host_tag()}-{2 ** 22 + 7}.00ff.part.h5"
    live = tmp_path / f".t.{_host_tag()}-{os.getpid()}.00ff.part.h5"
    other_host = tmp_path / f".t.00000000-{2 ** 22 + 7}.00ff.part.h5"
    for p in (dead, live, other_host):
        p.write_bytes(b"x")
    assert remove_stale_parts(tmp_path) == [dead]
    assert live.exists() and other_host.exists()


def test_output_checks(tmp_path):
    (tmp_path / "f").write_text("x")
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match="is a file"):
        check_output_dir(tmp_path / "f")
    with pytest.raises(InputError, match="is a folder"):
        check_output_file(tmp_path / "d")
    with pytest.raises(InputError, match="not a folder"):
        check_output_file(tmp_path / "f" / "x.h5")
    assert check_output_dir(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()              # checking creates nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d", "f"]
