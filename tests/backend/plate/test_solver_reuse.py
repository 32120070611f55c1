"""The deterministic engine reuses a plate's operators when only the instrument changes, or only the
outside table with it (plate.deterministic._reused_solver, PlateSolver.with_outside): the numbers
must be those of a fresh solver.  Its kernels are interpolated by gathers (`_apply`): equal to the
dense contraction."""
import numpy as np

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate import deterministic, tableview
from relief_bsdf.surface.synth import random_relief
from relief_bsdf.plate.memory import current_memory

GRID = TableGrid(3.0, 15.0, 15.0)
ROWS = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 6.0))


def _experiment() -> Experiment:
    relief = random_relief(64, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=3)
    face = ReliefFace(relief, "ray", samples=5_000, seed=0, options={"polarized": True})
    return Experiment(Plate(2e-3, ConstantIndex(1.5), face, FlatFace()))


def _fresh(ex: Experiment) -> np.ndarray:
    current_memory().drop("solver")
    return simulate(ex, ROWS, grid=GRID).values_per_sr


def test_an_instrument_change_reuses_the_operators_and_gives_a_fresh_solvers_numbers():
    ex = _experiment()
    _fresh(ex)                                             # operators of this plate built and kept
    ops = current_memory().values("solver")[-1]._ops
    changed = ex.with_instrument(polarization_q=1.0, blur_deg=1.5, background_per_sr=0.01)
    reused = simulate(changed, ROWS, grid=GRID).values_per_sr
    assert len(current_memory().values("solver")) == 1 and current_memory().values("solver")[-1]._ops is ops
    np.testing.assert_allclose(reused, _fresh(changed), rtol=1e-12, atol=0)
    assert not np.allclose(reused, _fresh(ex))             # the instrument did change the rows


def test_a_change_of_the_reading_or_the_source_polarisation_solves_only_what_it_has_not_solved(monkeypatch):
    """Stray light, cone and aperture blur act on how the rows read the field, the source polarisation
    linearly on the field (sum of the unit Stokes sources' fields): the unit fields kept with the
    operators are read again; a new unit source, or another outside table (a tilt), is solved anew.
    The numbers are a fresh solver's, and the sum of unit fields is the field of the source itself."""
    ex = _experiment()
    _fresh(ex)
    solves = []
    real = deterministic.PlateSolver._solve
    monkeypatch.setattr(deterministic.PlateSolver, "_solve", lambda self, *a: solves.append(a) or real(self, *a))
    read = ex.with_instrument(blur_deg=1.5, background_per_sr=0.01, detector_half_angle_deg=2.0)
    got = simulate(read, ROWS, grid=GRID).values_per_sr
    assert solves == []                                    # read from the kept field
    np.testing.assert_allclose(got, _fresh(read), rtol=1e-12, atol=0)
    assert len(solves) == 1                                # the fresh solver's own
    polarised = read.with_instrument(polarization_q=0.6)
    got = simulate(polarised, ROWS, grid=GRID).values_per_sr
    assert len(solves) == 2                                # the unit source (0, 1, 0, 0) alone
    other = simulate(read.with_instrument(polarization_q=-0.3), ROWS, grid=GRID).values_per_sr
    assert len(solves) == 2 and not np.allclose(other, got)
    np.testing.assert_allclose(got, _fresh(polarised), rtol=1e-12, atol=0)
    simulate(ex.with_instrument(tilt_deg=2.0), ROWS, grid=GRID)
    # a fresh solver of `polarised` (2), then the tilt: its incidences on the near side and, read from the
    # half-turned relief's outside table, the one it turns to the far side (theta_i 0: test_half_turn.py)
    assert len(solves) == 6


