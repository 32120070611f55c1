"""Speed of the Kirchhoff solver against the raw FFT limit, measured in the same run.

One incidence (30 deg, 550 nm, light from outside, R and T, the default 1 x 5 degree cells
over the whole hemisphere) on a periodic Gaussian relief (rms 0.1 um, correlation length
5 um, pitch 0.1 um: the intermediate regime where Kirchhoff is the method of choice).
Reference: one complex128 2-D FFT of the same size with scipy.fft, workers=2 (what the
notes call the library limit), timed here with the same load.  Also: scaling with size
against N^2 log N, and a colour plot (in-plane BSDF at 450 / 550 / 650 nm of a smoother
relief; PNG next to this script's output directory).

    .venv/bin/python benchmarks/bench_kirchhoff.py [--sizes 512,1024,2048] [--out out/bench]

Last line: one JSON object with seconds_per_incidence, fft_seconds, ratio (and more).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.fft as sfft

from relief_bsdf.methods import kirchhoff
from relief_bsdf.methods.rayleigh_rice import prepared_heights
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.surface.relief import Relief
from relief_bsdf.methods.request import Request
from relief_bsdf.methods.wave_filter import cell_samples, smoothing_width_dcos


def gaussian_relief(n, pitch, rms, corr, seed=0):
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n, pitch)
    amp = np.sqrt(np.exp(-(np.pi * corr) ** 2 * (f[None, :] ** 2 + f[:, None] ** 2)))
    h = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * amp))
    h -= h.mean()
    return Relief(h * rms / h.std(), pitch, pitch, periodic=True, source=f"synthetic {n}")


def best_of(fn, repeat=3):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def time_incidence(n, repeat=3):
    rel = gaussian_relief(n, 0.1e-6, 0.1e-6, 5e-6, seed=1)
    mat = Material(inside=ConstantIndex(1.5))
    req = Request(wavelengths_nm=(550.0,), theta_i_deg=(30.0,))
    width = smoothing_width_dcos(kirchhoff.speckle_dcos(rel, mat, req), req.theta_s_edges_deg)
    kirchhoff.check_sampling(rel, mat, req, width, {})
    h, w = prepared_heights(rel)
    cells = cell_samples(req.theta_s_edges_deg, req.phi_s_edges_deg, width)
    n1, n2 = mat.n_pair(550.0, "outside")
    info = {}

    def run():
        r = kirchhoff.solve_incidence(h, w, (rel.dx_m, rel.dy_m), True, 550.0, 30.0, 0.0, n1, n2, cells, width)
        info.update(r["info"])

    t = best_of(run, repeat)
    a = (np.random.default_rng(0).standard_normal((n, n)) + 1j * np.random.default_rng(1).standard_normal((n, n)))
    sfft.fft2(a, workers=2)
    t_fft = best_of(lambda: sfft.fft2(a, workers=2), max(repeat, 3))
    return t, t_fft, info


def colour_plot(out: Path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from relief_bsdf.methods import reconstruct
    rel = gaussian_relief(512, 0.1e-6, 0.05e-6, 3e-6, seed=6)
    mat = Material(inside=ConstantIndex(1.5))
    req = Request(wavelengths_nm=(450.0, 550.0, 650.0), theta_i_deg=(0.0,),
                  theta_s_edges_deg=tuple(np.linspace(0, 40, 41)), options={"band_limited": True})
    (tab,) = reconstruct(rel, mat, req, "kirchhoff")
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    psa = tab.projected_solid_angle_sr
    for iw, (wl, c) in enumerate(zip(tab.wavelength_nm, ("tab:blue", "tab:green", "tab:red"))):
        ang, vals = tab.in_plane("R", iw=iw)
        ax.semilogy(ang, vals[0], color=c, label=f"{wl:.0f} nm, specular R = {tab.specular_R[iw, 0, 0]:.4f}")
        # encircled reflectance: specular delta + cells inside theta, as a share of all reflected power
        ring = np.cumsum((tab.values_per_sr[iw, 0, 0, 0] * psa).sum(axis=1))
        total = ring[-1] + tab.specular_R[iw, 0, 0]
        ax2.plot(tab.theta_s_edges_deg[1:], (ring + tab.specular_R[iw, 0, 0]) / total, color=c, label=f"{wl:.0f} nm")
    ax.set_xlabel("signed scatter angle (deg)")
    ax.set_ylabel("BRDF (1/sr), diffuse part")
    ax.set_title("Kirchhoff, rms 50 nm, corr 3 um, normal incidence", fontsize=9)
    ax.legend(fontsize=8)
    ax2.set_xlabel("theta_s (deg)")
    ax2.set_ylabel("share of reflected power within theta_s")
    ax2.set_xlim(0, 15)
    ax2.set_title("sharper in the red (more specular, tighter core)", fontsize=9)
    ax2.legend(fontsize=8)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "kirchhoff_colour.png"
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="512,1024,2048")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    rows = []
    for n in sizes:
        t, t_fft, info = time_incidence(n, args.repeat)
        rows.append({"n": n, "seconds": t, "fft_seconds": t_fft, "ratio": t / t_fft,
                     "ffts": info.get("ffts"), "qz_nodes_R": info.get("qz_nodes_R"),
                     "qz_nodes_T": info.get("qz_nodes_T"), "pool": info.get("pool_R")})
        print(f"N={n:5d}  incidence {t * 1e3:8.1f} ms  complex128 FFT {t_fft * 1e3:7.1f} ms  ratio {t / t_fft:5.2f}  "
              f"(FFTs {info.get('ffts')}, q_z nodes R {info.get('qz_nodes_R')} T {info.get('qz_nodes_T')})",
              file=sys.stderr)
    base = rows[0]
    for r in rows:
        nlogn = (r["n"] ** 2 * np.log2(r["n"])) / (base["n"] ** 2 * np.log2(base["n"]))
        r["time_over_n2logn_rel"] = (r["seconds"] / base["seconds"]) / nlogn
    print("scaling (time / N^2 log N, relative to the smallest): "
          + ", ".join(f"{r['n']}: {r['time_over_n2logn_rel']:.2f}" for r in rows), file=sys.stderr)
    png = colour_plot(Path(args.out))
    print(f"colour plot: {png}", file=sys.stderr)
    big = rows[-1]
    print(json.dumps({"benchmark": "kirchhoff", "n": big["n"], "seconds_per_incidence": big["seconds"],
                      "fft_seconds": big["fft_seconds"], "ratio": big["ratio"], "target_ratio": 4.0,
                      "ffts_per_incidence": big["ffts"], "qz_nodes_R": big["qz_nodes_R"],
                      "qz_nodes_T": big["qz_nodes_T"], "scaling": rows, "colour_png": png}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
