"""Forward model vs an independent photon Monte Carlo through the real relief.

For each relief case: a clean recording made by the validation's photon engine
(`validation.record.trace_recording`: the relief triangulated and ray traced with Embree by
`conceal.HeightFieldFace`, its own transport loop and detector; nothing of plate/ or methods/)
at `--photons` photons per incidence (4 million by default), and the deterministic forward model
`plate.simulate(experiment, rows)` with `ReliefFace(method="ray")` on the same relief, on
`TableGrid` grids and ray samples given on the command line.  Reported per case and grid:

- rms z over all rows, R and T, theta_i 0-75 deg: z = (forward - recording) / sigma, sigma = the
  recording's sigma (its Monte-Carlo 1-sigma, floored at the one-photon level where the cone
  caught nothing; `trace_recording`), and the same split by side and by lobe / tail (in-lobe:
  recording >= 5 % of its incidence-and-side maximum);
- the worst rows (where and how the forward misses) and the forward's seconds;
- `--seeds 2`: the forward at two ray seeds, rms z between them = the table's own Monte-Carlo
  noise as seen on the recording's rows (sigma = recording sigma again);
- the generator's convergence (`--check-generator`): two independent runs of the recording at
  `--photons` each: rms z between them must be ~ sqrt(2) (noise only), and the generator at
  max_hits 20 vs 40 (inter-reflection depth).

Cases (geometric regime: rough on the wavelength scale, features >> 550 nm): Gaussian reliefs
of rms slope 0.12 / 0.24 / 0.35 with n 1.45 / 1.53 / 1.6, 1 / 2 / 3 mm, cones 1.5 / 2 / 2.5 deg;
light-guide dots (spherical caps with micro-roughness), exponential autocorrelation, two
scales, anisotropic (3:1 at 30 deg, scanned in-plane), and a measured map
(tests/data/topography/ST_x3p-2.x3p, levelled, cropped, its heights x 3 to bring its rms
slope from 0.06 into the range, mirrored into a periodic tile: see `measured_tile`).

    PYTHONPATH=backend/src RELIEF_BACKEND=serial python benchmarks/bench_forward_accuracy.py \
        --cases gauss_mid --grids 1,5,5 0.5,5,2.5 --photons 4000000 [--samples 200000] [--json out.json]

Grid specs: "default" = TableGrid(); "old" = the single-grid engine
(TableGrid(1, 5, 5, direct_theta_step_deg=None, inside_samples_scale=1)); "t,p,i[,s][,nodirect]".
`--cache DIR` keeps the independent recordings (rec_<case>_<photons>_<theta_i>.npz) for re-runs.
Runtime: the photon run is ~7 s per million photons per incidence on one core (256^2 relief),
so 4 M photons x 6 incidences is ~3 minutes per case; run cases one at a time on a shared machine.

The default grid (plate.grid) and the evidence that chose it: docs/decisions/018-forward-grid.md.

"""
from __future__ import annotations

import sys

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
THETA_I = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)
THETA_S = tuple(np.arange(1.0, 89.0, 2.0))


@dataclass(frozen=True)
class Case:
    """A relief and the plate and instrument it is recorded on."""

    name: str
    n_glass: float
    thickness_mm: float
    half_angle_deg: float


CASES = {
    "gauss_low": Case("gauss_low", 1.45, 1.0, 1.5),
    "gauss_mid": Case("gauss_mid", 1.53, 2.0, 2.0),
    "gauss_high": Case("gauss_high", 1.60, 3.0, 2.5),
    "dots": Case("dots", 1.49, 2.0, 2.0),
    "exponential": Case("exponential", 1.50, 2.0, 2.0),
    "two_scales": Case("two_scales", 1.50, 1.5, 2.0),
    "anisotropic": Case("anisotropic", 1.50, 2.0, 2.0),
    "measured": Case("measured", 1.52, 1.1, 2.0),
}


def measured_tile(n: int = 160, height_scale: float = 3.0):
    """ST_x3p-2.x3p (a real instrument map), plane-levelled, its central n x n crop, heights x
    `height_scale`, mirrored into a 2n x 2n periodic tile (validation.conceal.measured_tile)."""
    from relief_bsdf.validation.conceal import measured_tile as tile
    return tile(crop_n=n, height_scale=height_scale)


