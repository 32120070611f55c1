"""parallel.memory: the computing processes take no huge-page advice from numpy, unless the user says."""
import pytest
from numpy.core import multiarray          # numpy is pinned (1.26.4, by bpy 5.0.1): the switch is there

from relief_bsdf.parallel import memory


@pytest.fixture
def advice(monkeypatch):
    """numpy's huge-page advice on, no NUMPY_MADVISE_HUGEPAGE; both restored afterwards."""
    monkeypatch.delenv(memory.HUGEPAGE_ENV, raising=False)
    before = multiarray._set_madvise_hugepage(True)
    yield
    multiarray._set_madvise_hugepage(before)


def test_small_pages_turns_the_advice_off_here_and_for_the_processes_started_from_here(advice, monkeypatch):
    import os
    assert memory.small_pages() is True                      # it was on
    assert multiarray._set_madvise_hugepage(False) is False   # now off (the call returns the old setting)
    assert os.environ[memory.HUGEPAGE_ENV] == "0"             # a fork server or spawned worker inherits it


def test_a_users_setting_wins(advice, monkeypatch):
    monkeypatch.setenv(memory.HUGEPAGE_ENV, "1")
    assert memory.small_pages() is False
    assert multiarray._set_madvise_hugepage(True) is True     # left on


def test_trim_heap_returns_the_freed_blocks_the_ray_engine_lets_glibc_keep():
    """With the ray engine's malloc settings (`keep_freed_heap`: 4-MB blocks from the heap, 256 MB kept
    when freed) 200 MB allocated and freed stay resident; `trim_heap(collect=False)` (after every plate
    evaluation and ray request) hands them back.  In a fresh process: the settings are process-wide."""
    import subprocess
    import sys
    import textwrap
    code = textwrap.dedent("""
        import numpy as np
        from relief_bsdf.methods.ray.transport import keep_freed_heap
        from relief_bsdf.parallel.memory import trim_heap
        def rss():
            return int(open("/proc/self/statm").read().split()[1]) * 4096
        if not keep_freed_heap():
            print("skip")
            raise SystemExit
        blocks = [np.ones(500_000) for _ in range(50)]          # 4 MB each, 200 MB
        blocks = None
        kept = rss()
        assert trim_heap(collect=False)
        print(kept - rss())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    if out == ["skip"]:
        pytest.skip("not glibc: the allocator keeps its own defaults")
    assert int(out[0]) > 100e6                   # most of the 200 MB went back
