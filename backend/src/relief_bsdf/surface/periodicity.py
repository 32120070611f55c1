"""Whether a height map is one period of a seamless tile, and who said so.

A periodic tile is traced as one period of an infinite surface; a measured patch is
mirror-extended (or windowed) instead, which changes the surface seen by the methods.  The
decision, in this order of precedence:

1. a statement of the user: the `[relief] periodic` key of a sample.toml, or the CLI's
   `--periodic` / `--no-periodic`;
2. the file's own statement: an npz `periodic` array, a project sidecar or EXR attribute, an
   X3P written by this project (its comment says `periodic=true|false`), a reader that
   reports a periodic topography (the readers record it as metadata["periodic_source"]);
3. the wrap-around test below.

Wrap-around test: for a seamless tile the step from the last row back to the first (and
from the last column to the first) is one more neighbour difference, drawn from the same
distribution as the interior ones; for a measured patch the two edges are far apart on the
sample (plus tilt and drift), so the wrap step is much larger.  Per axis, with valid pairs
only,

    ratio = rms(h[first] - h[last]) / rms(h[i + 1] - h[i])

and the map is called periodic when both ratios are <= `WRAP_RATIO_MAX` (2.0).  Measured
on 40 seeds of 64 x 64 synthetic tiles (Gaussian and exponential autocovariance,
correlation lengths 2-32 px) the periodic ratios stay <= 1.81, the validation set's 17
seamless 256 x 256 tiles <= 1.2, while crops of the same fields give >= 1.3 (correlation
length 2 px, where a seam is indistinguishable from the interior and either treatment
gives the same surface statistics) to >= 4.4 (8 px and more), and the nine instrument
maps of ../shared/data/topography give 6.3 to 680 on their larger axis.  Heights are
not levelled first: a plane fitted to a tile is not periodic, and a measured map's tilt
is part of what makes its edges differ.  Fewer than `MIN_WRAP_PAIRS` valid wrap pairs on
an axis (holes along the edge, a tiny map) make the test inconclusive: not periodic.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: largest wrap / interior rms difference ratio (both axes) of a map called periodic
WRAP_RATIO_MAX = 2.0
#: fewest valid (first, last) pairs along an edge for the wrap test to decide
MIN_WRAP_PAIRS = 8


@dataclass(frozen=True)
class Periodicity:
    """periodic: the decision; source: "user", "file", "crop" (a window of the map) or "test";
    reason: plain words for logs."""

    periodic: bool
    source: str
    reason: str

    def line(self) -> str:
        kind = "periodic tile (traced as one period)" if self.periodic else \
            "measured patch, not periodic (mirror-extended where a method needs a period)"
        return f"{kind}: {self.reason}"

    def as_dict(self) -> dict:
        return {"periodic": self.periodic, "source": self.source, "reason": self.reason}


def wrap_ratios(heights_m: np.ndarray) -> tuple[float, float]:
    """(ratio along y, ratio along x) of the wrap-around test; NaN where it cannot decide."""
    out = []
    for axis in (0, 1):
        h = np.moveaxis(np.asarray(heights_m, float), axis, 0)
        wrap = h[0] - h[-1]
        inner = np.diff(h, axis=0)
        wrap, inner = wrap[np.isfinite(wrap)], inner[np.isfinite(inner)]
        if wrap.size < MIN_WRAP_PAIRS or inner.size == 0:
            out.append(float("nan"))
            continue
        rw, ri = np.sqrt(np.mean(wrap ** 2)), np.sqrt(np.mean(inner ** 2))
        out.append(float(rw / ri) if ri > 0 else (1.0 if rw == 0 else float("inf")))
    return out[0], out[1]


def tested_periodicity(heights_m: np.ndarray) -> Periodicity:
    """The wrap-around test's decision (module docstring), with the ratios in its reason."""
    ry, rx = wrap_ratios(heights_m)
    if np.isnan(ry) or np.isnan(rx):
        return Periodicity(False, "test", f"wrap-around test inconclusive (fewer than {MIN_WRAP_PAIRS} valid "
                                          "edge pairs on an axis): treated as a measured patch")
    periodic = ry <= WRAP_RATIO_MAX and rx <= WRAP_RATIO_MAX
    verdict = "seamless" if periodic else "not seamless"
    return Periodicity(periodic, "test", f"wrap-around test: edge-to-edge steps are {rx:.3g} (x) and {ry:.3g} (y) "
                                         f"times the rms neighbour step, {verdict} (periodic when both <= "
                                         f"{WRAP_RATIO_MAX:g}; state it with [relief] periodic or "
                                         "--periodic/--no-periodic)")


def decide_periodicity(relief, stated: bool | None = None, stated_by: str = "--periodic") -> Periodicity:
    """The user's statement, else the file's (relief.metadata["periodic_source"]), else the test."""
    if stated is not None:
        return Periodicity(bool(stated), "user", f"stated by {stated_by}")
    said = relief.metadata.get("periodic_source") if isinstance(relief.metadata, dict) else None
    if said:
        return Periodicity(bool(relief.periodic), "file", f"stated by {said}")
    return tested_periodicity(relief.heights_m)


def with_periodicity(relief, p: Periodicity):
    """The relief with `p` applied: its periodic flag, metadata["periodicity"] and a history entry."""
    meta = {**relief.metadata, "periodicity": p.as_dict()}
    return replace(relief, periodic=p.periodic, metadata=meta,
                   history=relief.history + (f"periodicity: {p.line()}",))
