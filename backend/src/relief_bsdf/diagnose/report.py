"""report.html of `relief diagnose`: residual maps before/after and in-plane curves, in the house
style of the fit report (relief_bsdf.report.html: one self-contained page, images embedded).

Residuals are the noise-normalised z = (measured - simulated) / s of `mismatch.residual_z`.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from relief_bsdf.diagnose.mismatch import residual_z
from relief_bsdf.io.atomic import write_text_atomic

__all__ = ["write_report"]

Z_LABEL = "z = (measured - simulated) / sigma"


def _signed(rows) -> np.ndarray:
    """Signed scatter angle: negative on the phi_s = phi_i + 180 half-plane."""
    rel = np.mod(np.asarray(rows.phi_s_deg) - np.asarray(rows.phi_i_deg), 360.0)
    return np.where(np.abs(rel - 180.0) < 90.0, -1.0, 1.0) * np.asarray(rows.theta_s_deg)


def _maps_png(rows, v0, s0, v1, s1, result: dict) -> bytes:
    from relief_bsdf.report import html as H
    from relief_bsdf.report.fit_report import _plt, residual_image
    plt = _plt()
    z0, z1 = residual_z(rows, v0, s0), residual_z(rows, v1, s1)
    multi_wl = np.unique(rows.wavelength_nm).size > 1
    extra = [f"{w:g} nm" for w in rows.wavelength_nm] if multi_wl else None
    keys = {(s, t, e) for s, t, e in zip(np.asarray(rows.side).tolist(), np.asarray(rows.theta_i_deg).tolist(),
                                         extra or [""] * len(rows))}
    lim = max(3.0, float(np.nanpercentile(np.abs(np.concatenate([z0, z1])), 98)))
    fig, axs = plt.subplots(1, 2, figsize=(13.0, 1.8 + 0.42 * len(keys)), sharey=True)
    residual_image(axs[0], rows.side, rows.theta_i_deg, _signed(rows), z0, lim, extra)
    axs[0].set_title(f"baseline (rms {result['rms_before']:.3g})", fontsize=9)
    im = residual_image(axs[1], rows.side, rows.theta_i_deg, _signed(rows), z1, lim, extra)
    axs[1].set_title(f"with {', '.join(result.get('effects') or [result['effect']])} (rms {result['rms_after']:.3g})",
                     fontsize=9)
    fig.colorbar(im, ax=axs, pad=0.01, shrink=0.9).set_label(Z_LABEL, fontsize=8)
    return H.figure_png(fig)


def _curves_png(rows, v0, v1, result: dict) -> bytes:
    from relief_bsdf.report import html as H
    from relief_bsdf.report.fit_report import _plt
    plt = _plt()
    groups = sorted({(float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]))
                     for k in range(len(rows))})
    ncol = 3
    nrow = int(math.ceil(len(groups) / ncol))
    fig, axs = plt.subplots(nrow, ncol, figsize=(13, 3.3 * nrow), squeeze=False)
    x_all = _signed(rows)
    for ax, g in zip(axs.ravel(), groups):
        sel = np.nonzero((rows.wavelength_nm == g[0]) & (rows.side == g[1]) & (rows.theta_i_deg == g[2]))[0]
        o = np.argsort(x_all[sel])
        sel, x = sel[o], x_all[sel][o]
        ax.errorbar(x, rows.bsdf_sr[sel], rows.sigma_sr[sel], fmt=".", ms=3, color="k", label="recording")
        ax.plot(x, v0[sel], "-", color="tab:red", label="baseline")
        named = " + ".join(result.get("effects") or [result["effect"]])
        ax.plot(x, v1[sel], "-", color="tab:blue", label=f"with {named}")
        ax.axvline(-g[2], color="0.5", ls=":", lw=0.9, label="specular / undeviated")
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.set_title(f"{g[1]}, theta_i = {g[2]:g} deg" + (f", {g[0]:g} nm" if len({q[0] for q in groups}) > 1 else ""),
                     fontsize=9)
        ax.set_xlabel("signed scatter angle theta_s (deg)", fontsize=8)
        ax.set_ylabel("plate BSDF (1/sr)", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axs.ravel()[len(groups):]:
        ax.axis("off")
    axs.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    return H.figure_png(fig)


def _candidates_html(result: dict) -> str:
    from relief_bsdf.report import html as H
    rows = []
    for c in result["candidates"]:
        if c.get("skipped"):
            rows.append([c["effect"], "not tried", "", H.Raw(H.esc(c["skipped"]))])
        elif c.get("screened"):
            rows.append([c["effect"], "screened out", "", H.Raw(H.esc(c["screened"]))])
        else:
            params = ", ".join(f"{k} = {H.fmt(v)}" for k, v in (c.get("parameters") or {}).items())
            rows.append([c["effect"], c["rms_after"], c["score"], params])
    return H.table_html(["effect", "rms after", "score (BIC, lower is better)", "parameters"], rows)


def _notes_html(notes: dict) -> str:
    from relief_bsdf.report import html as H
    if not notes:
        return ""
    return "<ul class='small'>" + "".join(f"<li><b>{H.esc(k)}</b>: {H.esc(v)}</li>" for k, v in notes.items()) + "</ul>"


def _alternatives_html(alts: list) -> str:
    from relief_bsdf.report import html as H
    rows = [[a["named"], a["alternative"], H.fmt(a["bic_difference"], 3),
             ", ".join(f"{k} = {H.fmt(v)}" for k, v in a["alternative_parameters"].items())] for a in alts]
    return ("<p>Candidates that fitted almost as well as a named effect at the step that named it (BIC within the "
            "selection's margin): the recording does not decide between them.</p>"
            + H.table_html(["named", "fits almost as well", "BIC difference", "its parameters"], rows))


def _unexplained_html(u: dict) -> str:
    from relief_bsdf.report import html as H
    best = ", ".join(u["best_combination"]) or "no candidate passed the bar"
    rows = [[m["side"], m["theta_i_deg"], m["phi_s_deg"],
             f"{H.fmt(m['theta_s_deg'][0])} - {H.fmt(m['theta_s_deg'][1])}",
             f"{100 * m['share']:.1f} %", m.get("shape", "")] for m in u["residual"]]
    return (f"<p>Best combination tried: {H.esc(best)} (rms {H.fmt(u['rms_best_combination'], 3)}), still short of "
            f"the noise: not named as the cause. The residual it leaves resembles: "
            f"{H.esc('; '.join(u['resembles']) or 'none of the simple shapes')}.</p>"
            + H.table_html(["side", "theta_i (deg)", "phi_s (deg)", "theta_s range (deg)", "share", "shape"], rows))


def write_report(path: Path, rows, v0, s0, v1, s1, result: dict) -> Path:
    """report.html: verdict, parameters with intervals, residual maps (before/after), in-plane curves."""
    from relief_bsdf.report import html as H
    effects = result.get("effects") or [result["effect"]]
    if result.get("unexplained"):
        head = ("The simulation misses the recording and no combination of candidates explains it: "
                "<b>no cause named</b>.")
    else:
        head = f"Left out: <b>{H.esc(', '.join(effects))}</b>."
    verdict = (f"<div class='verdict {'ok' if result['rms_after'] < result['rms_before'] else 'warn'}'>"
               f"{head} Metric {H.fmt(result['rms_before'], 3)} (baseline) "
               f"&rarr; {H.fmt(result['rms_after'], 3)} with it modelled.</div>"
               f"<p>{H.esc(result['explanation'])}</p><p class='small'><b>Metric.</b> {H.esc(result['metric'])}</p>")
    params = (H.table_html(["parameter", "unit", "value", "68 % interval"],
                           H.parameter_rows(result["parameters"], result.get("intervals")))
              + _notes_html(result.get("interval_notes") or {})
              if result.get("parameters") else "<p>No parameters (no effect named).</p>")
    mis = H.table_html(["side", "theta_i (deg)", "phi_s (deg)", "theta_s range (deg)", "share of residual", "shape",
                        "explained by"],
                       [[m["side"], m["theta_i_deg"], m["phi_s_deg"],
                         f"{H.fmt(m['theta_s_deg'][0])} - {H.fmt(m['theta_s_deg'][1])}", f"{100 * m['share']:.1f} %",
                         m.get("shape", ""), m.get("explained_by", "")] for m in result["mismatch"]])
    sections = [H.section("Verdict", verdict), H.section("Fitted parameters", params)]
    if result.get("alternatives"):
        sections.append(H.section("Not told apart", _alternatives_html(result["alternatives"])))
    sections.append(H.section("Where the baseline misses", mis))
    if result.get("unexplained"):
        sections.append(H.section("What no candidate explains", _unexplained_html(result["unexplained"])))
    sections += [
                H.section("Candidates (best first)", _candidates_html(result)),
                H.section("Residual maps", H.figure_html(_maps_png(rows, v0, s0, v1, s1, result),
                                                         "Residual per point, baseline (left) and with the effect "
                                                         "(right): one row per side and incidence, same colour "
                                                         "scale.")),
                H.section("In-plane curves", H.figure_html(_curves_png(rows, v0, v1, result),
                                                           "Recording (points, 1 sigma), baseline (red) and with "
                                                           "the effect (blue); dotted: specular / undeviated "
                                                           "direction.")),
                H.section("Units and conventions", f"<p>{H.CONVENTIONS}</p>")]
    return write_text_atomic(path, H.page("Diagnosis", f"format {H.esc(result.get('format', ''))}", sections))
