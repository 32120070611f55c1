"""Register / unregister, import of real height maps, operators' error reports."""
from __future__ import annotations

import numpy as np
import pytest

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TOPO = REPO / "tests" / "data" / "topography"   # instrument files (SOURCE.md)

import bpy


def _snapshot():
    return {
        "types": set(dir(bpy.types)),
        "ops": set(dir(bpy.ops.relief)),
        "scene": set(bpy.types.Scene.bl_rna.properties.keys()),
        "object": set(bpy.types.Object.bl_rna.properties.keys()),
        "import_menu": len(getattr(bpy.types.TOPBAR_MT_file_import, "_dyn_ui_initialize", lambda: [])()),
    }


def test_register_unregister_leave_nothing_behind(clean_bpy):
    import relief_addon
    before = _snapshot()
    relief_addon.register()
    during = _snapshot()
    # what the add-on promises while registered
    assert {"import_heightmap", "reconstruct", "simulate_plate", "fit", "diagnose", "infer", "bake_bsdf",
            "render_plate"} <= during["ops"]
    assert "relief" in during["scene"] and "relief_z_scale" in during["object"]
    assert {"RELIEF_PT_relief", "RELIEF_PT_reconstruct", "RELIEF_PT_plate", "RELIEF_PT_bake_render",
            "RELIEF_FH_heightmap"} <= during["types"]
    assert during["import_menu"] == before["import_menu"] + 1
    relief_addon.unregister()
    after = _snapshot()
    assert after == before
    # and again: a second cycle works (no stale class registrations)
    relief_addon.register()
    relief_addon.unregister()
    assert _snapshot() == before


def test_file_handler_covers_backend_formats(addon):
    fh = bpy.types.RELIEF_FH_heightmap
    exts = set(fh.bl_file_extensions.split(";"))
    assert {".x3p", ".gwy", ".sur", ".sdf", ".tif", ".tiff", ".exr", ".npz"} <= exts
    from relief_addon.operators import reader_suffixes
    # the file browser filter offers every suffix the SurfaceTopography readers know
    assert {"x3p", "gwy", "sur", "sdf", "npz", "exr", "frt", "plu", "opd", "nid", "mi"} <= set(reader_suffixes())


@pytest.mark.parametrize("name", ["ST_x3p-2.x3p", "ST_frt-1.frt"])
def test_import_real_file_true_heights(addon, name):
    from relief_bsdf.io.heightmaps import read_relief
    path = TOPO / name
    relief = read_relief(path)
    assert bpy.ops.relief.import_heightmap(filepath=str(path), z_scale=10.0) == {"FINISHED"}
    obj = bpy.context.active_object
    assert obj is not None and obj["relief_source"] == str(path)
    me = obj.data
    ny, nx = relief.shape
    assert len(me.vertices) == ny * nx
    pos = np.empty(3 * ny * nx, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(ny, nx, 3)
    h = relief.heights_m
    valid = np.isfinite(h)
    # z = height (m) x exaggeration at every valid point; x, y in metres at the file's pitch
    np.testing.assert_allclose(pos[..., 2][valid], (h[valid] * 10.0).astype(np.float32), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(np.diff(pos[0, :, 0]), relief.dx_m, rtol=1e-4)
    np.testing.assert_allclose(np.diff(pos[:, 0, 1]), relief.dy_m, rtol=1e-4)
    # quads touching invalid points are left out
    n_quads = int((valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]).sum())
    assert len(me.polygons) == n_quads
    # statistics in the object (panel): rms height after plane levelling, as the backend computes it
    from relief_bsdf.surface.stats import relief_stats
    st = relief_stats(relief).as_dict()
    assert obj["relief_stats"]["rms_height_m"] == pytest.approx(st["rms_height_m"], rel=1e-9)
    # changing the exaggeration rewrites z from the stored true heights
    obj.relief_z_scale = 1.0
    me.attributes["position"].data.foreach_get("vector", pos.ravel())
    np.testing.assert_allclose(pos[..., 2][valid], h[valid].astype(np.float32), rtol=1e-6, atol=1e-12)


def test_import_bad_file_is_a_report_not_a_crash(addon, tmp_path):
    bad = tmp_path / "broken.x3p"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(RuntimeError, match="broken.x3p"):
        bpy.ops.relief.import_heightmap(filepath=str(bad))
    assert not any(o.type == "MESH" for o in bpy.data.objects)


def test_operators_without_input_report_errors(addon):
    # no sample chosen: the operators report a one-line error (RuntimeError in background mode)
    for op in (bpy.ops.relief.fit, bpy.ops.relief.diagnose, bpy.ops.relief.simulate_plate, bpy.ops.relief.infer):
        with pytest.raises(RuntimeError, match="sample"):
            op()
    with pytest.raises(RuntimeError, match="not found"):
        bpy.ops.relief.bake_bsdf(filepath="/nonexistent/table.h5")


def test_reconstruct_operator_writes_table_and_bakes(addon, tmp_path):
    from relief_bsdf.io.hdf5 import load_tables
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    rng = np.random.default_rng(1)
    h = 0.2e-6 * rng.standard_normal((64, 64))
    path = write_relief(tmp_path / "r.npz", Relief(h, 1e-6, 1e-6))
    assert bpy.ops.relief.import_heightmap(filepath=str(path)) == {"FINISHED"}
    out = tmp_path / "t.h5"
    res = bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,30,60",
                                     sides="both", filepath=str(out))
    assert res == {"FINISHED"}
    tabs = load_tables(out)
    assert sorted(t.incident_from for t in tabs) == ["inside", "outside"]
    assert "Relief BSDF: r" in bpy.data.node_groups


