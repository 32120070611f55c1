"""`relief infer` on a real measurement: RPC Photonics' EDS10 engineered diffuser (../shared, SOURCE.md).

Inferred from `EDS10 0-0.txt` only; the inferred plate then PREDICTS the 5-deg files (azimuths 0 and
45) through the one forward model, and the lobe figures (infer.lobe) are compared with the measured
ones.  Issue targets: centroid 0.3 deg, half-maximum edges 0.005 in direction cosine, plateau 8 %,
transmittance 0.02.  What this version reaches (the index is assumed 1.5, not fitted; the relief is not
refined) is asserted; the message prints every figure.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "measured" / "eds10"


def _figures(rec, values):
    from relief_bsdf.infer.lobe import lobe_figures
    out = {}
    for ti, pi in rec.incidences():
        sel = (rec.theta_i_deg == ti) & (rec.phi_i_deg == pi) & (rec.side == "T")
        out[(ti, pi)] = lobe_figures(rec.subset(sel), values[sel])
    return out


def _compare(meas: dict, pred: dict) -> dict:
    return {"centroid_deg": abs(pred["centroid_offset_deg"] - meas["centroid_offset_deg"]),
            "edges_u": float(np.max(np.abs(np.subtract(pred["edges_u"], meas["edges_u"])))),
            "plateau_rel": abs(pred["plateau_sr"] / meas["plateau_sr"] - 1.0),
            "transmittance": abs(pred["transmittance"] - meas["transmittance"])}


@pytest.mark.slow
@pytest.mark.shared_data
def test_infer_from_0_deg_predicts_the_5_deg_files(tmp_path, capsys):
    from relief_bsdf.cli import main
    from relief_bsdf.fit.optimise import Forward
    from relief_bsdf.infer.job import distinct_directions
    from relief_bsdf.io.heightmaps import read_sample_relief
    from relief_bsdf.io.recording import read_sample
    from relief_bsdf.plate import TableGrid, experiment_from_sample
    from relief_bsdf.plate.memory import ForwardMemory, job_memory_bytes

    (tmp_path / "sample.toml").write_text(f'''format = "relief-sample/1"
[plate]
thickness_mm = 2.0
rough_face = "front"
[relief]
[instrument]
detector_half_angle_deg = 0.5
[recording]
file = "{(SHARED / 'EDS10 0-0.txt').as_posix()}"
wavelength_nm = 633.0
''')
    out = tmp_path / "out"
    assert main(["infer", str(tmp_path / "sample.toml"), "-o", str(out)]) == 0
    doc = json.loads((out / "infer.json").read_text())
    assert doc["format"] == "relief-infer/1" and not doc["index_stated"]
    assert doc["rms_after"] < doc["rms_before"]
    # the inverted density's rms slope is the relief's (the synthesis keeps it)
    assert doc["rms_slope"] == pytest.approx(doc["density"]["rms_slope"], rel=0.03)
    check = doc["synthesis"]["check"]
    assert check["ks_x"] < 1.0 / 64 and check["ks_y"] < 1.0 / 64, check
    assert doc["lobe"]["0/0"]["measured"]["transmittance"] == pytest.approx(0.898, abs=0.005)

    inferred = read_sample(out / "sample.toml")
    five = replace(inferred, recording_paths=(SHARED / "EDS10 5-0.txt", SHARED / "EDS10 5-45.txt"))
    rec = five.load_recording()
    relief = read_sample_relief(five)
    sim = np.zeros(len(rec))
    for ti, pi in rec.incidences():                       # one incidence at a time (the forward's memory)
        sel = np.flatnonzero((rec.theta_i_deg == ti) & (rec.phi_i_deg == pi))
        rows, inverse = distinct_directions(rec.subset(sel))   # the pole's repeated readings simulated once
        with ForwardMemory(job_memory_bytes() / 3).active():   # as the job: its own memory owner
            fwd = Forward(relief, experiment_from_sample(five, relief, samples=100_000, seed=0), rows,
                          grid=TableGrid())
            sim[sel] = fwd.simulate(1.0, 0.0)[inverse]
    meas, pred = _figures(rec, rec.bsdf_sr), _figures(rec, sim)
    diffs = {k: _compare(meas[k], pred[k]) for k in meas}
    msg = json.dumps({f"{k[0]:g}/{k[1]:g}": {"measured": meas[k], "predicted": pred[k], "differences": diffs[k]}
                      for k in meas}, indent=1)
    print(msg)
    for k, d in diffs.items():
        assert d["centroid_deg"] <= 0.3, msg                      # target met
        assert d["plateau_rel"] <= 0.08, msg                      # target met
        # target 0.02 NOT met (0.026 at 5/0, 0.031 at 5/45): n = 1.5 assumed, not fitted; the plate's Fresnel
        # losses set the level
        assert d["transmittance"] <= 0.035, msg
    assert diffs[(5.0, 0.0)]["edges_u"] <= 0.005, msg             # target met at azimuth 0
    # azimuth 45: NOT met; the plate's boundary tables are computed per polar incidence and turned with the
    # incidence azimuth (an isotropic relief's symmetry), so the square top-hat turns with the beam
    assert diffs[(5.0, 45.0)]["edges_u"] <= 0.03, msg
