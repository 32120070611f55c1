"""HTML reports (report/html.py, report/fit_report.py, diagnose/report.py): one self-contained page,
formatted numbers, intervals, the stop verdict, labelled figures."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.io.recording import Recording
from relief_bsdf.report import html as H
from relief_bsdf.report.fit_report import fit_plots, stop_verdict, write_fit_report


def recording(seed=0, sides=("R", "T")) -> Recording:
    """An in-plane scan: R and T, three incidences, phi_s in {0, 180}, a lobe at the specular side."""
    rng = np.random.default_rng(seed)
    rows = []
    for side in sides:
        for ti in (0.0, 30.0, 60.0):
            for ps in (0.0, 180.0):
                for ts in np.arange(1.0, 89.0, 4.0):
                    x = -ts if ps == 180.0 else ts
                    v = 0.01 + np.exp(-((x + ti) / 8.0) ** 2)
                    rows.append((550.0, ti, 0.0, side, ts, ps, v * np.exp(0.05 * rng.standard_normal()), 0.05 * v))
    cols = list(zip(*rows))
    return Recording(wavelength_nm=np.array(cols[0]), theta_i_deg=np.array(cols[1]), phi_i_deg=np.array(cols[2]),
                     side=np.array(cols[3]), theta_s_deg=np.array(cols[4]), phi_s_deg=np.array(cols[5]),
                     bsdf_sr=np.array(cols[6]), sigma_sr=np.array(cols[7]))


def fit_doc(**over):
    doc = {"format": "relief-fit/1", "metric": "log-chi: sqrt(mean(r^2))", "rms_before": 3.2123456789,
           "rms_after": 1.0412345678, "parameters": {"height_scale": 0.812345678, "filter_sigma_um": 1.23456789},
           "intervals": {"height_scale": [0.79123, 0.83456], "filter_sigma_um": None},
           "correlation": {"names": ["height_scale", "filter_sigma_um"], "matrix": [[1.0, -0.634], [-0.634, 1.0]]},
           "iterations": [{"parameters": {"height_scale": 1.0 - 0.01 * k, "filter_sigma_um": 0.1 * k},
                           "rms": 3.0 - 0.1 * k} for k in range(8)],
           "stopped": "max_iter", "seconds": 12.3456, "method": "microfacet+dw", "sample": "demo/sample.toml",
           "physics": {"front": {"face": "relief", "method": "microfacet+dw"}, "thickness_m": 0.002,
                       "index": {"model": "constant", "n": 1.49}}}
    doc.update(over)
    return doc


def strip_images(text: str) -> str:
    return re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "IMG", text)


@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    """The fit's four figures of `recording()` (before: twice the recording, after: the recording), drawn
    once for the module; `drawn(folder)` copies them into a test's own folder (the pages read them beside
    themselves) and returns `fit_plots`'s {name: file name}.  Nothing writes to the drawn originals."""
    import shutil
    src = tmp_path_factory.mktemp("fit_plots")
    rec = recording()
    plots = fit_plots(src, rec, rec.bsdf_sr * 2, rec.bsdf_sr)

    def into(folder: Path) -> dict:
        for name in plots.values():
            shutil.copyfile(src / name, folder / name)
        return dict(plots)
    return into


@pytest.mark.slow
def test_fit_report_is_self_contained_and_readable(tmp_path):
    rec = recording()
    rng = np.random.default_rng(1)
    before = rec.bsdf_sr * np.exp(0.6 * rng.standard_normal(len(rec)))
    after = rec.bsdf_sr * np.exp(0.05 * rng.standard_normal(len(rec)))
    plots = fit_plots(tmp_path, rec, before, after)
    render = tmp_path / "render.png"
    render.write_bytes((tmp_path / plots["plot_after"]).read_bytes())
    path = write_fit_report(tmp_path / "report.html", fit_doc(), plots, renders={"plate render after the fit": render})
    text = path.read_text()
    assert text.count("data:image/png;base64,") == 5                 # 4 figures + the render, embedded
    assert not re.search(r'src="(?!data:)', text)                    # no relative image paths: can be e-mailed
    body = strip_images(text)
    assert "plot_before" not in body and "residual_after" not in body  # captions, not internal keys
    assert "0.8123" in body and "0.812345678" not in body             # formatted numbers, not raw JSON
    assert "[0.7912, 0.8346]" in body and "not determined" in body    # intervals; null interval
    assert "-0.634" in body                                            # correlation shown
    assert "Not converged" in body and "evaluation limit" in body      # whether and why it stopped
    assert "microfacet+dw" in body and "1.49" in body                  # the physics used
    assert "1/sr" in body and "68 %" in body                           # units and conventions
    assert "plate render after the fit" in body


