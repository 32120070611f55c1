"""`relief infer` on an in-plane scan at normal incidence (the isotropic reading, infer.slopes.isotropic_reading).

The recording is the test's own: the transmitted lobe of isotropic Gaussian facet slopes (rms 0.15 per
axis) at n 1.5, written in the small-slope map u = (n - 1) s (a 2-D Gaussian in direction cosines of rms
0.075 per axis, 0.9 of the light in it), read only in the plane phi_s 0/180, 2 % noise.  The job must
read it as isotropic, say so, pick Gaussian slopes, and infer a relief of that rms slope through the plate
(the ray-traced relief, both faces, the detector): not the test's formula."""
from __future__ import annotations

import json

import numpy as np
import pytest

SIGMA = 0.15
N = 1.5


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    from relief_bsdf.infer.job import infer
    tmp = tmp_path_factory.mktemp("inplane")
    rng = np.random.default_rng(5)
    su = (N - 1) * SIGMA
    rows = ["# relief-recording/1", "wavelength_nm,theta_i_deg,phi_i_deg,side,theta_s_deg,phi_s_deg,bsdf_sr,sigma_sr"]
    for ts in np.arange(0.0, 41.0, 1.0):
        for ps in ((0.0,) if ts == 0 else (0.0, 180.0)):
            u = np.sin(np.radians(ts))
            f = 0.9 * np.exp(-0.5 * (u / su) ** 2) / (2 * np.pi * su**2) + 1e-3
            sig = 0.02 * f + 1e-3
            rows.append(f"633,0,0,T,{ts:g},{ps:g},{max(f + sig * rng.standard_normal(), 0.0):.6g},{sig:.4g}")
    (tmp / "recording.csv").write_text("\n".join(rows) + "\n")
    (tmp / "sample.toml").write_text('''format = "relief-sample/1"
[plate]
thickness_mm = 1.0
refractive_index = 1.5
rough_face = "front"
[relief]
[instrument]
detector_half_angle_deg = 0.5
[recording]
file = "recording.csv"
''')
    doc = infer(tmp / "sample.toml", tmp / "out", seed=2, samples=20_000, tile_px=256)
    return doc


@pytest.mark.slow
def test_an_in_plane_scan_is_read_as_isotropic_and_its_rms_slope_recovered(job):
    doc = job
    msg = json.dumps({k: doc[k] for k in ("parameters", "intervals", "inverted_from", "selection")}, indent=1, default=str)
    src = doc["inverted_from"]
    assert src["reading"] == "isotropic reading of an in-plane scan" and "isotropic" in src["assumption"], msg
    assert src["half_asymmetry_over_peak"] < 0.1, msg
    assert any("isotropic" in line for line in doc["limitations"]), msg
    assert doc["selection"]["chosen"] == "gaussian" or doc["selection"]["candidates"][
        [c["name"] for c in doc["selection"]["candidates"]].index(doc["selection"]["chosen"])].get(
        "same_density_as") == "gaussian", msg
    rx, ry = doc["parameters"]["rms_slope_x"], doc["parameters"]["rms_slope_y"]
    assert rx == pytest.approx(SIGMA, rel=0.05) and ry == pytest.approx(SIGMA, rel=0.05), msg
    assert doc["rms_after"] < doc["rms_before"], msg
