"""Where tables live, re-baking, and what a bake does to an object's materials."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

import bpy


@pytest.fixture
def cache(addon, tmp_path, monkeypatch):
    """The preferences' cache folder, pointed at a test folder (the add-on is registered without
    addon_utils here, so its preferences are the module defaults)."""
    from relief_addon import prefs
    folder = tmp_path / "cache"
    monkeypatch.setattr(prefs, "_DEFAULTS", type(prefs._DEFAULTS)(workers=0, cache_dir=str(folder)))
    return folder


def _flat_table(path: Path) -> Path:
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.io.hdf5 import save_tables
    from relief_bsdf.plate import flat_tables
    th = np.arange(0.0, 90.0, 10.0)
    save_tables(path, list(flat_tables(Material(ConstantIndex(1.5)), [550.0], th, th, np.linspace(0, 90, 10),
                                       np.arange(-15.0, 360, 30))))
    return path


def _relief(path: Path) -> Path:
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.relief import Relief
    h = 0.2e-6 * np.random.default_rng(1).standard_normal((24, 24))
    return write_relief(path, Relief(h, 1e-6, 1e-6))


def test_default_cache_is_per_user_not_temporary(addon):
    from relief_addon.prefs import default_cache_dir
    d = default_cache_dir().resolve()
    assert Path(tempfile.gettempdir()).resolve() not in d.parents
    assert Path(bpy.utils.resource_path("USER")).resolve() in d.parents


def test_unsaved_file_uses_cache_and_saved_file_gets_tables_beside_it(cache, tmp_path):
    assert not bpy.data.filepath
    src = _relief(tmp_path / "r.npz")
    assert bpy.ops.relief.import_heightmap(filepath=str(src)) == {"FINISHED"}
    assert bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,40",
                                      sides="both") == {"FINISHED"}
    s = bpy.context.scene.relief
    name = s.table_path[2:]
    assert s.table_path.startswith("//relief_table-")          # the .blend keeps the relative path
    assert (cache / name).is_file()
    assert bpy.data.node_groups["Relief BSDF: r"]["relief_table"] == s.table_path
    blend = tmp_path / "saved" / "scene.blend"
    blend.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert (blend.parent / name).read_bytes() == (cache / name).read_bytes()   # copied beside the .blend on save
    raw = blend.read_bytes()
    assert str(cache).encode() not in raw and tempfile.gettempdir().encode() + b"/relief" not in raw


def _sha12(path: Path) -> str:
    import hashlib
    return hashlib.sha256(path.read_bytes()).hexdigest()[:12]


def test_unsaved_sessions_get_distinct_tables_and_save_replaces_a_stale_one(cache, tmp_path):
    """Two unsaved sessions share the cache: each table is named by its content (SHA-256), so a second
    session's different table does not overwrite the first's; saving copies the session's table beside
    the .blend, replacing a stale file of the same name there; a later save copies nothing back."""
    import shutil
    from relief_bsdf.core.index import Material
    from relief_bsdf.io.hdf5 import load_tables
    assert bpy.ops.relief.import_heightmap(filepath=str(_relief(tmp_path / "r.npz"))) == {"FINISHED"}
    names = []
    for ior in (1.5, 1.6):                                        # session 1, then "session 2" (another table)
        bpy.context.scene.relief.table_path = "//relief_table.h5"  # each session starts from the default
        assert bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,40",
                                          sides="outside", ior=ior, bake=False) == {"FINISHED"}
        names.append(bpy.context.scene.relief.table_path[2:])
    assert names[0] != names[1]
    for name, ior in zip(names, (1.5, 1.6)):                     # both tables still there, each its own
        path = cache / name
        assert name == f"relief_table-{_sha12(path)}.h5"
        (t,) = load_tables(path)
        assert float(np.real(Material.from_dict(t.material).n_pair(550.0, "outside")[1])) == pytest.approx(ior)
    assert not list(cache.glob("*.writing-*"))                   # no scratch file left
    # a stale file of the same name beside the future .blend (another session's, or a hand copy): replaced
    saved = tmp_path / "saved"
    saved.mkdir()
    shutil.copy(cache / names[0], saved / names[1])
    blend = saved / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert (saved / names[1]).read_bytes() == (cache / names[1]).read_bytes()
    # saved: `//` is the .blend's folder now; a later save never copies the cache's file back over it
    (saved / names[1]).write_bytes(b"written after the save")
    bpy.ops.wm.save_mainfile()
    assert (saved / names[1]).read_bytes() == b"written after the save"


def test_rebake_updates_the_same_group_and_keeps_existing_materials(cache, tmp_path):
    table = _flat_table(tmp_path / "flat.h5")
    bpy.ops.mesh.primitive_plane_add(size=0.05)
    obj = bpy.context.active_object
    paint = bpy.data.materials.new("Paint")
    obj.data.materials.append(paint)
    assert bpy.ops.relief.bake_bsdf(filepath=str(table)) == {"FINISHED"}
    group = bpy.data.node_groups["Relief BSDF: flat"]
    ptr, n_groups = group.as_pointer(), len(bpy.data.node_groups)
    assert [m.name for m in obj.data.materials] == ["Paint", "Relief BSDF: flat"]
    assert [p.material_index for p in obj.data.polygons] == [1]
    # the user sets an input in the material; a second bake of the same table keeps group, material and value
    node = next(n for n in bpy.data.materials["Relief BSDF: flat"].node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
    node.inputs["Haze"].default_value = 0.3
    assert bpy.ops.relief.bake_bsdf(filepath=str(table)) == {"FINISHED"}
    assert len(bpy.data.node_groups) == n_groups
    assert bpy.data.node_groups["Relief BSDF: flat"].as_pointer() == ptr
    assert [m.name for m in obj.data.materials] == ["Paint", "Relief BSDF: flat"]
    node = next(n for n in bpy.data.materials["Relief BSDF: flat"].node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
    assert node.node_tree.as_pointer() == ptr and node.inputs["Haze"].default_value == pytest.approx(0.3)
    assert not any(n.endswith(".001") for n in bpy.data.node_groups.keys())


def test_worker_count_preference_reaches_the_backend(addon, tmp_path, monkeypatch):
    # the environment asks for 4 local worker processes; the preferences' 1 worker wins: the tasks run
    # in this process (a single worker is the serial backend), not on 4 processes
    from relief_addon import prefs
    from relief_bsdf.parallel import last_run
    monkeypatch.setenv("RELIEF_BACKEND", "processes")
    monkeypatch.setenv("RELIEF_WORKERS", "4")
    monkeypatch.setattr(prefs, "_DEFAULTS", type(prefs._DEFAULTS)(workers=1, cache_dir=str(tmp_path / "cache")))
    assert bpy.ops.relief.import_heightmap(filepath=str(_relief(tmp_path / "r.npz"))) == {"FINISHED"}
    assert bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,40", sides="both",
                                      filepath=str(tmp_path / "t.h5"), bake=False) == {"FINISHED"}
    run = last_run()
    assert run["backend"] == "serial" and run["total"] > 1


def test_unsaved_sessions_write_job_results_into_their_own_folders(cache, tmp_path):
    """An unsaved session's `//relief_out/` is in the shared cache: a job's results (fit.json, report.html,
    not content-named) go to a folder of this session's own, `<job>-<tag>`, the same for every job of the
    session; a chosen absolute folder is used as it is."""
    from types import SimpleNamespace
    from relief_addon import paths
    from relief_addon.operators import _sample_and_out
    sample = Path(__file__).resolve().parents[2] / "scenes" / "demo" / "sample.toml"
    assert not bpy.data.filepath
    op = SimpleNamespace(sample=str(sample), output_dir="")
    _, fit = _sample_and_out(op, bpy.context, "fit")
    _, diag = _sample_and_out(op, bpy.context, "diagnose")
    assert bpy.context.scene.relief.output_dir == "//relief_out/"
    assert fit.parent == diag.parent == cache / "relief_out"
    assert fit.name == f"fit-{paths._SESSION_TAG}" and diag.name == f"diagnose-{paths._SESSION_TAG}"
    _, mine = _sample_and_out(SimpleNamespace(sample=str(sample), output_dir=str(tmp_path / "out")), bpy.context, "fit")
    assert mine == tmp_path / "out" / "fit"