@pytest.mark.slow
def test_fit_report_without_intervals_or_render(tmp_path, drawn):
    plots = drawn(tmp_path)
    doc = fit_doc(stopped="converged")
    del doc["intervals"], doc["correlation"]
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "not computed" in body and "Plate renders" not in body and "Converged" in body


def test_stop_verdicts():
    assert stop_verdict(fit_doc(stopped="threshold"))[0] == "ok"
    assert stop_verdict(fit_doc(stopped="max_iter"))[0] == "warn"
    assert "Converged" in stop_verdict(fit_doc(stopped="converged"))[1]


def test_number_formatting():
    assert H.fmt(0.812345678) == "0.8123"
    assert H.fmt(1.234e-7) == "1.234e-07"
    assert H.fmt(float("nan")) == "n/a" and H.fmt(None) == "n/a" and H.fmt(3) == "3"
    rows = H.parameter_rows({"absorption_per_mm": 0.12, "x": 1.0}, {"absorption_per_mm": [0.1, 0.13]})
    assert rows[0][1] == "1/mm" and rows[0][3] == "[0.1, 0.13]" and rows[1][3] == "not determined"


def test_residual_map_has_one_row_per_incidence(tmp_path, drawn):
    """Readable aspect: a few incidences x many angles are rows of an image, not thin stripes."""
    import matplotlib.image as mpimg
    plots = drawn(tmp_path)
    img = mpimg.imread(tmp_path / plots["residual_before"])
    h, w = img.shape[:2]
    assert 0.3 < h / w < 1.0                                           # six rows on a page-wide image


def test_diagnosis_report_same_style(tmp_path):
    from relief_bsdf.diagnose.report import write_report
    rec = recording()
    result = {"format": "relief-diagnosis/1", "metric": "chi", "rms_before": 4.56789, "rms_after": 1.23456,
              "effect": "bulk_absorption", "effects": ["bulk_absorption"], "parameters": {"absorption_per_mm": 0.1234567},
              "intervals": {"absorption_per_mm": [0.11, 0.135]},
              "mismatch": [{"side": "T", "theta_i_deg": 60.0, "phi_s_deg": 180.0, "theta_s_deg": [35.0, 70.0],
                            "share": 0.55}],
              "candidates": [{"effect": "bulk_absorption", "rms_after": 1.23456, "score": -812.0,
                              "parameters": {"absorption_per_mm": 0.1234567}},
                             {"effect": "stray_light", "skipped": "no T rows"}],
              "alternatives": [{"named": "bulk_absorption", "alternative": "volume_scattering", "bic_difference": 4.25,
                                "alternative_parameters": {"scatter_per_mm": 0.0871}}],
              "explanation": "light is absorbed in the bulk"}
    s = np.full(len(rec), 0.05) * rec.bsdf_sr
    path = write_report(tmp_path / "report.html", rec, rec.bsdf_sr * 1.5, s, rec.bsdf_sr, s, result)
    text = path.read_text()
    assert text.count("data:image/png;base64,") == 2
    body = strip_images(text)
    assert H.STYLE.strip()[:30] in body                                # the house style
    assert "0.1235" in body and "[0.11, 0.135]" in body and "55.0 %" in body
    assert "not tried" in body and "1/sr" in body
    assert "Not told apart" in body and "volume_scattering" in body and "scatter_per_mm = 0.0871" in body


