"""`relief reconstruct`: run one reconstruction method on a relief and write the BSDF tables (HDF5)."""
from __future__ import annotations

import argparse
import json

import numpy as np


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("reconstruct", help="BSDF tables of a rough boundary from its height map",
                       description="Reconstruct the BSDF of the boundary described by RELIEF with one method and "
                                   "write one table per side of incidence to an HDF5 file. The refractive index "
                                   "of the material below the relief is required (--n or --cauchy); the lit "
                                   "medium is air (n = 1).")
    p.add_argument("relief", metavar="RELIEF", help="height map (.x3p, .gwy, .sur, .sdf, .tif, .exr, .npz)")
    from relief_bsdf import defaults
    from relief_bsdf.methods.registry import method_names
    p.add_argument("--method", default=defaults.METHOD,
                   help=" | ".join(method_names()) + " (methods.registry: each method's physics, regime of "
                   "validity and options; auto: chosen from the relief's statistics)")
    p.add_argument("--wavelengths-nm", default=defaults.as_text(defaults.WAVELENGTHS_NM),
                   help="comma-separated vacuum wavelengths")
    p.add_argument("--theta-i-deg", default=defaults.as_text(defaults.THETA_I_DEG),
                   help="incidence angles, degrees in [0, 90)")
    p.add_argument("--phi-i-deg", default="0", help="incidence azimuths (one value: isotropic table)")
    p.add_argument("--from", dest="incident_from", default="outside", choices=("outside", "inside", "both"),
                   help="side the light arrives from")
    idx = p.add_mutually_exclusive_group()
    idx.add_argument("--n", help="refractive index of the material: n or n,k (k >= 0 absorbing)")
    idx.add_argument("--cauchy", help="Cauchy coefficients A,B[,C] (B in nm^2, C in nm^4)")
    p.add_argument("--samples", type=int, default=defaults.SAMPLES,
                   help="rays (paths) per incidence for Monte-Carlo methods")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="random seed")
    p.add_argument("--coherence-length-um", type=float, default=None, help="source coherence length (wave methods)")
    p.add_argument("--theta-step-deg", type=float, default=1.0, help="scatter cell size in theta_s (divides 90)")
    p.add_argument("--phi-step-deg", type=float, default=5.0, help="scatter cell size in phi_s (divides 360); "
                   "cells are centred on phi_s = 0, step, ...")
    p.add_argument("--pitch-um", default=None, help="lateral pitch dx[,dy] in um for files without one (images)")
    p.add_argument("--polarized", action="store_true", help="also compute Mueller matrices (ray, microfacet)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="method option (value parsed as JSON when possible), e.g. distribution=\"ggx\", alpha=0.2, "
                        "grazing_heuristic=smith; repeatable; an option the method does not know is an error")
    p.add_argument("-o", "--out", required=True, help="output table (.h5)")
    from relief_bsdf.cli.maps import add_relief_args
    add_relief_args(p)
    from relief_bsdf.parallel import add_parallel_args
    add_parallel_args(p)            # --dask, --workers, --checkpoint-dir, --retries
    return p


def parse_floats(text: str, flag: str) -> tuple:
    from relief_bsdf.errors import InputError
    try:
        vals = tuple(float(v) for v in str(text).split(",") if v.strip() != "")
    except ValueError:
        raise InputError(flag, f"expected comma-separated numbers, got {text!r}") from None
    if not vals:
        raise InputError(flag, "expected at least one number")
    return vals


def material_from_args(args):
    """Material from --n / --cauchy (formats.md); InputError when missing or unphysical."""
    from relief_bsdf.errors import InputError
    from relief_bsdf.core.index import CauchyIndex, ConstantIndex, Material
    if args.n is None and args.cauchy is None:
        raise InputError("--n/--cauchy", "the refractive index of the material is required (e.g. --n 1.5 or "
                         "--cauchy 1.5046,4200)")
    if args.n is not None:
        v = parse_floats(args.n, "--n")
        if len(v) > 2:
            raise InputError("--n", f"expected n or n,k, got {args.n!r}")
        inside = ConstantIndex(v[0], v[1] if len(v) > 1 else 0.0)
    else:
        v = parse_floats(args.cauchy, "--cauchy")
        if len(v) not in (2, 3):
            raise InputError("--cauchy", f"expected A,B or A,B,C, got {args.cauchy!r}")
        inside = CauchyIndex(*v)
    return Material(inside=inside)


