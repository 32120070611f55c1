"""`relief synth`: a periodic synthetic relief.

--kind gaussian|exponential: random surface (formats.md autocovariance convention,
`synth.random_relief`).  --kind dots: light-guide-plate dot pattern on a jittered square
grid (`synth.lgp_dots`): spherical caps or Gaussian bumps (pits with a negative height),
spacing given directly (--dot-pitch-um) or through the area fill factor (--fill-factor).
"""
from __future__ import annotations

import argparse
import math

RANDOM_KINDS = ("gaussian", "exponential")
# options that belong to one family only (argparse default None = "not given")
RANDOM_ONLY = ("rms_height_um", "corr_length_um", "anisotropy", "angle_deg")
DOTS_ONLY = ("dot_radius_um", "dot_height_um", "dot_pitch_um", "fill_factor", "dot_shape", "jitter",
             "micro_rms_um", "micro_corr_um")
# synth.lgp_dots names its arguments in words; the CLI error names the option
_DOT_KEYS = {"pitch": "--pitch-um", "dot pitch": "--dot-pitch-um", "dot radius": "--dot-radius-um",
             "dot height": "--dot-height-um", "jitter": "--jitter", "shape": "--dot-shape",
             "size": "--size", "rms height": "--micro-rms-um", "correlation length": "--micro-corr-um"}


