"""report.html of `relief diagnose`: residual maps before/after and in-plane curves, PNGs embedded.

Residuals are the noise-normalised z = (measured - simulated) / s of `mismatch.residual_z`.
"""
from __future__ import annotations

import base64
import io
import json
import math
from pathlib import Path

import numpy as np

from relief_bsdf.diagnose.mismatch import residual_z
from relief_bsdf.io.atomic import write_text_atomic

__all__ = ["write_report"]


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _residual_map(rows, v, s, title, ax):
    z = residual_z(rows, v, s)
    keys = sorted({(float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]),
                    float(rows.phi_s_deg[k])) for k in range(len(z))})
    ths = np.unique(rows.theta_s_deg)
    img = np.full((len(keys), len(ths)), np.nan)
    kidx = {k: i for i, k in enumerate(keys)}
    for k in range(len(z)):
        key = (float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]), float(rows.phi_s_deg[k]))
        img[kidx[key], np.searchsorted(ths, rows.theta_s_deg[k])] = z[k]
    im = ax.imshow(img, aspect="auto", cmap="RdBu_r", vmin=-5, vmax=5, interpolation="nearest")
    ax.set_yticks(range(len(keys)))
    ax.set_yticklabels([f"{k[1]} ti={k[2]:g} ps={k[3]:g}" + (f" {k[0]:g}nm" if len({q[0] for q in keys}) > 1 else "")
                        for k in keys], fontsize=6)
    step = max(1, len(ths) // 10)
    ax.set_xticks(range(0, len(ths), step))
    ax.set_xticklabels([f"{t:g}" for t in ths[::step]], fontsize=7)
    ax.set_xlabel("theta_s (deg)")
    ax.set_title(title, fontsize=9)
    return im


def _candidate_row(c: dict, esc) -> str:
    if c.get("skipped"):
        return f"<tr><td>{esc(c['effect'])}</td><td colspan=3>not tried: {esc(c['skipped'])}</td></tr>"
    return (f"<tr><td>{esc(c['effect'])}</td><td>{c['rms_after']:.3f}</td><td>{c['score']:.1f}</td>"
            f"<td>{esc(json.dumps(c['parameters']))}</td></tr>")


def write_report(path: Path, rows, v0, s0, v1, s1, result: dict) -> Path:
    """report.html: residual maps (before/after) and in-plane curves, PNGs embedded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(1, 2, figsize=(11, 0.18 * len(np.unique(np.stack([rows.side, rows.theta_i_deg.astype(str),
                                                                           rows.phi_s_deg.astype(str),
                                                                           rows.wavelength_nm.astype(str)], 1),
                                                                 axis=0)) + 2))
    _residual_map(rows, v0, s0, f"baseline residual / sigma (rms {result['rms_before']:.2f})", axs[0])
    im = _residual_map(rows, v1, s1, f"with {result['effect']} (rms {result['rms_after']:.2f})", axs[1])
    fig.colorbar(im, ax=axs, shrink=0.6, label="(measured - simulated) / sigma")
    maps = _png(fig)
    # in-plane curves: signed angle theta_s * (+1 at phi_s = 0, -1 at 180)
    groups = sorted({(float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]))
                     for k in range(len(rows))})
    ncol = 3
    nrow = int(math.ceil(len(groups) / ncol))
    fig, axs = plt.subplots(nrow, ncol, figsize=(12, 3.0 * nrow), squeeze=False)
    for ax, g in zip(axs.ravel(), groups):
        sel = np.nonzero((rows.wavelength_nm == g[0]) & (rows.side == g[1]) & (rows.theta_i_deg == g[2]))[0]
        x = np.where(np.abs(((rows.phi_s_deg[sel] + 90) % 360) - 90) < 90, 1, -1) * rows.theta_s_deg[sel]
        o = np.argsort(x)
        sel, x = sel[o], x[o]
        ax.errorbar(x, rows.bsdf_sr[sel], rows.sigma_sr[sel], fmt=".", ms=3, color="k", label="recording")
        ax.plot(x, v0[sel], "-", color="tab:red", label="baseline")
        ax.plot(x, v1[sel], "-", color="tab:blue", label=result["effect"])
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.set_title(f"{g[1]} theta_i={g[2]:g} deg" + (f" {g[0]:g} nm" if len({q[0] for q in groups}) > 1 else ""),
                     fontsize=9)
        ax.set_xlabel("theta_s signed by phi_s (deg)")
        ax.set_ylabel("BSDF (1/sr)")
    for ax in axs.ravel()[len(groups):]:
        ax.axis("off")
    axs.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    curves = _png(fig)
    esc = lambda s: (str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;"))  # noqa: E731
    cand_rows = "".join(_candidate_row(c, esc) for c in result["candidates"])
    mis_rows = "".join(f"<tr><td>{m['side']}</td><td>{m['theta_i_deg']:g}</td><td>{m['phi_s_deg']:g}</td>"
                       f"<td>{m['theta_s_deg'][0]:g}-{m['theta_s_deg'][1]:g}</td><td>{m['share']:.1%}</td>"
                       f"<td>{esc(m.get('shape', ''))}</td></tr>" for m in result["mismatch"])
    html = f"""<!doctype html><html><head><meta charset="utf-8"><title>relief diagnose</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 6px;font-size:13px}}</style></head><body>
<h1>Diagnosis: {esc(result['effect'])}</h1>
<p>{esc(result['explanation'])}</p>
<p>Metric: {esc(result['metric'])}. Before: <b>{result['rms_before']:.3f}</b>, after: <b>{result['rms_after']:.3f}</b>.
Parameters: {esc(json.dumps(result['parameters']))}</p>
<h2>Where the baseline misses</h2><table><tr><th>side</th><th>theta_i</th><th>phi_s</th><th>theta_s</th><th>share</th>
<th>shape</th></tr>{mis_rows}</table>
<h2>Candidates (best first; score = BIC)</h2><table><tr><th>effect</th><th>rms after</th><th>score</th>
<th>parameters</th></tr>{cand_rows}</table>
<h2>Residual maps</h2><img src="data:image/png;base64,{maps}" style="max-width:100%">
<h2>In-plane curves</h2><img src="data:image/png;base64,{curves}" style="max-width:100%">
</body></html>"""
    return write_text_atomic(path, html)