def make_relief(name: str, seed: int = 11):
    """The case's relief (periodic tile, ~256^2; seeded)."""
    from relief_bsdf.surface.relief import Relief
    from relief_bsdf.surface.synth import DotPattern, RandomFieldSpec, lgp_dots, random_relief, relief_from_spec
    um = 1e-6
    if name.startswith("gauss_"):
        slope = {"gauss_low": 0.12, "gauss_mid": 0.24, "gauss_high": 0.35}[name]
        return random_relief(256, 1 * um, slope * 10 * um / 2, 10 * um, "gaussian", seed=seed)
    if name == "dots":
        d = lgp_dots(256, 1 * um, DotPattern(24 * um, 8 * um, 2.0 * um, micro_rms_m=0.3 * um, micro_corr_m=5 * um),
                     seed=seed)
        return d
    if name == "exponential":
        return random_relief(256, 1 * um, 0.7 * um, 12 * um, "exponential", seed=seed)
    if name == "two_scales":
        a = random_relief(256, 1 * um, 1.6 * um, 25 * um, "gaussian", seed=seed).heights_m
        b = random_relief(256, 1 * um, 0.4 * um, 5 * um, "gaussian", seed=seed + 1).heights_m
        return Relief(a + b, um, um, periodic=True, source="two scales: 1.6 um / 25 um + 0.4 um / 5 um")
    if name == "anisotropic":
        return relief_from_spec(RandomFieldSpec(256, 256, 1 * um, 1.2 * um, 8 * um, anisotropy=3.0, angle_deg=30.0),
                                seed)
    if name == "measured":
        return measured_tile()
    raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")


def rows_of(theta_i=THETA_I, theta_s=THETA_S):
    from relief_bsdf.plate import in_plane_rows
    return in_plane_rows(550.0, list(theta_i), list(theta_s))


def independent(relief, case: Case, rows, photons: int, seed: int, max_hits: int = 20):
    from relief_bsdf.validation.photon import PlatePhysics
    from relief_bsdf.validation.record import trace_recording
    phys = PlatePhysics(thickness_mm=case.thickness_mm, n_glass=case.n_glass)
    return trace_recording(relief, rows, phys, case.half_angle_deg, photons, seed=seed, max_hits=max_hits)


def forward(relief, case: Case, rows, grid, samples: int, seed: int = 0):
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, simulate
    ex = Experiment(Plate(case.thickness_mm * 1e-3, ConstantIndex(case.n_glass),
                          ReliefFace(relief, method="ray", samples=samples, seed=seed), FlatFace()),
                    Instrument(detector_half_angle_deg=case.half_angle_deg))
    return simulate(ex, rows, grid=grid).values_per_sr


def zstats(model, rec, sigma, rows) -> dict:
    """rms z overall, by side, in-lobe / tail, and the five worst rows."""
    z = (np.asarray(model) - rec) / sigma
    side = np.asarray(rows.side).astype(str)
    ti = np.asarray(rows.theta_i_deg, float)
    peak = np.zeros_like(rec)
    for s in ("R", "T"):
        for t in np.unique(ti):
            m = (side == s) & (ti == t)
            peak[m] = rec[m].max()
    lobe = rec >= 0.05 * peak

    def rms(m):
        return float(np.sqrt(np.mean(z[m] ** 2))) if m.any() else float("nan")
    worst = np.argsort(-np.abs(z))[:5]
    model = np.asarray(model, float)
    # the forward's level against the recording per side: in-lobe sum ratio, per incidence and pooled
    # (the systematic that shifts every scan of a side alike, which the intervals' nuisance level holds)
    level = {}
    for s in ("R", "T"):
        m = lobe & (side == s)
        level[s] = {"pooled": float(model[m].sum() / rec[m].sum()) if m.any() else float("nan"),
                    "by_theta_i": {f"{t:g}": float(model[m & (ti == t)].sum() / rec[m & (ti == t)].sum())
                                   for t in np.unique(ti[m])}}
    # the forward's lobe WIDTH against the recording per side: the in-lobe rows of each incidence as one
    # in-plane line (signed angle x = theta_s on the phi_i + 180 side, -theta_s on the other), width =
    # the rms spread of x weighted by the values, forward / recording on the same rows (the systematic
    # a slope parameter, height scale or filter, meets: plate.uncertainty.FORWARD_WIDTH_SD)
    ps = np.asarray(rows.phi_s_deg, float)
    x = np.where(np.isclose(np.mod(ps - np.asarray(rows.phi_i_deg, float), 360.0), 180.0),
                 np.asarray(rows.theta_s_deg, float), -np.asarray(rows.theta_s_deg, float))

    def spread(v, m):
        w = np.maximum(v[m], 0.0)
        c = np.sum(w * x[m]) / np.sum(w)
        return float(np.sqrt(np.sum(w * (x[m] - c) ** 2) / np.sum(w)))
    width = {}
    for s in ("R", "T"):
        by = {}
        for t in np.unique(ti):
            m = lobe & (side == s) & (ti == t)
            if m.sum() >= 3:
                by[f"{t:g}"] = spread(model, m) / spread(rec, m)
        width[s] = {"mean": float(np.mean(list(by.values()))) if by else float("nan"), "by_theta_i": by}
    return {"rms_z": rms(np.ones(z.size, bool)), "rms_z_R": rms(side == "R"), "rms_z_T": rms(side == "T"),
            "rms_z_lobe": rms(lobe), "rms_z_tail": rms(~lobe), "level": level, "width": width,
            "worst": [{"side": side[k], "theta_i": ti[k], "theta_s": float(rows.theta_s_deg[k]),
                       "phi_s": float(rows.phi_s_deg[k]), "model": float(model[k]), "recording": float(rec[k]),
                       "sigma": float(sigma[k]), "z": float(z[k])} for k in worst]}


