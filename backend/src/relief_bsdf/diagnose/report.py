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

__all__ = ["SHAPE_EFFECTS", "shape_against_search", "write_report"]

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
    """One panel per (wavelength, side, incidence) the recording has (no empty panel), log BSDF axes
    ending at the recording's noise level (values below it: triangles at that level), one legend
    under the panels, inside the figure."""
    from matplotlib.lines import Line2D
    from relief_bsdf.report import html as H
    from relief_bsdf.report.fit_report import _plt, censored, finish_log_axis, legend_below, noise_level
    plt = _plt()
    groups = sorted({(float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]))
                     for k in range(len(rows))})
    ncol = min(3, len(groups))
    nrow = int(math.ceil(len(groups) / ncol))
    fig, axs = plt.subplots(nrow, ncol, figsize=(4.4 * ncol, 3.3 * nrow + 0.8), squeeze=False)
    x_all = _signed(rows)
    floor = noise_level(rows)
    named = " + ".join(result.get("effects") or [result["effect"]])
    y_all, s_all = np.asarray(rows.bsdf_sr, float), np.asarray(rows.sigma_sr, float)
    for ax, g in zip(axs.ravel(), groups):
        sel = np.nonzero((rows.wavelength_nm == g[0]) & (rows.side == g[1]) & (rows.theta_i_deg == g[2]))[0]
        o = np.argsort(x_all[sel])
        sel, x = sel[o], x_all[sel][o]
        y, sg = y_all[sel], s_all[sel]
        up = y >= floor
        ax.errorbar(x[up], y[up], np.where(np.isfinite(sg[up]), np.minimum(sg[up], y[up] - floor / 1.6), 0.0),
                    fmt=".", ms=3, color="k", lw=0.8)
        ax.plot(x[~up], np.full(int((~up).sum()), floor), "v", color="k", ms=3.5, mfc="none", ls="none")
        censored(ax, x, np.asarray(v0)[sel], floor, "-", "tab:red")
        censored(ax, x, np.asarray(v1)[sel], floor, "-", "tab:blue")
        ax.axvline(-g[2], color="0.5", ls=":", lw=0.9)
        finish_log_axis(ax, floor, [y, np.asarray(v0)[sel], np.asarray(v1)[sel]])
        ax.axhline(floor, color="0.6", lw=0.6)
        ax.set_title(f"{g[1]}, theta_i = {g[2]:g} deg" + (f", {g[0]:g} nm" if len({q[0] for q in groups}) > 1 else ""),
                     fontsize=9)
        ax.set_xlabel("signed scatter angle theta_s (deg)", fontsize=8)
        ax.set_ylabel("plate BSDF (1/sr)", fontsize=8)
        ax.grid(alpha=0.3, which="both")
    for ax in axs.ravel()[len(groups):]:
        fig.delaxes(ax)
    handles = [Line2D([], [], color="k", marker=".", ls="none"), Line2D([], [], color="tab:red"),
               Line2D([], [], color="tab:blue"), Line2D([], [], color="0.5", ls=":"),
               Line2D([], [], color="k", marker="v", mfc="none", ls="none")]
    labels = ["recording (1 sigma)", "baseline", f"with {named}", "specular / undeviated direction",
              f"below the recording's noise level {floor:.2g} 1/sr (censored)"]
    h = legend_below(fig, handles, labels, ncol=3 if ncol > 1 else 1)
    fig.tight_layout(rect=(0, h, 1, 1))
    return H.figure_png(fig)


STATUS_WORDS = {"fitted": "fitted", "screened": "screened out", "outgained": "outgained",
                "skipped": "not tried", "dropped": "dropped"}


