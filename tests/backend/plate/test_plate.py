"""Plate model (plate.py): flat-plate Fresnel series per polarisation, energy, absorption, cone, rows."""
import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.core.fresnel import fresnel_power
from relief_bsdf.core.index import CauchyIndex, ConstantIndex, Material
from relief_bsdf.methods.flat import flat_tables
from relief_bsdf.plate.readout import simulate_rows
from relief_bsdf.plate.rows import Rows, in_plane_rows
from plate_setups import plate_setup  # tests/backend/plate/plate_setups.py
from relief_bsdf.plate.solver import PlateSolver
from relief_bsdf.methods.request import Request

N_GLASS = 1.5


def lambert(frm, aR, aT, th, spec_R=0.0, spec_T=0.0):
    """Isotropic table with constant (Lambertian) cells: albedos aR, aT at every incidence."""
    r = Request(theta_i_deg=tuple(th))
    v = np.zeros((1, len(th), 1, 2, r.theta_s_deg.size, r.phi_s_deg.size))
    v[:, :, :, 0] = aR / np.pi
    v[:, :, :, 1] = aT / np.pi
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, r.phi_i_deg, r.theta_s_edges_deg, r.phi_s_edges_deg, v,
                     incident_from=frm, specular_R=spec_R, specular_T=spec_T)


def flat_plate(theta_i, pol, face="front", n=N_GLASS, absorption=0.0):
    tt = float(np.degrees(np.arcsin(np.sin(np.radians(theta_i)) / n)))
    o, i = flat_tables(Material(ConstantIndex(n)), [550.0], sorted({0.0, theta_i}), sorted({0.0, tt, 60.0}))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(n), polarization=pol, rough_face=face,
                   absorption_per_m=absorption)
    return PlateSolver(m, i, o).solve(550.0, [theta_i])[0].hemispherical()


def stokes_series(R1):
    T1 = 1 - R1
    return R1 + T1**2 * R1 / (1 - R1**2), T1**2 / (1 - R1**2)


@pytest.mark.parametrize("theta_i", [0.0, 30.0, 60.0, 75.0])
@pytest.mark.parametrize("face", ["front", "back"])
def test_flat_plate_matches_incoherent_series_for_s_and_p(theta_i, face):
    Rs, Rp, _, _ = fresnel_power(np.cos(np.radians(theta_i)), 1.0, N_GLASS)
    for pol, R1 in (("s", Rs), ("p", Rp)):
        h = flat_plate(theta_i, pol, face)
        R, T = stokes_series(R1)
        assert h["R"] == pytest.approx(R, rel=1e-3)
        assert h["T"] == pytest.approx(T, rel=1e-3)
        assert h["R"] + h["T"] == pytest.approx(1.0, abs=1e-12)
    # unpolarised light = the mean of the s and p plates
    hu = flat_plate(theta_i, "unpolarized", face)
    assert hu["R"] == pytest.approx(0.5 * (stokes_series(Rs)[0] + stokes_series(Rp)[0]), rel=1e-3)


def test_averaging_fresnel_first_is_several_percent_wrong_at_60_deg():
    Rs, Rp, _, _ = fresnel_power(np.cos(np.radians(60.0)), 1.0, N_GLASS)
    right = flat_plate(60.0, "unpolarized")["R"]
    wrong = stokes_series(0.5 * (Rs + Rp))[0]
    assert abs(wrong - right) / right > 0.03


def test_absorbing_flat_plate_follows_beer_lambert_series():
    a = 300.0  # per metre
    theta_i = 45.0
    tt = np.arcsin(np.sin(np.radians(theta_i)) / N_GLASS)
    k = np.exp(-a * 2e-3 / np.cos(tt))
    Rs, _, _, _ = fresnel_power(np.cos(np.radians(theta_i)), 1.0, N_GLASS)
    h = flat_plate(theta_i, "s", absorption=a)
    T1 = 1 - Rs
    assert h["T"] == pytest.approx(T1**2 * k / (1 - Rs**2 * k**2), rel=1e-3)
    assert h["R"] == pytest.approx(Rs + T1**2 * Rs * k**2 / (1 - Rs**2 * k**2), rel=1e-3)


