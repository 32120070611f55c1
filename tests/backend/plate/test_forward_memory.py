"""The forward model's one memory owner (plate.memory): byte budget, eviction, scope, same numbers."""
from __future__ import annotations

import numpy as np

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate.faces import relief_digest
from relief_bsdf.plate.memory import ForwardMemory, current_memory, deep_nbytes
from relief_bsdf.surface.digest import relief_hash
from relief_bsdf.surface.synth import random_relief

GRID = TableGrid(3.0, 15.0, 15.0)
ROWS = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 8.0))


def _experiment() -> Experiment:
    relief = random_relief(48, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=5)
    return Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", samples=3_000, seed=0), FlatFace()))


def test_the_budget_evicts_the_least_recently_used_and_keeps_the_newest():
    m = ForwardMemory(budget_bytes=2500)
    m.put(("a",), np.zeros(100))           # 800 bytes each
    m.put(("b",), np.zeros(100))
    m.get(("a",), lambda: None)            # a is now the most recent
    m.put(("c",), np.zeros(100))
    assert m.held_bytes == 2400 and set(m._d) == {("a",), ("b",), ("c",)}
    m.put(("d",), np.zeros(100))           # over the budget: b (least recent) goes
    assert ("b",) not in m and ("a",) in m and m.held_bytes <= 2500 and m.evictions == 1
    m.put(("big",), np.zeros(1000))        # larger than the whole budget: held alone until the next put
    assert list(m._d) == [("big",)] and m.report()["peak_held_bytes"] >= 8000
    r = m.report()
    assert r["by_kind"]["table"] == {"entries": 1, "bytes": 8000} and r["budget_bytes"] == 2500


def test_what_is_dear_to_make_for_its_size_outlives_what_is_cheap():
    """GreedyDual-Size: an entry that took long to make per byte stays over more recent cheap ones while
    the clock (raised by each eviction to the evicted priority) is below its cost per GB."""
    m = ForwardMemory(budget_bytes=2500)
    m.put(("sector table",), np.zeros(100), cost_s=1.0)      # 800 bytes, dear
    m.put(("weights a",), np.zeros(100), cost_s=0.0)
    m.put(("weights b",), np.zeros(100), cost_s=0.0)
    m.put(("weights c",), np.zeros(100), cost_s=0.0)         # over: a cheap one goes, not the dear one
    assert ("sector table",) in m and ("weights a",) not in m
    for k in range(3):
        m.get(("weights c",), lambda: None)
        m.put((f"more {k}",), np.zeros(100), cost_s=0.0)
    assert ("sector table",) in m                              # the clock is still below its cost per GB
    assert m.report()["evictions"] == 4


def test_a_put_evicts_before_it_adds_so_the_held_bytes_never_pass_the_budget():
    m = ForwardMemory(budget_bytes=2500)
    for k in range(10):
        m.put((k,), np.zeros(100))                                  # 800 bytes each: three fit
    assert m.report()["peak_held_bytes"] <= 2500 and len(m) == 3 and m.evictions == 7


def test_a_buffer_two_entries_reach_counts_once_and_an_entry_that_frees_nothing_stays():
    """A solver reaches the tables it reads (held as entries of their own) and shares its tables' part
    with a solver of another bulk: each buffer counts once; evicting a table a held solver reads would
    free nothing, so the solver goes first."""
    m = ForwardMemory(budget_bytes=1700)
    table = np.zeros(100)                                           # 800 bytes
    m.put(("table",), table)
    m.put(("solver",), {"reads": table, "own": np.zeros(50)}, "solver")   # 400 bytes of its own
    assert m.held_bytes == 1200
    m.put(("other solver",), {"reads": table, "own": np.zeros(50)}, "solver")
    assert m.held_bytes == 1600
    del table
    m.put(("new",), np.zeros(25))                                  # 200 bytes more: over by 100
    assert ("table",) in m and ("solver",) not in m and m.held_bytes == 1400


def test_an_evicted_value_still_alive_is_reported_until_it_is_freed():
    m = ForwardMemory(budget_bytes=2000)
    in_use = np.zeros(100)                                          # an evaluation still holds it
    m.put(("a",), in_use)
    m.put(("b",), np.zeros(100))
    m.put(("c",), np.zeros(100))               # over: a goes, but it is alive: reported apart
    assert ("a",) not in m and ("b",) in m and ("c",) in m
    assert m.held_bytes == 1600 and m.report()["evicted_alive_bytes"] == 800
    del in_use
    m.refresh(None)
    assert m.held_bytes == 1600 and m.report()["evicted_alive_bytes"] == 0


