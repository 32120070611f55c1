"""The blind diagnosis of the independent validation set, scored and tabulated per case.

Scores the diagnoses that `bench_memory.py --cases ... --out DIR` left in DIR (one folder per case, each
with its diagnosis.json) with the validation set's own scorer (`../shared/tools/score_validation.py
--no-run`: it compares with the set's key, which this project never reads), joins the seconds and the
peak memory that bench_memory measured (benchmarks/results/memory.json), prints one Markdown row per
case and the scorer's summary, and writes benchmarks/results/validation_diagnose.json.

    .venv/bin/python benchmarks/bench_memory.py --cases all --no-fit --no-reconstruct --out DIR
    .venv/bin/python benchmarks/validation_diagnose_table.py --out DIR [--log BENCH_MEMORY_OUTPUT ...]

`--log`: bench_memory.py's printed lines (`diagnose case_07  wall_s=... peak_pss_gb=...`), for a run
stopped before it wrote memory.json.  A case without a diagnosis.json (not run, or still running) is
listed as such and scores 0.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

from measure import RESULTS_DIR, write_result

HERE = Path(__file__).resolve().parent
SCORER = HERE.parent.parent / "shared" / "tools" / "score_validation.py"


def _params(case: dict) -> str:
    """'name value (truth t, in/outside the 68 % interval)' for each scored parameter of a case."""
    out = []
    for effect, p in sorted(case.get("params", {}).items()):
        if "state_right" in p:
            out.append(f"{effect} {p.get('value')} (truth {p.get('true')})")
        elif p.get("value") is not None:
            inside = {True: "inside", False: "outside", None: "no"}[p.get("in_interval")]
            out.append(f"{p.get('name')} {p['value']:.4g} (truth {p['true']:.4g}, {inside} its interval)")
    return "; ".join(out) or "-"


def from_logs(paths: list[str]) -> dict:
    """{"diagnose case_XX": {"wall_s", "peak_pss_gb"}} from bench_memory.py's printed lines."""
    out = {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            m = re.match(r"(diagnose case_\d+)\s+wall_s=([\d.]+) peak_pss_gb=([\d.]+)", line)
            if m:
                out[m.group(1)] = {"wall_s": float(m.group(2)), "peak_pss_gb": float(m.group(3))}
    return out


def rows(score: dict, memory: dict) -> list[str]:
    lines = ["| case | relief | concealed | named | rms z before -> after | parameters | s | GB |",
             "|---|---|---|---|---|---|---|---|"]
    for c in score["cases"]:
        m = memory.get(f"diagnose {c['case']}", {})
        if c.get("called") is None:
            lines.append(f"| {c['case'][-2:]} | {c.get('family')} | {c['true']} | not run | - | - | - | - |")
            continue
        mark = "right" if c.get("named_right") else "wrong"
        rms = (f"{c['rms_before']:.3g} -> {c['rms_after']:.3g}" if c.get("rms_before") is not None else "-")
        lines.append(f"| {c['case'][-2:]} | {c.get('family')} | {c['true']} | {c['called']} ({mark}) | {rms} | "
                     f"{_params(c)} | {m.get('wall_s', '-')} | {m.get('peak_pss_gb', '-')} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the folder bench_memory.py wrote the diagnoses to")
    ap.add_argument("--memory", default=str(RESULTS_DIR / "memory.json"),
                    help="bench_memory.py's results (seconds and peak memory per case)")
    ap.add_argument("--log", nargs="*", default=[], help="bench_memory.py's printed output, for a stopped run")
    a = ap.parse_args(argv)
    if not SCORER.exists():
        print(f"{SCORER}: the validation set's scorer is not here (../shared)", file=sys.stderr)
        return 2
    out = Path(a.out)
    score_path = out / "score.json"
    subprocess.run([sys.executable, str(SCORER), "--no-run", "--out", str(out), "--json", str(score_path)],
                   check=True, stdout=subprocess.DEVNULL)
    score = json.loads(score_path.read_text())
    mem_path = Path(a.memory)
    memory = json.loads(mem_path.read_text())["figures"] if mem_path.exists() and not a.log else {}
    memory.update(from_logs(a.log))
    for line in rows(score, memory):
        print(line)
    s = score["summary"]
    print(f"\nnamed right {s['named_right']}/{s['cases']}: clean {s['none_right']}/{s['none_cases']}, "
          f"single effect {s['single_effect_named_right']}/{s['single_effect_cases']}, compound "
          f"{s['compound_named_right']}/{s['compound_cases']}; median rms ratio over the effect cases "
          f"{s['median_rms_ratio_effect_cases']}; truth inside the interval {s['truth_in_interval']}/"
          f"{s['intervals_given']}")
    write_result("validation_diagnose", {"summary": s, "cases": score["cases"],
                                         "seconds_and_memory": {k: v for k, v in memory.items()
                                                                if k.startswith("diagnose ")}},
                 "benchmarks/validation_diagnose_table.py " + " ".join(argv or sys.argv[1:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
