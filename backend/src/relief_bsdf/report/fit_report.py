"""Figures (matplotlib, PNG) and the HTML report of a fit; helpers shared with the diagnosis.

- `in_plane_figure`: measured vs simulated plate in-plane curves per incidence (paper figs. 4 and 9):
  x = signed scatter angle (negative on the phi_s = phi_i + 180 half-plane), log BSDF; the
  specular (R) / undeviated (T, through a parallel plate) direction of each incidence is marked.
- `residual_image`: a labelled residual map, one row per (side, theta_i) and one column per
  signed scatter angle, so a few incidences x many angles stay readable (rows, not stripes).
- `residual_map_figure`: the normalised residual (residual.LogChiMetric) of a fit as such a map.
- `write_fit_report`: report.html, one self-contained page (report.html house style).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.fit.residual import DEFAULT_METRIC, LogChiMetric
from relief_bsdf.io.atomic import atomic_path, write_text_atomic
from relief_bsdf.report import html as H

RESIDUAL_LABEL = "r = [ln(sim + b) - ln(meas + b)] / s  (+: simulation high; |r| ~ 1 = within noise)"


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def signed_angle(rec: Any) -> np.ndarray:
    """Signed scatter angle: negative on the phi_s = phi_i + 180 half-plane."""
    rel = np.mod(np.asarray(rec.phi_s_deg) - np.asarray(rec.phi_i_deg), 360.0)
    return np.where(np.abs(rel - 180.0) < 90.0, -1.0, 1.0) * np.asarray(rec.theta_s_deg)


def _save(fig, path: str | Path, dpi: int = 100) -> Path:
    plt = _plt()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)


def in_plane_figure(path: str | Path, rec: Any, sims: dict, title: str = "") -> Path:
    """Measured (solid, 1-sigma band) vs simulated (dashed, one per entry of `sims`) in-plane curves
    per incidence; dotted verticals mark each incidence's specular (R) / undeviated (T) direction."""
    plt = _plt()
    sides = [s for s in ("R", "T") if np.any(np.asarray(rec.side) == s)]
    fig, axes = plt.subplots(1, len(sides), figsize=(6.8 * len(sides), 4.8), squeeze=False)
    x = signed_angle(rec)
    incid = np.unique(rec.theta_i_deg)
    colors = plt.cm.viridis(np.linspace(0, 0.9, max(len(incid), 1)))
    styles = ["--", ":", "-."]
    sig = np.asarray(rec.sigma_sr, float)
    for ax, sd in zip(axes[0], sides):
        for k_inc, (c, ti) in enumerate(zip(colors, incid)):
            m = (np.asarray(rec.side) == sd) & (rec.theta_i_deg == ti)
            o = np.argsort(x[m])
            xm, ym = x[m][o], np.maximum(rec.bsdf_sr[m][o], 1e-12)
            ax.semilogy(xm, ym, "-", color=c, lw=1.3, label=f"theta_i {ti:g} deg, measured")
            sm = sig[m][o]
            if np.any(np.isfinite(sm)):
                ax.fill_between(xm, np.maximum(ym - sm, 1e-12), ym + sm, color=c, alpha=0.15, lw=0)
            for k, (name, v) in enumerate(sims.items()):
                ax.semilogy(xm, np.maximum(np.asarray(v)[m][o], 1e-12), styles[k % 3], color=c, lw=1.1,
                            label=f"{name}" if k_inc == 0 else None)
            ax.axvline(-ti, color=c, ls=":", lw=0.9)
        ax.set_xlabel("signed scatter angle theta_s (deg); < 0: phi_i + 180 half-plane")
        ax.set_ylabel(f"plate BSDF, {'reflection R' if sd == 'R' else 'transmission T'} (1/sr)")
        ax.set_title(f"{title}: side {sd}\ndotted: {'specular' if sd == 'R' else 'undeviated'} direction "
                     "(the coherent part's peak); band: measured +- 1 sigma", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return _save(fig, path)


def residual_image(ax, side: Any, theta_i: Any, signed_ts: Any, r: Any, lim: float, extra: Any = None):
    """Rows (side, theta_i[, extra]) x columns (signed theta_s) of residuals r on `ax`; returns the image."""
    side, theta_i, ts, r = (np.asarray(a) for a in (side, theta_i, signed_ts, r))
    keys = list(zip(side.tolist(), np.round(theta_i.astype(float), 6).tolist(),
                    [""] * len(r) if extra is None else [str(e) for e in extra]))
    rows = sorted(set(keys), key=lambda k: (k[0], k[1], k[2]))
    cols = np.unique(np.round(ts.astype(float), 6))
    img = np.full((len(rows), cols.size), np.nan)
    ri = {k: i for i, k in enumerate(rows)}
    img[[ri[k] for k in keys], np.searchsorted(cols, np.round(ts.astype(float), 6))] = r
    half = 0.5 * (np.diff(cols).min() if cols.size > 1 else 1.0)
    im = ax.imshow(img, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest",
                   extent=(cols[0] - half, cols[-1] + half, len(rows) - 0.5, -0.5))
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels([f"{k[0]}  theta_i {k[1]:g}" + (f"  {k[2]}" if k[2] else "") for k in rows], fontsize=7)
    ax.set_xlabel("signed scatter angle theta_s (deg)")
    return im


def residual_map_figure(path: str | Path, rec: Any, sim: Any, metric: LogChiMetric = DEFAULT_METRIC,
                        title: str = "", lim: float | None = None) -> Path:
    """Normalised residual r over (side, incidence) rows x signed scatter angle, labelled colour bar."""
    plt = _plt()
    r = metric.residuals(sim, rec.bsdf_sr, rec.sigma_sr)
    n_rows = len({(s, t) for s, t in zip(np.asarray(rec.side).tolist(), np.asarray(rec.theta_i_deg).tolist())})
    lim = lim or max(3.0, float(np.nanpercentile(np.abs(r), 98)))
    fig, ax = plt.subplots(figsize=(10.0, 1.6 + 0.42 * n_rows))
    im = residual_image(ax, rec.side, rec.theta_i_deg, signed_angle(rec), r, lim)
    ax.set_title(f"{title}: residual per point (rms {float(np.sqrt(np.mean(r ** 2))):.3g})", fontsize=9)
    fig.colorbar(im, ax=ax, pad=0.01).set_label(RESIDUAL_LABEL, fontsize=7)
    return _save(fig, path)


def fit_plots(out: Path, rec: Any, sim_before: Any, sim_after: Any) -> dict:
    """Before/after in-plane curves and residual maps (same colour scale); returns {name: file name}."""
    out = Path(out)
    both = np.concatenate([DEFAULT_METRIC.residuals(s, rec.bsdf_sr, rec.sigma_sr) for s in (sim_before, sim_after)])
    lim = max(3.0, float(np.nanpercentile(np.abs(both), 98)))
    return {
        "plot_before": in_plane_figure(out / "in_plane_before.png", rec, {"simulated, initial relief": sim_before},
                                       "before the fit").name,
        "plot_after": in_plane_figure(out / "in_plane_after.png", rec, {"simulated, fitted relief": sim_after},
                                      "after the fit").name,
        "residual_before": residual_map_figure(out / "residual_before.png", rec, sim_before, title="before the fit",
                                               lim=lim).name,
        "residual_after": residual_map_figure(out / "residual_after.png", rec, sim_after, title="after the fit",
                                              lim=lim).name,
    }


CAPTIONS = {
    "plot_before": "In-plane plate BSDF before the fit (initial relief): measured (solid, 1-sigma band) and "
                   "simulated (dashed); dotted lines mark the specular / undeviated directions.",
    "plot_after": "In-plane plate BSDF after the fit (fitted height scale and filter), same layout.",
    "residual_before": "Residual map before the fit: one row per side and incidence, one column per scatter angle.",
    "residual_after": "Residual map after the fit (same colour scale as before).",
}


def stop_verdict(doc: dict) -> tuple[str, str]:
    """(css class, sentence): whether and why the optimiser stopped."""
    stopped = str(doc.get("stopped", "unknown"))
    n = len(doc.get("iterations", []))
    rms = [i["rms"] for i in doc.get("iterations", []) if isinstance(i.get("rms"), (int, float))]
    tail = ""
    if len(rms) >= 6:
        best_early, best = min(rms[:-5]), min(rms)
        tail = (f" Over the last 5 evaluations the best metric changed by {H.fmt(best_early - best, 2)} "
                f"({H.fmt(100 * (best_early - best) / best_early if best_early else 0.0, 2)} %).")
    if stopped == "converged":
        return "ok", (f"Converged: Nelder-Mead met its tolerances (parameter step < 0.002, metric change < 1e-4) "
                      f"after {n} evaluations.{tail}")
    if stopped == "threshold":
        return "ok", f"Stopped after {n} evaluations: the metric reached the requested threshold.{tail}"
    if stopped == "max_iter":
        return "warn", (f"Not converged: stopped at the evaluation limit ({n} evaluations); the optimum may lie "
                        f"further on. Rerun with a larger --max-iter to confirm.{tail}")
    return "warn", f"Stopped: {H.esc(stopped)} after {n} evaluations.{tail}"


def _iterations_html(doc: dict) -> str:
    its = doc.get("iterations", [])
    if not its:
        return "<p>No evaluations recorded.</p>"
    names = list(its[0]["parameters"])
    best = min(range(len(its)), key=lambda k: its[k]["rms"])
    rows = [[k + 1] + [it["parameters"].get(n) for n in names] + [it["rms"], H.Raw("best" if k == best else "")]
            for k, it in enumerate(its)]
    head = ["#"] + [H.PARAMETER_UNITS.get(n, (n, ""))[0] for n in names] + ["metric", ""]
    return H.table_html(head, rows)


def write_fit_report(path: str | Path, doc: dict, plots: dict, renders: dict | None = None) -> Path:
    """report.html of `relief fit`: one self-contained page (images embedded as data URIs).

    `plots` {key: PNG file name beside `path`} (from `fit_plots`); `renders` {caption: PNG path} of
    plate renders (e.g. before / after), omitted when None or empty."""
    base = Path(path).parent
    verdict_cls, verdict = stop_verdict(doc)
    params = H.table_html(["parameter", "unit", "value", "68 % interval"],
                          H.parameter_rows(doc["parameters"], doc.get("intervals")))
    summary = (f"<div class='verdict {verdict_cls}'>{verdict}</div>"
               + H.table_html(["quantity", "value"], [["metric before the fit", doc["rms_before"]],
                                                      ["metric after the fit", doc["rms_after"]],
                                                      ["evaluations", len(doc.get("iterations", []))],
                                                      ["wall time (s)", doc.get("seconds", float("nan"))]])
               + f"<p class='small'><b>Metric.</b> {H.esc(doc['metric'])}</p>")
    fit_sec = params + H.correlation_html(doc.get("correlation"))
    if doc.get("intervals") is None:
        fit_sec += "<p class='small'>This fit did not estimate parameter intervals.</p>"
    if doc.get("warnings"):
        fit_sec += ("<p><b>What the recording determines:</b></p><ul>"
                    + "".join(f"<li>{H.esc(w)}</li>" for w in doc["warnings"]) + "</ul>")
    ident = doc.get("identifiability") or {}
    if ident.get("criterion"):
        parts = [ident[k] for k in ("criterion", "estimate", "interval_method") if ident.get(k)]
        fit_sec += f"<p class='small'>{H.esc('; '.join(parts))}.</p>"
    figs = "".join(H.figure_html(base / f, CAPTIONS.get(k, k)) for k, f in plots.items() if (base / f).exists())
    sections = [H.section("Summary", summary), H.section("Fitted parameters", fit_sec),
                H.section("Plate BSDF before and after", figs)]
    if renders:
        sections.append(H.section("Plate renders", "".join(H.figure_html(p, cap) for cap, p in renders.items())))
    physics = f"<p>Boundary method: <b>{H.esc(doc.get('method', 'unknown'))}</b>.</p>"
    if doc.get("method_reason"):
        physics += f"<p class='small'>Why: {H.esc(doc['method_reason'])}</p>"
    physics += H.kv_html(doc["physics"]) if doc.get("physics") else "<p>Not recorded.</p>"
    if doc.get("relief_history"):
        physics += "<p class='small'>Relief operations: " + H.esc("; ".join(map(str, doc["relief_history"]))) + "</p>"
    sections += [H.section("Physics used", physics), H.section("Units and conventions", f"<p>{H.CONVENTIONS}</p>"),
                 H.section("Evaluations", _iterations_html(doc))]
    sub = f"Sample {H.esc(doc.get('sample', ''))} &middot; format {H.esc(doc.get('format', ''))}"
    return write_text_atomic(path, H.page("Relief fit report", sub, sections))