@pytest.mark.parametrize("face", ["front", "back"])
def test_lossless_diffuse_plate_conserves_energy_and_absorption_removes_some(face):
    o = lambert("outside", 0.1, 0.9, [0, 30, 60])
    i = lambert("inside", 0.6, 0.4, np.arange(0, 90, 5.0))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), rough_face=face)
    for r in PlateSolver(m, i, o).solve(550.0, [0.0, 30.0, 60.0]):
        h = r.hemispherical()
        assert h["R"] + h["T"] == pytest.approx(1.0, abs=2e-3)
        # trapped light escapes: much more than the single-pass transmission leaves through the rough face
        assert h["diffuse_R"] > (0.1 if face == "front" else 0.0) + 0.05
    ma = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), rough_face=face, absorption_per_m=300.0)
    h = PlateSolver(ma, i, o).solve(550.0, [30.0])[0].hemispherical()
    assert 0.3 < h["R"] + h["T"] < 0.99


def test_trapped_light_series_matches_closed_form_for_lambertian_front():
    # Lambertian rough face (albedo R_in back into glass, T_in out); flat back face.  Light leaving the
    # rough face into the glass is Lambertian, so its flat-face reflectance is the hemispherical
    # (projected-solid-angle) average of Fresnel, r_bar.  Round trip gain g = r_bar * R_in and
    # R_plate = R_out + T_out * r_bar * T_in / (1 - g), T_plate = T_out * (1 - r_bar) / (1 - g).
    aR_o, aT_o, aR_i, aT_i = 0.1, 0.9, 0.6, 0.4
    o = lambert("outside", aR_o, aT_o, [0, 30])
    i = lambert("inside", aR_i, aT_i, np.arange(0, 90, 5.0))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS))
    h = PlateSolver(m, i, o).solve(550.0, [30.0])[0].hemispherical()
    mu = np.linspace(0, 1, 200001)[1:]
    Rs, Rp, _, _ = fresnel_power(mu, N_GLASS, 1.0)
    r_bar = np.trapz(0.5 * (Rs + Rp) * 2 * mu, mu)
    g = r_bar * aR_i
    assert h["R"] == pytest.approx(aR_o + aT_o * r_bar * aT_i / (1 - g), rel=2e-3)
    assert h["T"] == pytest.approx(aT_o * (1 - r_bar) / (1 - g), rel=2e-3)


def test_rows_use_detector_cone_for_the_delta_part():
    o, i = flat_tables(Material(ConstantIndex(N_GLASS)), [550.0], [30.0], np.arange(0, 90, 1.0))
    h = 1.5
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), detector_half_angle_deg=h)
    rows = Rows([550.0] * 4, [30.0] * 4, [0.0] * 4, ["R", "R", "R", "T"], [30.0, 30.0 + 0.8 * h, 30.0 + 1.2 * h, 30.0],
                [180.0, 180.0, 180.0, 180.0])
    v = simulate_rows(m, i, o, rows)
    tot = PlateSolver(m, i, o).solve(550.0, [30.0])[0].hemispherical()
    omega = 2 * np.pi * (1 - np.cos(np.radians(h)))
    assert v[0] == pytest.approx(tot["R"] / (omega * np.cos(np.radians(30.0))), rel=1e-9)
    assert v[1] == pytest.approx(v[0] * np.cos(np.radians(30)) / np.cos(np.radians(30 + 0.8 * h)), rel=1e-9)
    assert v[2] == 0.0
    assert v[3] == pytest.approx(tot["T"] / (omega * np.cos(np.radians(30.0))), rel=1e-9)


def test_diffuse_rows_of_lambertian_plate_are_flat_in_angle_and_reciprocal_in_sum():
    o = lambert("outside", 0.1, 0.9, [0, 30, 60])
    i = lambert("inside", 0.6, 0.4, np.arange(0, 90, 5.0))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS))
    rows = in_plane_rows(550.0, [0, 30], np.arange(2.5, 80, 5.0), sides=("R",))
    v = simulate_rows(m, i, o, rows)
    # R side: outside table constant + rough-face exit of a (nearly) isotropic internal field -> constant
    assert np.ptp(v) / v.mean() < 0.02


