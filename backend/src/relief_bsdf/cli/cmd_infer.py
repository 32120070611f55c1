"""`relief infer SAMPLE.toml -o OUTDIR`: a relief for a sample that has none, from its measured plate."""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    from relief_bsdf import defaults
    p = sub.add_parser("infer", help="infer a periodic relief from the sample's measured plate (no height map needed)",
                       description="Inverts the transmitted lobe at the incidence nearest the normal into a "
                                   "facet-slope density (geometric optics through both faces), synthesises a periodic "
                                   "relief with it (random crossed lenslets) and simulates the plate on every "
                                   "recording row: OUTDIR/relief.npz, sample.toml, simulated.csv, infer.json. "
                                   "[relief] file and [plate] refractive_index may be absent (index: 1.5 assumed, "
                                   "stated in infer.json).")
    p.add_argument("sample", help="sample.toml (its [recording] file: recording.csv or measured plate files)")
    p.add_argument("-o", "--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed (relief and rays)")
    p.add_argument("--samples", type=int, default=100_000,
                   help="Monte-Carlo samples per incidence of the ray-traced relief")
    return p


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.errors import InputError
    from relief_bsdf.infer.job import infer
    from relief_bsdf.progress import TerminalBar, keep_alive
    if args.samples < 1000:
        raise InputError("--samples", f"need at least 1000 samples, got {args.samples}")
    bar = TerminalBar("infer")
    with keep_alive(bar):
        doc = infer(args.sample, args.out, seed=args.seed, progress=bar, samples=args.samples)
    o = Path(args.out)
    print(f"family {doc['family']}, rms slope {doc['rms_slope']:.4g}, n = {doc['parameters']['refractive_index']:g}"
          f"{'' if doc['index_stated'] else ' (assumed)'}")
    print(f"metric (rms z) flat plate {doc['rms_before']:.4g} -> inferred relief {doc['rms_after']:.4g}")
    print(f"wrote {o / 'relief.npz'}, {o / 'sample.toml'}, {o / 'simulated.csv'}, {o / 'infer.json'}")
    return 0
