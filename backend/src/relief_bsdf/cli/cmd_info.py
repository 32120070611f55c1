"""`relief info FILE [--json]`: what is in a height map, a BSDF table, a recording or a sample."""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("info", help="summarise a height map, BSDF table (.h5), recording (.csv) or sample (.toml)",
                       description="Summarise a file. Height maps: size, pitch, valid fraction, rms height "
                                   "(after least-squares plane levelling), rms slope (forward differences), "
                                   "correlation length (1/e of the radially averaged autocorrelation).")
    p.add_argument("file", help="height map (x3p, gwy, sur, sdf, datx, plu, opd, di, nid, ibw, mi, frt, tif, exr, "
                                "npz, ...), BSDF table .h5 or WINDOW/Radiance .xml, recording .csv, sample .toml "
                                "or IS-BSDF .bsdf")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--channel", help="height-map channel (index or name) for multi-channel files")
    p.add_argument("--pitch-um", help="lateral pitch DX[,DY] in micrometres (images without sidecar)")
    from relief_bsdf.cli.maps import add_relief_args
    add_relief_args(p)
    return p



def _finite(x):
    """`x` with every non-finite float as None (JSON has no NaN: `--json` output is strict JSON, null)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
        return _finite(x.tolist())
    return x


def _json(d: dict) -> str:
    return json.dumps(_finite(d), default=str, allow_nan=False)

def _kind(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".toml":
        return "sample"
    if suffix == ".bsdf":
        return "is-bsdf"
    if suffix == ".xml":
        return "bsdf"
    from relief_bsdf.io.measured import sniff
    if sniff(path) == "rpc":
        return "measured"
    if suffix in (".h5", ".hdf5"):
        try:
            import h5py
            from relief_bsdf.io.hdf5 import FORMAT
            with h5py.File(path, "r") as f:
                if f.attrs.get("format") == FORMAT:
                    return "bsdf"
        except OSError:
            pass
        return "relief"
    if suffix == ".csv":
        try:
            with open(path, "rb") as f:
                head = f.readline().decode("utf-8-sig", errors="replace").strip()
        except OSError:
            head = ""
        if head.startswith("# relief-recording"):
            return "recording"
        return "relief"
    return "relief"


def _pitch(arg: str | None):
    if not arg:
        return None
    from relief_bsdf.errors import InputError
    try:
        parts = [float(v) * 1e-6 for v in arg.split(",")]
    except ValueError:
        raise InputError("--pitch-um", f"expected DX or DX,DY in micrometres, got {arg!r}") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2:
        raise InputError("--pitch-um", f"expected DX or DX,DY, got {arg!r}")
    return tuple(parts)


def relief_info(relief) -> dict:
    """The JSON object of `relief info` for a height map (formats.md keys first)."""
    from relief_bsdf.surface.stats import relief_stats
    s = relief_stats(relief).as_dict()
    out = {"kind": "relief", "shape": s["shape"], "pitch_m": s["pitch_m"], "valid_fraction": s["valid_fraction"],
           "rms_height_m": s["rms_height_m"], "rms_slope": s["rms_slope"],
           "correlation_length_m": s["correlation_length_m"]}
    for k in ("rms_slope_x", "rms_slope_y", "correlation_length_x_m", "correlation_length_y_m", "skewness",
              "kurtosis", "peak_to_valley_m", "mean_height_m"):
        out[k] = s[k]
    out["size_m"] = list(relief.size_m)
    out["periodic"] = relief.periodic
    if isinstance(relief.metadata, dict) and relief.metadata.get("periodicity"):
        out["periodicity"] = relief.metadata["periodicity"]
    out["history"] = list(relief.history)
    out["source"] = relief.source
    out["metadata"] = relief.metadata
    out.update(measured_map_info(relief))
    out["estimators"] = {"rms_height_m": "std of heights after least-squares plane levelling, valid points",
                         "rms_slope": "rms of forward differences between adjacent valid pixels, "
                                      "sqrt(sx^2 + sy^2)",
                         "correlation_length_m": "1/e point of the radially averaged autocorrelation"}
    return out


def measured_map_info(relief, wavelength_nm: float = 550.0, n: float = 1.5) -> dict:
    """Noise floor (from the PSD), what band-limiting to the propagating band at `wavelength_nm`
    (index n, any incidence) removes, and the spike / anisotropy flags (surface.stats)."""
    from relief_bsdf.surface.stats import band_limited, map_flags, noise_floor, propagating_f_max
    nf = noise_floor(relief)
    fl = map_flags(relief)
    f_max = propagating_f_max(wavelength_nm, n, n, 90.0)
    def finite(v: float) -> float | None:       # strict JSON: undefined (a flat map's) is null, never NaN
        return float(v) if math.isfinite(v) else None
    out = {"noise_floor": {"psd_m4": nf.psd_m4, "rms_m": nf.rms_m, "fraction_of_rms": finite(nf.fraction_of_rms),
                           "slope_rms": nf.slope_rms, "statement": nf.statement()},
           "flags": {"kurtosis": finite(fl.kurtosis), "spiky": fl.spiky, "anisotropy": fl.anisotropy,
                     "anisotropic": fl.anisotropic, "lay_angle_deg": finite(fl.lay_angle_deg),
                     "statements": fl.statements()}}
    if f_max < 0.5 / max(relief.dx_m, relief.dy_m):
        bl = band_limited(relief, f_max)
        out["band_limit"] = {"wavelength_nm": wavelength_nm, "n": n, "f_max_per_m": bl.f_max_per_m,
                             "removed_rms_m": bl.removed_rms_m, "removed_rms_slope": bl.removed_rms_slope,
                             "statement": bl.statement()}
    else:
        out["band_limit"] = {"wavelength_nm": wavelength_nm, "n": n, "f_max_per_m": f_max, "removed_rms_m": 0.0,
                             "removed_rms_slope": 0.0,
                             "statement": f"the pitch resolves only |f| <= {0.5e-6 / max(relief.dx_m, relief.dy_m):.3g}"
                                          f" /um of the {f_max * 1e-6:.3g} /um that scatter at {wavelength_nm:g} nm: "
                                          "wave methods run band-limited (nothing to remove)"}
    return out


def _fmt_len(m: float | None) -> str:
    if m is None or not math.isfinite(m):
        return "n/a"
    a = abs(m)
    if a >= 1e-3:
        return f"{m * 1e3:.4g} mm"
    if a >= 1e-6:
        return f"{m * 1e6:.4g} um"
    return f"{m * 1e9:.4g} nm"


def _print_relief(d: dict) -> None:
    ny, nx = d["shape"]
    dx, dy = d["pitch_m"]
    sx, sy = d["size_m"]
    md = d.get("metadata", {})
    print(f"height map   {d['source']}")
    if md.get("reader"):
        extra = f", channel {md['channel']!r}" if md.get("channel") else ""
        print(f"  read by    {md['reader']}{extra}, heights in file: {md.get('file_unit', '?')}")
    if md.get("instrument"):
        inst = md["instrument"]         # a dict (SurfaceTopography) or a name (io.native_readers)
        print(f"  instrument {inst.get('name', inst) if isinstance(inst, dict) else inst}")
    print(f"  grid       {nx} x {ny} px, pitch {_fmt_len(dx)} x {_fmt_len(dy)}, size {_fmt_len(sx)} x {_fmt_len(sy)}"
          + (" (periodic tile)" if d.get("periodic") else ""))
    filled = [h for h in d.get("history", []) if h.startswith("filled ")]
    print(f"  valid      {d['valid_fraction']:.1%} of the points" + (
        f" ({filled[-1]})" if filled else " (invalid points are kept as holes, not filled; --fill-holes fills them)"
        if d["valid_fraction"] < 1 else ""))
    if d.get("periodicity"):
        from relief_bsdf.surface.periodicity import Periodicity
        print(f"  periodic   {Periodicity(**d['periodicity']).line()}")
    for h in d.get("history", []):
        if not h.startswith(("filled ", "periodicity: ")):
            print(f"  done       {h}")
    print(f"  rms height {_fmt_len(d['rms_height_m'])} (Sq after plane levelling), peak-to-valley "
          f"{_fmt_len(d['peak_to_valley_m'])}")

    def deg(s):
        return f"{math.degrees(math.atan(s)):.3g} deg" if s is not None else "n/a"
    print(f"  rms slope  {d['rms_slope']:.4g} ({deg(d['rms_slope'])}); along x {d['rms_slope_x']:.4g}, "
          f"along y {d['rms_slope_y']:.4g}  [forward differences at the pixel pitch]")
    print(f"  corr. len. {_fmt_len(d['correlation_length_m'])} (1/e of radial ACF); along x "
          f"{_fmt_len(d['correlation_length_x_m'])}, along y {_fmt_len(d['correlation_length_y_m'])}")
    if d["skewness"] is not None:
        print(f"  moments    skewness {d['skewness']:.3g}, kurtosis {d['kurtosis']:.3g} (3 = Gaussian)")
    s = d["rms_height_m"]
    if s:
        g = (4 * math.pi * s / 550e-9) ** 2
        regime = ("smooth: first-order perturbation (Rayleigh-Rice) applies" if g < 0.1 else
                  "rough: geometric optics / Kirchhoff regime" if g > 1 else "intermediate roughness")
        print(f"  at 550 nm  Rayleigh parameter (4 pi Sq / lambda)^2 = {g:.3g} at normal incidence -> {regime}")
    if "noise_floor" in d:
        print(f"  noise      {d['noise_floor']['statement']}")
        print(f"  band       {d['band_limit']['statement']} (550 nm, n 1.5)")
        for line in d["flags"]["statements"]:
            print(f"  FLAG       {line}")


def run(args) -> int:
    from relief_bsdf.errors import InputError
    path = Path(args.file)
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        raise InputError(path, "is a folder; expected a file")
    if not path.is_file():
        raise InputError(path, "not a regular file (a FIFO, socket or device would block or never end)")
    show = {"relief": _info_relief, "bsdf": _info_bsdf, "recording": _info_recording, "sample": _info_sample,
            "is-bsdf": _info_isbsdf, "measured": _info_measured}[_kind(path)]
    return show(path, args)


def print_relief_summary(relief) -> None:
    """`relief info`'s text summary of a relief (statistics, regime, flags, what was done to it)."""
    _print_relief(relief_info(relief))