def test_relief_render_of_a_fit_folder_embeds_the_plate_render_in_its_report(tmp_path, drawn):
    """`relief render FITDIR` (what `make demo` runs after the fit) rewrites FITDIR/report.html with
    the before | after plate render embedded beside the fit's own figures (jobs.render.embed_in_report;
    the Cycles render itself is tested in tests/blender/test_render.py)."""
    import json
    import matplotlib.image as mpimg
    from relief_bsdf.jobs.render import embed_in_report
    plots = drawn(tmp_path)
    (tmp_path / "fit.json").write_text(json.dumps(fit_doc(files={"boundary_table": "boundary.h5", **plots})))
    write_fit_report(tmp_path / "report.html", fit_doc(), plots)
    assert "Plate renders" not in strip_images((tmp_path / "report.html").read_text())
    png = tmp_path / "plate.png"
    mpimg.imsave(png, np.linspace(0.0, 1.0, 48 * 100).reshape(48, 100), cmap="gray")
    path = embed_in_report(tmp_path, png)
    text = path.read_text()
    assert path == tmp_path / "report.html" and text.count("data:image/png;base64,") == 5   # 4 figures + render
    assert not re.search(r'src="(?!data:)', text)
    body = strip_images(text)
    assert "Plate renders" in body and "before | after" in body


def test_fit_report_says_how_the_estimate_and_its_intervals_were_made(tmp_path, drawn):
    plots = drawn(tmp_path)
    doc = fit_doc(identifiability={"filter_needed": False, "criterion": "BIC rule",
                                   "estimate": "likelihood optimum", "interval_method": "Newey-West"})
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "BIC rule; likelihood optimum; Newey-West." in body
    del doc["identifiability"]["estimate"]                       # a fit.json without the estimate
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "BIC rule; Newey-West." in body


def _steps_result():
    """A diagnosis whose remainder looks like stray light that the search screened out at step 2."""
    return {"format": "relief-diagnosis/1", "metric": "rms z", "rms_before": 11.4, "rms_after": 7.81,
            "effect": "polarization", "effects": ["polarization"], "parameters": {"stokes_q": -0.9},
            "intervals": {"stokes_q": [-0.95, -0.85]}, "mismatch": [], "candidates": [],
            "explanation": "polarised", "selection": {"chi2_baseline": 138000.0, "n_rows": 1068},
            "steps": [{"model": ["polarization"], "chi2": 64329.2, "added": "polarization", "candidates": [
                          {"effect": "polarization", "status": "fitted", "chi2": 64400.0, "bic_gain": 73000.0,
                           "reason": "named: the largest BIC gain of the step"},
                          {"effect": "stray_light", "status": "screened", "chi2": 130000.0, "bic_gain": 7993.0,
                           "reason": "not fitted: its linear screen gains at most about chi2 8000"}]},
                      {"model": ["polarization"], "chi2": 64329.2, "added": None, "candidates": [
                          {"effect": "stray_light", "status": "screened", "chi2": 64300.0, "bic_gain": 22.1,
                           "reason": "not fitted: short of the bar (BIC gain above 40)"},
                          {"effect": "bulk_absorption", "status": "skipped", "chi2": None, "bic_gain": None,
                           "reason": "stated in sample.toml"}]}],
            "stop": "step 2: no candidate was fitted"}


def test_diagnosis_report_shows_every_step_and_why_the_search_stopped(tmp_path):
    from relief_bsdf.diagnose.report import write_report
    rec = recording()
    s = 0.05 * rec.bsdf_sr
    body = strip_images(write_report(tmp_path / "r.html", rec, rec.bsdf_sr * 1.5, s, rec.bsdf_sr, s,
                                     _steps_result()).read_text())
    i = body.index("The search, step by step")
    steps = body[i:]
    assert "Step 1" in steps and "Step 2" in steps and "named <b>polarization</b>" in steps
    assert steps.count("screened out") == 2 and "not tried" in steps and "stated in sample.toml" in steps
    assert "short of the bar (BIC gain above 40)" in steps and "22.1" in steps
    assert "Why the search stopped:</b> step 2: no candidate was fitted" in steps


