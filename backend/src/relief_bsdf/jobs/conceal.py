"""The job `relief conceal`: seeded cases with one concealed effect (or none), the key kept apart.

Each case OUT/caseNN holds relief.x3p, recording.csv and sample.toml (nothing in them reveals the
effects); OUT/key.json holds the truth (`validation.conceal.generate`: an independent Monte-Carlo
photon plate through the ray-traced relief, with shot, gain and floor noise).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from relief_bsdf.errors import InputError
from relief_bsdf.jobs.control import CancelToken, check, watched
from relief_bsdf.progress import Progress


@dataclass(frozen=True)
class ConcealJob:
    """`per_effect` cases per concealed effect and `none` with nothing concealed, seeded by `seed`, into
    `out`; `photons` per incidence (None: the cases' default), `effects` a subset of the concealable
    effects (None: all; a compound case is kept when every effect it holds is asked for)."""

    out: Path
    per_effect: int = 2
    none: int = 4
    seed: int = 1
    photons: int | None = None
    effects: tuple | None = None


@dataclass(frozen=True)
class ConcealOutput:
    """`cases` cases written under `out`; the key file `key` (keep it apart)."""

    cases: int
    out: Path
    key: Path


def run_conceal(job: ConcealJob, progress: Progress | None = None,
                cancel: CancelToken | None = None) -> ConcealOutput:
    from relief_bsdf.validation.conceal import EFFECTS_CONCEALABLE, default_cases, generate
    if job.per_effect < 0 or job.none < 0:
        raise InputError("--per-effect/--none", "case counts must be >= 0")
    cases = default_cases(job.per_effect, job.none, job.seed)
    if job.effects is not None:
        bad = [e for e in job.effects if e not in EFFECTS_CONCEALABLE]
        if bad:
            raise InputError("--effects", f"unknown effect(s) {bad}; choose from {', '.join(EFFECTS_CONCEALABLE)}")
        cases = [c for c in cases if set(c.effects) <= set(job.effects)]
    if job.photons is not None:
        if job.photons < 1000:
            raise InputError("--photons", f"need at least 1000 photons, got {job.photons}")
        for c in cases:
            c.photons = job.photons
    check(cancel, "generating")
    key = generate(job.out, cases, watched(progress, cancel))
    return ConcealOutput(len(cases), Path(job.out), Path(key))
