"""`relief fit SAMPLE.toml -o OUTDIR`: optimise the relief's height scale and smoothing against the recording."""
from __future__ import annotations

import argparse
import json
import sys


def add_parser(sub) -> argparse.ArgumentParser:
    from relief_bsdf import defaults
    p = sub.add_parser("fit", help="fit relief height scale and Gaussian filter to the sample's recording")
    p.add_argument("sample", help="sample.toml")
    p.add_argument("-o", "--out", required=True, help="output directory (fit.json, relief, tables, plots, report)")
    p.add_argument("--method", default=defaults.METHOD,
                   help="boundary BSDF method of the relief face: auto (default: the relief's own physics, ray "
                        "tracing or wave optics, chosen once from its statistics), any `relief reconstruct` "
                        "method, or the fast surrogate microfacet+dw")
    p.add_argument("--samples", type=int, default=defaults.SAMPLES,
                   help="Monte-Carlo samples per incidence (ray methods)")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed")
    p.add_argument("--max-iter", type=int, default=60, help="most forward evaluations")
    p.add_argument("--threshold", type=float, default=0.0, help="stop once the metric (rms z) is at or below this")
    p.add_argument("--scale-bounds", default="0.1,10", metavar="MIN,MAX",
                   help="bounds of the height scale (default 0.1,10)")
    p.add_argument("--max-filter-um", type=float, default=None,
                   help="upper bound of the Gaussian filter sigma in um (default: 20 pixel pitches)")
    from relief_bsdf.plate.grid import TableGrid
    p.add_argument("--theta-step-deg", type=float, default=TableGrid.theta_step_deg,
                   help=f"theta cell size of the plate's engine grid (default {TableGrid.theta_step_deg:g}; the "
                        "outside ray tables also get a finer direct grid, plate.grid)")
    p.add_argument("--phi-step-deg", type=float, default=TableGrid.phi_step_deg,
                   help=f"azimuth cell size of the engine grid (default {TableGrid.phi_step_deg:g})")
    p.add_argument("--inside-step-deg", type=float, default=TableGrid.inside_theta_i_step_deg,
                   help=f"step between the incidences of the inside table (default "
                        f"{TableGrid.inside_theta_i_step_deg:g})")
    from relief_bsdf.cli import add_sectors_arg
    add_sectors_arg(p)
    p.add_argument("--progress", action="store_true", help="force the progress bar")
    from relief_bsdf.parallel import add_parallel_args
    add_parallel_args(p)            # --dask, --workers, --checkpoint-dir, --retries
    from relief_bsdf.cli.maps import add_relief_args
    add_relief_args(p)              # over the sample's [relief] periodic / fill_holes
    return p


def run(args) -> int:
    from relief_bsdf.errors import InputError
    from relief_bsdf.cli.maps import stated_options
    from pathlib import Path

    from relief_bsdf.jobs import FitJob, run_fit
    from relief_bsdf.plate import TableGrid
    from relief_bsdf.progress import TerminalBar, keep_alive
    if args.max_iter < 1:
        raise InputError("--max-iter", "must be >= 1")
    if not (0 < args.theta_step_deg <= 10 and 0 < args.phi_step_deg <= 30 and 360 % args.phi_step_deg == 0):
        raise InputError("--theta-step-deg/--phi-step-deg", "theta step in (0, 10], phi step in (0, 30] dividing 360")
    if not 0 < args.inside_step_deg <= 15:
        raise InputError("--inside-step-deg", f"must be in (0, 15], got {args.inside_step_deg:g}")
    grid = TableGrid(args.theta_step_deg, args.phi_step_deg, args.inside_step_deg, sectors=args.sectors)
    job = FitJob(Path(args.sample), Path(args.out), method=args.method, samples=args.samples, seed=args.seed,
                 max_iter=args.max_iter,
                 threshold=args.threshold, grid=grid, scale_bounds=_bounds(args.scale_bounds),
                 max_filter_um=args.max_filter_um, relief_options=stated_options(args))
    bar = TerminalBar("fit", force=args.progress)
    with keep_alive(bar):                 # a log line at once and at least every 30 s (batch logs)
        doc = run_fit(job, bar).doc
    for w in doc.get("warnings", []):
        print(f"relief fit: note: {w}", file=sys.stderr)
    print(json.dumps({k: doc[k] for k in ("rms_before", "rms_after", "parameters", "intervals", "stopped")}))
    return 0


def _bounds(text: str) -> tuple[float, float]:
    from relief_bsdf.errors import InputError
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError("--scale-bounds", f"expected MIN,MAX (two numbers), got {text!r}") from None
    if not (0 < lo < 1 < hi < float("inf")):
        raise InputError("--scale-bounds", f"need 0 < MIN < 1 < MAX, got {text!r}")
    return lo, hi
