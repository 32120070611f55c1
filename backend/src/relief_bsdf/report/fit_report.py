"""Figures (matplotlib, PNG) and the HTML report of a fit; helpers shared with the diagnosis.

- `in_plane_figure`: measured vs simulated in-plane curves per incidence (paper figs. 4 and 9):
  x = signed scatter angle (negative on the phi_s = phi_i + 180 half-plane), log BSDF.
- `residual_map_figure`: normalised residual (residual.LogChiMetric) over incidence x scatter angle.
"""
from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.io.atomic import atomic_path, write_text_atomic
from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric, residual_map


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _signed(rec: Any) -> np.ndarray:
    rel = np.mod(np.asarray(rec.phi_s_deg) - np.asarray(rec.phi_i_deg), 360.0)
    return np.where(np.abs(rel - 180.0) < 90.0, -1.0, 1.0) * np.asarray(rec.theta_s_deg)


def in_plane_figure(path: str | Path, rec: Any, sims: dict, title: str = "") -> Path:
    """Measured (solid) vs simulated (dashed, one per entry of `sims`) in-plane curves per incidence."""
    plt = _plt()
    sides = [s for s in ("R", "T") if np.any(np.asarray(rec.side) == s)]
    fig, axes = plt.subplots(1, len(sides), figsize=(6.5 * len(sides), 4.5), squeeze=False)
    x = _signed(rec)
    incid = np.unique(rec.theta_i_deg)
    colors = plt.cm.viridis(np.linspace(0, 0.9, max(len(incid), 1)))
    styles = ["--", ":", "-."]
    for ax, sd in zip(axes[0], sides):
        for k_inc, (c, ti) in enumerate(zip(colors, incid)):
            m = (np.asarray(rec.side) == sd) & (rec.theta_i_deg == ti)
            o = np.argsort(x[m])
            ax.semilogy(x[m][o], np.maximum(rec.bsdf_sr[m][o], 1e-12), "-", color=c, lw=1.2,
                        label=f"{ti:g} deg measured")
            for k, (name, v) in enumerate(sims.items()):
                ax.semilogy(x[m][o], np.maximum(np.asarray(v)[m][o], 1e-12), styles[k % 3], color=c, lw=1.0,
                            label=f"{name} (dashed)" if k_inc == 0 else None)
        ax.set_xlabel("signed scatter angle (deg)")
        ax.set_ylabel(f"plate BSDF {sd} (1/sr)")
        ax.set_title(f"{title} side {sd}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return Path(path)


def residual_map_figure(path: str | Path, rec: Any, sim: Any, metric: LogChiMetric = DEFAULT_METRIC,
                        title: str = "") -> Path:
    """Normalised residual r over (signed scatter angle, incidence), one panel per side."""
    plt = _plt()
    rm = residual_map(rec, sim, metric)
    fig, axes = plt.subplots(1, len(rm), figsize=(6.5 * len(rm), 3.8), squeeze=False)
    lim = max(3.0, float(np.nanpercentile(np.abs(np.concatenate([v[2] for v in rm.values()])), 98)))
    for ax, (sd, (ti, ts, r)) in zip(axes[0], rm.items()):
        sc = ax.scatter(ts, ti, c=r, cmap="coolwarm", vmin=-lim, vmax=lim, s=12, marker="s")
        ax.set_xlabel("signed scatter angle (deg)")
        ax.set_ylabel("theta_i (deg)")
        ax.set_title(f"{title} residual side {sd}")
        fig.colorbar(sc, ax=ax, label="r (sigma units, + = simulation high)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return Path(path)


def fit_plots(out: Path, rec: Any, sim_before: Any, sim_after: Any) -> dict:
    """Before/after in-plane curves and residual maps; returns {name: file name}."""
    out = Path(out)
    files = {
        "plot_before": in_plane_figure(out / "in_plane_before.png", rec, {"simulated before": sim_before},
                                       "before fit").name,
        "plot_after": in_plane_figure(out / "in_plane_after.png", rec, {"simulated after": sim_after},
                                      "after fit").name,
        "residual_before": residual_map_figure(out / "residual_before.png", rec, sim_before, title="before").name,
        "residual_after": residual_map_figure(out / "residual_after.png", rec, sim_after, title="after").name,
    }
    return files


def write_fit_report(path: str | Path, doc: dict, plots: dict) -> Path:
    """A self-contained HTML page: summary table, plots, iteration log."""
    p = doc["parameters"]
    rows = "".join(f"<tr><td>{k}</td><td>{json.dumps(i['parameters'])}</td><td>{i['rms']:.5g}</td></tr>"
                   for k, i in enumerate(doc["iterations"]))
    imgs = "".join(f'<figure><img src="{html.escape(v)}" style="max-width:100%"><figcaption>{html.escape(k)}'
                   "</figcaption></figure>" for k, v in plots.items())
    text = f"""<!doctype html><html><head><meta charset="utf-8"><title>relief fit</title></head><body>
<h1>Relief fit</h1>
<p>Sample: {html.escape(str(doc.get('sample', '')))} &middot; method: {html.escape(str(doc.get('method', '')))}</p>
<table border="1" cellpadding="4">
<tr><th>height scale</th><td>{p['height_scale']:.5g}</td></tr>
<tr><th>Gaussian filter sigma (um)</th><td>{p['filter_sigma_um']:.5g}</td></tr>
<tr><th>metric before</th><td>{doc['rms_before']:.5g}</td></tr>
<tr><th>metric after</th><td>{doc['rms_after']:.5g}</td></tr>
<tr><th>stopped</th><td>{html.escape(str(doc.get('stopped', '')))}</td></tr>
</table>
<p><b>Metric.</b> {html.escape(doc['metric'])}</p>
{imgs}
<h2>Iterations</h2><table border="1" cellpadding="2"><tr><th>#</th><th>parameters</th><th>metric</th></tr>{rows}</table>
</body></html>"""
    return write_text_atomic(path, text)
