"""The report of `relief infer`: measured vs predicted lobes, the refined parameters, the candidates.

The lobe plot: for each incidence whose transmitted rows form a full (theta_s, phi_s) grid, the BTDF
along the two axes of the direction-cosine plane through the undeviated ray (u - u0 along x and along
y, sampled as infer.lobe samples its half-maximum edges), measured and predicted, so the edges, the
plateau and the centre can be compared by eye.  Nothing here computes physics beyond that read-out.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

CUT_HALF_WIDTH_U = 0.2


def lobe_cuts(rows: Any, values: np.ndarray, half_width_u: float = CUT_HALF_WIDTH_U) -> dict:
    """{"r": offsets from u0, "x": f along x, "y": f along y} for the T rows of one incidence."""
    from relief_bsdf.infer.slopes import _lobe_interpolator
    ti, pi = float(rows.theta_i_deg[0]), float(rows.phi_i_deg[0])
    u0 = -np.sin(np.radians(ti)) * np.array([np.cos(np.radians(pi)), np.sin(np.radians(pi))])
    f = _lobe_interpolator(np.asarray(rows.theta_s_deg), np.asarray(rows.phi_s_deg), np.asarray(values, float))
    r = np.linspace(-half_width_u, half_width_u, 401)
    out = {"r": r}
    for axis, name in ((0, "x"), (1, "y")):
        q = np.tile(u0, (r.size, 1))
        q[:, axis] += r
        out[name] = f(q)
    return out


def lobe_figure(path: str | Path, rec: Any, predicted: np.ndarray, title: str = "",
                labels: tuple[str, str] = ("measured", "predicted")) -> Path | None:
    """The lobe plot of the module doc for every full-grid incidence of `rec` (None: none)."""
    from relief_bsdf.infer.lobe import full_grid
    from relief_bsdf.report.fit_report import _plt, _save
    incid = []
    for ti, pi in rec.incidences():
        sel = (rec.theta_i_deg == ti) & (rec.phi_i_deg == pi) & (rec.side == "T")
        if sel.any() and full_grid(rec.subset(sel)):
            incid.append((ti, pi, sel))
    if not incid:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, len(incid), figsize=(4.2 * len(incid), 3.4), squeeze=False, sharey=True)
    for ax, (ti, pi, sel) in zip(axes[0], incid):
        rows = rec.subset(sel)
        m = lobe_cuts(rows, rec.bsdf_sr[sel])
        p = lobe_cuts(rows, np.asarray(predicted)[sel])
        ax.plot(m["r"], m["x"], "-", color="0.1", lw=1.6, label=f"{labels[0]}, along x")
        ax.plot(m["r"], m["y"], "-", color="0.55", lw=1.6, label=f"{labels[0]}, along y")
        ax.plot(p["r"], p["x"], "--", color="tab:red", lw=1.3, label=f"{labels[1]}, along x")
        ax.plot(p["r"], p["y"], "--", color="tab:blue", lw=1.3, label=f"{labels[1]}, along y")
        ax.set_title(f"incidence {ti:g} deg, azimuth {pi:g} deg", fontsize=10)
        ax.set_xlabel("direction cosine from the undeviated ray")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("BTDF (1/sr)")
    axes[0][-1].legend(fontsize=8, loc="lower center")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def _lobe_rows(doc: dict) -> list[list]:
    rows = []
    for key, v in doc.get("lobe", {}).items():
        m, s = v["measured"], v["simulated"]
        de = float(np.max(np.abs(np.subtract(s["edges_u"], m["edges_u"]))))
        rows.append([key, m["transmittance"], s["transmittance"], m["plateau_sr"], s["plateau_sr"],
                     m["centroid_offset_deg"], s["centroid_offset_deg"], de])
    return rows


def write_infer_report(out: Path, doc: dict, rec: Any, predicted: np.ndarray) -> dict:
    """OUT/lobes.png and OUT/report.html (report.html's house style); returns the files written."""
    from relief_bsdf.io.atomic import write_text_atomic
    from relief_bsdf.report.html import (CONVENTIONS, esc, figure_html, fmt, kv_html, page, section,
                                         table_html)
    files = {}
    fig = lobe_figure(out / "lobes.png", rec, predicted, "measured vs the inferred relief's plate")
    if fig is not None:
        files["lobes_plot"] = fig.name
    ivals = doc.get("intervals", {})
    prm = []
    for k, v in doc["parameters"].items():
        iv = ivals.get(k)
        prm.append([k, v, "" if iv is None else f"[{fmt(iv[0])}, {fmt(iv[1])}]"])
    sel = doc["selection"]
    cand = [[c["name"], c["k"], c["chi2"], c.get("bic", float("nan")),
             "chosen" if c["name"] == sel["chosen"] else ""] for c in sel["candidates"]]
    secs = [
        section("Result", f"<p>Family: <b>{esc(doc['family'])}</b>; rms slope {fmt(doc['rms_slope'])}; "
                          f"metric (rms z over every recording row) flat plate {fmt(doc['rms_before'])} -> inferred "
                          f"relief {fmt(doc['rms_after'])}.</p>"
                          + table_html(["parameter", "value", "68 % interval"], prm)),
        section("Inside the glass", f"<p>{esc(doc['inside_table'])}</p>"),
        section("Measured and predicted lobes",
                (figure_html(out / "lobes.png", "BTDF along the two axes of the direction-cosine plane through "
                                                "the undeviated ray: measured (solid) and the inferred relief's "
                                                "plate (dashed)") if fig is not None else "<p>No full-grid lobe.</p>")
                + table_html(["incidence", "T measured", "T predicted", "plateau measured (1/sr)",
                              "plateau predicted (1/sr)", "centroid measured (deg)", "centroid predicted (deg)",
                              "max edge difference (direction cosine)"], _lobe_rows(doc))),
        section("Candidates (BIC = chi^2 + k ln n)", table_html(["candidate", "k", "chi^2", "BIC", ""], cand)
                + kv_html({"decisions": sel["decisions"]})),
        section("Limitations", "<ul>" + "".join(f"<li>{esc(t)}</li>" for t in doc["limitations"]) + "</ul>"),
        section("Conventions", f"<p class='small'>{esc(CONVENTIONS)}</p>"),
    ]
    write_text_atomic(out / "report.html", page("relief infer", esc(f"inverted from the incidence "
                                                                   f"{doc['inverted_from']['theta_i_deg']:g}/"
                                                                   f"{doc['inverted_from']['phi_i_deg']:g} deg"),
                                                secs))
    files["report"] = "report.html"
    return files