def test_import_frames_small_map_and_keeps_true_heights(addon, tmp_path):
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    # 83 um x 204 um, heights ~0.1 um: far below the default 10 mm clip start
    h = 0.1e-6 * np.random.default_rng(3).standard_normal((64, 32))
    path = write_relief(tmp_path / "small.npz", Relief(h, 83e-6 / 31, 204e-6 / 63))
    assert bpy.ops.relief.import_heightmap(filepath=str(path)) == {"FINISHED"}
    obj = bpy.context.active_object
    pos = np.empty(3 * h.size, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", pos)
    np.testing.assert_allclose(pos.reshape(64, 32, 3)[..., 2], h.astype(np.float32), rtol=1e-6)   # metres
    assert bpy.context.scene.unit_settings.length_unit == "MICROMETERS"
    assert bpy.context.scene.unit_settings.scale_length == 1.0                 # 1 unit stays 1 m
    size = 204e-6
    views = [sp for sc in bpy.data.screens for a in sc.areas for sp in a.spaces if sp.type == "VIEW_3D"]
    assert views
    for sp in views:
        assert sp.clip_start <= max(size / 100, 1e-6) and size * 10 <= sp.clip_end < 0.5   # map in, 1 m cube out
        assert sp.region_3d.view_distance == pytest.approx(2 * size, rel=1e-3)
        loc = sp.region_3d.view_location
        assert abs(loc.x) < size and abs(loc.y) < size


def test_panel_lengths_and_regime(addon, tmp_path):
    from relief_addon.panels import _fmt, fmt_length
    assert fmt_length(7.719e-8) == "77.19 nm"
    assert fmt_length(1.277e-7, 3.146e-7) == "127.7 x 314.6 nm"
    assert fmt_length(2.21e-6) == "2.21 um" and fmt_length(1.2e-3) == "1.2 mm" and fmt_length(2.0) == "2 m"
    assert _fmt("rms_height_m", 7.719e-8) == "77.19 nm" and _fmt("rms_slope", 0.0621) == "0.0621"
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.io.heightmaps import read_relief, write_relief
    from relief_bsdf.methods.auto import choose
    from relief_bsdf.methods.request import Request
    from relief_bsdf.surface.relief import Relief
    # a 5 nm rms relief is optically smooth at 550 nm: auto picks Rayleigh-Rice
    h = 5e-9 * np.random.default_rng(4).standard_normal((48, 48))
    path = write_relief(tmp_path / "smooth.npz", Relief(h, 0.5e-6, 0.5e-6))
    assert bpy.ops.relief.import_heightmap(filepath=str(path)) == {"FINISHED"}
    reg = bpy.context.active_object["relief_regime"]
    s = bpy.context.scene.relief
    req = Request(wavelengths_nm=(float(s.wavelengths_nm),),
                  theta_i_deg=tuple(float(x) for x in s.theta_i_deg.split(",")),
                  incident_from=("outside", "inside")).validate()
    assert reg["method"] == choose(read_relief(path), Material(ConstantIndex(s.ior)), req).method == "rayleigh-rice"
    assert reg["regime"] == "optically smooth" and reg["rayleigh_parameter"] < 0.1


class _Layout:
    """Stand-in for a panel's UILayout (no window in background mode): records labels and props."""

    def __init__(self, log):
        self.log = log

    def label(self, text="", icon=None):
        self.log.append(("label", text))

    def prop(self, data, name, **kw):
        self.log.append(("prop", name))

    def operator(self, idname, **kw):
        self.log.append(("operator", idname))
        return type("Props", (), {})()

    def separator(self):
        pass

    def box(self):
        return self

    def row(self, **kw):
        return self

    def column(self, **kw):
        return self


def test_panels_draw_units_regime_and_haze(addon, tmp_path):
    from types import SimpleNamespace
    from relief_addon import panels
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    h = 0.08e-6 * np.random.default_rng(5).standard_normal((40, 40))
    path = write_relief(tmp_path / "p.npz", Relief(h, 0.5e-6, 0.5e-6))
    assert bpy.ops.relief.import_heightmap(filepath=str(path)) == {"FINISHED"}
    assert bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,40", sides="both",
                                      filepath=str(tmp_path / "p.h5")) == {"FINISHED"}
    log = []
    for cls in panels.CLASSES:
        cls.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
    labels = [t for k, t in log if k == "label"]
    text = "\n".join(labels)
    assert "500 x 500 nm" in labels and any(t.endswith(" nm") for t in labels[labels.index("rms height"):][:2])
    assert "Optical regime:" in text and "auto would pick:" in text
    assert any(t.startswith("haze (T, normal incidence):") and t.endswith("%") for t in labels)
    assert ("operator", "relief.add_preset") in log


