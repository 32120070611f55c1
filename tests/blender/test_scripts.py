"""Operators from a user's script with no `if __name__ == "__main__":` guard.

Each test runs a script in a fresh Python with the bpy module, as `python script.py` (the same
`__main__` situation as `blender --background --python script.py`).  The script imports bpy at
top level, so a worker process that re-ran it would die at `import bpy` (no bpy in a forked
worker, as in Blender's own Python); it logs every execution of its top level to a file.
Each takes 2-3 s alone (a fresh bpy, worker start-up), more on a loaded machine: marked slow.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

HEADER = """\
import json, os, sys
import bpy                                        # top level, no main guard
sys.path.insert(0, os.environ["RELIEF_REPO"])
with open(os.environ["RUN_LOG"], "a") as f:
    f.write(f"{os.getpid()}\\n")
import numpy as np
from relief_bsdf.io.heightmaps import write_relief
from relief_bsdf.surface.relief import Relief
from relief_bsdf.parallel import last_run
d = os.environ["WORK_DIR"]
h = 0.2e-6 * np.random.default_rng(1).standard_normal((32, 32))
src = write_relief(os.path.join(d, "r.npz"), Relief(h, 1e-6, 1e-6))
"""

OPERATOR = HEADER + """\
import relief_addon
relief_addon.register()
bpy.ops.relief.import_heightmap(filepath=str(src))
res = bpy.ops.relief.reconstruct(method="microfacet", wavelengths_nm="550", theta_i_deg="0,40", sides="both",
                                 filepath=os.path.join(d, "t.h5"), bake=False)
print("RESULT " + json.dumps({"res": sorted(res), "run": last_run()}))
"""

DIRECT = HEADER + """\
from relief_bsdf.parallel import WorkerCrashed, map_tasks
from relief_bsdf.parallel.cluster import trivial_task
try:
    map_tasks(trivial_task, [1, 2, 3, 4], None, backend="processes", workers=2, retries=0)
    print("RESULT " + json.dumps({"error": None}))
except WorkerCrashed as e:
    print("RESULT " + json.dumps({"error": str(e)}))
"""


def _run(tmp_path: Path, code: str) -> tuple[dict, list[str]]:
    script = tmp_path / "user_script.py"
    script.write_text(code)
    log = tmp_path / "runs.log"
    env = dict(os.environ, RELIEF_REPO=str(REPO), RUN_LOG=str(log), WORK_DIR=str(tmp_path), RELIEF_WORKERS="2",
               RELIEF_BACKEND="processes", PYTHONPATH=os.pathsep.join([str(REPO / "backend" / "src"),
                                                                       os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=tmp_path,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    line = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[7:]), log.read_text().split()


@pytest.mark.slow
def test_unguarded_script_runs_reconstruct_on_worker_processes(tmp_path):
    res, runs = _run(tmp_path, OPERATOR)
    assert res["res"] == ["FINISHED"]
    # the work really ran on local worker processes, and none of them re-ran the script
    assert res["run"]["backend"] == "processes" and res["run"]["computed"] == res["run"]["total"] > 1
    assert len(runs) == 1
    from relief_bsdf.io.hdf5 import load_tables
    assert sorted(t.incident_from for t in load_tables(tmp_path / "t.h5")) == ["inside", "outside"]


@pytest.mark.slow
def test_worker_dying_at_start_is_reported_with_its_cause(tmp_path):
    # outside the add-on nothing cleans __main__: workers re-run the script and die at `import bpy`;
    # the error says so (exit status of a Python error), not "out of memory, try fewer workers"
    res, _ = _run(tmp_path, DIRECT)
    err = res["error"]
    assert err is not None and "exit status 1" in err and "Python error" in err
    assert "fewer workers" not in err
