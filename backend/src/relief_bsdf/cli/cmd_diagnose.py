"""`relief diagnose SAMPLE.toml -o OUTDIR`: name the physics the simulation leaves out."""
from __future__ import annotations

import argparse
import json


def add_parser(sub) -> argparse.ArgumentParser:
    from relief_bsdf import defaults
    p = sub.add_parser("diagnose", help="locate the simulation/recording mismatch and name the missing physics",
                       description="Simulates the plate as sample.toml describes it, locates where it misses the "
                                   "recording, fits every candidate effect (one module each in "
                                   "relief_bsdf.diagnose.effects: absorption, back-face roughness, tilt, blur, "
                                   "polarisation, stray light, relief scale/smoothing, index, dispersion, "
                                   "interreflection, diffraction, partial coherence, ...) on the one plate model and "
                                   "names every effect present by a stepwise BIC selection with a noise-consistency "
                                   "gate (joint refit, 68 % intervals); an effect sample.toml states is held "
                                   "fixed. Writes OUTDIR/diagnosis.json and "
                                   "OUTDIR/report.html.")
    p.add_argument("sample", help="sample.toml")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--method", default=None,
                   help="boundary BSDF method of the baseline's relief face (default: that of `relief fit`, "
                        "auto: the relief's own physics; or any `relief reconstruct` method or surrogate)")
    p.add_argument("--photons", type=int, default=defaults.SAMPLES,
                   help="Monte-Carlo samples per incidence of a sampling boundary method (ray, normals)")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed")
    p.add_argument("--effects", default=None, help="comma-separated subset of candidate effects")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: every core)")
    p.add_argument("--json", action="store_true", help="print diagnosis.json on stdout")
    from relief_bsdf.cli import add_sectors_arg
    add_sectors_arg(p)
    from relief_bsdf.parallel import add_parallel_args
    add_parallel_args(p)            # --dask, --checkpoint-dir, --retries; --workers is its own
    return p


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.errors import InputError
    from relief_bsdf.jobs import DiagnoseJob, run_diagnose
    from relief_bsdf.plate import DEFAULT_METHOD
    from relief_bsdf.progress import TerminalBar, keep_alive
    if args.photons < 1000:
        raise InputError("--photons", f"need at least 1000 photons per incidence, got {args.photons}")
    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
    bar = TerminalBar("diagnose")
    with keep_alive(bar):                 # a log line at once and at least every 30 s
        r = run_diagnose(DiagnoseJob(Path(args.sample), Path(args.out), method=args.method or DEFAULT_METHOD,
                                     photons=args.photons, seed=args.seed,
                                     effects=tuple(effects) if effects is not None else None, workers=args.workers,
                                     sectors=args.sectors), bar).doc
    if args.json:
        print(json.dumps(r, indent=1))
    else:
        print(f"{' + '.join(r['effects'])}: metric (rms z) {r['rms_before']:.3f} -> {r['rms_after']:.3f} "
              f"{json.dumps(r['parameters'])} 68 % intervals {json.dumps(r['intervals'])}")
        print(r["explanation"])
    return 0
