"""The deterministic engine reuses a plate's operators when only the instrument changes
(plate.deterministic._reused_solver): the numbers must be those of a fresh solver."""
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
    # (a tilt shows the sample other incidences: other outside tables, so other operators)
    changed = ex.with_instrument(polarization_q=1.0, blur_deg=1.5, background_per_sr=0.01)
    reused = simulate(changed, ROWS, grid=GRID).values_per_sr
    assert len(deterministic._SOLVERS) == 1 and deterministic._SOLVERS[-1][2]._ops is ops
    np.testing.assert_allclose(reused, _fresh(changed), rtol=1e-12, atol=0)
    assert not np.allclose(reused, _fresh(ex))             # the instrument did change the rows


def test_a_plate_change_builds_new_operators():
    ex = _experiment()
    _fresh(ex)
    absorbing = ex.with_bulk(absorption_per_m=200.0)
    got = simulate(absorbing, ROWS, grid=GRID).values_per_sr
    assert len(deterministic._SOLVERS) == 2
    np.testing.assert_allclose(got, _fresh(absorbing), rtol=1e-12, atol=0)
    assert got.sum() < _fresh(ex).sum()
