"""Peak memory and time of the jobs a user waits for, summed over every process (benchmarks/measure.py).

Jobs (each a `relief` command, one at a time, with both cores):
- `diagnose` of validation-set cases (../shared/data/validation: recordings of an engine independent
  of this project), as given (relief.npz, periodic) and, with `--x3p`, the same relief read from its
  relief.x3p as a measured map (mirror-extended); target 4 GB each (the job's default --memory-gb 3.5);
- `fit` of the demo scene (scenes/demo), target 3 GB;
- `reconstruct` of a 2048^2 map with `--method ray` and `--method kirchhoff` at their defaults, 4 GB.

    .venv/bin/python benchmarks/bench_memory.py [--cases case_05,case_12] [--x3p] [--no-fit]
        [--no-reconstruct] [--out DIR]

Prints one line per job and writes benchmarks/results/memory.json (command, machine, figures).
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

from measure import measure_command, write_result

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CASES = REPO.parent / "shared" / "data" / "validation" / "cases"
TARGET_GB = {"diagnose": 4.0, "fit": 3.0, "reconstruct": 4.0}


def relief_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "relief_bsdf.cli", *args]


def x3p_sample(case_dir: Path, work: Path) -> Path:
    """A copy of the case's sample.toml whose relief is its relief.x3p (a measured map: mirror-extended)."""
    d = work / (case_dir.name + "_x3p")
    d.mkdir(parents=True, exist_ok=True)
    for name in ("recording.csv", "relief.x3p"):
        shutil.copy(case_dir / name, d / name)
    text = (case_dir / "sample.toml").read_text().replace('"relief.npz"', '"relief.x3p"')
    (d / "sample.toml").write_text(text)
    return d / "sample.toml"


def run(name: str, kind: str, cmd: list[str], figures: dict) -> None:
    m = measure_command(cmd, stdout=__import__("subprocess").DEVNULL)
    ok = m.returncode == 0 and m.peak_pss_gb <= TARGET_GB[kind]
    figures[name] = {"kind": kind, "wall_s": round(m.wall_s, 1), "peak_pss_gb": round(m.peak_pss_gb, 3),
                     "hwm_sum_gb": round(m.hwm_sum_gb, 3), "sampler_cpu_s": round(m.sampler_cpu_s, 1),
                     "processes": m.peak_processes, "rc": m.returncode, "target_gb": TARGET_GB[kind],
                     "within_target": ok}
    print(f"{name:28s} {m.line()}  target {TARGET_GB[kind]:.0f} GB {'ok' if ok else 'OVER'}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="case_05,case_09,case_12,case_15",
                    help="validation cases to diagnose (comma-separated; 'all' for every case)")
    ap.add_argument("--x3p", action="store_true", help="also diagnose each case from its relief.x3p")
    ap.add_argument("--no-fit", action="store_true")
    ap.add_argument("--no-reconstruct", action="store_true")
    ap.add_argument("--out", default=None, help="keep the jobs' outputs here (default: a temporary folder)")
    a = ap.parse_args(argv)
    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="bench_memory_"))
    cases = sorted(p.name for p in CASES.iterdir()) if a.cases == "all" else a.cases.split(",")
    figures: dict = {}
    for c in cases:
        sample = CASES / c / "sample.toml"
        run(f"diagnose {c}", "diagnose", relief_cmd("diagnose", str(sample), "-o", str(work / c)), figures)
        if a.x3p:
            run(f"diagnose {c} (x3p)", "diagnose",
                relief_cmd("diagnose", str(x3p_sample(CASES / c, work)), "-o", str(work / (c + "_x3p_out"))), figures)
    if not a.no_fit:
        run("fit demo", "fit", relief_cmd("fit", str(REPO / "scenes" / "demo" / "sample.toml"), "-o",
                                          str(work / "fit"), "--max-iter", "40"), figures)
    if not a.no_reconstruct:
        big = work / "big.npz"
        run("synth 2048^2", "reconstruct", relief_cmd("synth", "--kind", "gaussian", "--rms-height-um", "0.5",
                                                      "--corr-length-um", "8", "--size", "2048", "--pitch-um", "0.5",
                                                      "--seed", "1", "-o", str(big)), figures)
        for method in ("ray", "kirchhoff"):
            run(f"reconstruct 2048^2 {method}", "reconstruct",
                relief_cmd("reconstruct", str(big), "--method", method, "-o", str(work / f"t_{method}.h5")), figures)
    path = write_result("memory", figures, "benchmarks/bench_memory.py " + " ".join(argv or sys.argv[1:]))
    print(f"written {path}")
    return 0 if all(f["within_target"] for f in figures.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
