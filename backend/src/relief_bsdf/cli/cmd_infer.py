"""`relief infer SAMPLE.toml -o OUTDIR`: a relief for a sample that has none, from its measured plate."""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    from relief_bsdf import defaults
    p = sub.add_parser("infer", help="infer a periodic relief from the sample's measured plate (no height map needed)",
                       description="Inverts the transmitted lobe at the incidence nearest the normal into a "
                                   "facet-slope density (geometric optics through both faces), synthesises a periodic "
                                   "relief with it (random crossed lenslets; relief families chosen by the information "
                                   "criterion), refines its height scale and, when not stated, the refractive index "
                                   "through the plate (68 % intervals): OUTDIR/relief.npz, sample.toml, simulated.csv, "
                                   "boundary.h5 (+ IS-BSDF files), report.html, infer.json. [relief] file and [plate] "
                                   "refractive_index may be absent.")
    p.add_argument("sample", help="sample.toml (its [recording] file: recording.csv or measured plate files)")
    p.add_argument("-o", "--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed (relief and rays)")
    p.add_argument("--samples", type=int, default=100_000,
                   help="Monte-Carlo samples per incidence of the ray-traced relief")
    return p


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.jobs import InferJob, run_infer
    from relief_bsdf.progress import TerminalBar, keep_alive
    bar = TerminalBar("infer")
    with keep_alive(bar):
        r = run_infer(InferJob(Path(args.sample), Path(args.out), seed=args.seed, samples=args.samples), bar)
    doc, o = r.doc, r.out
    print(f"family {doc['family']}, rms slope {doc['rms_slope']:.4g}, n = {doc['parameters']['refractive_index']:g}"
          f"{'' if doc['index_stated'] else ' (fitted)'}")
    print(f"metric (rms z) flat plate {doc['rms_before']:.4g} -> inferred relief {doc['rms_after']:.4g}")
    print(f"wrote {o / 'relief.npz'}, {o / 'sample.toml'}, {o / 'simulated.csv'}, {o / 'boundary.h5'}, "
          f"{o / 'report.html'}, {o / 'infer.json'}")
    return 0
