"""`relief synth`: a periodic synthetic random relief (formats.md autocovariance convention)."""
from __future__ import annotations

import argparse


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("synth", help="write a periodic synthetic random relief",
                       description="Periodic random relief by FFT filtering of white noise. Autocovariance "
                                   "s^2 exp(-r^2/L^2) (gaussian; rms slope magnitude 2 s / L) or s^2 exp(-r/L) "
                                   "(exponential). The realisation's rms height is normalised to exactly s.")
    p.add_argument("--kind", choices=("gaussian", "exponential"), default="gaussian")
    p.add_argument("--rms-height-um", type=float, required=True, help="rms height s in micrometres")
    p.add_argument("--corr-length-um", type=float, required=True, help="correlation length L in micrometres")
    p.add_argument("--size", type=int, required=True, help="grid size N (N x N pixels)")
    p.add_argument("--pitch-um", type=float, required=True, help="pixel pitch in micrometres")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--anisotropy", type=float, default=1.0, help="correlation length factor along --angle-deg")
    p.add_argument("--angle-deg", type=float, default=0.0, help="direction of the stretched axis from +x")
    p.add_argument("-o", "--out", required=True, help="output file: .x3p, .npz, .exr or .tif")
    return p


def run(args) -> int:
    from ..errors import InputError
    from ..readers import WRITE_SUFFIXES, write_relief
    from ..stats import relief_stats
    from ..synth import random_relief
    from pathlib import Path
    out = Path(args.out)
    if out.suffix.lower() not in WRITE_SUFFIXES:
        raise InputError(out, f"unsupported output type {out.suffix or '(none)'}; use one of {', '.join(WRITE_SUFFIXES)}")
    r = random_relief(args.size, args.pitch_um * 1e-6, args.rms_height_um * 1e-6, args.corr_length_um * 1e-6,
                      kind=args.kind, seed=args.seed, anisotropy=args.anisotropy, angle_deg=args.angle_deg)
    write_relief(out, r)
    s = relief_stats(r)
    print(f"wrote {out}: {args.kind} relief {args.size} x {args.size} px at {args.pitch_um:g} um; "
          f"rms height {s.rms_height_m * 1e9:.4g} nm, rms slope {s.rms_slope:.4g} "
          f"(requested {2 * args.rms_height_um / args.corr_length_um:.4g} for gaussian), "
          f"correlation length {s.correlation_length_m * 1e6:.4g} um")
    return 0
