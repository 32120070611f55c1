"""The simulation's own uncertainty (plate.uncertainty): tables' 1-sigma carried through the plate."""
import dataclasses

import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate.uncertainty import perturbed, rows_sigma
from relief_bsdf.surface.synth import random_relief

GRID = TableGrid(3.0, 15.0, 15.0)
ROWS = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 6.0))


def _experiment(seed: int, samples: int = 20_000, tile_uncertainty: bool = True) -> Experiment:
    relief = random_relief(96, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=3)      # rough: geometric optics
    face = ReliefFace(relief, "ray", samples=samples, seed=seed, options={"tile_uncertainty": tile_uncertainty})
    return Experiment(Plate(2e-3, ConstantIndex(1.5), face, FlatFace()))


def test_perturbed_table_moves_cells_within_their_sigma_and_keeps_a_table_without_sigma():
    ex = _experiment(0)
    out, ins = ex.plate.front.tables(ex.plate.material, GRID, [550.0], [0.0, 30.0])
    rng = np.random.default_rng(1)
    p = perturbed(ins, rng)
    z = (p.values_per_sr - ins.values_per_sr)[ins.sigma_per_sr > 0] / ins.sigma_per_sr[ins.sigma_per_sr > 0]
    assert 0.8 < np.std(z) < 1.2 and np.all(p.values_per_sr >= 0)
    bare = dataclasses.replace(ins, sigma_per_sr=None)
    assert perturbed(bare, rng) is bare


@pytest.mark.slow
def test_propagated_sigma_predicts_the_scatter_between_two_seeds():
    """The sigma says how far an independent Monte-Carlo draw of the same tables moves each row:
    the difference of two seeds, divided by sqrt(sigma_a^2 + sigma_b^2), is a unit normal.  Both
    seeds trace the same tile, so the tables' sigma is their Monte-Carlo part alone here
    (tile_uncertainty off: the tile's realisation is common to both and cannot show between them)."""
    a = simulate(_experiment(1, tile_uncertainty=False), ROWS, grid=GRID, table_sigma_draws=8, seed=1)
    b = simulate(_experiment(2, tile_uncertainty=False), ROWS, grid=GRID, table_sigma_draws=8, seed=2)
    s = np.sqrt(a.sigma_per_sr**2 + b.sigma_per_sr**2)
    lit = (a.values_per_sr > 0.002 * a.values_per_sr.max()) & (s > 0)
    z = (a.values_per_sr - b.values_per_sr)[lit] / s[lit]
    assert lit.sum() > 20
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6          # 8 draws: sigma itself known to ~25 %
    assert "carried through the plate" in a.info["sigma"]


def test_no_table_sigma_means_unknown_not_zero():
    ex = _experiment(0)
    out, ins = ex.plate.front.tables(ex.plate.material, GRID, [550.0], [0.0, 30.0])
    from relief_bsdf.plate import TableFace
    bare = ex.with_plate(front=TableFace(dataclasses.replace(ins, sigma_per_sr=None),
                                         dataclasses.replace(out, sigma_per_sr=None)))
    assert np.all(np.isnan(rows_sigma(bare, ROWS, GRID)))


def test_a_relief_face_reuses_its_tracer_across_heights_with_the_tables_of_a_fresh_build():
    """The fit's evaluations re-trace one grid with new heights: the plate keeps one tracer per grid
    and rewrites its heights (plate.faces._topology_tracer); the tables equal a fresh reconstruction."""
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.plate import current_memory
    from relief_bsdf.surface.operations import scale_and_filter
    current_memory().drop("tracer")                       # other tests leave their grids' tracers behind
    current_memory().drop("table")
    ex = _experiment(0, samples=4000)
    mat = ex.plate.material
    relief = ex.plate.front.relief
    ex.plate.front.tables(mat, GRID, [550.0], [30.0])
    tracer = current_memory().values("tracer")[0]
    other = scale_and_filter(relief, 1.3, 0.0)
    face = dataclasses.replace(ex.plate.front, relief=other)
    current_memory().drop("table")
    out, ins = face.tables(mat, GRID, [550.0], [30.0])
    again = current_memory().values("tracer")[0]
    assert len(current_memory().values("tracer")) == 1
    assert again is tracer or again.mesh.triangles is tracer.mesh.triangles
    from relief_bsdf.plate.faces import face_request
    req = face_request(dataclasses.replace(face, options={"backend": "serial"}), mat, GRID, [550.0], [30.0], "outside")
    (fresh,) = reconstruct(other, mat, req, "ray")
    np.testing.assert_array_equal(out.values_per_sr, fresh.values_per_sr)


