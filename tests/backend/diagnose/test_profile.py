"""The diagnosis's profile (diagnose.profile): evaluations per stage counted once, seconds exclusive."""
import time
from dataclasses import replace

import pytest

from relief_bsdf.diagnose.profile import Profile, captured, kind_of, merge, note_evaluations, profiling, stage
from relief_bsdf.plate import TableGrid
from relief_bsdf.plate.grid import NO_SECTORS_DEG


def test_counts_go_to_the_innermost_stage_and_seconds_are_exclusive():
    t0 = time.perf_counter()
    with profiling() as p:
        with stage("candidate_fits"):
            note_evaluations(TableGrid(), 3)
            time.sleep(0.05)
            with stage("null_restarts"):
                note_evaluations(TableGrid(), 8)
                time.sleep(0.1)
            note_evaluations(replace(TableGrid(), stokes_loop=False))
    wall = time.perf_counter() - t0
    doc = p.doc()
    by = {r["stage"]: r for r in doc["stages"]}
    assert by["candidate_fits"]["full_evaluations"] == 3
    assert by["candidate_fits"]["screening_evaluations"] == 1
    assert by["null_restarts"]["full_evaluations"] == 8
    # the restart's 0.1 s is its own, not also the fit's: the two add up to the block's wall time
    assert by["null_restarts"]["seconds"] >= 0.1 and by["candidate_fits"]["seconds"] >= 0.05
    assert by["null_restarts"]["seconds"] + by["candidate_fits"]["seconds"] == pytest.approx(wall, abs=0.01)
    assert doc["full_evaluations"] == 11 and doc["screening_evaluations"] == 1


def test_screening_grid_is_told_from_the_full_one():
    full = TableGrid()
    assert kind_of(full) == "full"
    assert kind_of(replace(full, sector_step_deg=NO_SECTORS_DEG)) == "screening"
    assert kind_of(replace(full, stokes_loop=False)) == "screening"


def test_a_task_counted_apart_is_merged_once():
    with profiling() as p:
        with stage("screens"):
            with captured() as task, stage("screens"):       # as a worker's task
                note_evaluations(TableGrid(), 2)
            merge(task.counts())
    assert p.counts() == {"screens": {"full": 2, "screening": 0}}


def test_nothing_is_counted_without_a_profile():
    note_evaluations(TableGrid(), 5)          # no error, nowhere to count
    assert Profile().counts() == {}