def edges_from_steps(theta_step: float, phi_step: float) -> tuple[tuple, tuple]:
    from relief_bsdf.errors import InputError
    for name, step, span in (("--theta-step-deg", theta_step, 90.0), ("--phi-step-deg", phi_step, 360.0)):
        n = span / step if step > 0 else 0
        if not (step > 0) or abs(n - round(n)) > 1e-9 or round(n) < 1:
            raise InputError(name, f"cell size must divide {span:g} degrees exactly, got {step}")
    nt = int(round(90.0 / theta_step))
    npf = int(round(360.0 / phi_step))
    te = tuple(np.linspace(0.0, 90.0, nt + 1))
    pe = tuple(-phi_step / 2 + phi_step * np.arange(npf + 1))
    return te, pe


#: Python's spellings of JSON's true, false and null, accepted in --option values
PYTHON_WORDS = {"True": True, "False": False, "None": None}


def parse_options(items: list[str]) -> dict:
    from relief_bsdf.errors import InputError
    out = {}
    for it in items:
        if "=" not in it:
            raise InputError("--option", f"expected KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        if v.strip() in PYTHON_WORDS:              # fill_holes=True as well as fill_holes=true
            out[k.strip()] = PYTHON_WORDS[v.strip()]
            continue
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


def build_request(args):
    """The Request of the command line; its options are checked against the method's options class."""
    from relief_bsdf.methods.request import Request
    te, pe = edges_from_steps(args.theta_step_deg, args.phi_step_deg)
    sides = ("outside", "inside") if args.incident_from == "both" else (args.incident_from,)
    opts = parse_options(args.option)
    if args.polarized:
        opts["polarized"] = True
    kw = {}
    if args.samples is not None:
        kw["samples"] = int(args.samples)
    request = Request(wavelengths_nm=parse_floats(args.wavelengths_nm, "--wavelengths-nm"),
                      theta_i_deg=parse_floats(args.theta_i_deg, "--theta-i-deg"),
                      phi_i_deg=parse_floats(args.phi_i_deg, "--phi-i-deg"), incident_from=sides,
                      theta_s_edges_deg=te, phi_s_edges_deg=pe, seed=int(args.seed),
                      coherence_length_m=None if args.coherence_length_um is None else args.coherence_length_um * 1e-6,
                      options=opts, **kw).validate()
    request.options_for(args.method)                 # unknown / mistyped option: exit 2 naming it
    return request


def run(args) -> int:
    from pathlib import Path

    from relief_bsdf.cli.maps import relief_options, show_prepared
    from relief_bsdf.jobs import ReconstructJob, run_reconstruct
    from relief_bsdf.jobs.reconstruct import check_method, check_table_out
    from relief_bsdf.progress import TerminalBar, keep_alive
    out = Path(args.out)
    check_table_out(out)
    check_method(args.method)                        # unknown method: fail before reading anything
    material = material_from_args(args)
    request = build_request(args)
    pitch = None
    if args.pitch_um is not None:
        v = parse_floats(args.pitch_um, "--pitch-um")
        pitch = (v[0] * 1e-6, (v[1] if len(v) > 1 else v[0]) * 1e-6)
    job = ReconstructJob(Path(args.relief), out, material, request, method=args.method, options=relief_options(args),
                         pitch_m=pitch)
    bar = TerminalBar(f"reconstruct {args.method}")
    with keep_alive(bar):
        r = run_reconstruct(job, bar)
    show_prepared(r.relief, args)
    tables = r.tables
    print(f"wrote {out}: method {args.method}" + (f" ({r.chosen})" if r.chosen else "") + f", {len(tables)} table(s)")
    print(f"{'from':8s} {'lambda_nm':>9s} {'theta_i':>7s} {'phi_i':>6s} {'R':>8s} {'T':>8s} {'spec_R':>8s} "
          f"{'spec_T':>8s} {'lost':>8s}")
    for t in tables:
        for r in t.albedo_rows():
            print(f"{r['from']:8s} {r['wavelength_nm']:9g} {r['theta_i_deg']:7g} {r['phi_i_deg']:6g} {r['R']:8.5f} "
                  f"{r['T']:8.5f} {r['specular_R']:8.5f} {r['specular_T']:8.5f} {r['lost']:8.5f}")
    from relief_bsdf.cli.cmd_info import band_limit_lines
    for line in band_limit_lines(tables):          # what the wave method removed from the heights
        print(line.strip())
    return 0