def _info_relief(path: Path, args) -> int:
    from relief_bsdf.cli.maps import read_map
    relief = read_map(path, args, pitch_m=_pitch(args.pitch_um), channel=args.channel)
    d = relief_info(relief)
    if args.json:
        print(_json(d))
    else:
        _print_relief(d)
    return 0


def _info_bsdf(path: Path, args) -> int:
    from relief_bsdf.io.tables import read_table_file
    tables = read_table_file(path)
    rows = [r for t in tables for r in t.albedo_rows()]
    from relief_bsdf.bsdf.appearance import appearance
    d = {"kind": "bsdf", "method": tables[0].method if tables else None, "albedo": rows,
         "tables": [{k: v for k, v in t.summary().items() if k != "albedo"} for t in tables],
         "appearance": [a.as_dict() for t in tables for a in appearance(t)],
         "energy_defect": {t.incident_from: t.metadata.get("energy_defect") for t in tables
                           if isinstance(t.metadata, dict) and t.metadata.get("energy_defect")},
         "height_band_limit": {t.incident_from: t.metadata.get("height_band_limit") for t in tables
                               if isinstance(t.metadata, dict) and t.metadata.get("height_band_limit")}}
    if args.json:
        print(_json(d))
        return 0
    print(f"BSDF table   {path}  (method {d['method']})")
    for t in tables:
        s = t.summary()
        print(f"  light from {t.incident_from}: {len(s['wavelength_nm'])} wavelength(s) {s['wavelength_nm']} nm, "
              f"theta_i {s['theta_i_deg']} deg, phi_i {s['phi_i_deg']} deg, "
              f"{s['theta_s_cells']} x {s['phi_s_cells']} scatter cells")
        _print_validity(t)
    print("  hemispherical integrals per incidence (R, T include the specular parts; lost = 1 - R - T, signed):")
    print(f"    {'from':8s} {'lambda/nm':>9s} {'theta_i':>7s} {'phi_i':>6s} {'R':>8s} {'T':>8s} "
          f"{'spec R':>8s} {'spec T':>8s} {'lost':>8s}")
    for r in rows:
        print(f"    {r['from']:8s} {r['wavelength_nm']:9.4g} {r['theta_i_deg']:7.3g} {r['phi_i_deg']:6.3g} "
              f"{r['R']:8.4f} {r['T']:8.4f} {r['specular_R']:8.4f} {r['specular_T']:8.4f} {r['lost']:+8.4f}")
    for t in tables:
        ed = t.metadata.get("energy_defect") if isinstance(t.metadata, dict) else None
        if isinstance(ed, dict) and ed.get("meaning") != "absorption" and ed.get("max_abs", 0) > 0.01:
            print(f"  WARNING    light from {t.incident_from}: R + T misses 1 by up to {-ed['worst_signed']:+.2%} "
                  f"({ed['meaning']}; the plate must not read it as absorption)")
    for line in band_limit_lines(tables):
        print(line)
    _print_appearance(d["appearance"])
    return 0


