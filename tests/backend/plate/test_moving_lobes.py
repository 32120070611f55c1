"""Between two incidences of an inside table the lobes move, they do not blend.

The truth here is an analytic lobe written for every incidence (a Gaussian around the Snell exit
direction or the specular direction), cell-averaged on the engine grid; the table holds it at
incidences every 2.5 deg and is read in between.  Nothing here is made by the engine under test."""
import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.methods.request import Request
from relief_bsdf.plate import TableGrid
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.plate.tableview import _psa_weights, _TableView
from relief_bsdf.plate.detector import unit
from test_direct_grid import _cell_averages  # tests/backend/plate/test_direct_grid.py: sub-cell quadrature

N_IN, N_OUT = 1.5, 1.0
WIDTH_DEG = 1.5


def _centre_deg(side, theta_in_deg):
    if side == "R":
        return theta_in_deg
    return np.degrees(np.arcsin(np.sin(np.radians(theta_in_deg)) * N_IN / N_OUT))


def _cells(side, theta_in_deg, te, pe, k=8):
    """Cell averages (projected solid angle) of a Gaussian lobe around the lobe's centre at table azimuth
    180 (the propagation azimuth of light incident from phi_i 0), integrated to 1 (unit albedo)."""
    if side == "T" and np.sin(np.radians(theta_in_deg)) * N_IN / N_OUT >= 1.0:
        return np.zeros((te.size - 1, pe.size - 1))          # totally reflected: nothing leaves
    c = unit(_centre_deg(side, theta_in_deg), 180.0)
    f = _cell_averages(lambda th, ph: np.exp(-0.5 * (np.degrees(np.arccos(np.clip(unit(th, ph) @ c, -1, 1)))
                                                     / WIDTH_DEG) ** 2), te, pe, k)
    return f / np.sum(f * projected_solid_angle(te, pe))


def _table(incidences):
    g = TableGrid()
    te, pe = np.asarray(g.theta_edges_deg()), np.asarray(g.phi_edges_deg())
    r = Request(theta_i_deg=tuple(incidences), theta_s_edges_deg=tuple(te), phi_s_edges_deg=tuple(pe))
    v = np.zeros((1, len(incidences), 1, 2, te.size - 1, pe.size - 1))
    for i, t in enumerate(incidences):
        v[0, i, 0, 0] = 0.1 * _cells("R", t, te, pe)
        v[0, i, 0, 1] = 0.8 * _cells("T", t, te, pe)
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, r.phi_i_deg, r.theta_s_edges_deg, r.phi_s_edges_deg, v,
                     incident_from="inside"), te, pe


def _axes(te, pe):
    tc = 0.5 * (te[1:] + te[:-1])
    delta = np.arange(pe.size - 1) * 360.0 / (pe.size - 1)
    return tc, delta