def parse_grid(spec: str):
    """"default": TableGrid(); "old": the single-grid engine (1,5,5, no direct grid, linear in the inside
    incidences); "t,p,i[,s]": TableGrid(theta_step_deg=t, phi_step_deg=p, inside_theta_i_step_deg=i[,
    inside_samples_scale=s]) with the default direct grid; trailing ",nodirect" drops the direct grid,
    ",linear" blends the inside tables between their incidences (lobes
    that do not move); ",sectors=7.5" the inside sector tables' azimuth step, ",sectors=always" the sector
    tables for every ray-traced relief (TableGrid.sectors), ",spread=45" the loop's inside table averaged over
    +-45 deg of incidence azimuth (TableGrid.inside_azimuth_spread_deg; 45 by default,
    ",spread=0" the table at its own azimuth); "default,linear" too."""
    from relief_bsdf.plate import TableGrid
    parts = spec.split(",")
    kw = {}
    while parts[-1] in ("nodirect", "linear") or parts[-1].startswith(("sectors=", "spread=")):
        last = parts.pop()
        if last.startswith("spread="):
            kw["inside_azimuth_spread_deg"] = float(last.split("=")[1])
        elif last == "nodirect":
            kw["direct_theta_step_deg"] = None
        elif last == "linear":
            kw["inside_interpolation"] = "linear"
        elif last == "sectors=always":
            kw["sectors"] = "always"
        else:
            kw["sector_step_deg"] = float(last.split("=")[1])
    if parts == ["default"]:
        return TableGrid(**kw)
    if parts == ["old"]:
        return TableGrid(1.0, 5.0, 5.0, direct_theta_step_deg=None, inside_samples_scale=1.0,
                         inside_interpolation="linear")
    v = [float(x) for x in parts]
    if len(v) > 3:
        kw["inside_samples_scale"] = v[3]
    return TableGrid(theta_step_deg=v[0], phi_step_deg=v[1], inside_theta_i_step_deg=v[2], **kw)


