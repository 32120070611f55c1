"""What left the relief layer: the ONE exit record of the ray method (`Exits`).

Every traced path ends exactly once, in one of the states below; `Exits` is a preallocated
structure of arrays filled by the transport loop as paths end (in no particular order) and
read by the binning (`relief_bsdf.bsdf.builder`) or re-ordered by input ray (`ordered`) for
`ReliefTracer.scatter`.  With a first-hit split a path of input index i has two outputs,
i (reflected branch) and i + n (transmitted branch).
"""
from __future__ import annotations

import numpy as np

from relief_bsdf import kernels

F32 = np.float32
ROW_PAD = 16          # float32 (one cache line) between the rows of a (rows, m) array: see `padded_rows`

# exit states
ABOVE, BELOW, LOST_BOUNCES, LOST_LEAK, LOST_ABSORBED = 0, 1, 2, 3, 4
STATE_NAMES = {LOST_BOUNCES: "max_bounces", LOST_LEAK: "numerical_leak", LOST_ABSORBED: "absorbed"}


def padded_rows(shape: tuple, m: int) -> np.ndarray:
    """An uninitialised float32 array (*shape, m) whose rows start one cache line apart modulo 4 KiB.

    A chunk's arrays have power-of-two lengths (2^16 rays, 2^17 exits): unpadded, the 16 rows of a
    Mueller record lie a power of two apart and fall into the same cache set, so a kernel writing or
    reading one record's entries across them (`relief_bsdf.kernels`) evicts its own lines; numpy's
    row-by-row passes do not care.  A view of a slightly wider array (rows ROW_PAD floats longer).
    """
    return np.empty(tuple(shape) + (m + ROW_PAD,), F32)[..., :m]


class Exits:
    """Exit records of one chunk: propagation direction k (m, 3) float32, power weight w, state
    (int8, above), bounce count nb (int16), output id, and, for polarised light, the Stokes
    columns A (4, K, m) in the exit frame s = z x k, p = s x k.  A record whose path interacted once may hold its Mueller columns compactly (`compact` 1: in the flat rows
    0-7 of A, the 6 factors of the interaction and cos / sin 2psi of the exit rotation, from which
    the binning computes the 16 entries: `transport.StokesCarrier.exit_columns`); `expand` writes them
    whole.  Filled by `put`;
    `n` records are valid.  `segments` (Embree queries), `n_paths` (input rays) and `m` (outputs
    per chunk: n_paths, or 2 n_paths with the first-hit split) are set when the chunk is done.
    """

    def __init__(self, m: int, K: int = 0):
        self.k = np.empty((m, 3), F32)
        self.w = np.empty(m, F32)
        self.state = np.empty(m, np.int8)
        self.nb = np.empty(m, np.int16)
        self.ids = np.empty(m, np.int64)
        self.A = padded_rows((4, K), m) if K else None
        self.compact = np.zeros(m, np.uint8) if K == 4 else None     # 1: A holds the record compactly
        self.n = 0
        self.m = m
        self.segments = 0
        self.n_paths = 0
        self.first_group = None          # (n_paths,) sub-tile of each input ray's first hit, when asked for

    def put(self, k, idx, w, nb, ids, state) -> slice:
        """Store rows `idx` of the arrays (idx None: every row); the slice of the new records, whose
        Stokes columns `A[:, :, slice]` the caller fills (the carrier, in the exit frame); rows idx are
        gathered in one pass (`kernels.gather_records`)."""
        a = self.n
        if idx is None:
            b = a + ids.size
            self.k[a:b] = k
            self.w[a:b] = w
            self.nb[a:b] = nb
            self.ids[a:b] = ids
        else:
            b = a + idx.size
            kernels.gather_records(idx, k, w, nb, ids, self.k[a:b], self.w[a:b], self.nb[a:b], self.ids[a:b])
        self.state[a:b] = state
        self.n = b
        return slice(a, b)

    # ------------------------------------------------------------------ views of the valid records
    def expand(self) -> None:
        """Write every compactly held record's Mueller columns whole (class doc)."""
        if self.compact is not None and self.compact[:self.n].any():
            kernels.expand_compact(self.A.reshape(16, -1)[:, :self.n], self.compact[:self.n])

    def records(self):
        """(k, w, state, nb, A or None) of the n valid records, in the order they ended (A's records may be
        compact: `compact[:n]`)."""
        e = self.n
        return self.k[:e], self.w[:e], self.state[:e], self.nb[:e], None if self.A is None else self.A[:, :, :e]

    def ordered(self):
        """(k, A, w, state, nb) arrays of length m in id order (never-ended ids: lost as leaks)."""
        self.expand()
        m, e = self.m, self.n
        k = np.zeros((m, 3), F32)
        w = np.zeros(m, F32)
        state = np.full(m, LOST_LEAK, np.int8)
        nb = np.zeros(m, np.int16)
        ids = self.ids[:e]
        k[ids] = self.k[:e]
        w[ids] = self.w[:e]
        state[ids] = self.state[:e]
        nb[ids] = self.nb[:e]
        A = None
        if self.A is not None:
            A = np.zeros((4, self.A.shape[1], m), F32)
            A[:, :, ids] = self.A[:, :, :e]
        return k, A, w, state, nb
