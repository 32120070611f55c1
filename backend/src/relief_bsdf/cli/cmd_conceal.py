"""`relief conceal -o OUTDIR`: seeded cases with one concealed effect (or none), key kept apart."""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("conceal", help="generate recordings with concealed effects (proof data for diagnose)",
                       description="Each case OUTDIR/caseNN holds relief.x3p, recording.csv and sample.toml "
                                   "(nothing in them reveals the effects); OUTDIR/key.json holds the truth. Cases: "
                                   "one effect each, compound pairs, clean, and non-Gaussian reliefs. Physics: "
                                   "independent Monte-Carlo photon plate through the ray-traced relief, with shot, "
                                   "gain and floor noise.")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--per-effect", type=int, default=2, help="cases per concealed effect (default 2)")
    p.add_argument("--none", type=int, default=4, help="cases with nothing concealed (default 4)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--photons", type=int, default=None, help="photons per incidence (default 600000)")
    p.add_argument("--effects", default=None, help="comma-separated subset of effects")
    return p


def run(args) -> int:
    from relief_bsdf.validation.conceal import EFFECTS_CONCEALABLE, default_cases, generate
    from relief_bsdf.errors import InputError
    from relief_bsdf.progress import TerminalBar, keep_alive
    if args.per_effect < 0 or args.none < 0:
        raise InputError("--per-effect/--none", "case counts must be >= 0")
    cases = default_cases(args.per_effect, args.none, args.seed)
    if args.effects:
        want = [e.strip() for e in args.effects.split(",") if e.strip()]
        bad = [e for e in want if e not in EFFECTS_CONCEALABLE]
        if bad:
            raise InputError("--effects", f"unknown effect(s) {bad}; choose from {', '.join(EFFECTS_CONCEALABLE)}")
        cases = [c for c in cases if set(c.effects) <= set(want)]    # compound cases: every effect asked for
    if args.photons is not None:
        if args.photons < 1000:
            raise InputError("--photons", f"need at least 1000 photons, got {args.photons}")
        for c in cases:
            c.photons = args.photons
    bar = TerminalBar("conceal")
    with keep_alive(bar):
        key = generate(args.out, cases, bar)
    print(f"{len(cases)} cases in {args.out}; key (keep apart) in {key}")
    return 0