def test_bad_rows_and_models_are_input_errors():
    o = lambert("outside", 0.1, 0.9, [0, 30])
    i = lambert("inside", 0.6, 0.4, [0, 45, 89])
    m = plate_setup(thickness_m=2e-3, index=CauchyIndex(1.49, 4000.0))
    with pytest.raises(InputError, match="wavelength"):
        simulate_rows(m, i, o, Rows([1200.0], [0.0], [0.0], ["R"], [10.0], [0.0]), where="rec.csv")
    with pytest.raises(InputError, match="theta_s_deg"):
        simulate_rows(m, i, o, Rows([550.0], [0.0], [0.0], ["R"], [90.0], [0.0]), where="rec.csv")
    with pytest.raises(InputError, match="theta_i_deg"):
        simulate_rows(m, i, o, Rows([550.0], [95.0], [0.0], ["R"], [10.0], [0.0]), where="rec.csv")
    with pytest.raises(InputError, match="detector_half_angle_deg"):
        plate_setup(thickness_m=2e-3, index=ConstantIndex(1.5), detector_half_angle_deg=0.0)


def test_dispersive_index_changes_the_plate():
    o, i = flat_tables(Material(CauchyIndex(1.49, 20000.0)), [450.0, 650.0], [45.0], np.arange(0, 90, 0.5))
    m = plate_setup(thickness_m=2e-3, index=CauchyIndex(1.49, 20000.0), polarization="s")
    s = PlateSolver(m, i, o)
    r_blue = s.solve(450.0, [45.0])[0].hemispherical()["R"]
    r_red = s.solve(650.0, [45.0])[0].hemispherical()["R"]
    assert r_blue > r_red


def test_tilted_flat_plate_moves_the_specular_peak_by_twice_the_tilt():
    o, i = flat_tables(Material(ConstantIndex(N_GLASS)), [550.0], np.arange(0, 90, 1.0), np.arange(0, 90, 0.5))
    tilt = 3.0
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), detector_half_angle_deg=1.0, tilt_deg=tilt)
    ts = np.arange(20.0, 50.0, 0.5)
    rows = Rows(np.full(ts.size, 550.0), np.full(ts.size, 30.0), np.zeros(ts.size), ["R"] * ts.size, ts,
                np.full(ts.size, 180.0))
    v = simulate_rows(m, i, o, rows)
    lit = ts[v > 0]
    # normal tilted toward the source (+x): incidence 30 - tilt on the sample, mirror at 30 - 2 tilt
    assert lit.min() >= 30 - 2 * tilt - 1.0 - 1e-9 and lit.max() <= 30 - 2 * tilt + 1.0 + 1e-9
    assert (v > 0).sum() >= 3


def test_stokes_loop_with_depolarising_mueller_tables_equals_the_scalar_loop():
    from dataclasses import replace
    o = lambert("outside", 0.1, 0.9, [0, 30, 60], spec_R=0.02)
    i = lambert("inside", 0.6, 0.35, np.arange(0, 90, 5.0), spec_T=0.03)
    dep = np.diag([1.0, 0, 0, 0])
    op = replace(o, mueller_per_sr=o.values_per_sr[..., None, None] * dep)
    ip = replace(i, mueller_per_sr=i.values_per_sr[..., None, None] * dep)
    for pol in ("unpolarized", "s"):
        m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), polarization=pol, absorption_per_m=50.0)
        rows = in_plane_rows(550.0, [0, 30, 60], np.arange(0.5, 90, 3.0))
        scalar = simulate_rows(m, i, o, rows)
        stokes_solver = PlateSolver(m, ip, op)
        assert stokes_solver.mueller
        stokes = simulate_rows(m, ip, op, rows, solver=stokes_solver)
        np.testing.assert_allclose(stokes, scalar, rtol=1e-9, atol=1e-12)