def test_a_remainder_shaped_like_a_screened_candidate_says_so_with_its_numbers():
    from relief_bsdf.diagnose.mismatch import SHAPE_PHYSICS
    from relief_bsdf.diagnose.report import SHAPE_EFFECTS, shape_against_search
    assert set(SHAPE_EFFECTS) == set(SHAPE_PHYSICS)
    r = _steps_result()
    text = shape_against_search([{"shape": "offset", "explained": 0.95}], r["steps"], r["effects"])
    assert "95 % offset" in text and "stray light was screened out at step 2" in text
    assert "chi2 6.43e+04 (screen estimate), BIC gain 22.1" in text and "short of the bar" in text
    # a shape whose effect is named, or a weak shape, adds nothing
    assert shape_against_search([{"shape": "asymmetry", "explained": 0.9}], r["steps"], ["polarization",
                                                                                         "sample_tilt"]) == ""
    assert shape_against_search([{"shape": "offset", "explained": 0.2}], r["steps"], r["effects"]) == ""


def _figures(monkeypatch, module, attr):
    """Capture the matplotlib figures a report function saves (drawn, not closed)."""
    figs = []
    real = getattr(module, attr)

    def keep(fig, *a, **k):
        fig.canvas.draw()
        figs.append(fig)
        return real(fig, *a, **k)
    monkeypatch.setattr(module, attr, keep)
    return figs


@pytest.mark.parametrize("sides", ["RT", "T"])
def test_bsdf_plots_end_at_the_noise_level_with_legends_inside_and_no_empty_panel(tmp_path, monkeypatch, sides):
    """Log axes from the recording's noise level up (no spike to 1e-12 where a row is 0, no tick <= 0), rows
    below it as censored triangles at that level, the legend inside the saved figure, one panel per side
    the recording has (a transmission-only file: no reflection panel); the diagnosis curves likewise."""
    from relief_bsdf.diagnose import report as D
    from relief_bsdf.report import fit_report as F
    from relief_bsdf.report import html as HH
    rec = recording(sides=tuple(sides))
    sim = rec.bsdf_sr.copy()
    sim[::5] = 0.0                                   # simulated rows at exactly zero
    floor = F.noise_level(rec)
    assert floor > 1e-4
    figs = _figures(monkeypatch, F, "_save")
    F.fit_plots(tmp_path, rec, sim, rec.bsdf_sr)
    dfigs = _figures(monkeypatch, HH, "figure_png")
    D.write_report(tmp_path / "d.html", rec, sim, 0 * sim, rec.bsdf_sr, 0 * sim, {
        "format": "relief-diagnosis/1", "metric": "rms z", "rms_before": 2.0, "rms_after": 1.0, "effect": "none",
        "effects": ["none"], "parameters": {}, "mismatch": [], "candidates": [], "explanation": "x"})
    curves = [figs[0], figs[1], dfigs[1]]            # in-plane before / after; the diagnosis's curves
    for fig in curves:
        axes = [a for a in fig.axes if a.get_yscale() == "log"]
        assert axes and len(axes) == len(fig.axes)   # no empty panel, every panel a BSDF panel
        for ax in axes:
            lo, hi = ax.get_ylim()
            assert lo >= floor / 1.6 * (1 - 1e-9) and hi > lo
            assert all(t > 0 for t in ax.get_yticks() if lo <= t <= hi)
            for line in ax.get_lines():
                if line.get_transform() != ax.transData:
                    continue                         # a vertical / horizontal marker line (axes coordinates)
                y = np.asarray(line.get_ydata(), float)
                assert np.all(y[np.isfinite(y)] >= floor * (1 - 1e-9))
        assert fig.legends, "one figure legend"
        fb, lb = fig.bbox, fig.legends[0].get_window_extent()
        assert fb.x0 - 1 <= lb.x0 and lb.x1 <= fb.x1 + 1 and fb.y0 - 1 <= lb.y0 and lb.y1 <= fb.y1 + 1
    assert len(figs[0].axes) == len(sides)
    assert sum(ax.get_title().startswith("R,") for ax in dfigs[1].axes) == (0 if sides == "T" else 3)