def test_the_field_of_a_polarised_source_is_the_sum_of_the_unit_sources_fields():
    """Linearity in the source's Stokes vector: solve() by unit sources equals one solve with s itself."""
    ex = _experiment().with_instrument(polarization_q=0.6)
    _fresh(ex)
    solver = current_memory().values("solver")[-1]
    thetas = np.array([0.0, 30.0])
    summed = solver.solve(550.0, thetas)
    direct = solver._solve(550.0, thetas, 0.0, solver.model.source_stokes)
    for a, b in zip(summed, direct):
        for name in ("grid_R", "grid_T", "loop_R", "loop_T"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(a.direct.R, b.direct.R, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(a.direct.T, b.direct.T, rtol=1e-10, atol=1e-14)
        assert [d[:3] for d in a.deltas] == [d[:3] for d in b.deltas]
        np.testing.assert_allclose([d[3] for d in a.deltas], [d[3] for d in b.deltas], rtol=1e-12)
    unpolarised = solver._solve(550.0, thetas, 0.0, np.array([1.0, 0.0, 0.0, 0.0]))
    assert not np.allclose(summed[1].grid_R, unpolarised[1].grid_R, rtol=1e-3)   # the source did change it


def test_a_bulk_change_builds_new_loop_operators_on_the_tables_kernels():
    """Absorption acts on the round trip, not on the tables: new loop operators, the tables' part
    (kernels in azimuthal modes, exit maps: `_table_ops`) shared; a fresh solver's numbers."""
    ex = _experiment()
    _fresh(ex)
    first = current_memory().values("solver")[-1]
    absorbing = ex.with_bulk(absorption_per_m=200.0)
    got = simulate(absorbing, ROWS, grid=GRID).values_per_sr
    assert len(current_memory().values("solver")) == 2
    second = current_memory().values("solver")[-1]
    assert second._ops is not first._ops and second._tops is first._tops
    assert second._ops[550.0]["sys_lu"] is not first._ops[550.0]["sys_lu"]
    np.testing.assert_allclose(got, _fresh(absorbing), rtol=1e-12, atol=0)
    assert got.sum() < _fresh(ex).sum()
    thicker = ex.with_plate(thickness_m=3e-3)          # the thickness too is the bulk's
    np.testing.assert_allclose(simulate(thicker, ROWS, grid=GRID).values_per_sr, _fresh(thicker), rtol=1e-12, atol=0)


def test_a_tilt_reuses_the_loop_operators_with_its_own_outside_table():
    """A tilt shows the sample other incidences: new outside tables, the same inside table.  The loop's
    operators (kernels, round trip, exit maps) are kept, the outside table's part re-derived."""
    ex = _experiment()
    _fresh(ex)
    loop = current_memory().values("solver")[-1]._ops[550.0]["sys_lu"]
    tilted = ex.with_instrument(tilt_deg=3.0)
    got = simulate(tilted, ROWS, grid=GRID).values_per_sr
    solver = current_memory().values("solver")[-1]
    assert solver._ops[550.0]["sys_lu"] is loop and solver.outside is not current_memory().values("solver")[0].outside
    np.testing.assert_allclose(got, _fresh(tilted), rtol=1e-12, atol=0)
    assert not np.allclose(got, _fresh(ex))


def test_after_a_tilt_the_untilted_plate_is_read_through_its_own_outside_table():
    """The tilted plate's solver is a copy of the untilted one with another outside table: it must not
    answer the untilted plate's request (`plate.reuse.held_for_request`), which would read the rows
    through the tilted incidences' table.  The untilted numbers after the tilt are those before it."""
    ex = _experiment()
    before = _fresh(ex)
    simulate(ex.with_instrument(tilt_deg=3.0), ROWS, grid=GRID)
    again = simulate(ex, ROWS, grid=GRID).values_per_sr
    np.testing.assert_allclose(again, before, rtol=1e-12, atol=0)


def test_interpolation_by_gathers_equals_the_dense_contraction():
    rng = np.random.default_rng(1)
    arr = rng.random((7, 9, 12, 4, 4)).astype(np.float32)
    cases = [(tableview._lin_matrix(np.arange(7) * 2.5, rng.uniform(-3, 20, 11)), 0),
             (tableview._lin_matrix(np.arange(9) + 0.5, rng.uniform(0, 9, 5)), 1),
             (tableview._periodic_matrix(np.arange(12) * 30.0, rng.uniform(-400, 400, 8)), 2),
             (tableview._periodic_matrix(np.arange(12) * 30.0, np.arange(12) * 30.0 + 60.0), 2),   # a rotation
             (tableview._lin_matrix([5.0], [1.0, 7.0]), 0)]
    for W, axis in cases:
        a = arr[:W.shape[1]] if axis == 0 else arr
        dense = np.moveaxis(np.tensordot(W, a, axes=([1], [axis])), 0, axis)
        got = tableview._apply(W, a, axis)
        assert got.dtype == dense.dtype and got.shape == dense.shape
        np.testing.assert_allclose(got, dense, rtol=1e-13, atol=1e-15)
    modes = np.fft.rfft(arr, axis=2)
    W = cases[0][0]
    np.testing.assert_allclose(tableview._apply(W, np.ascontiguousarray(modes), 0),
                               np.moveaxis(np.tensordot(W, modes, axes=([1], [0])), 0, 0), rtol=1e-12, atol=1e-14)
