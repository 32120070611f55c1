"""`auto` method choice from relief statistics, its stated reason, and the CLI path."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _wave_reliefs import gaussian_relief
from relief_bsdf.methods import auto, reconstruct
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods.request import Request

MAT = Material(inside=ConstantIndex(1.5))
SMALL = dict(theta_i_deg=(0.0, 30.0), theta_s_edges_deg=tuple(np.linspace(0, 60, 31)),
             phi_s_edges_deg=tuple(np.arange(-5, 360, 10.0)))


def test_small_roughness_picks_rayleigh_rice():
    rel = gaussian_relief(512, 0.1e-6, 5e-9, 1e-6, seed=1)
    (tab,) = reconstruct(rel, MAT, Request(**SMALL, options={"quiet": True}), "auto")
    assert tab.method == "rayleigh-rice"
    assert tab.metadata["auto_method"] == "rayleigh-rice"
    assert "Rayleigh parameter" in tab.metadata["auto_reason"]
    assert tab.metadata["auto_figures"]["rayleigh_parameter"] < 0.1


def test_intermediate_picks_kirchhoff():
    rel = gaussian_relief(512, 0.1e-6, 50e-9, 3e-6, seed=2)
    (tab,) = reconstruct(rel, MAT, Request(**SMALL, options={"quiet": True}), "auto")
    assert tab.method == "kirchhoff"
    assert "Rayleigh-Rice invalid" in tab.metadata["auto_reason"]
    assert tab.metadata["auto_valid"] == {"rayleigh-rice": False, "kirchhoff": True, "ray": False}


def test_rough_coarse_pitch_picks_ray_and_rayleigh_parameter_scales():
    rel = gaussian_relief(256, 1e-6, 2e-6, 20e-6, seed=3)
    c = auto.choose(rel, MAT, Request())
    assert c.method == "ray" and c.valid["ray"][0]
    assert "not feasible" in c.valid["kirchhoff"][1]
    # the Rayleigh parameter falls with wavelength: a 20 nm relief is "small" in the far infrared only
    smooth = gaussian_relief(256, 0.5e-6, 20e-9, 5e-6, seed=3)
    g = [auto.choose(smooth, MAT, Request(wavelengths_nm=(w,), theta_s_edges_deg=(0, 10, 20), theta_i_deg=(0,),
                                          options={"band_limited": True})).figures["rayleigh_parameter"]
         for w in (400.0, 800.0)]
    assert g[0] == pytest.approx(4 * g[1], rel=1e-6)


def test_no_valid_method_warns():
    rel = gaussian_relief(256, 0.05e-6, 0.3e-6, 0.5e-6, seed=4)      # steep, sub-wavelength bumps
    c = auto.choose(rel, MAT, Request(theta_i_deg=(0.0,)))
    assert c.reason.startswith("WARNING") and not any(v[0] for v in c.valid.values())


@pytest.mark.slow
def test_cli_auto_prints_reason_and_kirchhoff_coherence(tmp_path: Path):
    rel = gaussian_relief(256, 0.1e-6, 5e-9, 1e-6, seed=5)
    src = tmp_path / "r.npz"
    np.savez(src, heights=rel.heights_m, dx=rel.dx_m, dy=rel.dy_m)
    exe = [sys.executable, "-m", "relief_bsdf.cli"]
    out = tmp_path / "t.h5"
    r = subprocess.run(exe + ["reconstruct", str(src), "--method", "auto", "--n", "1.5", "--theta-i-deg", "0",
                              "--theta-step-deg", "2", "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "auto: rayleigh-rice" in r.stderr
    info = subprocess.run(exe + ["info", str(out), "--json"], capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    d = json.loads(info.stdout)
    assert d["method"] == "rayleigh-rice"
    out2 = tmp_path / "k.h5"
    r = subprocess.run(exe + ["reconstruct", str(src), "--method", "kirchhoff", "--n", "1.5", "--theta-i-deg", "0",
                              "--theta-step-deg", "2", "--coherence-length-um", "4", "--option", "band_limited=true",
                              "-o", str(out2)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(exe + ["reconstruct", str(src), "--method", "kirchhoff", "--n", "1.5", "--theta-i-deg", "0",
                              "-o", str(tmp_path / "bad.h5")], capture_output=True, text=True)
    assert r.returncode == 2 and "kirchhoff" in r.stderr and len(r.stderr.strip().splitlines()) == 1
