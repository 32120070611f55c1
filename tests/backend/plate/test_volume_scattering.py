"""Volume scattering in the deterministic plate (plate.slab, adding-doubling) and the photon engine."""
import numpy as np
import pytest

from relief_bsdf.core.bulk import hg_phase
from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import (Bulk, Experiment, FlatFace, Instrument, Plate, TableFace, TableGrid, in_plane_rows,
                               simulate)
from relief_bsdf.plate.deterministic import solver_of
from relief_bsdf.plate.photon import hemispherical, trace


def plate(bulk, n=1.5, front=None, cone=1.0, t=2e-3):
    return Experiment(Plate(t, ConstantIndex(n), front or FlatFace(), FlatFace(), bulk),
                      Instrument(detector_half_angle_deg=cone))


def hemi(ex, theta_i):
    rows = in_plane_rows(550.0, [theta_i], [10.0])
    return solver_of(ex, rows, TableGrid()).solve(550.0, [theta_i])[0].hemispherical()


@pytest.mark.slow   # physics-long: adding-doubling on the default grid
@pytest.mark.parametrize("g", [0.0, 0.6])
def test_lossless_scattering_plate_conserves_energy(g):
    for ti in (0.0, 30.0, 60.0):
        h = hemi(plate(Bulk(0.0, 500.0, g)), ti)
        assert h["R"] + h["T"] == pytest.approx(1.0, abs=1e-3), (ti, h)
        assert h["diffuse_R"] > 0.05 and h["diffuse_T"] > 0.1        # scattering did happen


@pytest.mark.slow
def test_lossless_scattering_with_a_depolarising_mueller_face_conserves_energy(lambert_table):
    # the Stokes (4-vector) loop with the slab: Rv, Tv act on S unchanged (scalar phase function)
    o = lambert_table("outside", 0.05, 0.95, [0, 30], mueller=True)
    i = lambert_table("inside", 0.5, 0.5, np.arange(0, 90, 5.0), mueller=True)
    ex = plate(Bulk(0.0, 300.0, 0.5), front=TableFace(i, o))
    h = hemi(ex, 30.0)
    assert h["R"] + h["T"] == pytest.approx(1.0, abs=2e-3)
    h0 = hemi(plate(Bulk(0.0, 300.0, 0.5), front=TableFace(*(lambert_table(f, a, b, th) for f, a, b, th in (
        ("inside", 0.5, 0.5, np.arange(0, 90, 5.0)), ("outside", 0.05, 0.95, [0, 30]))))), 30.0)
    # the scalar loop drops the polarisation the flat back face gives light that the bulk then carries
    # (unchanged) back to it; with depolarising rough-face tables that is a small effect
    assert h["R"] == pytest.approx(h0["R"], rel=1e-3)
    assert h["R"] != h0["R"]


def test_thin_slab_reflection_is_single_scattering():
    """Index-matched faces (n = 1): the plate is a bare slab; at tau = 1e-3 its diffuse BSDF is the
    single-scattering one, f = mu_s t p(Theta) / (mu_i mu_s) (van de Hulst 1980 eq. 5.1), within 2 %."""
    s, t, g, ti = 0.5, 2e-3, 0.5, 30.0
    ts = np.arange(10.0, 71.0, 5.0)
    rows = in_plane_rows(550.0, [ti], ts, sides=("R", "T"), phi_s_deg=(0.0,))
    v = simulate(plate(Bulk(0.0, s, g), n=1.0), rows).values_per_sr
    mi, ms = np.cos(np.radians(ti)), np.cos(np.radians(rows.theta_s_deg))
    si, ss = np.sin(np.radians(ti)), np.sin(np.radians(rows.theta_s_deg))
    # propagation directions: in (si, 0, -mi); R out (-ss, 0, +ms) at phi_s = 0 seen as direction; T out (ss,0,-ms)
    cosR = -si * ss - mi * ms
    cosT = -si * ss + mi * ms
    expect = np.where(rows.side == "R", s * t * hg_phase(cosR, g), s * t * hg_phase(cosT, g)) / (mi * ms)
    np.testing.assert_allclose(v, expect, rtol=0.02)


@pytest.mark.slow
def test_forward_peaked_scattering_tends_to_no_scattering():
    clear = hemi(plate(Bulk(0.0, 0.0, 0.0)), 30.0)
    diffuse = []
    for g in (0.9, 0.99, 0.999, 0.9999):
        h = hemi(plate(Bulk(0.0, 500.0, g)), 30.0)
        diffuse.append(h["diffuse_R"] + h["diffuse_T"])
    assert np.all(np.diff(diffuse) < 0)
    assert diffuse[-1] < 2e-3
    assert h["specular_T"] == pytest.approx(clear["specular_T"], abs=2e-3)
    assert h["specular_R"] == pytest.approx(clear["specular_R"], abs=2e-3)


@pytest.mark.slow   # physics-long: adding-doubling on the default grid
def test_photon_engine_agrees_with_the_deterministic_engine_on_a_scattering_plate():
    """Independent photon Monte Carlo (free paths + HG sampling) against adding-doubling, absorbing
    and scattering bulk, flat faces: hemispherical R and T within 0.5 % absolute, diffuse rows to the noise."""
    ex = plate(Bulk(50.0, 500.0, 0.6), cone=3.0)
    N = 200_000
    h_mc = hemispherical(trace(ex, 550.0, 30.0, 0.0, N, np.random.default_rng(1)))
    h = hemi(ex, 30.0)
    assert h_mc["R"] == pytest.approx(h["R"], abs=5e-3)
    assert h_mc["T"] == pytest.approx(h["T"], abs=5e-3)
    rows = in_plane_rows(550.0, [30.0], np.arange(2.0, 80.0, 4.0))
    keep = ~np.isclose(rows.theta_s_deg, 30.0)          # off the two delta beams
    d = simulate(ex, rows).values_per_sr[keep]
    p = simulate(ex, rows, engine="photon", photons=N, seed=1)
    z = (d - p.values_per_sr[keep]) / p.sigma_per_sr[keep]
    assert np.sqrt(np.mean(z**2)) < 1.5, z
    assert abs(d.sum() / p.values_per_sr[keep].sum() - 1) < 0.02


def test_the_phase_cells_are_kept_per_cells_and_g_and_the_slab_is_the_same():
    """`phase_cells` depends on the cells and g alone: a second slab with another absorption and scattering
    coefficient re-uses them (read-only), and its operators equal those of a slab made with none kept."""
    from relief_bsdf.plate import slab
    from relief_bsdf.plate.memory import current_memory
    e = np.arange(0.0, 90.01, 5.0)
    current_memory().drop("phase")
    first = slab.phase_cells(e, 12, 0.6)
    assert slab.phase_cells(e, 12, 0.6) is first and not first[0].flags.writeable
    assert slab.phase_cells(e, 12, 0.5) is not first
    kept = slab.slab_operators(e, 12, 1e-3, 200.0, 80.0, 0.6)
    current_memory().drop("phase")
    fresh = slab.slab_operators(e, 12, 1e-3, 200.0, 80.0, 0.6)
    assert np.array_equal(kept.R, fresh.R) and np.array_equal(kept.T, fresh.T)
    np.testing.assert_allclose(slab.phase_cells(e, 12, 0.6)[1], first[1], rtol=0, atol=0)
