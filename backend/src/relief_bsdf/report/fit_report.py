"""Figures (matplotlib, PNG) and the HTML report of a fit; helpers shared with the diagnosis.

- `in_plane_figure`: measured vs simulated plate in-plane curves per incidence (paper figs. 4 and 9):
  x = signed scatter angle (negative on the phi_s = phi_i + 180 half-plane), log BSDF; the
  specular (R) / undeviated (T, through a parallel plate) direction of each incidence is marked.
- `residual_image`: a labelled residual map, one row per (side, theta_i) and one column per
  signed scatter angle, so a few incidences x many angles stay readable (rows, not stripes).
- `residual_map_figure`: the residual z of the metric (fit.residual.rms_z) of a fit as such a map.
- `write_fit_report`: report.html, one self-contained page (report.html house style).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from relief_bsdf.fit.residual import rms_z, z_residuals
from relief_bsdf.io.atomic import atomic_path, write_text_atomic
from relief_bsdf.report import html as H

RESIDUAL_LABEL = "z = (measured - simulated) / s  (+: recording above the simulation; |z| ~ 1 = within noise)"


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


def noise_level(rec: Any) -> float:
    """The recording's noise level (1/sr): the 10 % quantile of its rows' 1-sigma, unknown ones by the
    documented fallback (io.recording.sigma_with_fallback).  A log axis of a plot ends there: a
    value below it is not resolved by the recording, so it is drawn as a censored marker at this
    level (`censored`), not as a spike toward zero."""
    from relief_bsdf.io.recording import sigma_with_fallback
    s = sigma_with_fallback(np.asarray(rec.bsdf_sr, float), np.asarray(rec.sigma_sr, float))
    s = s[np.isfinite(s) & (s > 0)]
    if s.size:
        return float(np.quantile(s, 0.1))
    pos = np.asarray(rec.bsdf_sr, float)
    pos = pos[np.isfinite(pos) & (pos > 0)]
    return float(1e-3 * pos.max()) if pos.size else 1e-6


def censored(ax, x: Any, y: Any, floor: float, style: str, color: Any, lw: float = 1.2, label: str | None = None):
    """A curve on a log axis floored at `floor`: the part at or above it as a line, each point below it
    as a downward triangle at the floor (an upper limit: "below the noise"), never a spike."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    low = ~(y >= floor)
    ax.plot(x, np.where(low, np.nan, y), style, color=color, lw=lw, label=label)
    if low.any():
        ax.plot(x[low], np.full(int(low.sum()), floor), "v", color=color, ms=3.5, mfc="none", mew=0.8,
                linestyle="none")


def finish_log_axis(ax, floor: float, values: list) -> None:
    """Log y from just below the noise `floor` to above the largest value: no tick below the floor's
    decade that no row reaches, no negative or zero tick (a log axis has none)."""
    top = max([float(np.nanmax(v)) for v in values if np.any(np.isfinite(v))] + [floor * 10])
    ax.set_yscale("log")
    ax.set_ylim(floor / 1.6, top * 2.0)


def legend_below(fig, handles: list, labels: list, ncol: int) -> float:
    """One legend for the whole figure, inside it, under the axes; returns the height share it takes
    (for tight_layout's rect), so a saved figure never clips it."""
    rows = int(np.ceil(len(labels) / max(ncol, 1)))
    h = min(0.45, (0.26 + 0.2 * rows) / fig.get_figheight())
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7, frameon=False, bbox_to_anchor=(0.5, 0.0))
    return h