@pytest.mark.parametrize("theta_s, half_angle, tol", [(30.0, 2.0, 2e-3), (85.0, 2.0, 2e-3), (88.0, 3.0, 1e-2)])
def test_detector_weights_each_cone_direction_by_its_own_projection(theta_s, half_angle, tol):
    """formats.md: f = P / (P_inc Omega cos theta_s), P collecting f cos(theta) d(omega) over the cone.
    For a BSDF f = cos(theta) the reading is the cone's mean cos^2(theta) / cos(theta_s), checked
    against a direct Monte-Carlo integral over the cone (uniform in solid angle); the horizon's kink
    (88 deg, 3 deg cone) limits the quadrature to ~1 %."""
    from relief_bsdf.plate.detector import offset_directions, projection_weights, quadrature_offsets
    off = quadrature_offsets(half_angle, 400)
    th, _ = offset_directions(np.array([theta_s]), np.array([0.0]), off)
    w = projection_weights(np.array([theta_s]), off)
    f = np.cos(np.radians(th))
    got = float(np.mean(f * w))
    rng = np.random.default_rng(0)
    n = 400_000
    cos_h = np.cos(np.radians(half_angle))
    cz = 1 - rng.random(n) * (1 - cos_h)                 # uniform in solid angle about the row direction
    az = rng.random(n) * 2 * np.pi
    sz = np.sqrt(1 - cz**2)
    t = np.radians(theta_s)
    z = np.maximum(cz * np.cos(t) - sz * np.cos(az) * np.sin(t), 0.0)     # cos(theta) of each direction
    want = np.mean(z * z) / np.cos(t)
    assert got == pytest.approx(want, rel=tol)
    if theta_s >= 85:
        assert abs(np.mean(f) / got - 1.0) > 0.005       # equal weights (the old reading) were off here


def test_the_draws_on_threads_give_the_numbers_of_one_thread(monkeypatch):
    """rows_sigma solves its draws on threads, the perturbations drawn in order: the same sigma."""
    import relief_bsdf.plate.uncertainty as unc
    relief = random_relief(48, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=4)
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", samples=3_000, seed=0), FlatFace()))
    rows = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 8.0))
    grid = TableGrid(3.0, 15.0, 15.0)
    monkeypatch.setattr(unc, "default_workers", lambda: 1)
    one = rows_sigma(ex, rows, grid, draws=4)
    monkeypatch.setattr(unc, "default_workers", lambda: 3)
    three = rows_sigma(ex, rows, grid, draws=4)
    assert np.all(np.isfinite(one)) and np.any(one > 0)
    np.testing.assert_array_equal(one, three)


def test_the_draws_solvers_are_not_kept_and_the_baselines_stays():
    """The model sigma's draws solve perturbed tables once each: their solvers are not kept for reuse, so
    the baseline's solver (kept by the simulation before them) is still there for the next evaluation."""
    from relief_bsdf.plate import current_memory
    relief = random_relief(48, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=4)
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", samples=3_000, seed=0), FlatFace()))
    rows = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 8.0))
    grid = TableGrid(3.0, 15.0, 15.0)
    current_memory().drop("solver")
    sim = simulate(ex, rows, grid=grid, table_sigma_draws=6)
    assert np.all(np.isfinite(sim.sigma_per_sr)) and np.any(sim.sigma_per_sr > 0)
    assert len(current_memory().values("solver")) == 1
    baseline = current_memory().values("solver")[0]
    again = simulate(ex.with_instrument(background_per_sr=0.01), rows, grid=grid)
    assert len(current_memory().values("solver")) == 1 and current_memory().values("solver")[0]._ops is baseline._ops
    np.testing.assert_allclose(again.values_per_sr, sim.values_per_sr + 0.01, rtol=1e-12)


def test_the_deviations_are_the_draws_behind_the_sigma():
    """deviations (the intervals' shared model noise) are the draws of rows_sigma, centred: their standard
    deviation is rows_sigma; relative_deviations are those divided by the values, their standard deviation
    relative_sigma, row by row; without a sigma, none."""
    from relief_bsdf.plate.uncertainty import deviations, relative_deviations, relative_sigma
    relief = random_relief(48, 1.0e-6, 0.6e-6, 5.0e-6, "gaussian", seed=4)
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", samples=3_000, seed=0), FlatFace()))
    rows = in_plane_rows(550.0, [0.0, 30.0], np.arange(2.0, 88.0, 8.0))
    grid = TableGrid(3.0, 15.0, 15.0)
    dev = relative_deviations(ex, rows, grid, draws=5)
    assert dev.shape == (5, len(rows)) and np.allclose(dev.mean(axis=0), 0.0, atol=1e-12)
    v = simulate(ex, rows, grid=grid).values_per_sr
    sigma = rows_sigma(ex, rows, grid, draws=5)
    want = np.clip(np.divide(sigma, np.abs(v), out=np.zeros_like(v), where=v != 0), 0.0, 1.0)
    np.testing.assert_allclose(dev.std(axis=0, ddof=1), want, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(relative_sigma(ex, rows, grid, draws=5), want, rtol=1e-9, atol=1e-12)
    absolute = deviations(ex, rows, grid, draws=5)
    np.testing.assert_allclose(absolute.std(axis=0, ddof=1), sigma, rtol=1e-9, atol=1e-15)
    flat = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()))
    assert relative_deviations(flat, rows, grid, draws=5).shape == (0, len(rows))
