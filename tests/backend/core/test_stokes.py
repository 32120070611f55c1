"""The one Stokes-frame rotation (core/stokes.py) and its fast kernels, tested equal to the reference."""
import numpy as np

from relief_bsdf.core.frames import cross_rows, direction, divide_rows, dot, dot_rows, normalize, scale_rows
from relief_bsdf.core.stokes import (apply_interface_mueller, apply_interface_mueller_columns, rotate_stokes,
                                     rotate_stokes_columns, rotation_by_angle, s_axis, s_axis_rows,
                                     stokes_rotation)
from relief_bsdf.core.fresnel import mueller_interface


def _beams(n=50, seed=0):
    rng = np.random.default_rng(seed)
    k = normalize(rng.normal(size=(n, 3)))
    s = s_axis(k)
    S = np.column_stack([np.ones(n), rng.uniform(-0.5, 0.5, (n, 3))])
    return k, s, S, rng


def _rotated_axis(k, s, psi_rad):
    """s' = cos(psi) s + sin(psi) p with p = s x k."""
    p = np.cross(s, k)
    return np.cos(psi_rad)[:, None] * s + np.sin(psi_rad)[:, None] * p


def test_rotating_by_a_then_minus_a_is_identity():
    k, s, S, rng = _beams()
    a = rng.uniform(-np.pi, np.pi, k.shape[0])
    s1 = _rotated_axis(k, s, a)
    back = rotate_stokes(rotate_stokes(S, k, s, s1), k, s1, s)
    np.testing.assert_allclose(back, S, atol=1e-12)
    L = stokes_rotation(k, s1, s) @ stokes_rotation(k, s, s1)
    np.testing.assert_allclose(L, np.broadcast_to(np.eye(4), L.shape), atol=1e-12)


def test_ninety_degrees_swaps_s_and_p_so_s1_flips():
    k, s, _, _ = _beams()
    S = np.tile([1.0, 1.0, 0.0, 0.0], (k.shape[0], 1))           # linearly polarised along s
    s90 = _rotated_axis(k, s, np.full(k.shape[0], np.pi / 2))
    out = rotate_stokes(S, k, s, s90)
    np.testing.assert_allclose(out, np.tile([1.0, -1.0, 0.0, 0.0], (k.shape[0], 1)), atol=1e-12)
    # 45 degrees turns S1 into S2 (sign by the p = s x k convention); S0 and S3 never change
    s45 = _rotated_axis(k, s, np.full(k.shape[0], np.pi / 4))
    np.testing.assert_allclose(rotate_stokes(S, k, s, s45), np.tile([1.0, 0.0, -1.0, 0.0], (k.shape[0], 1)),
                               atol=1e-12)


def test_matrix_vector_and_angle_forms_agree():
    k, s, S, rng = _beams(seed=3)
    psi = rng.uniform(-np.pi, np.pi, k.shape[0])
    s1 = _rotated_axis(k, s, psi)
    L = stokes_rotation(k, s, s1)
    np.testing.assert_allclose(L, rotation_by_angle(np.degrees(psi)), atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", L, S), rotate_stokes(S, k, s, s1), atol=1e-12)
    # float32 batches stay float32
    assert rotate_stokes(S.astype(np.float32), k.astype(np.float32), s.astype(np.float32),
                         s1.astype(np.float32)).dtype == np.float32


def test_s_axis_is_transverse_and_horizontal_with_fallback_on_the_normal():
    k = direction([0.0, 30.0, 60.0, 89.0], [0.0, 45.0, 200.0, 300.0])
    s = s_axis(k, np.radians([90.0, 0, 0, 0]))
    np.testing.assert_allclose(np.linalg.norm(s, axis=-1), 1.0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s, k), 0.0, atol=1e-12)
    np.testing.assert_allclose(s[:, 2], 0.0)
    np.testing.assert_allclose(s[0], [-1.0, 0.0, 0.0], atol=1e-12)   # k = z: (-sin phi, cos phi, 0), phi = 90


def test_apply_interface_mueller_equals_the_matrix():
    _, _, S, _ = _beams(seed=5)
    ci = np.linspace(0.1, 1.0, S.shape[0])
    M = mueller_interface(ci, 1.0, 1.5, "R")
    out = apply_interface_mueller(S, M[:, 0, 0], M[:, 0, 1], M[:, 2, 2], M[:, 2, 3])
    np.testing.assert_allclose(out, np.einsum("nij,nj->ni", M, S), atol=1e-14)


def test_row_kernels_equal_dot_and_cross():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 1000, 3)).astype(np.float32)
    np.testing.assert_allclose(dot_rows(a, b), dot(a, b), rtol=1e-6, atol=1e-6)
    assert dot_rows(a, b).dtype == np.float32
    np.testing.assert_allclose(cross_rows(a, b), np.cross(a, b), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(cross_rows(a[0], b), np.cross(a[0], b), rtol=1e-6, atol=1e-6)   # broadcast
    r = rng.uniform(0.5, 2.0, 1000).astype(np.float32)
    np.testing.assert_array_equal(scale_rows(a, r), a * r[:, None])          # the same numbers, bit for bit
    v = a.copy()
    divide_rows(v, r)
    np.testing.assert_array_equal(v, a / r[:, None])


def test_float32_column_kernels_equal_the_reference_definitions():
    """The ray loop's in-place kernels on the (4, K, n) layout are the reference formulas."""
    rng = np.random.default_rng(0)
    n = 5000
    k = normalize(rng.normal(size=(n, 3)))
    k[:10] = (0.0, 0.0, -1.0)                                 # along z: the azimuthal fallback
    k32 = k.astype(np.float32)
    np.testing.assert_allclose(s_axis_rows(k32, 0.7), s_axis(k32, 0.7), atol=1e-6)
    assert s_axis_rows(k32, 0.7).dtype == np.float32
    s_old = s_axis(k)
    s_new = normalize(cross_rows(rng.normal(size=(n, 3)), k))
    A = rng.normal(size=(4, 3, n)).astype(np.float32)
    want = np.stack([rotate_stokes(A[:, j].T.astype(float), k, s_old, s_new) for j in range(3)], axis=1)
    got = A.copy()
    rotate_stokes_columns(got, s_old.astype(np.float32), k32, s_new.astype(np.float32))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want.transpose(2, 1, 0), atol=2e-5)
    a, b, c, d = (rng.random(n).astype(np.float32) for _ in range(4))
    p = rng.random(n).astype(np.float32) + 0.5
    want = np.stack([apply_interface_mueller(A[:, j].T.astype(float), a, b, c, d) / p[:, None]
                     for j in range(3)], axis=1)
    got = A.copy()
    apply_interface_mueller_columns(got, a, b, c, d, 1 / p)
    np.testing.assert_allclose(got, want.transpose(2, 1, 0), atol=2e-5)


def test_column_rotation_is_identity_when_the_axis_does_not_change():
    k, s, _, rng = _beams(n=200, seed=7)
    A = rng.normal(size=(4, 4, k.shape[0])).astype(np.float32)
    got = A.copy()
    rotate_stokes_columns(got, s.astype(np.float32), k.astype(np.float32), s.astype(np.float32))
    np.testing.assert_allclose(got, A, atol=1e-6)