def in_plane_figure(path: str | Path, rec: Any, sims: dict, title: str = "") -> Path:
    """Measured (solid, 1-sigma band) vs simulated (dashed, one per entry of `sims`) in-plane curves
    per incidence, one panel per side the recording has (none for a side without rows); dotted
    verticals mark each incidence's specular (R) / undeviated (T) direction.  Log BSDF axes end at the
    recording's noise level (`noise_level`): values below it are triangles at that level."""
    from matplotlib.lines import Line2D
    plt = _plt()
    sides = [s for s in ("R", "T") if np.any(np.asarray(rec.side) == s)]
    fig, axes = plt.subplots(1, len(sides), figsize=(6.8 * len(sides), 5.4), squeeze=False)
    x = signed_angle(rec)
    incid = np.unique(rec.theta_i_deg)
    colors = plt.cm.viridis(np.linspace(0, 0.9, max(len(incid), 1)))
    styles = ["--", ":", "-."]
    sig = np.asarray(rec.sigma_sr, float)
    floor = noise_level(rec)
    for ax, sd in zip(axes[0], sides):
        shown = []
        for c, ti in zip(colors, incid):
            m = (np.asarray(rec.side) == sd) & (rec.theta_i_deg == ti)
            if not m.any():
                continue
            o = np.argsort(x[m])
            xm, ym = x[m][o], np.asarray(rec.bsdf_sr, float)[m][o]
            censored(ax, xm, ym, floor, "-", c, 1.3)
            sm = sig[m][o]
            if np.any(np.isfinite(sm)):
                ax.fill_between(xm, np.maximum(ym - sm, floor), np.maximum(ym + sm, floor), color=c, alpha=0.15, lw=0)
            for k, v in enumerate(sims.values()):
                vm = np.asarray(v, float)[m][o]
                censored(ax, xm, vm, floor, styles[k % 3], c, 1.1)
                shown.append(vm)
            shown.append(ym)
            ax.axvline(-ti, color=c, ls=":", lw=0.9)
        finish_log_axis(ax, floor, shown)
        ax.axhline(floor, color="0.6", lw=0.6)
        ax.set_xlabel("signed scatter angle theta_s (deg); < 0: phi_i + 180 half-plane")
        ax.set_ylabel(f"plate BSDF, {'reflection R' if sd == 'R' else 'transmission T'} (1/sr)")
        ax.set_title(f"{title}: side {sd}\ndotted: {'specular' if sd == 'R' else 'undeviated'} direction "
                     "(the coherent part's peak); band: measured +- 1 sigma", fontsize=9)
        ax.grid(alpha=0.3, which="both")
    handles = [Line2D([], [], color=c, lw=2) for c in colors]
    labels = [f"theta_i {ti:g} deg" for ti in incid]
    handles += [Line2D([], [], color="k", ls="-", lw=1.3)] + [Line2D([], [], color="k", ls=styles[k % 3], lw=1.1)
                                                               for k in range(len(sims))]
    labels += ["measured"] + list(sims)
    handles.append(Line2D([], [], color="k", marker="v", mfc="none", ls="none"))
    labels.append(f"below the recording's noise level {floor:.2g} 1/sr (censored)")
    h = legend_below(fig, handles, labels, ncol=min(4, len(labels)) if len(sides) > 1 else 2)
    fig.tight_layout(rect=(0, h, 1, 1))
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


def residual_map_figure(path: str | Path, rec: Any, sim: Any, model_sigma: Any = None, title: str = "",
                        lim: float | None = None) -> Path:
    """The residual z of the metric per point (fit.residual.z_residuals: its rms, in the title, is the
    metric) over (side, incidence) rows x signed scatter angle, labelled colour bar."""
    plt = _plt()
    r = z_residuals(rec.bsdf_sr, rec.sigma_sr, sim, model_sigma)
    n_rows = len({(s, t) for s, t in zip(np.asarray(rec.side).tolist(), np.asarray(rec.theta_i_deg).tolist())})
    lim = lim or max(3.0, float(np.nanpercentile(np.abs(r), 98)))
    fig, ax = plt.subplots(figsize=(10.0, 1.6 + 0.42 * n_rows))
    im = residual_image(ax, rec.side, rec.theta_i_deg, signed_angle(rec), r, lim)
    m = rms_z(rec.bsdf_sr, rec.sigma_sr, sim, model_sigma)
    ax.set_title(f"{title}: residual per point (metric, rms z {m:.3g})", fontsize=9)
    fig.colorbar(im, ax=ax, pad=0.01).set_label(RESIDUAL_LABEL, fontsize=7)
    return _save(fig, path)


