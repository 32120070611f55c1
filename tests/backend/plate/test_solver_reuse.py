"""The deterministic engine reuses a plate's operators when only the instrument changes, or only the
outside table with it (plate.deterministic._reused_solver, PlateSolver.with_outside): the numbers
must be those of a fresh solver.  Its kernels are interpolated by gathers (`_apply`): equal to the
dense contraction."""
import numpy as np

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate import deterministic
from relief_bsdf.surface.synth import random_relief

GRID = TableGrid(3.0, 15.0, 15.0)
ROWS = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 6.0))


def _experiment() -> Experiment:
    relief = random_relief(64, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=3)
    face = ReliefFace(relief, "ray", samples=5_000, seed=0, options={"polarized": True})
    return Experiment(Plate(2e-3, ConstantIndex(1.5), face, FlatFace()))


def _fresh(ex: Experiment) -> np.ndarray:
    deterministic._SOLVERS.clear()
    return simulate(ex, ROWS, grid=GRID).values_per_sr


def test_an_instrument_change_reuses_the_operators_and_gives_a_fresh_solvers_numbers():
    ex = _experiment()
    _fresh(ex)                                             # operators of this plate built and kept
    ops = deterministic._SOLVERS[-1][2]._ops
    changed = ex.with_instrument(polarization_q=1.0, blur_deg=1.5, background_per_sr=0.01)
    reused = simulate(changed, ROWS, grid=GRID).values_per_sr
    assert len(deterministic._SOLVERS) == 1 and deterministic._SOLVERS[-1][2]._ops is ops
    np.testing.assert_allclose(reused, _fresh(changed), rtol=1e-12, atol=0)
    assert not np.allclose(reused, _fresh(ex))             # the instrument did change the rows


def test_a_change_of_the_reading_alone_finds_the_field_solved_and_a_polarisation_solves_anew(monkeypatch):
    """Stray light, cone and aperture blur act on how the rows read the field: the solved field of the
    same incidences and source is kept with the operators and read again (no solve); another source
    polarisation, or another outside table (a tilt), is solved anew.  A fresh solver's numbers."""
    ex = _experiment()
    _fresh(ex)
    solves = []
    real = deterministic.PlateSolver._solve
    monkeypatch.setattr(deterministic.PlateSolver, "_solve", lambda self, *a: solves.append(a) or real(self, *a))
    read = ex.with_instrument(blur_deg=1.5, background_per_sr=0.01, detector_half_angle_deg=2.0)
    got = simulate(read, ROWS, grid=GRID).values_per_sr
    assert solves == []                                    # read from the kept field
    fresh = _fresh(read)
    assert len(solves) == 1
    np.testing.assert_allclose(got, fresh, rtol=1e-12, atol=0)
    polarised = read.with_instrument(polarization_q=1.0)
    got = simulate(polarised, ROWS, grid=GRID).values_per_sr
    assert len(solves) == 2
    np.testing.assert_allclose(got, _fresh(polarised), rtol=1e-12, atol=0)
    simulate(ex.with_instrument(tilt_deg=2.0), ROWS, grid=GRID)
    assert len(solves) == 4                                # a fresh solver of `polarised`, then the tilt


def test_a_bulk_change_builds_new_loop_operators_on_the_tables_kernels():
    """Absorption acts on the round trip, not on the tables: new loop operators, the tables' part
    (kernels in azimuthal modes, exit maps: `_table_ops`) shared; a fresh solver's numbers."""
    ex = _experiment()
    _fresh(ex)
    first = deterministic._SOLVERS[-1][2]
    absorbing = ex.with_bulk(absorption_per_m=200.0)
    got = simulate(absorbing, ROWS, grid=GRID).values_per_sr
    assert len(deterministic._SOLVERS) == 2
    second = deterministic._SOLVERS[-1][2]
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
    loop = deterministic._SOLVERS[-1][2]._ops[550.0]["sys_lu"]
    tilted = ex.with_instrument(tilt_deg=3.0)
    got = simulate(tilted, ROWS, grid=GRID).values_per_sr
    solver = deterministic._SOLVERS[-1][2]
    assert solver._ops[550.0]["sys_lu"] is loop and solver.outside is not deterministic._SOLVERS[0][2].outside
    np.testing.assert_allclose(got, _fresh(tilted), rtol=1e-12, atol=0)
    assert not np.allclose(got, _fresh(ex))


def test_interpolation_by_gathers_equals_the_dense_contraction():
    rng = np.random.default_rng(1)
    arr = rng.random((7, 9, 12, 4, 4)).astype(np.float32)
    cases = [(deterministic._lin_matrix(np.arange(7) * 2.5, rng.uniform(-3, 20, 11)), 0),
             (deterministic._lin_matrix(np.arange(9) + 0.5, rng.uniform(0, 9, 5)), 1),
             (deterministic._periodic_matrix(np.arange(12) * 30.0, rng.uniform(-400, 400, 8)), 2),
             (deterministic._periodic_matrix(np.arange(12) * 30.0, np.arange(12) * 30.0 + 60.0), 2),   # a rotation
             (deterministic._lin_matrix([5.0], [1.0, 7.0]), 0)]
    for W, axis in cases:
        a = arr[:W.shape[1]] if axis == 0 else arr
        dense = np.moveaxis(np.tensordot(W, a, axes=([1], [axis])), 0, axis)
        got = deterministic._apply(W, a, axis)
        assert got.dtype == dense.dtype and got.shape == dense.shape
        np.testing.assert_allclose(got, dense, rtol=1e-13, atol=1e-15)
    modes = np.fft.rfft(arr, axis=2)
    W = cases[0][0]
    np.testing.assert_allclose(deterministic._apply(W, np.ascontiguousarray(modes), 0),
                               np.moveaxis(np.tensordot(W, modes, axes=([1], [0])), 0, 0), rtol=1e-12, atol=1e-14)
