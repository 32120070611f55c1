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
    from relief_bsdf.fit.residual import rms_z
    from relief_bsdf.io.recording import read_sample, write_recording
    sample = read_sample(args.sample)
    rec = sample.load_recording()
    from relief_bsdf.progress import TerminalBar, keep_alive
    with keep_alive(TerminalBar("simulate")):
        sim = _simulate(args, sample, rec)
    o = Path(args.out)
    o.mkdir(parents=True, exist_ok=True)
    m = rms_z(rec.bsdf_sr, rec.sigma_sr, sim.values_per_sr, sim.sigma_per_sr)     # the metric of fit and diagnose
    physics = physics_line(sim.info)
    write_recording(o / "simulated.csv", rec.with_values(sim.values_per_sr, sim.sigma_per_sr),
                    comments=[f"relief simulate {Path(args.sample).name}", f"physics: {physics}",
                              f"metric (rms z) vs recording: {m:.6g}"])
    print(f"physics: {physics}")
    print(f"wrote {o / 'simulated.csv'} ({len(rec)} rows); metric (rms z) vs recording {m:.4g}")
    return 0


def _simulate(args, sample, rec):
    """The sample's Experiment (relief face by --method, or the --table file's tables) through plate.simulate."""
    from dataclasses import replace

    import numpy as np
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.cli.maps import show_prepared, stated_options
    from relief_bsdf.io.heightmaps import read_sample_relief
    from relief_bsdf.plate import TableFace, TableGrid, experiment_from_sample, simulate
    relief = read_sample_relief(sample, stated_options(args)) if not args.table else None
    if relief is not None:
        show_prepared(relief, args)
    exp = experiment_from_sample(sample, relief, method=args.method, samples=args.samples, seed=args.seed)
    if not args.table:
        # the simulation's own sigma as the fit and the diagnosis take it (the relief as read: its tables'
        # relative 1-sigma, scaled with the values), so the metric is theirs at the same parameters
        fwd = Forward(relief, exp, rec, grid=TableGrid(sectors=args.sectors), where=str(sample.recording_path))
        sim = fwd.simulated(args.height_scale, args.filter_sigma_um)
        return replace(sim, sigma_per_sr=fwd.model_rel_sigma() * np.abs(sim.values_per_sr))
    from relief_bsdf.io.hdf5 import load_tables, table_for
    tabs = load_tables(args.table)
    front = sample.plate.rough_face == "front"
    ins = table_for(tabs, "inside", args.table)
    out = table_for(tabs, "outside", args.table) if front else None
    exp = exp.with_plate(**{sample.plate.rough_face: TableFace(ins, out)})
    # the plate's azimuth grid follows the table's azimuth cells (as in `relief fit`)
    grid = TableGrid(phi_step_deg=360.0 / ins.phi_s_deg.size)
    return simulate(exp, rec, grid=grid, where=str(sample.recording_path))


def physics_line(info: dict) -> str:
    """One line naming the physics a simulation used (faces' methods, bulk, engine)."""
    ph = info.get("physics", {})

    def face(d: dict) -> str:
        if d.get("face") == "relief":
            return f"relief by {d.get('method')}" + (f" ({d['chosen_by']})" if d.get("chosen_by") else "")
        return d.get("face", "?") + (f" ({d['method']})" if d.get("method") else "")
    b = ph.get("bulk", {})
    bulk = "absorption {:g}/m, scattering {:g}/m (g {:g})".format(b.get("absorption_per_m", 0.0),
                                                                 b.get("scatter_per_m", 0.0), b.get("hg_g", 0.0))
    sectors = info.get("inside_sectors")
    loop = (f"; loop by azimuth sector ({len(sectors['centres_deg'])} inside sector tables)" if sectors else "")
    return (f"front {face(ph.get('front', {}))}, back {face(ph.get('back', {}))}; bulk {bulk}; "
            f"engine {info.get('engine', '?')}{loop}")
