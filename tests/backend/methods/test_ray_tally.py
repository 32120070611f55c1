"""A ray task's total of its chunks' sums (`methods.ray.method._merged`): the first chunk's tally is taken as the
total's start instead of being added to a zeroed total; the sums are the same bit for bit.  Adding x to +0 gives
x for every float except -0, and a sum that starts at +0 never becomes -0 (round to nearest: only -0 + -0 is
-0), even when every term is -0 (Mueller entries -(b S) with b S = 0)."""
from __future__ import annotations

import numpy as np

from relief_bsdf.bsdf.builder import CellIndex, ExitSamples
from relief_bsdf.methods.ray.method import _merged, _new_tally

F32 = np.float32


def chunk_tally(seed: int, cells: CellIndex):
    rng = np.random.default_rng(seed)
    n = 4000
    k = rng.normal(size=(n, 3))
    k = (k / np.linalg.norm(k, axis=1)[:, None]).astype(F32)
    w = rng.random(n).astype(F32)
    M = rng.normal(size=(16, n)).astype(F32)
    M[:, : n // 4] = -0.0                                  # exits whose every entry is -0
    M[3, :] = -0.0
    t = _new_tally(cells, 4, (2, 2))
    t.acc.add(ExitSamples(k, w, (k[:, 2] < 0).astype(np.int8), M, None, rng.integers(0, 4, n).astype(np.int32)))
    t.acc.lose("max_bounces", 0.25)
    t.acc.count_paths(rng.integers(0, 4, n))
    t.segments, t.paths, t.exits, t.bounce_sum = 3 * n, n, n, 1.5 * n
    return t


def fields(t):
    a = t.acc
    return [a.sum_w, a.sum_w2, a.sum_M, a.spec, a.spec_M, a.paths_group, a.sum_w_group(),
            np.array([a.outside_table, t.segments, t.paths, t.exits, t.bounce_sum, *a.lost.values()])]


def test_first_chunk_as_the_total_equals_adding_it_to_zeros():
    cells = CellIndex(tuple(np.linspace(0.0, 90.0, 19)), tuple(np.arange(0.0, 361.0, 30.0)))
    zero = _new_tally(cells, 4, (2, 2))
    zero.merge(chunk_tally(1, cells))
    zero.merge(chunk_tally(2, cells))
    taken = _merged(_merged(None, chunk_tally(1, cells)), chunk_tally(2, cells))
    for x, y in zip(fields(zero), fields(taken), strict=True):
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    assert not np.signbit(taken.acc.sum_M[:, 3]).any()    # the all -0 entry sums to +0
    assert np.count_nonzero(taken.acc.sum_M) > 1000
