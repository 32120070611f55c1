"""`relief simulate SAMPLE.toml -o OUTDIR`: the plate as the instrument sees it, on the recording's rows."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> argparse.ArgumentParser:
    from relief_bsdf import defaults
    p = sub.add_parser("simulate", help="simulate the plate of a sample on its recording's rows")
    p.add_argument("sample", help="sample.toml")
    p.add_argument("-o", "--out", required=True, help="output directory (writes simulated.csv)")
    p.add_argument("--method", default=defaults.METHOD,
                   help="boundary BSDF method of the relief face: auto (default: the relief's own physics), any "
                        "`relief reconstruct` method, or the fast surrogate microfacet+dw")
    p.add_argument("--samples", type=int, default=defaults.SAMPLES,
                   help="Monte-Carlo samples per incidence (ray methods)")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed")
    p.add_argument("--height-scale", type=float, default=1.0, help="relief height scale")
    p.add_argument("--filter-sigma-um", type=float, default=0.0, help="Gaussian filter sigma (um)")
    from relief_bsdf.cli import add_sectors_arg
    add_sectors_arg(p)
    p.add_argument("--table", help="use this boundary table file (HDF5, outside+inside) instead of deriving one")
    from relief_bsdf.parallel import add_parallel_args
    add_parallel_args(p)            # --dask, --workers, --checkpoint-dir, --retries
    from relief_bsdf.cli.maps import add_relief_args
    add_relief_args(p)              # over the sample's [relief] periodic / fill_holes
    return p


def run(args) -> int:
    from relief_bsdf.cli.maps import show_prepared, stated_options
    from relief_bsdf.jobs import SimulateJob, run_simulate
    from relief_bsdf.progress import TerminalBar, keep_alive
    job = SimulateJob(Path(args.sample), Path(args.out), method=args.method, samples=args.samples, seed=args.seed,
                      height_scale=args.height_scale, filter_sigma_um=args.filter_sigma_um, sectors=args.sectors,
                      table=Path(args.table) if args.table else None,
                      relief_options=None if args.table else stated_options(args))
    bar = TerminalBar("simulate")
    with keep_alive(bar):
        r = run_simulate(job, bar)
    if r.relief is not None:
        show_prepared(r.relief, args)
    print(f"physics: {r.physics}")
    print(f"wrote {r.path} ({r.rows} rows); metric (rms z) vs recording {r.metric:.4g}")
    return 0
