"""Blind diagnosis of concealed-effect cases (issue 6 proof).

Generates seeded cases with `relief_bsdf.validation.conceal` (independent Monte-Carlo photon plate
through the ray-traced height field, realistic noise; one concealed effect or none per
case, the key kept apart), runs `relief_bsdf.diagnose.run.diagnose` on each without the key,
then compares.  Prints one line per case, a summary, and as last line one JSON object with
`cases`, `named_right`, `none_right`, `median_rms_ratio` (over effect cases), parameter
errors and timings.

    .venv/bin/python benchmarks/bench_diagnose.py [--out DIR] [--seed 1] [--per-effect 2] [--none 4]
        [--method microfacet+dw] [--only bulk_absorption,...] [--candidates ...] [--case-photons N]

`--only` keeps the cases of the named effects (and `none`), `--candidates` restricts the
effects the diagnosis tries, `--case-photons` lowers the generator's photons: quick subsets
for day-to-day checks; the full benchmark is the default.  Effects without a fitted
parameter (interreflection, diffraction: a face swap) have no parameter error.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from relief_bsdf.validation.conceal import default_cases, generate
from relief_bsdf.diagnose.forward import DEFAULT_METHOD
from relief_bsdf.diagnose.run import diagnose
from relief_bsdf.parallel import map_tasks

KEY_PARAM = {"bulk_absorption": "absorption_per_mm", "volume_scattering": "scatter_per_mm",
             "back_face_roughness": "back_alpha", "sample_tilt": "tilt_deg", "instrument_blur": "blur_deg",
             "polarization": "polarization_q", "stray_light": "background_per_sr", "relief_scale": "height_scale",
             "relief_smoothing": "filter_sigma_um", "dispersion": "cauchy_B_nm2",
             "interreflection": "interreflection_weight", "diffraction": "coherent_scale",
             "partial_coherence": "coherence_length_um", "refractive_index": "index_offset"}
PARAMETER_FREE = ("interreflection", "diffraction")     # a face swap: the key's weight 1 is the effect itself


def _diag(context, name):
    root, photons, method, candidates = context
    t = time.time()
    r = diagnose(Path(root) / name / "sample.toml", Path(root) / name / "diagnosis", method=method, photons=photons,
                 effects=candidates, workers=1)
    return {"effect": r["effect"], "parameters": r["parameters"], "rms_before": r["rms_before"],
            "rms_after": r["rms_after"], "seconds": time.time() - t,
            "candidates": [(c["effect"], c["score"]) for c in r["candidates"][:3]]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="folder for the cases (default: a temporary one)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--per-effect", type=int, default=2)
    ap.add_argument("--none", type=int, default=4)
    ap.add_argument("--photons", type=int, default=200_000,
                    help="diagnosis: Monte-Carlo samples per incidence of a sampling boundary method")
    ap.add_argument("--method", default=DEFAULT_METHOD, help="boundary method of the diagnosis baseline")
    ap.add_argument("--only", default=None, help="comma-separated effects whose cases are kept (plus none)")
    ap.add_argument("--candidates", default=None, help="comma-separated candidate effects the diagnosis tries")
    ap.add_argument("--case-photons", type=int, default=None, help="generator photons per incidence (default: its own)")
    ap.add_argument("--reuse", action="store_true", help="reuse cases already in --out")
    a = ap.parse_args(argv)
    root = Path(a.out or tempfile.mkdtemp(prefix="bench_diagnose_"))
    cases = default_cases(a.per_effect, a.none, a.seed)
    if a.only:
        keep = set(a.only.split(",")) | {"none"}
        cases = [c for c in cases if c.effect in keep]
    if a.case_photons:
        for c in cases:
            c.photons = int(a.case_photons)
    candidates = a.candidates.split(",") if a.candidates else None
    t0 = time.time()
    if not (a.reuse and (root / "key.json").is_file()):
        generate(root, cases)
    t_gen = time.time() - t0
    keys = {k["case"]: k for k in json.loads((root / "key.json").read_text())["cases"]}
    t1 = time.time()
    res = map_tasks(_diag, [c.name for c in cases], (str(root), a.photons, a.method, candidates), label="diagnose")
    t_diag = time.time() - t1
    named = none_ok = n_none = 0
    ratios, perr = [], {}
    for c, r in zip(cases, res):
        k = keys[c.name]
        ok = r["effect"] == k["effect"]
        named += ok
        if k["effect"] == "none":
            n_none += 1
            none_ok += ok
        else:
            ratios.append(r["rms_after"] / r["rms_before"])
            if ok and k["effect"] not in PARAMETER_FREE:
                p = KEY_PARAM[k["effect"]]
                tv, fv = k["parameters"][p], r["parameters"].get(p, float("nan"))
                perr.setdefault(k["effect"], []).append({"true": round(tv, 5), "fitted": round(fv, 5),
                                                         "rel_error": round(abs(fv - tv) / abs(tv), 4)})
        print(f"{c.name} true={k['effect']:20s} named={r['effect']:20s} {'OK ' if ok else 'BAD'} "
              f"rms {r['rms_before']:.2f}->{r['rms_after']:.2f} true={k['parameters']} fit={r['parameters']} "
              f"top={r['candidates']} {r['seconds']:.0f}s", flush=True)
    n = len(cases)
    summary = {"cases": n, "named_right": named, "named_right_fraction": round(named / n, 4),
               "none_cases": n_none, "none_right": none_ok,
               "median_rms_ratio": round(float(np.median(ratios)), 4) if ratios else None,
               "parameter_errors": perr,
               "median_param_rel_error": round(float(np.median([e["rel_error"] for v in perr.values() for e in v])), 4)
               if perr else None,
               "seconds_generate": round(t_gen, 1), "seconds_diagnose_total": round(t_diag, 1),
               "seconds_per_diagnose_median": round(float(np.median([r["seconds"] for r in res])), 1),
               "method": a.method, "cases_dir": str(root)}
    print(f"named right {named}/{n}, none called none {none_ok}/{n_none}, median rms ratio over effect cases "
          f"{summary['median_rms_ratio']}")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
