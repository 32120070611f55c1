"""The one content digest of a relief: SHA-256 of its heights, pitch and periodicity.

Every cache key and every BVH key that stands for a relief's content is made here, so two
places never disagree on whether two reliefs are the same (NaN heights hash by their bit
pattern: the same missing points give the same digest).
"""
from __future__ import annotations

import hashlib
from typing import Any

import numpy as np


def relief_hash(relief: Any, extra: tuple = ()) -> "hashlib._Hash":
    """sha256 object of the heights (float64, C order), shape, pitch, periodicity and `extra`
    (e.g. a tracer's mesh options); `.hexdigest()` or `.copy()` it as needed."""
    h = hashlib.sha256()
    hm = np.ascontiguousarray(relief.heights_m, dtype=np.float64)
    h.update(hm)
    h.update(repr((hm.shape, float(relief.dx_m), float(relief.dy_m), bool(relief.periodic), *extra)).encode())
    return h


def relief_digest(relief: Any) -> str:
    """Hex SHA-256 content digest of a relief (heights, shape, pitch, periodicity)."""
    return relief_hash(relief).hexdigest()