@pytest.mark.parametrize("side,theta_in", [("T", 18.75), ("T", 8.75), ("T", 36.25), ("T", 1.25)])
def test_a_lobe_between_two_incidences_moves_to_where_it_belongs(side, theta_in):
    """Halfway between two incidences, the table read with moving lobes holds one lobe at the query's own
    exit direction and height (the analytic truth there, within 5 % at its peak); the linear blend holds
    two half lobes around it (its peak, the check that this test can fail, far lower)."""
    table, te, pe = _table(np.arange(0.0, 87.6, 2.5))
    tc, delta = _axes(te, pe)
    truth = (0.1 if side == "R" else 0.8) * _cells(side, theta_in, te, pe)      # (T, A) in table azimuths
    truth = np.roll(truth, -(truth.shape[1] // 2), axis=1)                      # relative azimuth delta
    moved = _TableView(table, 550.0, False, "t", moving=(N_IN, N_OUT)).diffuse(side, [theta_in], tc, delta)[0]
    blend = _TableView(table, 550.0, False, "t").diffuse(side, [theta_in], tc, delta)[0]
    peak = np.unravel_index(np.argmax(truth), truth.shape)
    assert np.unravel_index(np.argmax(moved), moved.shape) == peak
    assert moved[peak] == pytest.approx(truth[peak], rel=0.05)
    assert blend.max() < 0.8 * truth[peak]
    # the whole lobe, not just its peak: the L1 distance to the truth a fraction of the blend's
    psa = _psa_weights(tc)[:, None]
    err_moved, err_blend = (float(np.sum(np.abs(x - truth) * psa)) for x in (moved, blend))
    assert err_moved < 0.35 * err_blend


def test_moving_lobes_keep_each_incidences_albedo_and_the_tables_own_incidences():
    """At the table's own incidences the read is the table itself; in between, the albedo (the power the
    loop passes on, R and T apart) is the linear blend's, so a lossless boundary stays lossless.  The
    reflected side is the linear blend itself (it does not move: plate.deterministic docstring)."""
    table, te, pe = _table(np.arange(0.0, 87.6, 2.5))
    tc, delta = _axes(te, pe)
    mv = _TableView(table, 550.0, False, "t", moving=(N_IN, N_OUT))
    lin = _TableView(table, 550.0, False, "t")
    psa = _psa_weights(tc)
    for side in ("R", "T"):
        own = np.array([5.0, 20.0, 40.0])
        np.testing.assert_allclose(mv.diffuse(side, own, tc, delta), lin.diffuse(side, own, tc, delta), rtol=1e-12)
        q = np.linspace(0.3, 85.0, 23)
        a_mv = np.einsum("jta,t->j", mv.diffuse(side, q, tc, delta), psa)
        a_lin = np.einsum("jta,t->j", lin.diffuse(side, q, tc, delta), psa)
        np.testing.assert_allclose(a_mv, a_lin, rtol=1e-12)
        if side == "R":
            np.testing.assert_array_equal(mv.diffuse(side, q, tc, delta), lin.diffuse(side, q, tc, delta))
        else:
            assert not np.allclose(mv.diffuse(side, q, tc, delta), lin.diffuse(side, q, tc, delta))
        # the loop's modes are the FFT of the same cells
        np.testing.assert_allclose(mv.diffuse_modes(side, q, tc, delta),
                                   np.fft.rfft(mv.diffuse(side, q, tc, delta), axis=2), rtol=1e-10, atol=1e-9)


def test_an_unknown_inside_interpolation_is_refused_by_name():
    from relief_bsdf.errors import InputError
    from plate_setups import plate_setup  # tests/backend/plate/plate_setups.py
    from relief_bsdf.core.index import ConstantIndex
    with pytest.raises(InputError, match="inside_interpolation"):
        TableGrid(inside_interpolation="cubic")
    with pytest.raises(InputError, match="inside_interpolation"):
        plate_setup(thickness_m=1e-3, index=ConstantIndex(1.5), inside_interpolation="cubic")


def test_the_sector_step_sets_the_sector_tables_azimuths_and_must_divide_a_half_turn():
    from relief_bsdf.errors import InputError
    from relief_bsdf.plate.faces import SECTOR_AZIMUTHS_DEG
    assert TableGrid().sector_azimuths_deg() == SECTOR_AZIMUTHS_DEG == tuple(float(p) for p in range(0, 180, 15))
    fine = TableGrid(sector_step_deg=7.5).sector_azimuths_deg()
    assert len(fine) == 24 and fine[0] == 0.0 and fine[1] == 7.5 and fine[-1] == 172.5
    from relief_bsdf.plate.grid import NO_SECTORS_DEG
    assert TableGrid(sector_step_deg=NO_SECTORS_DEG).sector_azimuths_deg() == ()    # no sector tables
    for bad in (7.0, 0.0, -15.0, 360.0, 200.0, float("nan")):
        with pytest.raises(InputError, match="sector_step_deg"):
            TableGrid(sector_step_deg=bad)