def _steps_html(result: dict) -> str:
    """Every step of the search (diagnosis.json `steps` and `stop`): what each candidate did, why."""
    from relief_bsdf.report import html as H
    steps = result.get("steps")
    if not steps:
        return "<p>This diagnosis.json holds no record of the search's steps.</p>"
    sel = result.get("selection") or {}
    out = []
    if sel.get("chi2_baseline") is not None:
        out.append(f"<p>Baseline (the plate as described): chi2 = {H.fmt(sel['chi2_baseline'])} for "
                   f"{H.fmt(sel.get('n_rows'))} rows. Each step fits every remaining candidate with the named "
                   f"effects held, names the one with the largest gain in BIC = chi2 + k ln n if it passes the "
                   f"bar (judged on chi2 divided by the larger model's reduced chi2 while it misses the noise: "
                   f"QBIC), then refits all named effects jointly (the step's chi2 is after that refit).</p>")
    prev = []
    for k, st in enumerate(steps, 1):
        before = ", ".join(prev) or "the baseline"
        what = (f"named <b>{H.esc(st['added'])}</b>" if st.get("added") else "named nothing")
        out.append(f"<h3>Step {k}: from {H.esc(before)}, {what}; model {H.esc(', '.join(st['model']) or 'none')}, "
                   f"chi2 {H.fmt(st['chi2'])}</h3>")
        rows = [[c["effect"], STATUS_WORDS.get(c["status"], c["status"]),
                 c["chi2"] if c.get("chi2") is not None else "", c["bic_gain"] if c.get("bic_gain") is not None else "",
                 c.get("reason", "")] for c in st.get("candidates", [])]
        out.append(H.table_html(["candidate", "status", "chi2 (screened: estimate)", "BIC gain", "why"], rows))
        for c in st.get("correlations") or []:
            r = c.get("correlation")
            out.append(f"<p>{H.esc(' and '.join(c['pair']))} trade against each other on these rows (both widen, "
                       f"narrow or move a lobe): fitted jointly from both starts, correlation of "
                       f"{H.esc(' and '.join(c['parameters']))} {H.fmt(r) if r is not None else 'not determined'}"
                       f"{' (the rows hardly tell them apart)' if r is not None and abs(r) > 0.9 else ''}.</p>")
        prev = list(st["model"])
    out.append(f"<p><b>Why the search stopped:</b> {H.esc(result.get('stop') or 'not recorded')}.</p>")
    check = result.get("method_check")
    if check:
        out.append(f"<p><b>The boundary method</b> ({H.esc(check.get('method') or '')}): "
                   f"{H.esc(check.get('verdict') or '')}.</p>")
    return "".join(out)


# the candidate effects that make each residual shape of `mismatch.SHAPE_PHYSICS` (the same physics
# its words name: an offset is stray light, a broadening a blur, a relief scale or smoothing, ...)
SHAPE_EFFECTS = {
    "offset": ("stray_light",),
    "gain": (),
    "shift": ("sample_tilt", "refractive_index"),
    "broadening": ("instrument_blur", "relief_scale", "relief_smoothing", "back_face_roughness"),
    "path_deficit": ("bulk_absorption", "volume_scattering"),
    "asymmetry": ("sample_tilt", "polarization"),
    "colour_trend": ("dispersion",),
}


def shape_against_search(shapes: list, steps: list, named: list) -> str:
    """Sentences that keep the shape analysis of a remainder consistent with the search: for each shape
    the remainder resembles (more than 30 % of it, at most two, as the explanation's own words), every
    candidate that makes that shape and was not named, with what the search's last step that
    considered it did and its numbers (`steps`: diagnosis.json's record).  '' when there is none."""
    out = []
    for sh in [x for x in shapes if x.get("explained", 0.0) > 0.3][:2]:
        word = sh["shape"].replace("_", " ")
        parts = []
        for effect in SHAPE_EFFECTS.get(sh["shape"], ()):
            if effect in named:
                continue
            found = next(((k, c) for k, st in reversed(list(enumerate(steps, 1)))
                          for c in st.get("candidates", []) if c["effect"] == effect), None)
            if found is None:
                parts.append(f"{effect.replace('_', ' ')} was not among the candidates searched")
                continue
            k, c = found
            nums = []
            if c.get("chi2") is not None:
                nums.append(f"chi2 {c['chi2']:.4g}" + (" (screen estimate)" if c["status"] in ("screened",
                                                                                           "outgained") else ""))
            if c.get("bic_gain") is not None:
                nums.append(f"BIC gain {c['bic_gain']:.1f}")
            parts.append(f"{effect.replace('_', ' ')} was {STATUS_WORDS.get(c['status'], c['status'])} at step {k}"
                         + (f" ({', '.join(nums)})" if nums else "") + f": {c['reason']}")
        if parts:
            out.append(f" The remainder is {100 * sh['explained']:.0f} % {word}, a signature of "
                       f"{' or '.join(e.replace('_', ' ') for e in SHAPE_EFFECTS[sh['shape']])}, yet none of them "
                       f"is named: " + "; ".join(parts) + ".")
    return "".join(out)


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
             ", ".join(f"{k} = {H.fmt(v)}" for k, v in a["alternative_parameters"].items()),
             H.fmt(a["correlation"], 3) if a.get("correlation") is not None else ""] for a in alts]
    return ("<p>Candidates that fitted almost as well as a named effect at the step that named it (BIC within the "
            "selection's margin), and members of a trading pair whose fitted correlation is near 1 that the rows "
            "do not separate from the named one: the recording does not decide between them.</p>"
            + H.table_html(["named", "alternative", "BIC difference", "its parameters", "correlation"], rows))


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
               f"{head} Metric (rms z) {H.fmt(result['rms_before'], 3)} (baseline) "
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
                H.section("The search, step by step", _steps_html(result)),
                H.section("Candidates at the first step (best first)", _candidates_html(result)),
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
