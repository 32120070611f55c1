"""WINDOW/Radiance XML BSDF export and import (io/radiance_xml.py), Radiance itself as the oracle.

pyradiance (test-only dependency, requirements/test.txt) bundles Radiance's BSDF library and its
checkBSDF tool: the file must load there, and Radiance's own directional-hemispherical
integrals (SDdirectHemi) and point values (SDevalBSDF) must agree with the table it came from.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction
from relief_bsdf.errors import InputError
from relief_bsdf.io.radiance_xml import (KLEMS, disc_to_square, read_radiance_xml, square_to_disc,
                                         write_radiance_xml)

import pyradiance  # noqa: E402  (test-only oracle, pinned in requirements/test.txt: a missing one fails)
from pyradiance import bsdf as rbsdf  # noqa: E402

CHECKBSDF = Path(pyradiance.__file__).parent / "bin" / "checkBSDF"
_LOADED: list = []


def load_bsdf(path):
    """Radiance's SDcacheFile via pyradiance, kept alive for the whole session: pyradiance 1.3.1 hands
    Python the cached SDData, and letting it be collected frees the cache entry (a later load then
    crashes).  Radiance caches by file name without the directory: tests use distinct names."""
    sd = rbsdf.load_file(str(path))
    assert sd is not None, path
    _LOADED.append(sd)
    return sd


TE = np.linspace(0, 90, 31)
PE = np.linspace(0, 360, 73)
N_GLASS = 1.5
MATERIAL = {"inside": {"model": "constant", "n": N_GLASS, "k": 0.0},
            "outside": {"model": "constant", "n": 1.0, "k": 0.0}}


def boundary_table(frm: str) -> BsdfTable:
    """Smooth lobes about the mirror / undeviated directions, brighter toward phi = 0 (so a turned
    azimuth shows), plus delta parts (no delta transmission past the critical angle from inside)."""
    ti = np.arange(0.0, 90.0, 10.0)
    tc, pc = 0.5 * (TE[1:] + TE[:-1]), 0.5 * (PE[1:] + PE[:-1])
    d = direction(tc[:, None], pc[None, :])
    asym = 1 + 0.5 * np.sin(np.radians(tc))[:, None] * np.cos(np.radians(pc))[None, :]
    v = np.zeros((1, ti.size, 1, 2, tc.size, pc.size))
    for i, t in enumerate(ti):
        c = d @ direction(t, 180.0)
        v[0, i, 0, 0] = (0.02 + 0.3 * np.exp((c - 1) / 0.05)) * asym
        v[0, i, 0, 1] = (0.05 + 0.6 * np.exp((c - 1) / 0.1)) * asym
    crit = np.degrees(np.arcsin(1 / N_GLASS))
    spec_t = np.full(ti.size, 0.1) if frm == "outside" else np.where(ti < crit, 0.05, 0.0)
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=ti, phi_i_deg=[0.0], theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, incident_from=frm, specular_R=0.04,
                     specular_T=spec_t[None, :, None], material=MATERIAL, method="test")


@pytest.fixture(scope="module")
def klems_file(tmp_path_factory):
    tabs = [boundary_table("outside"), boundary_table("inside")]
    path = write_radiance_xml(tmp_path_factory.mktemp("xml") / "klems_pair.xml", tabs, samples_per_patch=4)
    return path, tabs


def test_checkbsdf_accepts_the_klems_file(klems_file):
    path, _ = klems_file
    r = subprocess.run([str(CHECKBSDF), str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "Klems_Full" in r.stdout and "error" not in r.stderr.lower()


def test_radiance_hemispherical_totals_match_the_table(klems_file):
    """Radiance's SDdirectHemi (R and T, delta parts included) within 1 % of the table's totals, both sides.
    WINDOW front = light from outside = Radiance's -z hemisphere (Radiance reverses WINDOW's sides)."""
    path, tabs = klems_file
    sd = load_bsdf(path)
    for t in tabs:
        h = t.hemispherical()
        for i, ti in enumerate(t.theta_i_deg[:8]):          # Klems rings up to 75 deg hold the table's grid
            theta = 180.0 - ti if t.incident_from == "outside" else ti
            for key, flag in (("R", rbsdf.SAMPLE_R), ("T", rbsdf.SAMPLE_T)):
                got = rbsdf.direct_hemi(sd, theta, 17.0, flag | rbsdf.SAMPLE_SP | rbsdf.SAMPLE_DF)
                want = h[key][0, i, 0]
                assert got == pytest.approx(want, rel=0.01), (t.incident_from, ti, key, got, want)


def patch_average(t: BsdfTable, side: str, theta_i: float, ts: float, radiance_phi: float, m: int = 24) -> float:
    """Mean of the table over the Klems patch holding (ts, radiance_phi), uniform in sin^2 theta and phi."""
    p = KLEMS.patches()
    k = int(KLEMS.index(ts, radiance_phi))
    u = (np.arange(m) + 0.5) / m
    s2 = np.sin(np.radians(p["theta_lo"][k])) ** 2 + u * (np.sin(np.radians(p["theta_hi"][k])) ** 2
                                                          - np.sin(np.radians(p["theta_lo"][k])) ** 2)
    th = np.degrees(np.arcsin(np.sqrt(s2)))
    ph = p["phi_lo"][k] + u * (p["phi_hi"][k] - p["phi_lo"][k])
    TH, PH = np.meshgrid(th, ph)
    return float(t.eval(550.0, theta_i, 0.0, side, TH, -PH % 360.0).mean())


def test_radiance_point_values_follow_the_lobe(klems_file):
    """SDevalBSDF at chosen direction pairs equals the table averaged over the Klems patch that holds
    the direction: the lobe sits where the table has it (a turned or mirrored azimuth convention
    would swap the forward and backward values)."""
    path, tabs = klems_file
    sd = load_bsdf(path)
    t = tabs[0]
    # light from outside at 30 deg, table azimuth 0 -> Radiance direction (180 - 30, 0): WINDOW front
    for side, ts in (("R", 40.0), ("T", 40.0), ("R", 70.0), ("T", 60.0)):  # off the delta patches
        for ps in (0.0, 180.0):
            theta_out = 180.0 - ts if side == "R" else ts
            got = rbsdf.query(sd, 150.0, 0.0, theta_out, -ps % 360.0)[1]
            want = patch_average(t, side, 30.0, ts, -ps % 360.0)
            assert got == pytest.approx(want, rel=0.02), (side, ts, ps, got, want)
    fwd = rbsdf.query(sd, 150.0, 0.0, 180.0 - 45.0, 180.0)[1]
    back = rbsdf.query(sd, 150.0, 0.0, 180.0 - 45.0, 0.0)[1]
    assert fwd > 2 * back                      # the specular side of the lobe is the bright one


def test_tensor_tree_loads_in_radiance(tmp_path):
    tabs = [boundary_table("outside"), boundary_table("inside")]
    path = write_radiance_xml(tmp_path / "tt.xml", tabs, structure="tensor-tree", depth=5)
    r = subprocess.run([str(CHECKBSDF), str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "Isotropic_Tensor_Tree" in r.stdout, r.stdout + r.stderr
    sd = load_bsdf(path)
    h = tabs[0].hemispherical()
    for i, ti in enumerate(tabs[0].theta_i_deg[:6]):   # resolution in sin(theta_i) is 1/16 at depth 5
        got = rbsdf.direct_hemi(sd, 180.0 - ti, 0.0, rbsdf.SAMPLE_T | rbsdf.SAMPLE_SP | rbsdf.SAMPLE_DF)
        assert got == pytest.approx(h["T"][0, i, 0], rel=0.05), (ti, got)


def test_klems_round_trip_keeps_totals(klems_file):
    path, tabs = klems_file
    back = read_radiance_xml(path)
    assert [b.incident_from for b in back] == ["outside", "inside"]
    assert back[0].wavelength_nm[0] == 550.0
    for a, b in zip(tabs, back):
        ha, hb = a.hemispherical(), b.hemispherical()
        for i, ti in enumerate(a.theta_i_deg[:8]):
            j = int(np.argmin(np.abs(b.theta_i_deg - ti)))
            assert b.theta_i_deg[j] == pytest.approx(ti)
            for key in ("R", "T"):
                assert hb[key][0, j, 0] == pytest.approx(ha[key][0, i, 0], rel=0.01), (a.incident_from, ti, key)


def test_concentric_map_inverse_and_area():
    rng = np.random.default_rng(3)
    a, b = rng.random(2000), rng.random(2000)
    x, y = square_to_disc(a, b)
    assert np.all(np.hypot(x, y) <= 1 + 1e-12)
    a2, b2 = disc_to_square(x, y)
    np.testing.assert_allclose(a2, a, atol=1e-12)
    np.testing.assert_allclose(b2, b, atol=1e-12)
    # area preserving: a quarter of the square (a < 0.5, b < 0.5) is a quarter of the disc
    x, y = square_to_disc(*rng.random((2, 200000)))
    assert np.mean(np.hypot(x, y) < 0.5) == pytest.approx(0.25, abs=0.005)


def test_klems_basis_solid_angles():
    assert KLEMS.size == 145
    assert KLEMS.projected_solid_angle_sr().sum() == pytest.approx(np.pi, rel=1e-12)
    p = KLEMS.patches()
    idx = KLEMS.index(p["theta_c"] + 0.1, p["phi_c"] + 0.1)
    np.testing.assert_array_equal(idx, np.arange(145))


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="inside"):
        write_radiance_xml(tmp_path / "x.xml", [boundary_table("outside")])
    bad = tmp_path / "bad.xml"
    bad.write_text("<WindowElement><Optical>")
    with pytest.raises(InputError, match="bad.xml"):
        read_radiance_xml(bad)
    with pytest.raises(InputError, match="missing.xml"):
        read_radiance_xml(tmp_path / "missing.xml")


def test_radiance_renders_the_layer(tmp_path):
    """Radiance's renderer (oconv + rtrace, direct light only) with the exported layer: a distant source
    on the front (light from outside, theta_i = 30 deg) seen through the layer from the back.  The
    rendered radiance is f_T * E (E = L_source * Omega_source * cos theta_i) with f_T the table's Klems
    patch value; away from the lobe Radiance's source sampling does not blur it (within 10 %), and the
    patch holding the refracted delta is the brightest.  (Radiance averages the BSDF over the incident
    patch when it samples a source, so on the lobe's flank it differs by up to ~30 %: not asserted.)"""
    import os
    bindir = CHECKBSDF.parent
    tabs = [boundary_table("outside"), boundary_table("inside")]
    write_radiance_xml(tmp_path / "render_layer.xml", tabs, samples_per_patch=4)
    theta_i, radiance = 30.0, 1000.0
    w = direction(theta_i, 0.0)
    src = (w[0], -w[1], -w[2])                              # table frame -> Radiance frame (module doc)
    (tmp_path / "scene.rad").write_text(
        f"void light sunlight 0 0 3 {radiance} {radiance} {radiance}\n"
        f"sunlight source sun 0 0 4 {src[0]:.9f} {src[1]:.9f} {src[2]:.9f} 0.533\n"
        "void BSDF layer 6 0 render_layer.xml 0 1 0 . 0 0\n"
        "layer polygon square 0 0 12 -1 -1 0 1 -1 0 1 1 0 -1 1 0\n")     # normal +z: WINDOW's back side
    env = dict(os.environ, PATH=f"{bindir}:{os.environ.get('PATH', '')}")
    octree = subprocess.run([str(bindir / "oconv"), "scene.rad"], cwd=tmp_path, capture_output=True, env=env,
                            timeout=60, check=True).stdout
    (tmp_path / "scene.oct").write_bytes(octree)
    views = [(40.0, 0.0), (20.0, 90.0), (20.0, 180.0)]      # (theta_s, phi_s) of T in the table frame
    rays = []
    for ts, ps in views:
        o = direction(ts, ps)
        out = np.array([o[0], -o[1], o[2]])                 # T direction (z < 0 in ours) -> Radiance z > 0
        rays.append(" ".join(f"{v:.9f}" for v in np.concatenate([0.5 * out, -out])))
    # Radiance samples the BSDF at random for each ray (seeded per run): each view is traced REPEAT times
    # and averaged, so the oracle's own Monte-Carlo noise (~5 % per ray) stays well inside the tolerance
    repeat = 64
    r = subprocess.run([str(bindir / "rtrace"), "-h", "-ab", "0", "-ov", "-ds", "0", "-dj", "0", "scene.oct"],
                       cwd=tmp_path, input="\n".join(x for x in rays for _ in range(repeat)) + "\n",
                       capture_output=True, text=True, env=env, timeout=120, check=True)
    per_ray = np.array([[float(x) for x in line.split()] for line in r.stdout.strip().splitlines()])[:, 1]
    got = per_ray.reshape(len(views), repeat).mean(axis=1)
    e = radiance * 2 * np.pi * (1 - np.cos(np.radians(0.533 / 2))) * np.cos(np.radians(theta_i))
    for (ts, ps), g in zip(views[:2], got[:2]):
        assert g == pytest.approx(patch_average(tabs[0], "T", theta_i, ts, -ps % 360.0) * e, rel=0.10), (ts, ps)
    assert got[2] > 3 * got[:2].max()
