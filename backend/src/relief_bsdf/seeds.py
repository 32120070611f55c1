"""The project's one derivation of random streams: `task_rng(seed, *key)`.

A stream is PCG64 seeded by numpy's SeedSequence over the run's seed and the integer key of
the piece of work (a task, an incidence, a relief realisation), each taken modulo 2^32.
Streams of different keys are statistically independent (SeedSequence hashes the whole
entropy pool), and a stream depends on (seed, key) only: the same numbers whichever process,
thread or backend draws them.  It sits at the foot of the package (it imports numpy only), so
`surface` (random reliefs) and `parallel` (tasks) draw from the same scheme without importing
each other.
"""
from __future__ import annotations

import numpy as np


def task_rng(seed: int, *key: int) -> np.random.Generator:
    """Random generator for one piece of work, derived from the run's seed and the work's integer key."""
    ints = [int(seed) & 0xFFFFFFFF] + [int(k) & 0xFFFFFFFF for k in key]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(ints)))