def _opt(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("synth", help="write a periodic synthetic relief (random surface or light-guide dots)",
                       description="Periodic synthetic relief. gaussian / exponential: random surface by FFT "
                                   "filtering of white noise, autocovariance s^2 exp(-r^2/L^2) (gaussian; rms slope "
                                   "magnitude 2 s / L) or s^2 exp(-r/L) (exponential); the realisation's rms height "
                                   "is normalised to exactly s. dots: light-guide-plate dots (spherical caps or "
                                   "Gaussian bumps, pits if the height is negative) on a jittered square grid.")
    p.add_argument("--kind", choices=RANDOM_KINDS + ("dots",), default="gaussian")
    p.add_argument("--size", type=int, required=True, help="grid size N (N x N pixels)")
    p.add_argument("--pitch-um", type=float, required=True, help="pixel pitch in micrometres")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--out", required=True, help="output file: .x3p, .npz, .exr or .tif")
    g = p.add_argument_group("random surface (--kind gaussian|exponential)")
    g.add_argument("--rms-height-um", type=float, help="rms height s in micrometres (required)")
    g.add_argument("--corr-length-um", type=float, help="correlation length L in micrometres (required)")
    g.add_argument("--anisotropy", type=float, help="correlation length factor along --angle-deg (default 1)")
    g.add_argument("--angle-deg", type=float, help="direction of the stretched axis from +x (default 0)")
    d = p.add_argument_group("light-guide dots (--kind dots)")
    d.add_argument("--dot-radius-um", type=float, help="dot base radius a in micrometres (required; for "
                                                       "--dot-shape gaussian the 1/e^2 radius, dot cut at 2a)")
    d.add_argument("--dot-height-um", type=float, help="dot height h in micrometres (required; negative: pits)")
    d.add_argument("--dot-pitch-um", type=float, help="centre-to-centre dot spacing in micrometres "
                                                      "(this or --fill-factor)")
    d.add_argument("--fill-factor", type=float, help="fraction of the area covered by dots, in (0, 1): sets the "
                                                     "spacing to sqrt(pi r^2 / f), r = a (cap) or 2a (gaussian); the spacing is "
                                                     "then rounded to a whole number of dots per tile and the "
                                                     "realised fill factor is printed")
    d.add_argument("--dot-shape", choices=("cap", "gaussian"), help="dot profile (default cap: spherical cap)")
    d.add_argument("--jitter", type=float, help="random displacement of each dot, fraction of the spacing "
                                                "(default 0.2)")
    d.add_argument("--micro-rms-um", type=float, help="Gaussian micro-roughness inside the dots, rms in "
                                                      "micrometres (default 0: smooth dots)")
    d.add_argument("--micro-corr-um", type=float, help="correlation length of that micro-roughness in "
                                                       "micrometres (default 4 pixels)")
    return p


def _given(args, names) -> list[str]:
    return [_opt(n) for n in names if getattr(args, n, None) is not None]


def _check_family(args) -> None:
    from relief_bsdf.errors import InputError
    if args.kind == "dots":
        wrong = _given(args, RANDOM_ONLY)
        if wrong:
            raise InputError(wrong[0], "applies to --kind gaussian|exponential only, not to --kind dots "
                                       "(roughness inside the dots: --micro-rms-um / --micro-corr-um)")
        for name in ("dot_radius_um", "dot_height_um"):
            if getattr(args, name) is None:
                raise InputError(_opt(name), "required for --kind dots")
        if (args.dot_pitch_um is None) == (args.fill_factor is None):
            raise InputError("--dot-pitch-um", "give exactly one of --dot-pitch-um and --fill-factor for --kind dots")
        if args.micro_corr_um is not None and not args.micro_rms_um:
            raise InputError("--micro-corr-um", "needs --micro-rms-um > 0")
    else:
        wrong = _given(args, DOTS_ONLY)
        if wrong:
            raise InputError(wrong[0], f"applies to --kind dots only, not to --kind {args.kind}")
        for name in ("rms_height_um", "corr_length_um"):
            if getattr(args, name) is None:
                raise InputError(_opt(name), f"required for --kind {args.kind}")


def dot_spacing_um(dot_radius_um: float, fill_factor: float, shape: str) -> float:
    """Dot spacing (um) giving an area fill factor f: one dot of footprint pi r^2 per spacing^2,
    r = a for a cap, 2a for a Gaussian bump (cut at 2a)."""
    from relief_bsdf.errors import InputError
    if not (math.isfinite(fill_factor) and 0 < fill_factor < 1):
        raise InputError("--fill-factor", f"must be in (0, 1), got {fill_factor!r}")
    if not (math.isfinite(dot_radius_um) and dot_radius_um > 0):
        raise InputError("--dot-radius-um", f"must be a positive number, got {dot_radius_um!r}")
    reach = dot_radius_um * (2.0 if shape == "gaussian" else 1.0)
    return math.sqrt(math.pi * reach * reach / fill_factor)


def _dots(args):
    from relief_bsdf.errors import InputError
    from relief_bsdf.surface.synth import DotPattern, lgp_dots
    shape = args.dot_shape or "cap"
    if args.size < 4:
        raise InputError("--size", f"grid size must be at least 4 pixels, got {args.size}")
    spacing = (args.dot_pitch_um if args.fill_factor is None
               else dot_spacing_um(args.dot_radius_um, args.fill_factor, shape))
    micro = args.micro_rms_um or 0.0
    if not (math.isfinite(micro) and micro >= 0):
        raise InputError("--micro-rms-um", f"must be >= 0, got {micro!r}")
    if args.micro_corr_um is not None and not (math.isfinite(args.micro_corr_um) and args.micro_corr_um > 0):
        raise InputError("--micro-corr-um", f"must be a positive number, got {args.micro_corr_um!r}")
    try:
        dots = DotPattern(spacing * 1e-6, args.dot_radius_um * 1e-6, args.dot_height_um * 1e-6, shape=shape,
                          jitter=0.2 if args.jitter is None else args.jitter, micro_rms_m=micro * 1e-6,
                          micro_corr_m=None if args.micro_corr_um is None else args.micro_corr_um * 1e-6)
        return lgp_dots(args.size, args.pitch_um * 1e-6, dots, seed=args.seed)
    except InputError as e:
        opt = _DOT_KEYS.get(e.where or "", e.where)
        if opt == "--dot-pitch-um" and args.fill_factor is not None:
            opt = "--fill-factor"
        extra = f" (spacing {spacing:.4g} um from --fill-factor {args.fill_factor:g})" \
            if args.fill_factor is not None and opt in ("--dot-radius-um", "--fill-factor") else ""
        raise InputError(opt, e.message + extra) from None


def run(args) -> int:
    from relief_bsdf.errors import InputError
    from relief_bsdf.io.heightmaps import WRITE_SUFFIXES, write_relief
    from relief_bsdf.surface.stats import relief_stats
    from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec
    from pathlib import Path
    out = Path(args.out)
    if out.suffix.lower() not in WRITE_SUFFIXES:
        raise InputError(out, f"unsupported output type {out.suffix or '(none)'}; use one of {', '.join(WRITE_SUFFIXES)}")
    _check_family(args)
    if args.kind == "dots":
        r = _dots(args)
        write_relief(out, r)
        m = r.metadata
        print(f"wrote {out}: {m['dot_count']} {m['shape']} dots {args.size} x {args.size} px at {args.pitch_um:g} um; "
              f"radius {args.dot_radius_um:g} um, height {args.dot_height_um:g} um, spacing "
              f"{m['dot_pitch_m'][0] * 1e6:.4g} x {m['dot_pitch_m'][1] * 1e6:.4g} um, fill factor "
              f"{m['fill_fraction']:.4g}" + (f" (requested {args.fill_factor:g})" if args.fill_factor else ""))
        return 0
    anisotropy = 1.0 if args.anisotropy is None else args.anisotropy
    angle = 0.0 if args.angle_deg is None else args.angle_deg
    spec = RandomFieldSpec(nx=args.size, ny=args.size, pitch_m=args.pitch_um * 1e-6,
                           rms_height_m=args.rms_height_um * 1e-6, corr_length_m=args.corr_length_um * 1e-6,
                           kind=args.kind, anisotropy=anisotropy, angle_deg=angle)
    r = relief_from_spec(spec, seed=args.seed)
    write_relief(out, r)
    s = relief_stats(r)
    print(f"wrote {out}: {args.kind} relief {args.size} x {args.size} px at {args.pitch_um:g} um; "
          f"rms height {s.rms_height_m * 1e9:.4g} nm, rms slope {s.rms_slope:.4g} "
          f"(requested {2 * args.rms_height_um / args.corr_length_um:.4g} for gaussian), "
          f"correlation length {s.correlation_length_m * 1e6:.4g} um")
    return 0
