"""Haze (ASTM D1003 > 2.5 deg), clarity, TIS and coherent fractions (bsdf.appearance), and `relief info`."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _wave_reliefs import gaussian_relief
from relief_bsdf.bsdf.appearance import appearance
from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import reconstruct
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.relief import Relief

MAT = Material(inside=ConstantIndex(1.5))
TE = tuple(np.linspace(0, 90, 91))
PE = tuple(np.arange(-2.5, 360.0, 5.0))


def _lambertian_T(t_diffuse, t_spec, theta_i=0.0):
    S, A = len(TE) - 1, len(PE) - 1
    v = np.zeros((1, 1, 1, 2, S, A))
    v[..., 1, :, :] = t_diffuse / np.pi
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=[theta_i], phi_i_deg=[0.0], theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, specular_T=t_spec, specular_R=1 - t_diffuse - t_spec,
                     material=MAT.describe(), method="test")


def test_haze_of_a_lambertian_transmitter_is_its_share_beyond_2p5_deg():
    """Diffuse part Lambertian (its power inside a cone of half-angle a is T_d sin^2 a); clarity from the
    specular core and the 0.1-2.5 deg ring.  The haze is the one D1003 plate haze (bsdf.haze, tested
    there on this case); seen from n = 1 (no plate refraction) it is T_d (1 - sin^2 2.5 deg) / (T_d + T_s)."""
    td, ts = 0.3, 0.6
    (a,) = appearance(_lambertian_T(td, ts), sub=16)
    s25, s01 = np.sin(np.radians(2.5)) ** 2, np.sin(np.radians(0.1)) ** 2
    from relief_bsdf.bsdf.haze import haze_astm_d1003
    assert a.haze == haze_astm_d1003(_lambertian_T(td, ts))
    assert abs(haze_astm_d1003(_lambertian_T(td, ts), n=1.0, sub=16) - td * (1 - s25) / (td + ts)) < 3e-4
    i_c, i_r = ts + td * s01, td * (s25 - s01)
    assert abs(a.clarity - (i_c - i_r) / (i_c + i_r)) < 2e-4
    assert abs(a.tis_T - td) < 1e-9 and abs(a.coherent_fraction_T - ts / (td + ts)) < 1e-9


def test_flat_boundary_has_no_haze_and_full_clarity():
    rel = Relief(np.zeros((64, 64)), 0.1e-6, 0.1e-6, periodic=True, source="flat")
    (tab,) = reconstruct(rel, MAT, Request(theta_i_deg=(0.0, 40.0)), "flat")
    for a in appearance(tab):                   # D1003 haze: normal incidence only
        assert (a.haze == 0) if a.theta_i_deg == 0 else np.isnan(a.haze)
        assert a.clarity == 1 and abs(a.tis_R) < 1e-12 and abs(a.tis_T) < 1e-12
        assert a.coherent_fraction_R == 1 and a.coherent_fraction_T == 1


@pytest.mark.slow
def test_haze_falls_toward_the_red_and_info_reports_it(tmp_path: Path):
    """A smooth relief seen by wave optics: less haze and more coherent transmission at 650 than at
    450 nm (colour dependence); `relief info TABLE --json` carries the same figures and the signed
    energy defect."""
    rel = gaussian_relief(512, 0.125e-6, 40e-9, 2e-6, seed=2)
    req = Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0,), theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                  options={"band_limited": True, "backend": "serial"})
    (tab,) = reconstruct(rel, MAT, req, "kirchhoff")
    blue, red = appearance(tab)
    assert red.haze < blue.haze and red.coherent_fraction_T > blue.coherent_fraction_T
    from relief_bsdf.io.hdf5 import save_tables
    out = tmp_path / "t.h5"
    save_tables(out, [tab])
    r = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "info", str(out), "--json"], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert [round(x["haze"], 9) for x in d["appearance"]] == [round(blue.haze, 9), round(red.haze, 9)]
    assert "outside" in d["energy_defect"]
    txt = subprocess.run([sys.executable, "-m", "relief_bsdf.cli", "info", str(out)], capture_output=True, text=True)
    assert "haze" in txt.stdout and "signed" in txt.stdout


def test_relief_info_reports_noise_band_and_flags():
    """A map with 2 nm of white noise added: the PSD floor finds the noise level and band-limiting at
    550 nm removes most of it; with spikes added the spike flag is raised (spikes are white too)."""
    from relief_bsdf.cli.cmd_info import relief_info
    rng = np.random.default_rng(3)
    base = gaussian_relief(256, 0.05e-6, 30e-9, 2e-6, seed=4).heights_m
    noisy = base + 2e-9 * rng.standard_normal(base.shape)
    d = relief_info(Relief(noisy, 0.05e-6, 0.05e-6, periodic=True, source="noisy"))
    assert 1.6e-9 < d["noise_floor"]["rms_m"] < 2.5e-9
    assert 1.2e-9 < d["band_limit"]["removed_rms_m"] < 2.1e-9 and not d["flags"]["spiky"]
    clean = relief_info(Relief(base, 0.05e-6, 0.05e-6, periodic=True, source="clean"))
    assert not clean["flags"]["spiky"] and clean["noise_floor"]["rms_m"] < 0.3e-9
    spiky = noisy.copy()
    spiky[rng.random(base.shape) < 2e-3] += 300e-9
    s = relief_info(Relief(spiky, 0.05e-6, 0.05e-6, periodic=True, source="spiky"))
    assert s["flags"]["spiky"] and s["flags"]["kurtosis"] > 5 and "spiky" in s["flags"]["statements"][0]


def test_plot_note_states_the_specular_parts_per_wavelength():
    """`relief plot` annotates what the cells cannot show: the specular deltas and the haze, one line
    per wavelength (colour dependence)."""
    from relief_bsdf.cli.cmd_plot import specular_note
    rel = Relief(np.zeros((64, 64)), 0.1e-6, 0.1e-6, periodic=True, source="flat")
    (tab,) = reconstruct(rel, MAT, Request(wavelengths_nm=(450.0, 650.0), theta_i_deg=(0.0, 40.0)), "flat")
    note = specular_note(tab).splitlines()
    assert len(note) == 3 and note[1].startswith("450 nm") and note[2].startswith("650 nm")
    assert f"{tab.specular_T[0, 0, 0]:.4f}" in note[1] and "haze (ASTM D1003, plate) 0.0000" in note[1]