def band_limit_lines(tables) -> list[str]:
    """What a wave method removed from the heights before diffracting them (its metadata
    height_band_limit: components finer than the propagating band, mostly instrument noise), one line
    per distinct statement, for `relief reconstruct` and `relief info TABLE`."""
    said = []
    for t in tables:
        b = t.metadata.get("height_band_limit") if isinstance(t.metadata, dict) else None
        if isinstance(b, dict) and b.get("statement") and b["statement"] not in said:
            said.append(b["statement"])
    return [f"  heights    {s} ({tables[0].method}: finer components scatter into no propagating direction)"
            for s in said]


def _print_appearance(rows: list) -> None:
    print("  appearance (haze: ASTM D1003 share of T deviated > 2.5 deg; clarity (I_C - I_R) / (I_C + I_R), "
          "I_C within 0.1 deg, I_R 0.1-2.5 deg; TIS = diffuse R, T; coherent = specular / total):")
    print(f"    {'from':8s} {'lambda/nm':>9s} {'theta_i':>7s} {'haze':>7s} {'clarity':>7s} {'TIS R':>8s} "
          f"{'TIS T':>8s} {'coh R':>6s} {'coh T':>6s}")
    for a in rows:
        print(f"    {a['incident_from']:8s} {a['wavelength_nm']:9.4g} {a['theta_i_deg']:7.3g} {a['haze']:7.4f} "
              f"{a['clarity']:7.4f} {a['tis_R']:8.4f} {a['tis_T']:8.4f} {a['coherent_fraction_R']:6.3f} "
              f"{a['coherent_fraction_T']:6.3f}")


