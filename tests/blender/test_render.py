"""Plate renders: `relief render` (bpy module) and scenes/render_plate.py write before/after side by side."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

WIDTH = 96


def _read(path):
    from relief_bsdf.io import oiio as loader
    oiio = loader.load()
    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return buf.get_pixels(oiio.FLOAT)


def _halves(img):
    gap = max(2, WIDTH // 64)
    return img[:, :WIDTH, :3], img[:, WIDTH + gap:, :3]


def _check_pair(img):
    h = int(round(WIDTH * 0.75))
    assert img.shape[1] == 2 * WIDTH + max(2, WIDTH // 64)
    # below the renders: the boundary BSDF curves of both plates (plate_scene.with_bsdf_panel)
    assert img.shape[0] > h + 100
    panel = img[h + 2:, :, :3]
    assert panel.min() < 0.3 and panel.mean() > 0.6
    img = img[:h]
    left, right = _halves(img)
    # same board, light and camera: the rows above the plate (far board) agree within noise...
    top = slice(0, h // 6)
    assert np.mean(left[top]) == pytest.approx(np.mean(right[top]), rel=0.1)
    assert 0.05 < np.mean(left[top]) < 0.95
    return left, right


def _contrast(img, width):
    """Checkerboard contrast seen through the plate: std of 2x2-binned grey values in its centre."""
    h = img.shape[0]
    c = img[int(0.38 * h):int(0.62 * h), int(0.4 * width):int(0.6 * width)].mean(axis=2)
    c = c[: c.shape[0] // 2 * 2, : c.shape[1] // 2 * 2]
    return float(c.reshape(c.shape[0] // 2, 2, c.shape[1] // 2, 2).mean(axis=(1, 3)).std())


@pytest.mark.slow
def test_relief_render_cli_on_sample(tmp_path):
    out = tmp_path / "plate.png"
    r = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "render", str(REPO / "scenes/demo/sample.toml"),
                        "-o", str(out), "--width", str(WIDTH), "--samples", "4"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    _check_pair(_read(out))


def test_relief_render_cli_bad_input_exit_2(tmp_path):
    r = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "render", str(tmp_path / "missing.toml"),
                        "-o", str(tmp_path / "x.png")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert "missing.toml" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_scene_script_on_fit_folder(clean_bpy, tmp_path):
    """The scene script's code path (as under `blender --background --python`) on a fit folder."""
    fit = tmp_path / "fit"
    fit.mkdir()
    (fit / "fit.json").write_text(json.dumps({
        "format": "relief-fit/1", "sample": str(REPO / "scenes/demo/sample.toml"), "method": "microfacet+dw",
        "parameters": {"height_scale": 6.0, "filter_sigma_um": 0.0}, "rms_before": 1.0, "rms_after": 0.5}))
    spec = importlib.util.spec_from_file_location("render_plate_script", REPO / "scenes/render_plate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "fit.png"
    assert mod.main([str(fit), "-o", str(out), "--width", str(WIDTH), "--samples", "16"]) == 0
    left, right = _check_pair(_read(out))
    # the fit roughened the relief 6x: the checkerboard seen through the plate loses contrast
    assert _contrast(right, WIDTH) < 0.8 * _contrast(left, WIDTH)
    # bad input: one line, exit code 2
    assert mod.main([str(tmp_path), "-o", str(out)]) == 2


@pytest.mark.slow
def test_render_scene_code_ships_in_the_installed_distribution(tmp_path):
    """`relief render` works from an installed package: the backend wheel carries `relief_addon`
    (the scene code) beside `relief_bsdf`, and the command finds it there, not in a checkout."""
    sys.path.insert(0, str(REPO / "relief_addon"))
    try:
        import build_extension as bx
    finally:
        sys.path.remove(str(REPO / "relief_addon"))
    wheel = bx.build_backend_wheel(tmp_path / "cache")
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(site),
                        str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (site / "relief_addon" / "render_plate.py").is_file()
    assert (site / "relief_addon" / "data" / "cycles_albedo.npz").is_file()
    probe = ("import sys, relief_bsdf, relief_bsdf.jobs.render as c; f = c.plate_renderer(); "
             "print(relief_bsdf.__file__); print(sys.modules[f.__module__].__file__)")
    env = {**os.environ, "PYTHONPATH": str(site)}
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert all(line.startswith(str(site)) for line in r.stdout.split())
    bad = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "render", str(tmp_path / "missing.toml"), "-o",
                          str(tmp_path / "x.png")], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert bad.returncode == 2 and "missing.toml" in bad.stderr


def test_plate_scene_has_label_and_denoiser(clean_bpy):
    import bpy
    from relief_addon.plate_scene import _remove_scene, build_scene
    from relief_bsdf.bake import bake_lut
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.plate import flat_tables
    th = np.arange(0.0, 90.0, 10.0)
    lut = bake_lut(list(flat_tables(Material(ConstantIndex(1.5)), [550.0], th, th, np.linspace(0, 90, 10),
                                    np.arange(-15.0, 360, 30))), "flat")
    sc = build_scene({"label": "before fit", "lut": lut, "thickness_m": 0.003, "rough_face": "front", "ior": 1.5},
                     32, 4)
    import _cycles
    assert sc.cycles.use_denoising == bool(_cycles.with_openimagedenoise) and sc.cycles.sample_clamp_indirect > 0
    labels = [o for o in sc.collection.objects if o.type == "FONT"]
    assert [o.data.body for o in labels] == ["before fit"] and labels[0].parent == sc.camera
    # in front of the camera, beyond its clip start, inside the lower part of the frame
    from bpy_extras.object_utils import world_to_camera_view
    bpy.context.view_layer.update()
    for o in sc.collection.objects:
        if o.parent == sc.camera:
            o.matrix_world = sc.camera.matrix_world @ o.matrix_basis
    p = world_to_camera_view(sc, sc.camera, labels[0].matrix_world.translation)
    assert 0.0 < p.x < 1.0 and 0.0 < p.y < 0.25 and p.z > sc.camera.data.clip_start
    _remove_scene(sc)
