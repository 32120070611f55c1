"""Run every reconstruction method on ONE relief and compare them: figure + table.

For a periodic Gaussian relief (`synth.random_relief`; defaults: rms height 0.34 um, correlation
length 4 um, i.e. per-axis rms slope 0.12, pitch 0.25 um, 256 x 256 px, n = 1.5, 550 nm) the
methods microfacet, normals, ray, kirchhoff and rayleigh-rice are run for light from outside and
inside at the requested incidences.  Written:

- OUT.png: top row, in-plane BSDF curves (plane of incidence, signed angle; < 0 is the
  phi_i + 180 half-plane) of R and T from outside and inside at one incidence, one line per
  method; bottom row, hemispherical R and T (cells + delta parts) against theta_i per method,
  and `lost` (what the model does not send out: single-scattering deficit, band limit).
- OUT.csv: the table, one row per (method, side of incidence, theta_i): R, T, specular_R,
  specular_T, lost, seconds.
- stdout: the same table as text, then one JSON object (all figures) as the last line.

Validity is each method's own business (a 0.34 um relief is outside Rayleigh-Rice's first-order
regime, which the figure then shows); `--rms-height-um 0.005 --corr-length-um 1 --pitch-um 0.08`
gives the regime where the wave methods agree and ray refuses (tile too small is avoided by
`--size`).  A method that refuses the relief (RequestError) is listed with its reason.

    .venv/bin/python benchmarks/compare_methods.py [-o compare_methods.png] [--theta-i-deg 0,30,60]
        [--rms-height-um 0.34] [--corr-length-um 4] [--pitch-um 0.25] [--size 256] [--samples 100000]
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from relief_bsdf.report import plots

from relief_bsdf.surface import synth
from relief_bsdf.errors import InputError, RequestError
from relief_bsdf.methods import reconstruct
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request

METHODS = ("microfacet", "normals", "ray", "kirchhoff", "rayleigh-rice")
OPTIONS = {"microfacet": {}, "normals": {}, "ray": {"polarized": False}, "kirchhoff": {"band_limited": True},
           "rayleigh-rice": {"polarized": False}}
STYLE = {"microfacet": ("C0", "-"), "normals": ("C1", "--"), "ray": ("k", "-"), "kirchhoff": ("C2", "-."),
         "rayleigh-rice": ("C3", ":")}


def _floats(text: str) -> tuple:
    return tuple(float(v) for v in text.split(",") if v.strip())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--out", default="compare_methods.png")
    ap.add_argument("--theta-i-deg", default="0,30,60")
    ap.add_argument("--rms-height-um", type=float, default=0.34)
    ap.add_argument("--corr-length-um", type=float, default=4.0)
    ap.add_argument("--pitch-um", type=float, default=0.25)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--n", type=float, default=1.5)
    ap.add_argument("--wavelength-nm", type=float, default=550.0)
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--plot-theta-i-deg", type=float, default=30.0, help="incidence of the in-plane curves")
    a = ap.parse_args(argv)

    relief = synth.random_relief(a.size, a.pitch_um * 1e-6, a.rms_height_um * 1e-6, a.corr_length_um * 1e-6,
                                 seed=a.seed)
    material = Material(inside=ConstantIndex(a.n))
    thetas = _floats(a.theta_i_deg)
    req = Request(wavelengths_nm=(a.wavelength_nm,), theta_i_deg=thetas, phi_i_deg=(0.0,),
                  incident_from=("outside", "inside"), theta_s_edges_deg=tuple(np.linspace(0.0, 90.0, 46)),
                  phi_s_edges_deg=tuple(np.arange(-5.0, 360.0, 10.0)), samples=a.samples, seed=a.seed)
    tables, seconds, refused = {}, {}, {}
    for m in METHODS:
        t0 = time.perf_counter()
        try:
            out = reconstruct(relief, material, Request(**{**req.__dict__, "options": dict(OPTIONS[m])}), m)
        except (RequestError, InputError) as e:
            refused[m] = str(e)
            print(f"{m}: refused: {e}", file=sys.stderr)
            continue
        seconds[m] = time.perf_counter() - t0
        tables[m] = {t.incident_from: t for t in out}

    rows = []
    for m, tabs in tables.items():
        for frm in ("outside", "inside"):
            h = tabs[frm].hemispherical()
            for i, ti in enumerate(thetas):
                rows.append({"method": m, "from": frm, "theta_i_deg": ti,
                             **{k: float(h[k][0, i, 0]) for k in ("R", "T", "specular_R", "specular_T", "lost")},
                             "seconds": round(seconds[m], 3)})

    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(2, 4, figsize=(22, 9.5))
    ip = int(np.argmin(np.abs(np.asarray(thetas) - a.plot_theta_i_deg)))
    for col, (frm, side) in enumerate((("outside", "R"), ("outside", "T"), ("inside", "R"), ("inside", "T"))):
        ax = axs[0, col]
        for m, tabs in tables.items():
            t = tabs[frm]
            one = t.__class__(**{**t.__dict__, "theta_i_deg": t.theta_i_deg[ip:ip + 1],
                                 "values_per_sr": t.values_per_sr[:, ip:ip + 1],
                                 "specular_R": t.specular_R[:, ip:ip + 1], "specular_T": t.specular_T[:, ip:ip + 1],
                                 "lost": t.lost[:, ip:ip + 1], "sigma_per_sr": None, "mueller_per_sr": None,
                                 "specular_mueller_R": None, "specular_mueller_T": None})
            c, ls = STYLE[m]
            plots.plot_in_plane(ax, one, side, style=plots.CurveStyle(linestyle=ls, label_prefix=f"{m} ", colors=(c,)))
        ax.legend(fontsize=7)
    for col, (frm, key) in enumerate((("outside", "R"), ("outside", "T"), ("inside", "R"), ("inside", "T"))):
        ax = axs[1, col]
        for m in tables:
            c, ls = STYLE[m]
            sel = [r for r in rows if r["method"] == m and r["from"] == frm]
            ax.plot([r["theta_i_deg"] for r in sel], [r[key] for r in sel], ls, color=c, marker="o", label=m)
            ax.plot([r["theta_i_deg"] for r in sel], [r["lost"] for r in sel], ls, color=c, marker="x", alpha=0.4)
        big = [r["method"] for r in rows if r["from"] == frm and r[key] > 1.05]
        ax.set_ylim(0.0, 1.05)                 # a method outside its regime may exceed 1: named, not drawn
        if big:
            ax.text(0.02, 0.5, "off scale (> 1): " + ", ".join(sorted(set(big))), transform=ax.transAxes, fontsize=8)
        ax.set_xlabel("theta_i (deg)")
        ax.set_ylabel(f"hemispherical {key} (o), lost (x)")
        ax.set_title(f"{key}, light from {frm}", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"one relief, every method: s = {a.rms_height_um:g} um, L = {a.corr_length_um:g} um, "
                 f"pitch {a.pitch_um:g} um, {a.size} px, n = {a.n:g}, {a.wavelength_nm:g} nm"
                 + (f"; refused: {', '.join(refused)}" if refused else ""), fontsize=10)
    fig.tight_layout()
    out = plots.save_figure(fig, a.out)

    csv_path = Path(a.out).with_suffix(".csv")
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["method"])
        w.writeheader()
        w.writerows(rows)
    print(f"{'method':<14}{'from':<9}{'theta_i':>8}{'R':>9}{'T':>9}{'spec_R':>9}{'spec_T':>9}{'lost':>9}")
    for r in rows:
        print(f"{r['method']:<14}{r['from']:<9}{r['theta_i_deg']:>8g}{r['R']:>9.4f}{r['T']:>9.4f}"
              f"{r['specular_R']:>9.4f}{r['specular_T']:>9.4f}{r['lost']:>9.4f}")
    print(f"wrote {out} and {csv_path}", file=sys.stderr)
    print(json.dumps({"rows": rows, "seconds": seconds, "refused": refused}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
