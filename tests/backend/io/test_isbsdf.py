"""Zemax IS-BSDF export / import (bsdf_isbsdf.py)."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction
from relief_bsdf.io.isbsdf import (export_isbsdf, from_specular_coords, import_isbsdf, read_isbsdf,
                                     read_isbsdf_all, refracted_theta_deg, to_specular_coords)
from relief_bsdf.errors import InputError

TE = np.linspace(0, 90, 31)       # 3 degree cells
PE = np.linspace(0, 360, 73)      # 5 degree cells


# Round trips of smooth lobes go through two linear interpolations (table -> specular grid ->
# table cells); with 3 x 5 degree cells and lobes of ~25 degrees 1/e width the expected error is
# ~ 2 * h^2 / 8 * |f''/f| < 3 %, which is the tolerance used below.


def lobe_table(theta_i, phi_i=(0.0,), wl=(550.0,), symmetric=True, seed=None):
    """Smooth test BSDF: a Lambertian floor plus a broad lobe about the mirror direction (R)
    and the undeviated direction (T); optional random values (not smooth) when seed is given."""
    ti, pi = np.asarray(theta_i, float), np.asarray(phi_i, float)
    tc, pc = 0.5 * (TE[1:] + TE[:-1]), 0.5 * (PE[1:] + PE[:-1])
    v = np.zeros((len(wl), ti.size, pi.size, 2, tc.size, pc.size))
    d = direction(tc[:, None], pc[None, :])
    for i, t in enumerate(ti):
        for p, ph in enumerate(pi):
            m = direction(t, ph + 180.0)
            c = np.clip(d @ m, -1, 1)
            # smooth on the sphere (no pole singularity): 1 + 0.5 sin(theta) sin(phi - phi_i)
            asym = 1.0 if symmetric else 1.0 + 0.5 * np.sin(np.radians(tc))[:, None] * np.sin(np.radians(pc - ph))[None, :]
            v[:, i, p, 0] = (0.05 + 0.8 * np.exp((c - 1) / 0.1)) * asym
            v[:, i, p, 1] = (0.02 + 0.5 * np.exp((c - 1) / 0.15)) * asym
    if seed is not None:
        v = np.random.default_rng(seed).random(v.shape)
    return BsdfTable(wavelength_nm=wl, theta_i_deg=ti, phi_i_deg=pi, theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, method="test", specular_R=0.04, material=MATERIAL)


MATERIAL = {"inside": {"model": "constant", "n": 1.5, "k": 0.0}, "outside": {"model": "constant", "n": 1.0, "k": 0.0}}


def test_specular_coordinates_round_trip_and_convention():
    th, ph = np.meshgrid(np.linspace(1, 89, 12), np.linspace(3, 357, 17))
    r, a = to_specular_coords(30.0, 20.0, th, ph)
    th2, ph2, up = from_specular_coords(30.0, 20.0, r, a)
    assert up.all()
    np.testing.assert_allclose(th2, th, atol=1e-9)
    np.testing.assert_allclose(ph2, ph, atol=1e-9)
    # radial 0 is the mirror direction; azimuth 0 points from it toward the normal
    r0, _ = to_specular_coords(30.0, 20.0, 30.0, 200.0)
    assert r0 == pytest.approx(0.0, abs=1e-6)
    r1, a1 = to_specular_coords(30.0, 20.0, 20.0, 200.0)
    assert r1 == pytest.approx(10.0) and a1 == pytest.approx(0.0, abs=1e-9)
    r2, a2 = to_specular_coords(30.0, 20.0, 40.0, 200.0)
    assert r2 == pytest.approx(10.0) and a2 == pytest.approx(180.0)


def test_normal_incidence_round_trip_is_exact(tmp_path):
    t = lobe_table([0.0], seed=5)          # arbitrary (non-smooth) values
    paths = export_isbsdf(t, tmp_path / "x.bsdf")
    assert [p.name for p in paths] == ["x_BRDF.bsdf", "x_BTDF.bsdf"]
    back = import_isbsdf(paths, TE, PE)
    assert back.wavelength_nm[0] == 550.0 and back.incident_from == "outside" and back.method == "test"
    np.testing.assert_allclose(back.values_per_sr, t.values_per_sr, rtol=1e-5)


def test_oblique_round_trip_and_tis(tmp_path):
    t = lobe_table([0.0, 20.0, 45.0], phi_i=(0.0,))
    paths = export_isbsdf(t, tmp_path / "x.bsdf")
    blocks = [read_isbsdf(p) for p in paths]
    assert [b.scatter_type for b in blocks] == ["BRDF", "BTDF"]
    assert blocks[0].symmetry == "PlaneSymmetrical"
    assert blocks[0].azimuth_deg[0] == 0 and blocks[0].azimuth_deg[-1] == 180
    # TIS is the diffuse hemispherical integral of each side
    h = t.hemispherical()
    np.testing.assert_allclose(blocks[0].tis[0], h["diffuse_R"][0, :, 0], rtol=1e-5)
    np.testing.assert_allclose(blocks[1].tis[0], h["diffuse_T"][0, :, 0], rtol=1e-5)
    back = import_isbsdf(paths, TE, PE)
    keep = 0.5 * (TE[1:] + TE[:-1]) < 80       # grazing cells straddle the horizon nodes
    a = back.values_per_sr[..., keep, :]
    b = t.values_per_sr[..., keep, :]
    assert np.max(np.abs(a - b) / b) < 0.03
    # hemispherical integrals survive within 2 %
    hb = back.hemispherical()
    np.testing.assert_allclose(hb["diffuse_R"], h["diffuse_R"], rtol=0.02)
    np.testing.assert_allclose(hb["diffuse_T"], h["diffuse_T"], rtol=0.02)


def test_asymmetric_and_multi_wavelength(tmp_path):
    t = lobe_table([10.0], wl=(450.0, 650.0), symmetric=False)
    paths = export_isbsdf(t, tmp_path / "y.bsdf")
    assert sorted(p.name for p in paths) == sorted(["y_BRDF_450nm.bsdf", "y_BRDF_650nm.bsdf",
                                                    "y_BTDF_450nm.bsdf", "y_BTDF_650nm.bsdf"])
    b = read_isbsdf(tmp_path / "y_BRDF_650nm.bsdf")
    assert b.symmetry == "Asymmetrical" and b.azimuth_deg[-1] == 360
    back = import_isbsdf([tmp_path / "y_BRDF_650nm.bsdf"], TE, PE)
    assert back.wavelength_nm[0] == 650.0
    keep = 0.5 * (TE[1:] + TE[:-1]) < 80
    ratio = back.values_per_sr[0, 0, 0, 0][keep] / t.values_per_sr[1, 0, 0, 0][keep]
    assert np.max(np.abs(ratio - 1)) < 0.03
    assert np.all(back.values_per_sr[..., 1, :, :] == 0)   # no BTDF file given
    one = export_isbsdf(t, tmp_path / "single.bsdf", sides=("R",), wavelength_nm=450.0)
    assert [p.name for p in one] == ["single.bsdf"]


@pytest.mark.parametrize("mutate, words", [
    (lambda s: s.replace("DataEnd", ""), "DataEnd"),
    (lambda s: s.replace("ScatterType  BRDF", "ScatterType  BXDF"), "ScatterType"),
    (lambda s: s.replace("Monochrome\nDataBegin", "TristimulusX\nDataBegin"), "Monochrome"),
    (lambda s: s[: len(s) // 2], "truncated"),
    (lambda s: s.replace("TIS", "TIZ", 1), "TIS"),
    (lambda s: "", "empty"),
])
def test_malformed_files(tmp_path, mutate, words):
    t = lobe_table([0.0, 30.0])
    [p] = export_isbsdf(t, tmp_path / "z.bsdf", sides=("R",))
    bad = tmp_path / "bad.bsdf"
    bad.write_text(mutate(p.read_text()))
    with pytest.raises(InputError) as e:
        read_isbsdf(bad)
    assert "bad.bsdf" in str(e.value) and words in str(e.value)


def test_foreign_file_needs_wavelength(tmp_path):
    t = lobe_table([0.0])
    [p] = export_isbsdf(t, tmp_path / "f.bsdf", sides=("R",))
    foreign = tmp_path / "foreign.bsdf"
    foreign.write_text("\n".join(l for l in p.read_text().splitlines() if not l.startswith("#")))
    with pytest.raises(InputError, match="wavelength"):
        import_isbsdf(foreign)
    tab = import_isbsdf(foreign, wavelength_nm=600.0)
    assert tab.wavelength_nm[0] == 600.0 and tab.values_per_sr.shape[-2:] == (90, 72)


def test_combined_file_round_trip(tmp_path):
    """Older combined files (all blocks in one file) are still read."""
    t = lobe_table([0.0], wl=(450.0, 650.0), seed=9)
    parts = export_isbsdf(t, tmp_path / "part.bsdf")
    order = sorted(parts, key=lambda q: ("650" in q.name, "BTDF" in q.name))
    p = tmp_path / "all.isbsdf"
    p.write_text("".join(q.read_text() for q in order))
    blocks = read_isbsdf_all(p)
    assert [b.scatter_type for b in blocks] == ["BRDF", "BTDF", "BRDF", "BTDF"]
    assert [b.relief_tag("wavelength_nm") for b in blocks] == ["450.0", "450.0", "650.0", "650.0"]
    back = import_isbsdf(p, TE, PE)
    assert back.wavelength_nm.tolist() == [450.0, 650.0]
    np.testing.assert_allclose(back.values_per_sr, t.values_per_sr, rtol=1e-5)
    only = import_isbsdf(p, TE, PE, wavelength_nm=650.0)
    np.testing.assert_allclose(only.values_per_sr[0], t.values_per_sr[1], rtol=1e-5)


def refracted_lobe_table(frm="outside", n=1.5, ti=(0.0, 30.0, 60.0, 75.0)):
    """T lobe about the refracted direction (the physics of a smooth-ish boundary), R about the mirror."""
    ti = np.asarray(ti, float)
    tc, pc = 0.5 * (TE[1:] + TE[:-1]), 0.5 * (PE[1:] + PE[:-1])
    d = direction(tc[:, None], pc[None, :])
    n1, n2 = (1.0, n) if frm == "outside" else (n, 1.0)
    v = np.zeros((1, ti.size, 1, 2, tc.size, pc.size))
    for i, t in enumerate(ti):
        v[0, i, 0, 0] = 0.05 + 0.8 * np.exp((d @ direction(t, 180.0) - 1) / 0.1)
        tt = refracted_theta_deg(t, n1, n2)
        v[0, i, 0, 1] = 0.02 + 0.5 * np.exp((d @ direction(tt, 180.0) - 1) / 0.15)
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=ti, phi_i_deg=[0.0], theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, method="test", incident_from=frm, material=MATERIAL)


def test_btdf_is_centred_on_the_refracted_direction_by_default(tmp_path):
    """OpticStudio's convention: the BTDF lobe of a boundary peaks at ScatterRadial 0 (refracted ray);
    the old undeviated centring puts it ~25 deg off at 60 deg into n = 1.5."""
    t = refracted_lobe_table()
    [p] = export_isbsdf(t, tmp_path / "t.bsdf", sides=("T",))
    b = read_isbsdf(p)
    assert b.relief_tag("btdf_centre") == "refracted" and float(b.relief_tag("n_transmitted")) == 1.5
    i = list(b.angle_of_incidence_deg).index(60.0)
    a, r = np.unravel_index(np.argmax(b.data_per_sr[0, i]), b.data_per_sr[0, i].shape)
    assert b.radial_deg[r] <= 1.5
    [q] = export_isbsdf(t, tmp_path / "u.bsdf", sides=("T",), btdf_centre="undeviated")
    u = read_isbsdf(q)
    a, r = np.unravel_index(np.argmax(u.data_per_sr[0, i]), u.data_per_sr[0, i].shape)
    assert u.radial_deg[r] == pytest.approx(60.0 - float(refracted_theta_deg(60.0, 1.0, 1.5)), abs=1.6)
    assert 60.0 - float(refracted_theta_deg(60.0, 1.0, 1.5)) == pytest.approx(24.7, abs=0.1)


@pytest.mark.parametrize("frm", ["outside", "inside"])
@pytest.mark.parametrize("centre", ["refracted", "undeviated"])
def test_round_trip_both_centrings_within_interpolation_error(tmp_path, frm, centre):
    """export -> import gives the table back within the two linear interpolations' error (3 %, see
    the note at the top), from inside too (past the critical angle the block is centred on 90 deg)."""
    t = refracted_lobe_table(frm)
    paths = export_isbsdf(t, tmp_path / "r.bsdf", btdf_centre=centre)
    back = import_isbsdf(paths, TE, PE)
    assert back.incident_from == frm
    ht, hb = t.hemispherical(), back.hemispherical()
    np.testing.assert_allclose(hb["diffuse_R"], ht["diffuse_R"], rtol=0.03)
    np.testing.assert_allclose(hb["diffuse_T"], ht["diffuse_T"], rtol=0.03)
    pk = t.values_per_sr[..., 1, :, :] > 0.2 * t.values_per_sr[..., 1, :, :].max()
    err = np.abs(back.values_per_sr[..., 1, :, :] - t.values_per_sr[..., 1, :, :])[pk]
    assert np.median(err / t.values_per_sr[..., 1, :, :][pk]) < 0.03


def test_measured_file_without_tags_is_read_as_opticstudio(tmp_path):
    """A file with no relief comments (e.g. a scatterometer export) is refracted-centred; with the
    default indices 1 and 1 (sample in air) that is the undeviated direction; given the indices of a
    boundary, the lobe lands on the refracted direction."""
    t = refracted_lobe_table()
    [p] = export_isbsdf(t, tmp_path / "m.bsdf", sides=("T",))
    foreign = tmp_path / "foreign.bsdf"
    foreign.write_text("\n".join(l for l in p.read_text().splitlines() if not l.startswith("#")))
    tab = import_isbsdf(foreign, TE, PE, wavelength_nm=550.0, n_incident=1.0, n_transmitted=1.5)
    tt = float(refracted_theta_deg(60.0, 1.0, 1.5))
    assert tab.eval(550.0, 60.0, 0.0, "T", tt, 180.0) == pytest.approx(0.52, rel=0.05)
    air = import_isbsdf(foreign, TE, PE, wavelength_nm=550.0)
    assert air.eval(550.0, 60.0, 0.0, "T", 60.0, 180.0) == pytest.approx(0.52, rel=0.05)


def test_refracted_block_reaches_the_far_horizon(tmp_path):
    """From inside at 40 deg the refracted ray leaves at 74.6 deg: the block's radial grid must reach
    90 + 74.6 deg, not 90 + theta_i, or the far side of the lobe is lost."""
    t = refracted_lobe_table("inside", ti=(40.0,))
    b = read_isbsdf(export_isbsdf(t, tmp_path / "far.bsdf", sides=("T",))[0])
    assert b.radial_deg.max() >= 90.0 + float(refracted_theta_deg(40.0, 1.5, 1.0)) - 1e-6
    back = import_isbsdf(tmp_path / "far.bsdf", TE, PE)
    np.testing.assert_allclose(back.hemispherical()["diffuse_T"], t.hemispherical()["diffuse_T"], rtol=0.03)
