"""The demo picture's boundary-BSDF panel: curves before / after a fit, haze in the legend."""
import numpy as np
import pytest

from relief_bsdf.plate import ReliefFace, TableGrid
from relief_bsdf.report.plots import before_after_figure, boundary_haze, figure_rgb


def _outside_table(relief, glass):
    face = ReliefFace(relief, method="microfacet", samples=1000, seed=0)
    out, _ = face.tables(glass, TableGrid(2.0, 10.0, 10.0), [550.0], np.array([0.0, 30.0]), True)
    return out


@pytest.mark.slow
def test_haze_grows_with_the_relief_slopes_and_the_panel_draws_both_tables(gaussian_relief, glass):
    gentle = _outside_table(gaussian_relief(64, 1e-6, 0.2e-6, 8e-6, seed=1), glass)
    rough = _outside_table(gaussian_relief(64, 1e-6, 0.6e-6, 8e-6, seed=1), glass)
    h_gentle, h_rough = boundary_haze(gentle), boundary_haze(rough)
    # rms slope ~0.035 vs ~0.1: the transmitted lobe (deviation ~ (n - 1) slope) widens past 2.5 deg
    assert 0.0 <= h_gentle < h_rough <= 1.0
    fig = before_after_figure([gentle, rough], ["before fit", "after fit"], width_px=400, height_px=240)
    texts = [t.get_text() for ax in fig.axes for t in ax.get_legend().get_texts()]
    assert any(f"haze {100 * h_rough:.0f} %" in t for t in texts)
    assert any(t.startswith("before fit") for t in texts) and any(t.startswith("after fit") for t in texts)
    rgb = figure_rgb(fig)
    assert rgb.shape == (240, 400, 3)
    assert rgb.min() < 0.3 and np.mean(rgb) > 0.6          # lines and text on a white page


def test_demo_picture_gets_the_panel_below_the_renders(gaussian_relief, glass):
    from relief_addon.plate_scene import with_bsdf_panel
    t = _outside_table(gaussian_relief(64, 1e-6, 0.3e-6, 8e-6, seed=2), glass)
    img = np.full((72, 194, 3), 0.5, np.float32)
    out = with_bsdf_panel(img, [{"label": "before fit", "table_outside": t}, {"label": "after fit", "table_outside": t}])
    assert out.shape[1] == 194 and out.shape[0] > 72 + 100
    assert np.array_equal(out[:72], img)
    # no outside table (e.g. a plate without one): the picture is left as it is
    assert with_bsdf_panel(img, [{"label": "x", "table_outside": None}]) is img


@pytest.mark.slow
def test_the_demo_fit_changes_the_haze_the_picture_shows(tmp_path):
    """Issue 15 item 5 on the demo itself: `make demo` renders the relief as measured (before) and with
    the fitted scale and filter (after; the fit recovers make_demo's truth, fit/test_fit_real_relief.py).
    The picture's boundary tables (plate_scene.prepare_plates, bpy-free) must differ in haze by more
    than 5 points, or the two plates look alike (measured: 55 % -> 64 %)."""
    import importlib.util
    import json
    from pathlib import Path
    from relief_addon.plate_scene import prepare_plates
    repo = Path(__file__).resolve().parents[3]
    spec = importlib.util.spec_from_file_location("make_demo", repo / "scenes" / "make_demo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    (tmp_path / "fit.json").write_text(json.dumps({
        "format": "relief-fit/1", "sample": str(repo / "scenes/demo/sample.toml"), "method": "ray",
        "parameters": {"height_scale": demo.TRUE_SCALE, "filter_sigma_um": demo.TRUE_FILTER_UM}}))
    before, after = prepare_plates(tmp_path)
    assert (before["label"], after["label"]) == ("before fit", "after fit")
    h0, h1 = boundary_haze(before["table_outside"]), boundary_haze(after["table_outside"])
    assert abs(h1 - h0) > 0.05, (h0, h1)
