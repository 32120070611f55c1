"""`relief infer` on known reliefs: the validation set's clean cases with the relief file withheld.

For each case (../shared/data/validation/cases, whose key in keys.json says effects == ["none"]), the
relief is withheld: a sample.toml is written as a user without a height map would write it (the
case's plate, instrument and recording, no [relief] file), and `relief infer` infers a relief from
the incidence nearest the normal alone (the recordings are in-plane scans phi_s 0/180: the inversion
reads that cut as an isotropic lobe, infer.slopes.isotropic_reading).  The job's final simulation of
every recording row predicts the five other incidences (the refinement read theta_i = 0 only).  Per
case: rms z per incidence (fit.residual.rms_z, the project's metric), and the inferred relief's rms
slope per axis, sqrt((rms_x^2 + rms_y^2) / 2), against the key's `relief.file.rms_slope_pooled`
(target: within 3 %).  One case at a time, each job in its own process (time and peak PSS measured).

    .venv/bin/python benchmarks/bench_infer_validation.py [--cases case_09 case_16 ...] [--out DIR]

Writes benchmarks/results/bench_infer_validation.json (benchmarks/measure.py's bench).  Without
--cases: every clean case of keys.json.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

from measure import bench, measure_command

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
VALIDATION = REPO.parent / "shared" / "data" / "validation"
TARGET_SLOPE_REL = 0.03


def clean_cases(keys: dict) -> list[str]:
    return sorted(k for k, v in keys["cases"].items() if list(v.get("effects", [])) == ["none"])


def withheld_sample(case_dir: Path) -> str:
    """The case's sample.toml without its relief file (the [relief] table kept empty), the recording by
    its absolute path."""
    text = (case_dir / "sample.toml").read_text()
    text = re.sub(r'(?m)^file\s*=\s*"relief\.[a-z0-9]+"\s*\n', "", text)
    return re.sub(r'(?m)^file\s*=\s*"recording\.csv"', f'file = "{(case_dir / "recording.csv").as_posix()}"', text)


def per_incidence_rms_z(rec, values) -> dict:
    from relief_bsdf.fit.residual import rms_z
    out = {}
    for ti, pi in rec.incidences():
        sel = (rec.theta_i_deg == ti) & (rec.phi_i_deg == pi)
        out[f"{ti:g}"] = rms_z(rec.bsdf_sr[sel], rec.sigma_sr[sel], values[sel])
    return out


def run_case(case: str, key: dict, work: Path) -> dict:
    import numpy as np
    from relief_bsdf.io.heightmaps import read_relief
    from relief_bsdf.io.recording import read_recording
    from relief_bsdf.surface.stats import rms_slope_xy
    case_dir = VALIDATION / "cases" / case
    w = work / case
    w.mkdir(parents=True, exist_ok=True)
    (w / "sample.toml").write_text(withheld_sample(case_dir))
    job = measure_command(["nice", "-n", "5", sys.executable, "-m", "relief_bsdf.cli", "infer", str(w / "sample.toml"),
                           "-o", str(w / "out")])
    if job.returncode != 0:
        return {"case": case, "returncode": job.returncode}
    doc = json.loads((w / "out" / "infer.json").read_text())
    rec = read_recording(case_dir / "recording.csv")
    sim = read_recording(w / "out" / "simulated.csv")
    rx, ry = rms_slope_xy(read_relief(w / "out" / "relief.npz"))
    pooled = float(np.sqrt((rx * rx + ry * ry) / 2))
    truth = key["relief"]["file"]
    rel = pooled / truth["rms_slope_pooled"] - 1.0
    return {"case": case, "family_key": key["family"], "infer_s": round(job.wall_s, 1),
            "infer_peak_pss_gb": round(job.peak_pss_gb, 3), "candidate": doc["candidate"],
            "height_scale": doc["parameters"]["height_scale"], "intervals": doc["intervals"],
            "rms_z_by_theta_i": per_incidence_rms_z(rec, sim.bsdf_sr), "rms_after": doc["rms_after"],
            "rms_before": doc["rms_before"], "rms_slope_per_axis": pooled, "rms_slope_xy": [rx, ry],
            "key_rms_slope_pooled": truth["rms_slope_pooled"], "key_rms_slope_xy": truth["rms_slope_xy"],
            "rms_slope_rel_error": rel, "rms_slope_within_target": bool(abs(rel) <= TARGET_SLOPE_REL),
            "reading": doc["inverted_from"].get("reading"),
            "half_asymmetry_over_peak": doc["inverted_from"].get("half_asymmetry_over_peak")}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", help="case names (default: every clean case of keys.json)")
    ap.add_argument("--out", help="work folder (default: a temporary one)")
    a = ap.parse_args(argv)
    keys = json.loads((VALIDATION / "keys.json").read_text())
    clean = clean_cases(keys)
    cases = a.cases or clean
    for c in cases:
        if c not in clean:
            print(f"bench_infer_validation: error: {c} is not a clean case (keys.json effects != ['none'])",
                  file=sys.stderr)
            return 2
    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="bench_infer_validation_"))
    results = []
    for c in cases:
        r = run_case(c, keys["cases"][c], work)
        results.append(r)
        print(json.dumps(r), file=sys.stderr, flush=True)
    print(json.dumps({"cases": results, "target_rms_slope_rel": TARGET_SLOPE_REL}))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    sys.exit(bench("bench_infer_validation", main))
