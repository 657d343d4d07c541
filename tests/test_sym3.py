"""Closed-form inverse of symmetric 3x3 stacks against LAPACK."""

import numpy as np
import pytest

from camloc import sym3


@pytest.mark.parametrize("scales", [(1.0, 1.0, 1.0), (1e3, 1e3, 1e6), (1e-2, 1e4, 3.0)])
def test_inverse_matches_lapack_and_is_exactly_symmetric(rng, scales):
    # information matrices as files give them: normalized image coordinates beside depth, or pixels
    D = np.diag(np.sqrt(scales))
    B = rng.normal(size=(500, 3, 3))
    S = D @ (B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)) @ D
    inverse = sym3.inverse(S)
    np.testing.assert_allclose(inverse, np.linalg.inv(S), rtol=1e-9, atol=1e-12 * np.abs(np.linalg.inv(S)).max())
    assert np.array_equal(inverse, np.swapaxes(inverse, 1, 2))
    # only the upper triangle is read
    lower_garbage = S.copy()
    lower_garbage[:, 1, 0] = lower_garbage[:, 2, 0] = lower_garbage[:, 2, 1] = np.nan
    assert np.array_equal(sym3.inverse(lower_garbage), inverse)


def test_inverse_keeps_the_stack_s_shape(rng):
    S = np.broadcast_to(np.diag([2.0, 4.0, 8.0]), (2, 5, 3, 3))
    np.testing.assert_array_equal(sym3.inverse(S), np.broadcast_to(np.diag([0.5, 0.25, 0.125]), (2, 5, 3, 3)))


@pytest.mark.parametrize("scale", [1e300, 1e150, 1e-150, 1e-300])
def test_inverse_of_matrices_whose_determinant_leaves_the_float_range(rng, scale):
    # the determinant of 1e300 * S is 1e900: unscaled, the inverse came out as zeros (or, for
    # tiny matrices, infinities) where 1e-300 * S^-1 is a representable answer
    B = rng.normal(size=(20, 3, 3))
    S = B @ np.swapaxes(B, 1, 2) + np.eye(3)
    np.testing.assert_allclose(sym3.inverse(scale * S) * scale, np.linalg.inv(S), rtol=1e-9)


def test_inverse_of_a_singular_matrix_is_not_finite():
    assert not np.all(np.isfinite(sym3.inverse(np.zeros((1, 3, 3)))))


@pytest.mark.parametrize("scales", [(1.0, 1.0, 1.0), (1e3, 1e3, 1e6), (1e-2, 1e4, 3.0), (1e-200, 1e-200, 1e-200), (1e200, 1e200, 1e200)])
def test_log_abs_det_matches_lapack(rng, scales):
    # observation covariances as files give them, and some whose determinant leaves the float range
    D = np.diag(np.sqrt(scales))
    B = rng.normal(size=(500, 3, 3))
    S = D @ (B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)) @ D
    np.testing.assert_allclose(sym3.log_abs_det(S), np.linalg.slogdet(S)[1], rtol=1e-12, atol=1e-9)
    lower_garbage = S.copy()
    lower_garbage[:, 1, 0] = lower_garbage[:, 2, 0] = lower_garbage[:, 2, 1] = np.nan
    assert np.array_equal(sym3.log_abs_det(lower_garbage), sym3.log_abs_det(S))


def test_log_abs_det_of_indefinite_and_singular_matrices():
    indefinite = np.diag([2.0, -3.0, 0.5])[None]
    np.testing.assert_allclose(sym3.log_abs_det(indefinite), [np.log(3.0)])
    assert sym3.log_abs_det(np.zeros((2, 3, 3))).tolist() == [-np.inf, -np.inf]