def fit_plots(out: Path, rec: Any, sim_before: Any, sim_after: Any, sigma_before: Any = None,
              sigma_after: Any = None) -> dict:
    """Before/after in-plane curves and residual maps (same colour scale); `sigma_*`: the simulations'
    own 1-sigma per row (the metric's model sigma; None: 0).  Returns {name: file name}."""
    out = Path(out)
    both = np.concatenate([z_residuals(rec.bsdf_sr, rec.sigma_sr, s, m)
                           for s, m in ((sim_before, sigma_before), (sim_after, sigma_after))])
    lim = max(3.0, float(np.nanpercentile(np.abs(both), 98)))
    return {
        "plot_before": in_plane_figure(out / "in_plane_before.png", rec, {"simulated, initial relief": sim_before},
                                       "before the fit").name,
        "plot_after": in_plane_figure(out / "in_plane_after.png", rec, {"simulated, fitted relief": sim_after},
                                      "after the fit").name,
        "residual_before": residual_map_figure(out / "residual_before.png", rec, sim_before, sigma_before,
                                               title="before the fit", lim=lim).name,
        "residual_after": residual_map_figure(out / "residual_after.png", rec, sim_after, sigma_after,
                                              title="after the fit", lim=lim).name,
    }


CAPTIONS = {
    "plot_before": "In-plane plate BSDF before the fit (initial relief): measured (solid, 1-sigma band) and "
                   "simulated (dashed); dotted lines mark the specular / undeviated directions.",
    "plot_after": "In-plane plate BSDF after the fit (fitted height scale and filter), same layout.",
    "residual_before": "Residual map before the fit: one row per side and incidence, one column per scatter angle.",
    "residual_after": "Residual map after the fit (same colour scale as before).",
}


FILE_PURPOSES = {
    "fit.json": "the fit's numbers: parameters with 68 % intervals, metric before and after, every evaluation, "
                "the physics and grid used (relief-fit/1)",
    "report.html": "this page",
    "checkpoint.json": "every evaluated parameter set: a rerun into this folder replays them instead of "
                       "recomputing (deleted by nothing; safe to remove)",
    "boundary_table": "the fitted relief's boundary BSDF tables (HDF5; light from outside and inside): input to "
                      "`relief simulate --table`, `relief export` and the Blender bake",
    "isbsdf_outside": "the fitted boundary for light from outside as Zemax OpticStudio IS-BSDF files (one scatter "
                      "type per file: BRDF, BTDF centred on the refracted ray)",
    "isbsdf_inside": "the same for light arriving from inside the plate",
    "relief": "the optimised relief: the measured heights scaled and filtered by the fitted parameters (.npz, "
              "metres; its history names the operations)",
    "simulated": "the plate simulated with the fitted relief on every recording row (recording.csv layout; "
                 "sigma_sr: the simulation's own 1-sigma)",
    "plot_before": "figure: in-plane plate BSDF before the fit",
    "plot_after": "figure: in-plane plate BSDF after the fit",
    "residual_before": "figure: residual map before the fit",
    "residual_after": "figure: residual map after the fit",
}


def files_html(doc: dict) -> str:
    """Every file the fit wrote, with a line on what it is for (names relative to the output folder)."""
    rows = [[name, FILE_PURPOSES[name]] for name in ("fit.json", "report.html", "checkpoint.json")]
    for key, names in (doc.get("files") or {}).items():
        for name in ([names] if isinstance(names, str) else list(names)):
            rows.append([name, FILE_PURPOSES.get(key, key.replace("_", " "))])
    return ("<p>Written into the output folder (names relative to it):</p>"
            + H.table_html(["file", "what it is for"], rows, numeric=False))


