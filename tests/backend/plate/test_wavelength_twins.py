"""Wavelengths without dispersion: a geometric-optics face is traced once and the plate solved once.

In geometric optics the wavelength enters only through the refractive indices, so at wavelengths
where the indices are the same the tables are one table (plate.faces.same_indices, traced at the
longest of them) and the plate's solution is one solution (PlateSolver._twin_wavelength).  With a
dispersive index every wavelength keeps its own table and solve, and Fresnel's law shows it.
"""
import numpy as np
import pytest

from relief_bsdf.core.index import CauchyIndex, ConstantIndex, Material
from relief_bsdf.plate import current_memory, Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, simulate
from relief_bsdf.plate.rows import Rows, in_plane_rows
from relief_bsdf.plate.sector_loop import _SectorKernels
from relief_bsdf.plate.faces import same_indices
from relief_bsdf.surface.synth import random_relief

GRID = TableGrid(5.0, 15.0, 15.0)
WAVELENGTHS = (450.0, 550.0, 650.0)


def _rough():
    return random_relief(32, 0.25e-6, 0.15e-6, 1.0e-6, "gaussian", seed=3)


def _rows(wavelengths):
    parts = [in_plane_rows(w, [0.0, 30.0], np.arange(2.0, 80.0, 6.0)) for w in wavelengths]
    return Rows(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                  ("wavelength_nm", "theta_i_deg", "phi_i_deg", "side", "theta_s_deg", "phi_s_deg")))


def test_same_indices_groups_wavelengths_by_index_pair_and_keeps_the_longest():
    flat = Material(ConstantIndex(1.5))
    assert same_indices(flat, WAVELENGTHS, "outside") == ((650.0,), (0, 0, 0))
    assert same_indices(flat, WAVELENGTHS, "inside") == ((650.0,), (0, 0, 0))
    dispersive = Material(CauchyIndex(1.5, 4200.0))
    assert same_indices(dispersive, WAVELENGTHS, "outside") == (WAVELENGTHS, (0, 1, 2))


def test_a_ray_face_without_dispersion_is_traced_once_at_the_longest_wavelength():
    face = ReliefFace(_rough(), method="ray", samples=4000, seed=1)
    mat = Material(ConstantIndex(1.5))
    current_memory().drop("table")
    out3, in3 = face.tables(mat, GRID, WAVELENGTHS, [0.0, 30.0])
    current_memory().drop("table")
    out1, in1 = face.tables(mat, GRID, [650.0], [0.0, 30.0])
    assert np.array_equal(in3.wavelength_nm, WAVELENGTHS)
    for three, one in ((out3, out1), (in3, in1)):
        for k in range(3):
            np.testing.assert_array_equal(three.values_per_sr[k], one.values_per_sr[0])
            np.testing.assert_array_equal(three.mueller_per_sr[k], one.mueller_per_sr[0])
            np.testing.assert_array_equal(three.specular_R[k], one.specular_R[0])
        assert three.values_per_sr[..., 1, :, :].sum() > 0          # something was traced


def test_a_dispersive_flat_face_keeps_fresnels_wavelength_dependence():
    """A flat relief traced by rays reflects exactly Fresnel's R at each wavelength's own index."""
    flat = random_relief(32, 1e-6, 1e-12, 4e-6, "gaussian", seed=0).scaled(0.0)
    idx = CauchyIndex(1.5, 4200.0)
    current_memory().drop("table")
    out, _ = ReliefFace(flat, method="ray", samples=2000, seed=0).tables(Material(idx), GRID, WAVELENGTHS, [0.0])
    for k, w in enumerate(WAVELENGTHS):
        n = idx.n(w).real
        assert out.specular_R[k, 0, 0] == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-6)
    assert out.specular_R[0, 0, 0] > out.specular_R[2, 0, 0] * 1.02


def test_the_plate_at_wavelengths_without_dispersion_is_the_plate_solved_at_one():
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(_rough(), method="ray", samples=4000, seed=1),
                          FlatFace()), Instrument(detector_half_angle_deg=2.0))
    current_memory().drop("table")
    three = simulate(ex, _rows(WAVELENGTHS), grid=GRID).values_per_sr.reshape(3, -1)
    current_memory().drop("table")
    one = simulate(ex, _rows([650.0]), grid=GRID).values_per_sr
    assert one.max() > 0
    for k in range(3):
        np.testing.assert_array_equal(three[k], one)


def test_a_dispersive_plate_is_solved_at_each_wavelength():
    flat = random_relief(32, 1e-6, 1e-12, 4e-6, "gaussian", seed=0).scaled(0.0)
    idx = CauchyIndex(1.5, 4200.0)
    ex = Experiment(Plate(2e-3, idx, ReliefFace(flat, method="ray", samples=2000, seed=0), FlatFace()),
                    Instrument(detector_half_angle_deg=2.0))
    rows = Rows([450.0, 650.0], [0.0, 0.0], [0.0, 0.0], ["T", "T"], [0.0, 0.0], [0.0, 0.0])
    current_memory().drop("table")
    t450, t650 = simulate(ex, rows, grid=GRID).values_per_sr
    # through two flat faces (incoherent sum of the internal reflections): T = (1 - R) / (1 + R) per face pair
    tr = []
    for w in (450.0, 650.0):
        n = idx.n(w).real
        r = ((n - 1) / (n + 1)) ** 2
        tr.append((1 - r) / (1 + r))
    assert t450 / t650 == pytest.approx(tr[0] / tr[1], rel=1e-4)
    assert t450 < t650


def test_the_stacked_sector_kernels_are_the_sum_of_the_complex_products():
    """_SectorKernels: one real product of the stacked kernels equals sum_k dK_k Y_k, and `weighted`
    sum_k w_k dK_k (complex double arithmetic on the same single-precision kernels)."""
    rng = np.random.default_rng(4)
    K, M, nc, q = 3, 5, 8, 2
    dK = (rng.normal(size=(K, M, nc, nc)) + 1j * rng.normal(size=(K, M, nc, nc))).astype(np.complex64)
    loop = np.concatenate([np.concatenate([d.real, d.imag], axis=1) for d in dK], axis=2)
    sk = _SectorKernels(np.array([15.0, 30.0, 45.0]), loop.astype(np.float32), ())
    Y = rng.normal(size=(K, M, nc, q)) + 1j * rng.normal(size=(K, M, nc, q))
    want = sum(dK[k].astype(complex) @ Y[k] for k in range(K))
    got = sk.apply(Y)
    assert got.shape == (M, nc, q)
    assert np.abs(got - want).max() < 1e-5 * np.abs(want).max()
    w = np.array([0.2, 0.5, 0.3])
    want_w = sum(w[k] * dK[k].astype(complex) for k in range(K))
    assert np.abs(sk.weighted(w) - want_w).max() < 1e-6 * np.abs(want_w).max()
