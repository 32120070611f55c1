"""`auto` method choice from relief statistics, its stated reason, and the CLI path."""
import json
import subprocess
import sys
import warnings
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
    assert "rayleigh-rice (missed by" in tab.metadata["auto_reason"]
    assert tab.metadata["auto_valid"] == {"rayleigh-rice": False, "kirchhoff": True, "ray": False, "two_scale": False}


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


TOPO = Path(__file__).resolve().parents[2] / "data" / "topography"


def _area_maps():
    from relief_bsdf.io.heightmaps import read_relief
    out = {}
    for p in sorted(TOPO.glob("ST_*")):
        try:
            rel = read_relief(p)
        except Exception:           # the 1-D profile (a line, not a map)
            continue
        out[p.name] = rel
    return out


@pytest.mark.slow
def test_real_maps_never_ray_while_a_coherent_part_remains():
    """Every area map of tests/data/topography: geometric optics only where the coherent specular
    share at normal incidence is below 1 % (or no wave method is within a decade of valid); the
    summary is one line.  ST_plu-1.plu (Sensofar, 18 nm rms, 1.66 um pitch) gets band-limited kirchhoff."""
    maps = _area_maps()
    assert len(maps) >= 8
    req = Request(theta_i_deg=(0.0, 30.0, 60.0), incident_from=("outside", "inside"))
    for name, rel in maps.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c = auto.choose(rel, MAT, req)
        assert "\n" not in c.summary and len(c.summary) < 300, name
        if c.figures["coherent_max"] > 0.05:
            assert c.method != "ray", (name, c.summary)
    c = auto.choose(maps["ST_plu-1.plu"], MAT, req)
    assert c.method == "kirchhoff" and c.options.get("band_limited") is True


def test_exponential_wavelength_scale_facets_not_ray():
    """An exponential-autocorrelation relief, sigma 1 um, l 6 um: rough enough for ray on sigma and l
    alone, but its facets (radius of curvature) are about a wavelength: ray's condition k R_c >= 10
    fails, so ray is not called valid."""
    from relief_bsdf.surface.synth import random_relief
    rel = random_relief(256, 0.1e-6, 1e-6, 6e-6, kind="exponential", seed=3)
    c = auto.choose(rel, MAT, Request(theta_i_deg=(0.0,), options={"band_limited": True}))
    assert not c.valid["ray"][0]
    assert "k R_c (facets" in c.valid["ray"][1]


@pytest.mark.parametrize("method", ["auto", "kirchhoff"])
def test_misspelled_option_is_an_error_naming_it(tmp_path: Path, method):
    rel = gaussian_relief(64, 0.1e-6, 5e-9, 1e-6, seed=5)
    src = tmp_path / "r.npz"
    np.savez(src, heights=rel.heights_m, dx=rel.dx_m, dy=rel.dy_m)
    r = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "reconstruct", str(src), "--method", method, "--n",
                        "1.5", "--theta-i-deg", "0", "--option", "bandlimited=true", "-o", str(tmp_path / "t.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "unknown option 'bandlimited'" in r.stderr and "band_limited" in r.stderr
    assert not (tmp_path / "t.h5").exists()
