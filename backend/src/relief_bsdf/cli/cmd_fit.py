"""`relief fit SAMPLE.toml -o OUTDIR`: optimise the relief's height scale and smoothing against the recording."""
from __future__ import annotations

import argparse
import json


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("fit", help="fit relief height scale and Gaussian filter to the sample's recording")
    p.add_argument("sample", help="sample.toml")
    p.add_argument("-o", "--out", required=True, help="output directory (fit.json, relief, tables, plots, report)")
    p.add_argument("--method", default="microfacet+dw",
                   help="boundary BSDF method: microfacet+dw (default, fast), or any `relief reconstruct` method")
    p.add_argument("--samples", type=int, default=200_000, help="Monte-Carlo samples per incidence (ray methods)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-iter", type=int, default=60, help="most forward evaluations")
    p.add_argument("--threshold", type=float, default=0.0, help="stop once the metric is at or below this")
    p.add_argument("--theta-step-deg", type=float, default=1.0, help="boundary table theta cell size")
    p.add_argument("--phi-step-deg", type=float, default=5.0,
                   help="boundary table azimuth cell size (also the plate's azimuth grid)")
    p.add_argument("--inside-step-deg", type=float, default=5.0,
                   help="step between the incidences of the inside table (narrow lobes: 1-2)")
    p.add_argument("--progress", action="store_true", help="force the progress bar")
    from relief_bsdf.parallel import add_parallel_args
    add_parallel_args(p)            # --dask, --workers, --checkpoint-dir, --retries (issue 8)
    return p


def run(args) -> int:
    from relief_bsdf.errors import InputError
    from relief_bsdf.fit.optimise import FitJob, run_fit_job
    from relief_bsdf.plate import TableGrid
    from relief_bsdf.progress import TerminalBar
    if args.max_iter < 1:
        raise InputError("--max-iter", "must be >= 1")
    if not (0 < args.theta_step_deg <= 10 and 0 < args.phi_step_deg <= 30 and 360 % args.phi_step_deg == 0):
        raise InputError("--theta-step-deg/--phi-step-deg", "theta step in (0, 10], phi step in (0, 30] dividing 360")
    if not 0 < args.inside_step_deg <= 15:
        raise InputError("--inside-step-deg", f"must be in (0, 15], got {args.inside_step_deg:g}")
    grid = TableGrid(args.theta_step_deg, args.phi_step_deg, args.inside_step_deg)
    job = FitJob(method=args.method, samples=args.samples, seed=args.seed, max_iter=args.max_iter,
                 threshold=args.threshold, grid=grid)
    doc = run_fit_job(args.sample, args.out, job, progress=TerminalBar("fit", force=args.progress))
    print(json.dumps({k: doc[k] for k in ("rms_before", "rms_after", "parameters", "stopped")}))
    return 0
