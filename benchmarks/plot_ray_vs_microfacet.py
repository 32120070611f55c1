"""Figure: where the single-scattering microfacet model departs from ray tracing the relief.

For periodic Gaussian reliefs of growing rms slope (per axis 0.05 ... 0.5), n = 1.5, the
`ray` tables are compared with Walter 2007 / Beckmann (Smith G) at alpha = the rms slope
magnitude measured on the traced facets.  Left: in-plane BSDF (R from inside at 60 degrees,
where light trapped between facets matters most) for a low and a high slope.  Right: the
relative difference of the lobe (cells above half the model's maximum) and of the
hemispherical totals vs slope, for R and T from both sides at 60 degrees.

    .venv/bin/python benchmarks/plot_ray_vs_microfacet.py [-o ray_vs_microfacet.png] [--samples N]

Prints one JSON object (the curves) as its last line.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from relief_bsdf.surface.mesh import build_tile_mesh
from relief_bsdf.methods import microfacet as mf
from relief_bsdf.methods import ray
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief

TE = tuple(np.linspace(0.0, 90.0, 31))
PE = tuple(np.arange(-7.5, 360.0, 15.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("-o", "--out", default="ray_vs_microfacet.png")
    ap.add_argument("--samples", type=int, default=100000)
    ap.add_argument("--size", type=int, default=192)
    a = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    slopes = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5)
    L = 8e-6
    glass = Material(ConstantIndex(1.5))
    req = Request(theta_i_deg=(60.0,), incident_from=("outside", "inside"), samples=a.samples,
                  theta_s_edges_deg=TE, phi_s_edges_deg=PE, options={"polarized": False})
    curves = {f"{side}_{k}": {"lobe": [], "hemi": []} for side in ("outside", "inside") for k in "RT"}
    inplane = {}
    alphas = []
    wi = np.array([[np.sin(np.radians(60.0)), 0.0, np.cos(np.radians(60.0))]])
    for s in slopes:
        relief = random_relief(a.size, 1e-6, s * np.sqrt(2) * L / 2, L, seed=5)
        nrm = build_tile_mesh(relief).triangle_normals().astype(float)
        alpha = float(np.sqrt(np.mean((nrm[:, 0] ** 2 + nrm[:, 1] ** 2) / nrm[:, 2] ** 2)))
        alphas.append(alpha)
        for tab in ray.reconstruct(relief, glass, req):
            n_i, n_t = (1.0, 1.5) if tab.incident_from == "outside" else (1.5, 1.0)
            psa = tab.projected_solid_angle_sr
            for k, side in enumerate("RT"):
                ref = mf.cell_average(lambda wo: mf.walter_bsdf(wi, wo, n_i, n_t, mf.Roughness(alpha)), TE, PE, side, 6)
                v = tab.values_per_sr[0, 0, 0, k]
                c = curves[f"{tab.incident_from}_{side}"]
                if np.sum(ref * psa) < 0.01:              # no lobe to compare (e.g. T past the critical angle)
                    c["lobe"].append(float("nan"))
                    c["hemi"].append(float("nan"))
                    continue
                lobe = ref > 0.5 * ref.max()
                c["lobe"].append(float(np.sum(v[lobe] - ref[lobe]) / np.sum(ref[lobe])))
                c["hemi"].append(float((np.sum(v * psa) - np.sum(ref * psa)) / max(np.sum(ref * psa), 1e-12)))
                if tab.incident_from == "inside" and side == "R" and s in (0.1, 0.5):
                    a0 = int(np.argmin(np.abs(tab.phi_s_deg - 0.0)))
                    a1 = int(np.argmin(np.abs(tab.phi_s_deg - 180.0)))
                    ang = np.concatenate([-tab.theta_s_deg[::-1], tab.theta_s_deg])
                    inplane[s] = (ang, np.concatenate([v[::-1, a1], v[:, a0]]),
                                  np.concatenate([ref[::-1, a1], ref[:, a0]]))

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2))
    for s, (ang, v, ref) in inplane.items():
        ax0.semilogy(ang, np.maximum(v, 1e-4), "-", label=f"ray, slope {s}/axis")
        ax0.semilogy(ang, np.maximum(ref, 1e-4), "--", label=f"Walter/Beckmann, slope {s}/axis")
    ax0.set_xlabel("signed scatter angle (deg), negative = specular side")
    ax0.set_ylabel("BRDF from inside (1/sr), theta_i = 60")
    ax0.legend(fontsize=8)
    for key, c in curves.items():
        ax1.plot(slopes, 100 * np.asarray(c["lobe"]), "o-", label=f"{key} lobe")
    ax1.plot(slopes, 100 * np.asarray(curves["inside_R"]["hemi"]), "k:", label="inside_R hemispherical")
    ax1.axhspan(-5, 5, color="0.9", zorder=0)
    ax1.set_xlabel("rms slope per axis")
    ax1.set_ylabel("ray - microfacet (% of microfacet), theta_i = 60")
    ax1.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")
    print(json.dumps({"slopes_per_axis": slopes, "alpha_measured": alphas, "curves": curves}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
