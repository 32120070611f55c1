"""The plate's table interpolation (`_apply`) is the contraction with its weight matrix, whichever way
it is computed (in-place blocks along the leading axis, gathers along an inner one, a selection)."""
import numpy as np
import pytest

from relief_bsdf.plate.tableview import _apply, _lin_matrix, _periodic_matrix


def _dense(W, arr, axis):
    return np.moveaxis(np.tensordot(W, arr, axes=([1], [axis])), 0, axis)


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.complex128])
def test_linear_interpolation_along_any_axis_is_the_contraction_with_its_weights(axis, dtype):
    rng = np.random.default_rng(3)
    arr = (rng.random((7, 6, 5, 4)) + (1j * rng.random((7, 6, 5, 4)) if dtype is np.complex128 else 0)).astype(dtype)
    grid = np.sort(rng.uniform(0.0, 90.0, arr.shape[axis]))
    x = np.concatenate([[-5.0, 95.0], grid[:2], rng.uniform(0.0, 90.0, 9)])   # clamped ends, nodes, between
    W = _lin_matrix(grid, x)
    got = _apply(W, arr, axis)
    want = _dense(W, arr.astype(np.result_type(arr.dtype, W.dtype)), axis)
    assert got.dtype == np.result_type(arr.dtype, W.dtype)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)


@pytest.mark.parametrize("axis", [0, 2])
def test_periodic_interpolation_and_a_pure_rotation_are_the_contraction_too(axis):
    rng = np.random.default_rng(4)
    arr = rng.random((12, 3, 12))
    centres = np.arange(12) * 30.0 + 15.0
    for x in (centres + 7.0, np.roll(centres, 5)):       # between the cells; exactly on them (a selection)
        W = _periodic_matrix(centres, x)
        np.testing.assert_allclose(_apply(W, arr, axis), _dense(W, arr, axis), rtol=1e-12, atol=0)


def test_a_table_with_one_incidence_is_read_at_every_incidence():
    arr = np.arange(10.0).reshape(1, 10)
    W = _lin_matrix(np.array([30.0]), np.array([0.0, 30.0, 80.0]))
    np.testing.assert_array_equal(_apply(W, arr, 0), np.repeat(arr, 3, axis=0))
