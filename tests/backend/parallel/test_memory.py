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
