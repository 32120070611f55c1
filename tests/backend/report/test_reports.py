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


def recording(seed=0) -> Recording:
    """An in-plane scan: R and T, three incidences, phi_s in {0, 180}, a lobe at the specular side."""
    rng = np.random.default_rng(seed)
    rows = []
    for side in ("R", "T"):
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
def test_fit_report_without_intervals_or_render(tmp_path):
    rec = recording()
    plots = fit_plots(tmp_path, rec, rec.bsdf_sr * 2, rec.bsdf_sr)
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


def test_residual_map_has_one_row_per_incidence(tmp_path):
    """Readable aspect: a few incidences x many angles are rows of an image, not thin stripes."""
    import matplotlib.image as mpimg
    rec = recording()
    plots = fit_plots(tmp_path, rec, rec.bsdf_sr * 2, rec.bsdf_sr)
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


def test_relief_render_of_a_fit_folder_embeds_the_plate_render_in_its_report(tmp_path):
    """`relief render FITDIR` (what `make demo` runs after the fit) rewrites FITDIR/report.html with
    the before | after plate render embedded beside the fit's own figures (cmd_render._embed_in_report;
    the Cycles render itself is tested in tests/blender/test_render.py)."""
    import json
    import matplotlib.image as mpimg
    from relief_bsdf.cli.cmd_render import _embed_in_report
    rec = recording()
    plots = fit_plots(tmp_path, rec, rec.bsdf_sr * 2, rec.bsdf_sr)
    (tmp_path / "fit.json").write_text(json.dumps(fit_doc(files={"boundary_table": "boundary.h5", **plots})))
    write_fit_report(tmp_path / "report.html", fit_doc(), plots)
    assert "Plate renders" not in strip_images((tmp_path / "report.html").read_text())
    png = tmp_path / "plate.png"
    mpimg.imsave(png, np.linspace(0.0, 1.0, 48 * 100).reshape(48, 100), cmap="gray")
    path = _embed_in_report(tmp_path, png)
    text = path.read_text()
    assert path == tmp_path / "report.html" and text.count("data:image/png;base64,") == 5   # 4 figures + render
    assert not re.search(r'src="(?!data:)', text)
    body = strip_images(text)
    assert "Plate renders" in body and "before | after" in body


def test_fit_report_says_how_the_estimate_and_its_intervals_were_made(tmp_path):
    rec = recording()
    plots = fit_plots(tmp_path, rec, rec.bsdf_sr * 2, rec.bsdf_sr)
    doc = fit_doc(identifiability={"filter_needed": False, "criterion": "BIC rule",
                                   "estimate": "likelihood optimum", "interval_method": "Newey-West"})
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "BIC rule; likelihood optimum; Newey-West." in body
    del doc["identifiability"]["estimate"]                       # a fit.json of an earlier round
    body = strip_images(write_fit_report(tmp_path / "r.html", doc, plots).read_text())
    assert "BIC rule; Newey-West." in body
