"""The Infer operator: the infer job's relief comes back as a mesh with its baked material (the job is
replaced by one that writes a small relief; the reconstruct job and the bake are real)."""
from __future__ import annotations

import bpy
import numpy as np


def test_infer_operator_imports_the_relief_and_bakes_it(addon, tmp_path, monkeypatch):
    import relief_bsdf.jobs.infer as infer_job
    from relief_bsdf.io.hdf5 import load_tables
    from relief_bsdf.io.heightmaps import write_relief
    from relief_bsdf.surface.synth import random_relief
    calls = []

    def fake_infer(job, progress=None, cancel=None):
        calls.append(job)
        job.out.mkdir(parents=True, exist_ok=True)
        write_relief(job.out / "relief.npz", random_relief(48, 1e-6, 0.2e-6, 4e-6, "gaussian", seed=3))
        doc = {"family": "random crossed lenslets", "rms_slope": 0.2, "parameters": {"refractive_index": 1.49},
               "index_stated": True, "rms_before": 9.0, "rms_after": 1.5}
        return infer_job.InferOutput(doc, job.out)
    monkeypatch.setattr(infer_job, "run_infer", fake_infer)
    (tmp_path / "sample.toml").write_text("# read by the infer job only\n")
    s = bpy.context.scene.relief
    s.method, s.wavelengths_nm, s.theta_i_deg, s.samples = "microfacet", "550", "0,30,60", 20000
    assert bpy.ops.relief.infer(sample=str(tmp_path / "sample.toml"), output_dir=str(tmp_path / "out")) == {"FINISHED"}
    assert len(calls) == 1
    obj = bpy.context.active_object
    assert obj is not None and obj.type == "MESH" and len(obj.data.vertices) == 48 * 48
    table = tmp_path / "out" / "infer" / "boundary.h5"
    tabs = load_tables(table)
    assert sorted(t.incident_from for t in tabs) == ["inside", "outside"]
    from relief_bsdf.core.index import Material
    assert np.real(Material.from_dict(tabs[0].material).inside.n(550.0)) == np.float64(1.49)   # the index infer used
    assert any(m and m.name.startswith("Relief BSDF") for m in obj.data.materials)
