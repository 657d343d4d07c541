"""The sparse Cholesky (camloc.cholesky) against dense linear algebra: its solves, its factor,
its refusal of a matrix that is not positive definite, and the selected inversion of its factor."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from camloc.cholesky import Cholesky, NotPositiveDefinite
from camloc.selected_inverse import selected_inverse


def _spd(rng, n: int = 60, density: float = 0.05) -> sp.csc_matrix:
    """A random sparse symmetric positive definite matrix (n, n)."""
    B = sp.random(n, n, density=density, random_state=np.random.RandomState(int(rng.integers(1 << 31))))
    return sp.csc_matrix(B @ B.T + sp.identity(n))


def test_solves_equal_dense_solves(rng):
    A = _spd(rng)
    factor = Cholesky(A)
    b = rng.normal(size=(A.shape[0], 3))
    expected = np.linalg.solve(A.toarray(), b)
    np.testing.assert_allclose(factor.solve(b), expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(factor.solve(b[:, 1]), expected[:, 1], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(factor.solve(b, trans="T"), expected, rtol=1e-10, atol=1e-12)


def test_its_factor_reproduces_the_permuted_matrix_and_solves_go_on_after_it(rng):
    A = _spd(rng)
    factor = Cholesky(A)
    L, D, perm = factor.ldl()
    assert np.allclose(L.diagonal(), 1.0) and sp.triu(L, k=1).nnz == 0 and np.all(D > 0)
    LDLt = (L @ sp.diags(D) @ L.T).toarray()
    dense = A.toarray()
    np.testing.assert_allclose(LDLt[np.ix_(perm, perm)], dense, atol=1e-12)  # A[u, v] = (L D L^T)[perm[u], perm[v]]
    b = rng.normal(size=A.shape[0])
    np.testing.assert_allclose(factor.solve(b), np.linalg.solve(dense, b), rtol=1e-10, atol=1e-12)


def test_a_matrix_without_a_positive_pivot_is_refused_naming_its_unknown(rng):
    A = _spd(rng, n=12).tolil()
    A[7, :] = 0.0
    A[:, 7] = 0.0
    A[7, 7] = -1.0  # decoupled: its pivot is -1 whatever the ordering
    with pytest.raises(NotPositiveDefinite) as refused:
        Cholesky(sp.csc_matrix(A))
    assert refused.value.index == 7 and isinstance(refused.value, np.linalg.LinAlgError)


def test_selected_inversion_of_the_factor_equals_the_dense_inverse_on_its_pattern(rng):
    A = _spd(rng, n=80, density=0.03)
    inverse = np.linalg.inv(A.toarray())
    L, D, perm = Cholesky(A).ldl()
    Z, perm = selected_inverse(L, D, perm, closed=True)
    Zc = Z.tocoo()
    order = np.argsort(perm)  # factor position -> A's index
    np.testing.assert_allclose(Zc.data, inverse[order[Zc.row], order[Zc.col]], rtol=1e-9, atol=1e-12)
    # pairs off the factor's pattern, asked for: added, and the pattern closed again
    spread = np.arange(0, 80, 14)  # six unknowns far apart: every pair of them
    needed = sp.coo_matrix((np.ones(36), (np.repeat(spread, 6), np.tile(spread, 6))), shape=A.shape)
    Z, perm = selected_inverse(L, D, perm, needed, closed=True)
    u, v = perm[needed.row], perm[needed.col]
    values = np.asarray(Z[np.maximum(u, v), np.minimum(u, v)]).ravel()
    np.testing.assert_allclose(values, inverse[needed.row, needed.col], rtol=1e-9, atol=1e-12)