def test_reserve_makes_room_for_what_a_computation_is_about_to_allocate():
    m = ForwardMemory(budget_bytes=2000)
    m.put(("a",), np.zeros(100))
    m.put(("b",), np.zeros(100))
    m.reserve(500)                                                  # 1600 + 500 > 2000: the older goes
    assert ("a",) not in m and ("b",) in m and m.held_bytes == 800


def test_deep_nbytes_counts_each_buffer_once():
    a = np.zeros(1000)
    assert deep_nbytes({"x": a, "y": a[10:], "z": [a.reshape(10, 100)]}) == 8000
    assert deep_nbytes((np.zeros(3, np.float32), "text", 4)) == 12


def test_active_scopes_the_owner_and_the_process_one_is_found_outside():
    outside = current_memory()
    mine = ForwardMemory(1e6)
    with mine.active():
        assert current_memory() is mine
    assert current_memory() is outside and outside is not mine


def test_one_relief_digest_for_tables_and_tracers():
    relief = random_relief(16, 1e-6, 0.1e-6, 3e-6, "gaussian", seed=1)
    assert relief_digest(relief) == relief_hash(relief).hexdigest() and len(relief_digest(relief)) == 64
    assert relief_digest(relief.scaled(2.0)) != relief_digest(relief)


def test_a_solver_is_held_measured_and_a_starved_budget_gives_the_same_numbers():
    ex = _experiment()
    with ForwardMemory(4e9).active() as roomy:
        first = simulate(ex, ROWS, grid=GRID).values_per_sr
        report = roomy.report()
        assert report["by_kind"]["solver"]["entries"] >= 1
        assert report["by_kind"]["solver"]["bytes"] > 1e5           # measured after it solved (`refresh`)
        assert report["by_kind"]["table"]["entries"] >= 2
        again = simulate(ex.with_instrument(background_per_sr=0.01), ROWS, grid=GRID).values_per_sr
        assert roomy.report()["misses"] == report["misses"]           # everything reused
    with ForwardMemory(1.0).active() as starved:                      # nothing can stay: recomputed each time
        got = simulate(ex, ROWS, grid=GRID).values_per_sr
        assert len(starved) <= 1 and starved.evictions > 0
    np.testing.assert_array_equal(got, first)
    np.testing.assert_allclose(again, first + 0.01, rtol=1e-12)


def test_threads_of_one_job_share_the_owner_safely():
    """The plate's threads (the model sigma's draws, a screen beside the workers) put and evict in one
    owner at once: no error, the budget held, every value found or made again."""
    from concurrent.futures import ThreadPoolExecutor
    m = ForwardMemory(budget_bytes=20_000)

    def work(t: int) -> int:
        n = 0
        for k in range(300):
            v = m.get(("w", t, k % 37), lambda: np.full(100, float(k % 37)))
            n += int(v[0] == k % 37)
        return n
    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(work, range(4))) == [300] * 4
    assert m.held_bytes <= 20_000 and m.evictions > 0


def test_the_plan_counts_what_a_pool_adds_and_its_processes_fit_the_total():
    """Each process of a pool holds POOL_SHARE evaluations beyond the one-process model (the forward model
    sent to the workers): at the default 3.5 GB a 0.31 GB evaluation runs in one process, with more
    memory on a pool, and the planned processes together never pass the total."""
    from relief_bsdf.plate.memory import POOL_SHARE, PROCESS_BASE_BYTES, TRANSIENT_SHARE, plan_processes
    per = 0.312e9
    one = plan_processes(3.5e9, per, 2)
    assert one.workers == 1 and one.fits
    assert PROCESS_BASE_BYTES + one.main_budget_bytes + TRANSIENT_SHARE * per <= 3.5e9 + 1
    pool = plan_processes(8e9, per, 2)
    assert pool.workers == 2 and pool.fits
    per_process = PROCESS_BASE_BYTES + pool.worker_budget_bytes + (TRANSIENT_SHARE + POOL_SHARE) * per
    planned = (pool.workers + 1) * per_process
    assert planned <= 8e9 + 1
    # without the pool's share the same 3.5 GB would have planned two workers
    assert 3.5e9 / 3 - PROCESS_BASE_BYTES - TRANSIENT_SHARE * per >= per
