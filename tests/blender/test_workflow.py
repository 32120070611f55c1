"""The sidebar workflow through the operators (synchronous execute, as in background batches)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

import bpy

SAMPLE = REPO / "scenes" / "demo" / "sample.toml"


def test_bake_operator_assigns_group_to_rough_face(addon, tmp_path):
    """A plate the add-on made (`relief_rough_face`): the group on its rough face, the others glass
    (any other mesh: every face, tests/blender/test_bake_any_mesh.py)."""
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.plate import flat_tables
    th = np.arange(0.0, 90.0, 10.0)
    save_tables(tmp_path / "flat.h5", list(flat_tables(Material(ConstantIndex(1.5)), [550.0], th, th,
                                                       np.linspace(0, 90, 10), np.arange(-15.0, 360, 30))))
    bpy.ops.mesh.primitive_cube_add(size=0.05)
    cube = bpy.context.active_object
    cube["relief_rough_face"] = "front"
    assert bpy.ops.relief.bake_bsdf(filepath=str(tmp_path / "flat.h5"), name="flat") == {"FINISHED"}
    assert "Relief BSDF: flat" in bpy.data.node_groups and "Relief LUT: flat" in bpy.data.images
    top = [p.material_index for p in cube.data.polygons if p.normal.z > 0.5]
    others = [p.material_index for p in cube.data.polygons if p.normal.z <= 0.5]
    assert top == [1] and set(others) == {0}
    assert cube.data.materials[1].node_tree.nodes[0].node_tree.name == "Relief BSDF: flat"


@pytest.mark.slow
def test_simulate_fit_render_from_operators(addon, tmp_path):
    s = bpy.context.scene.relief
    s.sample_path = str(SAMPLE)
    s.output_dir = str(tmp_path)
    assert bpy.ops.relief.simulate_plate() == {"FINISHED"}
    sim = (tmp_path / "simulate" / "simulated.csv").read_text().splitlines()
    assert sim[0] == "# relief-recording/1"
    rec = (SAMPLE.parent / "recording.csv").read_text().splitlines()
    assert len([x for x in sim if not x.startswith("#")]) == len([x for x in rec if not x.startswith("#")])
    assert bpy.ops.relief.fit(max_iter=1) == {"FINISHED"}
    doc = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert doc["format"] == "relief-fit/1" and doc["rms_after"] <= doc["rms_before"]
    assert s.fit_dir == str(tmp_path / "fit")
    out = tmp_path / "plate.png"
    assert bpy.ops.relief.render_plate(filepath=str(out), width=32, samples=2) == {"FINISHED"}
    assert out.stat().st_size > 0


@pytest.mark.slow
def test_presets_make_a_scene_ready_to_render(addon, tmp_path):
    hazes = {}
    for key in ("anti_glare_film", "frosted_acrylic"):
        before = set(bpy.data.scenes.keys())
        assert bpy.ops.relief.add_preset(preset=key) == {"FINISHED"}
        (name,) = set(bpy.data.scenes.keys()) - before
        sc = bpy.data.scenes[name]
        assert sc.camera is not None and sc.render.engine == "CYCLES"
        plate = next(o for o in sc.collection.objects if o.name.startswith("Relief plate"))
        group = [m for m in plate.data.materials if m.name.startswith("Relief BSDF")][0].node_tree.nodes[0].node_tree
        hazes[key] = group["relief_haze"]
        sc.render.resolution_x, sc.render.resolution_y, sc.cycles.samples = 24, 18, 2
        sc.render.image_settings.file_format = "PNG"
        sc.render.filepath = str(tmp_path / f"{key}.png")
        bpy.ops.render.render(write_still=True, scene=sc.name)
        assert (tmp_path / f"{key}.png").stat().st_size > 0
    # the frosted plate scatters far more of the transmitted light out of the beam than the film
    assert 0.0 < hazes["anti_glare_film"] < hazes["frosted_acrylic"] <= 1.0


@pytest.mark.slow
def test_light_guide_dots_preset_haze_is_the_share_deviated_by_the_dots(addon, tmp_path):
    """Light-guide dots: spherical caps (radius 10 um, height 3 um, 32 um grid) on a flat plate.  Geometric
    optics (caps >> 550 nm): at normal incidence from air a facet tilted by theta refracts the beam by
    delta = theta - asin(sin(theta) / n) (Snell); the haze (ASTM D1003) is the share of the area whose
    delta exceeds 2.5 deg (the flat ground between the dots, ~69 %, passes undeviated; Fresnel changes
    by < 1 % over the caps' slopes).  Oracle: that share from the relief's own height gradients, per
    pixel, without the tables; 15 % for the finite differences on a cap 5 pixels in radius."""
    from relief_addon.presets import PRESETS, _relief
    p = PRESETS["light_guide_dots"]
    relief = _relief(p)
    gy, gx = np.gradient(relief.heights_m, relief.dy_m, relief.dx_m)
    tilt = np.arctan(np.hypot(gx, gy))
    delta_deg = np.degrees(tilt - np.arcsin(np.sin(tilt) / p.ior))
    haze_oracle = float(np.mean(delta_deg > 2.5))
    assert 0.25 < haze_oracle < 0.45                                   # ~ the dots' area share pi a^2 / s^2
    before = set(bpy.data.scenes.keys())
    assert bpy.ops.relief.add_preset(preset="light_guide_dots") == {"FINISHED"}
    (name,) = set(bpy.data.scenes.keys()) - before
    plate = next(o for o in bpy.data.scenes[name].collection.objects if o.name.startswith("Relief plate"))
    slot = next(k for k, m in enumerate(plate.data.materials) if m.name.startswith("Relief BSDF"))
    group = plate.data.materials[slot].node_tree.nodes[0].node_tree
    assert group["relief_haze"] == pytest.approx(haze_oracle, rel=0.15)
    # the dots are on the back face: the baked material is on the faces looking down (-z) only
    rough = [p.normal.z for p in plate.data.polygons if p.material_index == slot]
    assert rough and all(nz < -0.5 for nz in rough)


@pytest.mark.slow
def test_default_reconstruct_keeps_the_shared_x3p_anisotropic(addon, tmp_path):
    """The shared x3p is anisotropic (correlation 2.2 um along x, 40 um along y: its slopes are about
    twice as steep along x).  Reconstruct with its default method, then the bake: the reflection lobe
    at normal incidence is wider along x than along y (`reflection_slope_ratio` > 1.5; any isotropic
    lobe gives 1) and the node group gets an anisotropic closure.  Oracle for the direction and the
    size of the effect: the relief's own slope statistics, not the table."""
    from relief_bsdf.bake import reflection_slope_ratio
    from relief_bsdf.io.hdf5 import load_tables
    x3p = REPO / "tests" / "data" / "topography" / "ST_x3p-2.x3p"
    assert bpy.ops.relief.import_heightmap(filepath=str(x3p)) == {"FINISHED"}
    stats = bpy.context.active_object["relief_stats"]
    assert stats["rms_slope_x"] / stats["rms_slope_y"] > 1.8                   # the relief: steeper along x
    out = tmp_path / "x3p.h5"
    assert bpy.ops.relief.reconstruct(wavelengths_nm="550", theta_i_deg="0,40", sides="outside",
                                      filepath=str(out)) == {"FINISHED"}
    (table,) = load_tables(out)
    assert reflection_slope_ratio(table, 550.0) > 1.5
    group = bpy.data.node_groups["Relief BSDF: ST_x3p-2"]
    assert group["relief_anisotropy"] > 0.3
