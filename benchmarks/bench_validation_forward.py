"""The forward model against the independent validation set's clean recordings.

For every clean case of `../shared/data/validation` (keys.json: effects == ["none"]; an engine that
shares no code with the project, `../shared/notes/independent-validation.md`), `relief simulate` with
its defaults (the `simulate` job: method auto, 200 000 ray samples, seed 0) and the rms z of its rows
against the recording (`fit.residual.rms_z`, the metric of simulate, fit and diagnose: the recording's
sigma and the simulation's own sigma in quadrature), over all rows and per (side, theta_i) group.
Targets: rms z <= 1.2 over all rows and <= 1.5 in every group, for every relief kind.

    PYTHONPATH=backend/src .venv/bin/python benchmarks/bench_validation_forward.py \
        [--validation ../shared/data/validation] [--cases case_06,case_09] [--json OUT.json]

Prints one table row per case (all rows, the worst group, every group over 1.5), then one JSON line;
writes benchmarks/results/bench_validation_forward.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from relief_bsdf.fit.residual import rms_z
from relief_bsdf.io.recording import read_recording
from relief_bsdf.jobs.simulate import SimulateJob, run_simulate

HERE = Path(__file__).resolve().parent
ALL_ROWS_TARGET = 1.2
GROUP_TARGET = 1.5


def clean_cases(root: Path) -> list[tuple[str, str]]:
    """(case, relief family) of every case whose key names no effect."""
    keys = json.loads((root / "keys.json").read_text())["cases"]
    return [(c, k.get("family", "?")) for c, k in sorted(keys.items()) if list(k.get("effects", [])) == ["none"]]


def groups(rec, sim) -> dict[str, float]:
    """rms z per (side, theta_i) group, keyed "R0", "T60", ..."""
    out = {}
    for side in ("R", "T"):
        for t in np.unique(rec.theta_i_deg):
            m = (rec.side == side) & (rec.theta_i_deg == t)
            if m.any():
                out[f"{side}{t:g}"] = rms_z(rec.bsdf_sr[m], rec.sigma_sr[m], sim.bsdf_sr[m], sim.sigma_sr[m])
    return out


def run_case(case_dir: Path, out: Path) -> dict:
    t = time.time()
    res = run_simulate(SimulateJob(case_dir / "sample.toml", out))
    seconds = time.time() - t
    rec = read_recording(case_dir / "recording.csv")
    sim = read_recording(res.path)
    g = groups(rec, sim)
    worst = max(g, key=g.get)
    return {"rms_z": res.metric, "groups": g, "worst_group": worst, "worst_rms_z": g[worst],
            "over_group_target": sorted(k for k, v in g.items() if v > GROUP_TARGET),
            "physics": res.physics, "seconds": round(seconds, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--validation", default=str(HERE.parent.parent / "shared" / "data" / "validation"))
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: every clean case)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    root = Path(a.validation)
    cases = clean_cases(root)
    if a.cases:
        wanted = set(a.cases.split(","))
        cases = [c for c in cases if c[0] in wanted]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case, family in cases:
            r = run_case(root / "cases" / case, Path(tmp) / case)
            r["family"] = family
            results[case] = r
            over = ",".join(f"{k}:{r['groups'][k]:.2f}" for k in r["over_group_target"]) or "-"
            ok = r["rms_z"] <= ALL_ROWS_TARGET and not r["over_group_target"]
            print(f"{case} {family:12s} rms_z={r['rms_z']:.3f} worst={r['worst_group']}:{r['worst_rms_z']:.2f} "
                  f"groups_over_1.5={over} {r['seconds']}s {'meets' if ok else 'MISSES'}", flush=True)
    summary = {"cases": len(results),
               "meet_all_rows": sum(r["rms_z"] <= ALL_ROWS_TARGET for r in results.values()),
               "meet_every_group": sum(not r["over_group_target"] for r in results.values()),
               "per_case": results}
    line = json.dumps(summary, default=float)
    if a.json:
        Path(a.json).write_text(line + "\n")
    sys.path.insert(0, str(HERE))
    from measure import write_result
    command = "benchmarks/bench_validation_forward.py " + " ".join(argv or sys.argv[1:])
    write_result("bench_validation_forward", summary, command)
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
