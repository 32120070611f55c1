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
    from pathlib import Path

    from relief_bsdf.jobs import ConcealJob, run_conceal
    from relief_bsdf.progress import TerminalBar, keep_alive
    effects = tuple(e.strip() for e in args.effects.split(",") if e.strip()) if args.effects else None
    job = ConcealJob(Path(args.out), per_effect=args.per_effect, none=args.none, seed=args.seed,
                     photons=args.photons, effects=effects)
    bar = TerminalBar("conceal")
    with keep_alive(bar):
        r = run_conceal(job, bar)
    print(f"{r.cases} cases in {args.out}; key (keep apart) in {r.key}")
    return 0