def test_back_face_table_lambertian_closed_form_and_flat_table_limit():
    # both faces Lambertian: R = aR_o + aT_o bR aT_i / (1 - aR_i bR), T = aT_o bT / (1 - aR_i bR)
    aR_o, aT_o, aR_i, aT_i, bR, bT = 0.1, 0.9, 0.5, 0.45, 0.3, 0.65
    o = lambert("outside", aR_o, aT_o, [0, 30])
    i = lambert("inside", aR_i, aT_i, np.arange(0, 90, 5.0))
    b = lambert("inside", bR, bT, np.arange(0, 90, 5.0))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS))
    h = PlateSolver(m, i, o, back=b).solve(550.0, [30.0])[0].hemispherical()
    g = aR_i * bR
    assert h["R"] == pytest.approx(aR_o + aT_o * bR * aT_i / (1 - g), rel=1e-6)
    assert h["T"] == pytest.approx(aT_o * bT / (1 - g), rel=1e-6)
    # a back-face table that is a flat Fresnel boundary gives the flat-back plate
    _, flat_in = flat_tables(Material(ConstantIndex(N_GLASS)), [550.0], [0.0], np.arange(0, 90.01, 0.25))
    rows = in_plane_rows(550.0, [0, 30], np.arange(0.5, 90, 3.0))
    ref = simulate_rows(m, i, o, rows)
    got = simulate_rows(m, i, o, rows, back=flat_in)
    # past 80 deg in air the exit samples Fresnel T next to the critical angle, where a tabulated
    # (linearly interpolated) transmission cannot follow the exact one
    ok = (rows.side == "R") | (rows.theta_s_deg < 80)
    np.testing.assert_allclose(got[ok], ref[ok], rtol=5e-3)


def _lossless_inside(th, aR, aT, spec_T_below_critical, n=N_GLASS):
    """Lambertian inside table with a delta part: specular T only below the critical angle (as a flat
    interface would allow), specular R taking the rest, so R + T = 1 at every incidence."""
    from dataclasses import replace
    t = lambert("inside", aR, aT, th)
    crit = np.degrees(np.arcsin(1.0 / n))
    sT = np.where(np.asarray(th) < crit, spec_T_below_critical, 0.0)[None, :, None]
    return replace(t, specular_T=sT, specular_R=1.0 - aR - aT - sT)


@pytest.mark.slow
@pytest.mark.parametrize("mueller", [False, True])
def test_lossless_plate_with_specular_parts_conserves_energy(mueller):
    # diffuse light inside meets the rough face's delta part too: specular reflection keeps it in the
    # loop, specular transmission lets it out (dropping either loses energy)
    from dataclasses import replace
    o = lambert("outside", 0.05, 0.65, [0, 30, 60], spec_R=0.04, spec_T=0.26)
    i = _lossless_inside(np.arange(0, 90, 1.0), 0.25, 0.35, 0.3)
    if mueller:
        dep = np.diag([1.0, 0, 0, 0])
        o = replace(o, mueller_per_sr=o.values_per_sr[..., None, None] * dep)
        i = replace(i, mueller_per_sr=i.values_per_sr[..., None, None] * dep)
    b = _lossless_inside(np.arange(0, 90, 1.0), 0.2, 0.3, 0.4)       # a second face with its own table
    for face, back in (("front", None), ("back", None), ("front", b)):
        m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), rough_face=face)
        solver = PlateSolver(m, i, o if face == "front" else None, back=back)
        for h in solver.solve(550.0, [0.0, 30.0, 60.0]):
            h = h.hemispherical()
            assert h["R"] + h["T"] == pytest.approx(1.0, abs=2e-3), (face, back is not None, h)


def test_back_relief_with_a_flat_front_face_table_equals_the_fresnel_front_face():
    i = lambert("inside", 0.3, 0.5, np.arange(0, 90, 5.0))
    m = plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS), rough_face="back", absorption_per_m=30.0)
    f_out, f_in = flat_tables(Material(ConstantIndex(N_GLASS)), [550.0], [0.0, 30.0], np.arange(0, 90.01, 0.25))
    rows = in_plane_rows(550.0, [0, 30], np.arange(0.5, 90, 3.0))
    ref = simulate_rows(m, i, None, rows)
    got = simulate_rows(m, i, None, rows, front=(f_out, f_in))
    assert ref.max() > 0.05
    # past 80 deg in air the exit samples Fresnel T next to the critical angle (tabulated, interpolated)
    ok = rows.theta_s_deg < 80
    np.testing.assert_allclose(got[ok], ref[ok], rtol=5e-3)
    with pytest.raises(InputError, match="front face"):
        PlateSolver(plate_setup(thickness_m=2e-3, index=ConstantIndex(N_GLASS)), i, None, front=(f_out, f_in))