def run_case(name: str, args) -> dict:
    from relief_bsdf.surface.stats import rms_height_and_slope
    case = CASES[name]
    relief = make_relief(name, args.relief_seed)
    rows = rows_of(args.theta_i)
    h, m = rms_height_and_slope(relief)
    out = {"case": name, "relief": {"shape": list(relief.shape), "rms_height_um": h * 1e6, "rms_slope": m},
           "theta_i_deg": list(args.theta_i),
           "plate": case.__dict__, "photons": args.photons, "grids": []}
    t0 = time.time()
    tag = "" if args.relief_seed == 11 else f"_relief{args.relief_seed}"
    cache = Path(args.cache) / f"rec_{name}{tag}_{args.photons}_{'_'.join(f'{t:g}' for t in args.theta_i)}.npz" \
        if args.cache else None
    if cache is not None and cache.exists():
        d = np.load(cache)
        rec, sig, info = d["rec"], d["sig"], {"cached": str(cache)}
    else:
        rec, sig, info = independent(relief, case, rows, args.photons, seed=1)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            np.savez(cache, rec=rec, sig=sig)
    out["generator"] = {"seconds": time.time() - t0, **info}
    if args.check_generator:
        rec2, sig2, _ = independent(relief, case, rows, args.photons, seed=2)
        out["generator"]["rms_z_two_seeds"] = zstats(rec2, rec, np.hypot(sig, sig2), rows)["rms_z"]
        rec3, sig3, _ = independent(relief, case, rows, args.photons, seed=3, max_hits=40)
        out["generator"]["rms_z_max_hits_40"] = zstats(rec3, rec, np.hypot(sig, sig3), rows)["rms_z"]
    print(f"{name}: rms slope {m:.3f}, generator {out['generator']['seconds']:.0f} s", flush=True)
    for spec in args.grids:
        grid = parse_grid(spec)
        for samples in args.samples:
            t0 = time.time()
            vals = forward(relief, case, rows, grid, samples, seed=0)
            row = {"grid": spec, "samples": samples, "seconds": time.time() - t0, **zstats(vals, rec, sig, rows)}
            if args.seeds > 1:
                v2 = forward(relief, case, rows, grid, samples, seed=1)
                row["rms_z_forward_seed_to_seed"] = zstats(v2, vals, sig, rows)["rms_z"]
            out["grids"].append(row)
            print(f"  grid {spec:14s} samples {samples:>8d}: rms z {row['rms_z']:.2f} (R {row['rms_z_R']:.2f}, "
                  f"T {row['rms_z_T']:.2f}; lobe {row['rms_z_lobe']:.2f}, tail {row['rms_z_tail']:.2f})"
                  + (f", seed-to-seed {row['rms_z_forward_seed_to_seed']:.2f}" if args.seeds > 1 else "")
                  + f"  {row['seconds']:.0f} s", flush=True)
            print("     in-lobe level forward / recording: " + ", ".join(
                f"{sd} {row['level'][sd]['pooled']:.4f} (" + " ".join(f"{k}:{v:.3f}" for k, v in row['level'][sd]['by_theta_i'].items()) + ")"
                for sd in ("R", "T")), flush=True)
            print("     in-lobe width forward / recording: " + ", ".join(
                f"{sd} {row['width'][sd]['mean']:.4f} (" + " ".join(f"{k}:{v:.3f}" for k, v in row['width'][sd]['by_theta_i'].items()) + ")"
                for sd in ("R", "T")), flush=True)
            w = row["worst"][0]
            print(f"     worst: {w['side']} ti {w['theta_i']:g} ts {w['theta_s']:g} phi {w['phi_s']:g}: "
                  f"model {w['model']:.4g} rec {w['recording']:.4g} +- {w['sigma']:.2g} (z {w['z']:.1f})", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    ap.add_argument("--grids", nargs="+", default=["1,5,5"])
    ap.add_argument("--samples", nargs="+", type=int, default=[200_000])
    ap.add_argument("--photons", type=int, default=4_000_000)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--relief-seed", type=int, default=11,
                    help="the synthetic reliefs' realisation (11: the one every grid choice was made on; the "
                         "measured map has none)")
    ap.add_argument("--check-generator", action="store_true")
    ap.add_argument("--theta-i", type=lambda v: tuple(float(x) for x in v.split(",")), default=THETA_I,
                    help="incidences, comma separated (default 0,15,...,75)")
    ap.add_argument("--json")
    ap.add_argument("--cache", help="folder where the independent recordings are kept and re-used")
    args = ap.parse_args(argv)
    results = [run_case(c, args) for c in args.cases]
    print("\n| case | rms slope | n | t mm | cone deg | grid t,p,i | ray samples | rms z | R | T | lobe | tail | "
          "forward s |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        p = r["plate"]
        for g in r["grids"]:
            print(f"| {r['case']} | {r['relief']['rms_slope']:.3f} | {p['n_glass']:g} | {p['thickness_mm']:g} | "
                  f"{p['half_angle_deg']:g} | {g['grid']} | {g['samples']} | {g['rms_z']:.2f} | {g['rms_z_R']:.2f} | "
                  f"{g['rms_z_T']:.2f} | {g['rms_z_lobe']:.2f} | {g['rms_z_tail']:.2f} | {g['seconds']:.0f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    from measure import bench
    sys.exit(bench("bench_forward_accuracy", main))