def _print_validity(table) -> None:
    v = table.metadata.get("validity") if isinstance(table.metadata, dict) else None
    if isinstance(v, dict) and "valid" in v:
        where = ""
        if not v["valid"] and "valid_per_incidence" in v:
            bad = np.argwhere(~np.asarray(v["valid_per_incidence"], bool))
            where = " at " + ", ".join(f"{v['wavelength_nm'][i]:g} nm / {v['theta_i_deg'][j]:g} deg"
                                       for i, j in bad[:4]) + (" ..." if len(bad) > 4 else "")
        print(f"    validity: {'within' if v['valid'] else 'OUTSIDE'} the method's regime{where} "
              f"({v.get('criterion', '')})")


def _info_recording(path: Path, args) -> int:
    from relief_bsdf.io.recording import read_recording
    rec = read_recording(path)
    d = rec.summary()
    if args.json:
        print(_json(d))
        return 0
    print(f"recording    {path}")
    print(f"  rows       {d['rows']} ({d['rows_per_side']['R']} reflected, {d['rows_per_side']['T']} transmitted)")
    print(f"  wavelength {', '.join(f'{w:g}' for w in d['wavelengths_nm'])} nm")
    print(f"  incidences {', '.join(f'({t:g}, {p:g})' for t, p in d['incidences_deg'])} deg (theta_i, phi_i)")
    print(f"  BSDF range {d['bsdf_range_sr'][0]:.4g} .. {d['bsdf_range_sr'][1]:.4g} 1/sr; "
          f"uncertainty given for {d['sigma_known_fraction']:.0%} of the rows")
    for c in rec.comments[:5]:
        print(f"  # {c}")
    return 0