def test_fit_report_names_the_algorithm_that_ran_and_every_file_written(tmp_path, drawn):
    plots = drawn(tmp_path)
    from relief_bsdf.fit.optimise import ALGORITHM
    files = {"boundary_table": "boundary.h5", "isbsdf_outside": ["boundary_outside_brdf.bsdf",
                                                                  "boundary_outside_btdf.bsdf"],
             "relief": "relief_optimised.npz", "simulated": "simulated.csv", **plots}
    doc = fit_doc(stopped="converged", algorithm=ALGORITHM, files=files)
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "Nelder" not in body and "Gauss-Newton" in body and "response surface" in body
    files_sec = body[body.index("Files written"):]
    for name in ("fit.json", "report.html", "checkpoint.json", "boundary.h5", "boundary_outside_brdf.bsdf",
                 "boundary_outside_btdf.bsdf", "relief_optimised.npz", "simulated.csv", "in_plane_before.png",
                 "residual_after.png"):
        assert f"<td>{name}</td>" in files_sec, name
    assert "OpticStudio" in files_sec and "optimised relief" in files_sec


def test_user_paths_writes_derived_paths_in_the_users_terms(tmp_path):
    from relief_bsdf.report.html import user_paths
    import os
    doc = {"sample": "runs/sample.toml", "physics": {"relief": os.path.abspath("runs/relief.npz")},
           "notes": [f"read {os.path.abspath('out/x.csv')}"]}
    fixed = user_paths(doc, "runs/sample.toml", "out")
    assert fixed == {"sample": "runs/sample.toml", "physics": {"relief": os.path.join("runs", "relief.npz")},
                     "notes": [f"read {os.path.join('out', 'x.csv')}"]}
    absolute = str(tmp_path / "sample.toml")
    assert user_paths({"a": str(tmp_path / "r.npz")}, absolute) == {"a": str(tmp_path / "r.npz")}
    here = os.path.abspath("runs")
    assert user_paths({"a": here + "x/r.npz", "b": "1/sr"}, "runs/sample.toml") == {"a": here + "x/r.npz", "b": "1/sr"}
    assert user_paths({"a": f"in {here}, then"}, "runs/sample.toml") == {"a": "in runs, then"}
    assert user_paths({"b": "1/sr, /a/b"}, "/sample.toml") == {"b": "1/sr, /a/b"}       # the root: nothing


def test_relief_plot_of_a_transmission_only_table_has_no_reflection_panel_and_keeps_its_legend(tmp_path):
    """A BTDF-only table (a measured IS-BSDF file read as a table): one side, no empty R panel; the saved
    file holds the legend beside the axes."""
    import matplotlib.image as mpimg
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.methods.request import Request
    from relief_bsdf.report.plots import save_figure, sides_with_data, table_figure
    req = Request(theta_i_deg=(0.0, 30.0), incident_from=("outside",), theta_s_edges_deg=tuple(np.linspace(0, 90, 19)),
                  phi_s_edges_deg=tuple(np.arange(-15.0, 360, 30)), options={"alpha": 0.3, "distribution": "ggx"})
    (t,) = [x for x in reconstruct(None, Material(ConstantIndex(1.5)), req, "microfacet")
            if x.incident_from == "outside"]
    assert sides_with_data([t], ("R", "T")) == ["R", "T"]
    from dataclasses import replace
    v = np.array(t.values_per_sr, copy=True)
    v[..., 0] = 0.0
    btdf = replace(t, values_per_sr=v, specular_R=np.zeros_like(t.specular_R))
    assert sides_with_data([btdf], ("R", "T")) == ["T"]
    fig = table_figure(btdf)
    curves = [a for a in fig.axes if a.get_legend() is not None]      # the in-plane panels
    assert len(curves) == 1 and "transmission" in curves[0].get_title()
    assert all(a.get_title().startswith("T,") for a in fig.axes if a.name == "polar")
    fig.canvas.draw()
    legend = curves[0].get_legend().get_window_extent()
    path = save_figure(fig, tmp_path / "btdf.png")
    w_px = mpimg.imread(path).shape[1]
    assert w_px >= legend.x1 * 110 / fig.dpi - 2      # the legend beside the axes is inside the saved file