def stop_verdict(doc: dict) -> tuple[str, str]:
    """(css class, sentence): which algorithm ran (fit.json's `algorithm`, the optimiser's own
    account), whether and why it stopped."""
    stopped = str(doc.get("stopped", "unknown"))
    n = len(doc.get("iterations", []))
    algo = str(doc.get("algorithm") or "the search")
    rms = [i["rms"] for i in _of_record(doc.get("iterations", [])) if isinstance(i.get("rms"), (int, float))]
    tail = ""
    if len(rms) >= 6:
        best_early, best = min(rms[:-5]), min(rms)
        tail = (" Over the last 5 evaluations of the model of record the best metric changed by "
                f"{H.fmt(best_early - best, 2)} "
                f"({H.fmt(100 * (best_early - best) / best_early if best_early else 0.0, 2)} %).")
    if stopped == "converged":
        return "ok", (f"Converged after {n} evaluations: {H.esc(algo)}; the search stopped where its steps fell "
                      f"below the finite-difference step or gained less than 1e-4 of chi2.{tail}")
    if stopped == "threshold":
        return "ok", (f"Stopped after {n} evaluations: the metric reached the requested threshold "
                      f"({H.esc(algo)}).{tail}")
    if stopped == "max_iter":
        return "warn", (f"Not converged: {H.esc(algo)} stopped at the evaluation limit ({n} evaluations); the "
                        f"optimum may lie further on. Rerun with a larger --max-iter to confirm.{tail}")
    return "warn", f"Stopped: {H.esc(stopped)} after {n} evaluations ({H.esc(algo)}).{tail}"


def _of_record(its: list) -> list:
    """The evaluations of the forward model of record (fit.json `iterations[].model` "record", or no model
    named): the search model's (a quarter of the rays, intensity loop) are on another scale."""
    return [it for it in its if it.get("model", "record") == "record"]


def _iterations_html(doc: dict) -> str:
    its = doc.get("iterations", [])
    if not its:
        return "<p>No evaluations recorded.</p>"
    names = list(its[0]["parameters"])
    has_search = all("search" in it for it in its)
    has_model = any("model" in it for it in its)
    key = "search" if has_search else "rms"
    record = [k for k, it in enumerate(its) if it.get("model", "record") == "record"] or list(range(len(its)))
    best = min(record, key=lambda k: its[k][key])
    rows = [[k + 1] + [it["parameters"].get(n) for n in names] + [it["rms"]]
            + ([it["search"]] if has_search else []) + ([it.get("model", "record")] if has_model else [])
            + [H.Raw("best of the model of record" if k == best else "")]
            for k, it in enumerate(its)]
    head = (["#"] + [H.PARAMETER_UNITS.get(n, (n, ""))[0] for n in names] + ["metric (rms z)"]
            + (["search objective (log-chi)"] if has_search else []) + (["model"] if has_model else []) + [""])
    note = ("<p class='small'>The search steps on the log-chi objective (fit.json's search_objective); the metric "
            "is the one that simulate, fit and diagnose report. The answer is the likelihood's optimum near the "
            "search's best point, not necessarily one of these rows.</p>" if has_search else "")
    return note + H.table_html(head, rows)


def write_fit_report(path: str | Path, doc: dict, plots: dict, renders: dict | None = None) -> Path:
    """report.html of `relief fit`: one self-contained page (images embedded as data URIs).

    `plots` {key: PNG file name beside `path`} (from `fit_plots`); `renders` {caption: PNG path} of
    plate renders (e.g. before / after), omitted when None or empty."""
    base = Path(path).parent
    verdict_cls, verdict = stop_verdict(doc)
    params = H.table_html(["parameter", "unit", "value", "68 % interval"],
                          H.parameter_rows(doc["parameters"], doc.get("intervals")))
    summary = (f"<div class='verdict {verdict_cls}'>{verdict}</div>"
               + H.table_html(["quantity", "value"], [["metric (rms z) before the fit", doc["rms_before"]],
                                                      ["metric (rms z) after the fit", doc["rms_after"]],
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
    sections += [H.section("Physics used", physics), H.section("Files written", files_html(doc)),
                 H.section("Units and conventions", f"<p>{H.CONVENTIONS}</p>"),
                 H.section("Evaluations", _iterations_html(doc))]
    sub = f"Sample {H.esc(doc.get('sample', ''))} &middot; format {H.esc(doc.get('format', ''))}"
    return write_text_atomic(path, H.page("Relief fit report", sub, sections))
