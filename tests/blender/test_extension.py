"""The extension: manifest validation, a built linux zip installs into the bpy module and enables."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile

import pytest

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

sys.path.insert(0, str(REPO / "relief_addon"))
import build_extension as bx  # noqa: E402

WHEEL_CACHE = REPO / "build" / "wheels"        # gitignored; filled from PyPI on first use


def test_manifest_validates_with_blenders_validator(tmp_path):
    stage = bx.stage(tmp_path / "stage", [], ["linux-x64"])
    r = subprocess.run([sys.executable, str(bx.blender_ext_script()), "validate", str(stage)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    text = (stage / "blender_manifest.toml").read_text()
    assert 'id = "relief_addon"' in text and 'platforms = ["linux-x64"]' in text


def test_bundle_excludes_numpy_and_includes_backend_deps():
    deps = bx.dependency_closure()
    assert "numpy" not in deps and "bpy" not in deps
    assert {"scipy", "h5py", "surfacetopography", "embreex", "mufft"} <= set(deps)


def test_surface_topography_formats_claimed_only_with_all_it_needs():
    # SurfaceTopography cannot be imported without muFFT (a compiled package whose wheels may be missing
    # for a platform where SurfaceTopography has one): a zip with the one but not the other reads with
    # the project's own readers only, and must not claim SurfaceTopography's formats
    r = subprocess.run([sys.executable, "-c", "import sys; sys.modules['muFFT'] = None; import SurfaceTopography"],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "muFFT" in r.stderr
    need = bx.dependency_closure("SurfaceTopography")
    assert {"surfacetopography", "mufft", "mugrid"} <= set(need) and "numpy" not in need
    full = [f"{k.replace('-', '_')}-1.0-cp311-cp311-macosx_14_0_arm64.whl" for k in need]
    full.append("relief_bsdf-0.1.0-py3-none-any.whl")
    assert bx.surface_topography_complete(full)
    assert not bx.surface_topography_complete([w for w in full if not w.startswith("mufft-")])
    assert not bx.surface_topography_complete([w for w in full if not w.startswith("surfacetopography-")])


@pytest.mark.slow
def test_linux_zip_installs_and_enables(tmp_path):
    zips = bx.build(tmp_path / "dist", ["linux-x64"], WHEEL_CACHE)
    assert [z.name for z in zips] == ["relief_addon-0.1.0-linux_x64.zip"]
    with zipfile.ZipFile(zips[0]) as zf:
        names = zf.namelist()
    wheels = [n.split("/")[-1] for n in names if n.endswith(".whl")]
    assert any(w.startswith("relief_bsdf-") for w in wheels)
    assert any(w.startswith("embreex-") and "manylinux" in w for w in wheels)
    assert not any(w.startswith("numpy-") for w in wheels)
    assert {"__init__.py", "blender_manifest.toml", "bake_nodes.py", "data/cycles_albedo.npz"} <= set(names)
    assert "build_extension.py" not in names
    # a user script without a main guard: install, enable, set the preferences, import the demo X3P,
    # reconstruct on 2 worker processes, bake onto the relief
    script = (
        "import json, sys, bpy\n"
        "bpy.ops.extensions.package_install_files(filepath=sys.argv[-2], repo='user_default', enable_on_install=True)\n"
        "mods = sorted(bpy.context.preferences.addons.keys())\n"
        "ok = 'RELIEF_PT_relief' in dir(bpy.types) and 'relief' in dir(bpy.ops)\n"
        "import importlib; m = importlib.import_module('bl_ext.user_default.relief_addon')\n"
        "prefs = bpy.context.preferences.addons['bl_ext.user_default.relief_addon'].preferences\n"
        "prefs.workers = 2\n"
        "bpy.ops.relief.import_heightmap(filepath=sys.argv[-1])\n"
        "res = bpy.ops.relief.reconstruct(method='microfacet', wavelengths_nm='550', theta_i_deg='0,40',\n"
        "                                 sides='both')\n"
        "import relief_bsdf\n"
        "from relief_bsdf.parallel import last_run\n"
        "print('RESULT ' + json.dumps({'addons': mods, 'panel': ok, 'file': m.__file__, 'res': sorted(res),\n"
        "     'backend_file': relief_bsdf.__file__, 'run': last_run(), 'table': bpy.context.scene.relief.table_path,\n"
        "     'cache': str(m.prefs.per_user_cache()), 'groups': sorted(bpy.data.node_groups.keys()),\n"
        "     'ops': sorted(dir(bpy.ops.relief))}))\n")
    (tmp_path / "user_script.py").write_text(script)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"), RELIEF_BACKEND="processes")
    env.pop("PYTHONPATH", None)                  # the backend must come from the installed extension
    r = subprocess.run([sys.executable, str(tmp_path / "user_script.py"), str(zips[0]),
                        str(REPO / "scenes" / "demo" / "relief.x3p")], capture_output=True, text=True, env=env,
                       timeout=900, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    line = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")][-1]
    res = json.loads(line[7:])
    assert "bl_ext.user_default.relief_addon" in res["addons"]
    assert res["panel"] and str(tmp_path / "user") in res["file"]
    assert {"import_heightmap", "reconstruct", "bake_bsdf", "render_plate", "add_preset"} <= set(res["ops"])
    assert str(tmp_path / "user") in res["backend_file"]                      # the bundled wheel's relief_bsdf
    assert res["res"] == ["FINISHED"] and res["run"]["backend"] == "processes" and res["run"]["total"] > 1
    # unsaved file: the table went to the extension's per-user folder under its content name, and the
    # scene keeps "//relief_table-<sha256 12>.h5"
    assert re.fullmatch(r"//relief_table-[0-9a-f]{12}\.h5", res["table"]) and str(tmp_path / "user") in res["cache"]
    assert (Path(res["cache"]) / res["table"][2:]).is_file()
    assert "Relief BSDF: relief" in res["groups"]


@pytest.mark.slow
def test_reader_report_checks_each_zip_by_reading(tmp_path):
    # a zip like the Windows one (relief_bsdf, no SurfaceTopography wheel) reads x3p with its own readers;
    # a zip without the backend cannot read its main inputs and is never called validated
    import zipfile
    wheel = bx.build_backend_wheel(tmp_path / "cache")
    win = tmp_path / "relief_addon-0.1.0-windows_x64.zip"
    with zipfile.ZipFile(win, "w") as zf:
        zf.write(wheel, "wheels/" + wheel.name)
    rep = bx.reader_report(win, tmp_path / "cache")
    assert rep["main_ok"] and {"x3p", "gwy", "npz"} <= set(rep["formats"]) and "surfacetopography" not in rep["formats"]
    assert {"dat", "opd", "di", "nid", "mi", "frt", "ibw"} <= set(rep["formats"])          # the instrument readers of io/native_instruments.py
    assert "native_readers (x3p)" in rep["text"] and "not available" in rep["text"]
    bare = tmp_path / "bare.zip"
    with zipfile.ZipFile(bare, "w") as zf:
        zf.writestr("__init__.py", "")
    rep = bx.reader_report(bare, tmp_path / "cache")
    assert not rep["main_ok"] and rep["formats"] == []