def _info_sample(path: Path, args) -> int:
    from relief_bsdf.io.recording import read_sample
    s = read_sample(path)
    d = s.summary()
    if args.json:
        print(_json(d))
        return 0
    pl = d["plate"]
    idx = pl["index"]
    n = (f"n = {idx['n']}" if idx.get("model") == "constant" else
         f"Cauchy A={idx.get('A')}, B={idx.get('B_nm2')} nm^2, C={idx.get('C_nm4')} nm^4")
    print(f"sample       {path}")
    print(f"  plate      {pl['thickness_mm']} mm, {n}, relief on the {pl['rough_face']} face, absorption "
          + ("not known" if pl["absorption_per_mm"] is None else f"{pl['absorption_per_mm']} /mm"))
    ins = d["instrument"]
    print(f"  instrument detector half-angle {ins['detector_half_angle_deg']} deg "
          f"({ins['detector_solid_angle_sr']:.3g} sr), {ins['polarization']} light")
    ro = d.get("relief_options", {})
    per = {True: "periodic (stated)", False: "not periodic (stated)"}.get(ro.get("periodic"),
                                                                        "periodicity from the file or its test")
    print(f"  relief     {d['relief']}; {per}" + ("; holes filled before use" if ro.get("fill_holes") else ""))
    for f in d["recording_files"]:
        print(f"  recording  {f['path']} ({f['kind']})")
    if d["relative_sigma"] is not None or d["recording_wavelength_nm"] is not None:
        print(f"             relative_sigma {d['relative_sigma']}, wavelength of measured files "
              f"{d['recording_wavelength_nm']} nm")
    if any(f["kind"] != "recording.csv" for f in d["recording_files"]):
        from relief_bsdf.errors import InputError
        try:
            r = s.load_recording().summary()
        except InputError as e:          # the description is shown; what its recording still needs, said
            print(f"  rows       not readable yet: {e.one_line()}")
            return 0
        print(f"  rows       {r['rows']} at {', '.join(f'{w:g}' for w in r['wavelengths_nm'])} nm, incidences "
              f"{', '.join(f'({t:g}, {p:g})' for t, p in r['incidences_deg'])} deg (theta_i, phi_i)")
    return 0


def _info_measured(path: Path, args) -> int:
    """A measured plate file (RPC text, untagged IS-BSDF): io.measured.measured_info."""
    from relief_bsdf.io.measured import measured_info, print_measured_info
    d = measured_info(path)
    if args.json:
        print(_json(d))
    else:
        print_measured_info(d)
    return 0


def _info_isbsdf(path: Path, args) -> int:
    from relief_bsdf.io.isbsdf import read_isbsdf
    from relief_bsdf.io.measured import is_measured
    if is_measured(path):
        return _info_measured(path, args)
    b = read_isbsdf(path)
    d = {"kind": "is-bsdf", "scatter_type": b.scatter_type, "symmetry": b.symmetry,
         "sample_rotation_deg": b.sample_rotation_deg.tolist(), "angle_of_incidence_deg": b.angle_of_incidence_deg.tolist(),
         "azimuths": int(b.azimuth_deg.size), "radials": int(b.radial_deg.size), "tis": b.tis.tolist()}
    if args.json:
        print(_json(d))
    else:
        print(f"IS-BSDF      {path}: {b.scatter_type}, {b.symmetry}, incidences {d['angle_of_incidence_deg']} deg, "
              f"{d['azimuths']} azimuths x {d['radials']} radial angles; TIS {[round(v, 4) for v in b.tis[0]]}")
    return 0