def test_bake_panel_says_how_the_transmitted_lobe_is_baked(addon):
    """An anisotropic bake with a facet tilt: the panel says the transmitted lobe is stretched by it (Cycles
    has no anisotropic refraction closure; README, Blender extension); anisotropic without a tilt (a table
    without normal incidence for its inside, say): isotropic transmission named; isotropic: neither."""
    from types import SimpleNamespace
    from relief_addon import panels
    for an, tilt, say in ((0.6, 0.4, "transmitted lobe stretched: facet tilt 0.40"),
                          (0.6, 0.0, "transmitted lobes: isotropic"), (0.0, 0.0, None)):
        g = bpy.data.node_groups.new(f"Relief BSDF: a{an} {tilt}", "ShaderNodeTree")
        g["relief_haze"], g["relief_anisotropy"], g["relief_transmission_tilt"] = 0.3, an, tilt
        bpy.context.scene.relief.last_group = g.name
        log = []
        panels.RELIEF_PT_bake_render.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
        text = " ".join(t for k, t in log if k == "label")              # wrapped lines joined
        assert (say in text) if say else ("transmitted" not in text), text
        assert ("no anisotropic refraction closure" in text) is (tilt > 0), text


def test_diagnose_reports_every_named_effect(addon):
    """A compound diagnosis names all its effects in Blender's report line, most important first."""
    from types import SimpleNamespace
    from relief_addon.operators import RELIEF_OT_diagnose
    said = []
    fake = SimpleNamespace(report=lambda kind, msg: said.append((kind, msg)))
    RELIEF_OT_diagnose.finish(fake, bpy.context, {"effect": "stray_light", "effects": ["stray_light", "bulk_absorption"],
                                                  "rms_before": 17.97, "rms_after": 0.697, "explanation": "both"})
    assert said == [({"INFO"}, "Diagnosis: stray_light + bulk_absorption (metric, rms z 17.97 -> 0.697): both")]


def test_the_panel_fills_holes_crops_and_downsamples_the_map_before_reconstructing(addon, tmp_path, capfd):
    """The Reconstruct panel's map settings (Fill holes, Crop, Downsample, Periodicity) reach the backend as
    the command line's flags do: a map with missing points dead-ends the ray method without Fill holes and
    is traced with it; the table's relief history records the fill, the crop and the downsampling."""
    from relief_bsdf.io.hdf5 import load_tables
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    h = 0.2e-6 * np.random.default_rng(2).standard_normal((200, 200))
    h[10:13, 20:22] = np.nan
    path = write_relief(tmp_path / "holes.npz", Relief(h, 1e-6, 1e-6, periodic=True))
    s = bpy.context.scene.relief
    args = dict(method="ray", wavelengths_nm="550", theta_i_deg="0", sides="outside", samples=2000,
                relief_path=str(path), bake=False)
    with pytest.raises(RuntimeError, match="fill"):
        bpy.ops.relief.reconstruct(filepath=str(tmp_path / "no.h5"), **args)
    s.fill_holes, s.crop, s.downsample, s.periodic = True, "0,0,180,180", 2, "no"
    try:
        assert bpy.ops.relief.reconstruct(filepath=str(tmp_path / "t.h5"), **args) == {"FINISHED"}
    finally:
        s.fill_holes, s.crop, s.downsample, s.periodic = False, "", 1, "auto"
    history = " ".join(str(x) for x in load_tables(tmp_path / "t.h5")[0].relief.get("history", []))
    assert "fill" in history and "crop" in history and "downsampl" in history, history
    out, err = capfd.readouterr()                # the statistics of the map as read, recomputed and shown
    assert "As read (" in out + err and "90 x 90 points" in out + err, (out + err)[-1500:]


def test_a_warning_of_the_work_is_one_report_line_and_the_status(addon, tmp_path, capfd):
    """A warning the backend raises during an operator's work (a table of a small tile) is reported
    once as `relief: warning: ...` (no Python file name or source line) and shown in the panel's status;
    bad input reports one line and prints no traceback."""
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.synth import random_relief
    path = write_relief(tmp_path / "small.npz", random_relief(64, 1e-6, 0.5e-6, 4e-6, "gaussian", 3))
    res = bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,30",
                                     sides="outside", samples=3000, relief_path=str(path),
                                     filepath=str(tmp_path / "t.h5"), bake=False)
    assert res == {"FINISHED"}
    out, err = capfd.readouterr()
    both = out + err
    assert "relief: warning:" in both and ".py:" not in both and "RuntimeWarning" not in both, both[-2000:]
    assert bpy.context.scene.relief.job_status.startswith("relief: warning:")
    with pytest.raises(RuntimeError):
        bpy.ops.relief.reconstruct(method="ray", wavelengths_nm="550", theta_i_deg="0", sides="outside",
                                   relief_path=str(tmp_path / "missing.npz"), filepath=str(tmp_path / "u.h5"))
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
