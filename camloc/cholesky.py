"""Sparse Cholesky factorization of a symmetric positive definite matrix: CHOLMOD's supernodal
``P A P^T = L L^T`` (Chen, Davis, Hager and Rajamanickam, 2008), as the cvxopt wheels ship it.

CHOLMOD orders A with approximate minimum degree (AMD), finds its supernodes (runs of columns of
L with a common pattern) and factors each as one dense block with BLAS (the wheels' own): at
20,000 poses the reduced pose system (``camloc.schur``) factored in 1.6-3 s (after about 1 s of
ordering and symbolic analysis) where SuperLU in symmetric mode took 11 s on the same machine
(docs/performance.md). A solve is a forward and a
back substitution with L, never an inverse.

The factor itself, for the selected inversion of the landmarks' covariances
(``camloc.selected_inverse``), is handed over as ``L = L_1 diag(l)`` with ``L_1`` unit lower
triangular, so that ``P A P^T = L_1 D L_1^T`` with ``D = l^2``: the form that recurrence reads.

Pure: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from cvxopt import cholmod, matrix, spmatrix


class NotPositiveDefinite(np.linalg.LinAlgError):
    """No positive pivot at A's row and column ``index``: A is singular, indefinite, or so nearly
    singular that rounding made the pivot non-positive."""

    def __init__(self, index: int) -> None:
        super().__init__(f"the matrix is not positive definite (no positive pivot at its unknown {index})")
        self.index = index


class Cholesky:
    """``P A P^T = L L^T`` of a symmetric positive definite sparse A, with solves.

    Parameters
    ----------
    A : (n, n) symmetric positive definite; only its lower triangle is read.

    Raises
    ------
    NotPositiveDefinite : A is not positive definite (to working precision).
    """

    def __init__(self, A: sp.spmatrix) -> None:
        A = sp.csc_matrix(A)
        self.shape = A.shape
        self._lower = _cvxopt_lower(A)
        self._factor = cholmod.symbolic(self._lower, uplo="L")
        try:
            cholmod.numeric(self._lower, self._factor)
        except ArithmeticError as error:
            raise NotPositiveDefinite(self._unknown_of_column(A, int(error.args[0]))) from None
        self._ldl: tuple[sp.csc_matrix, np.ndarray, np.ndarray] | None = None

    def _unknown_of_column(self, A: sp.csc_matrix, column: int) -> int:
        """A's index of the factor's ``column``. The ordering depends on A's pattern alone, so it
        is read from the factor of a matrix with that pattern that is positive definite
        (diagonally dominant), A's own having failed."""
        magnitude = abs(A)
        dominant = magnitude + sp.diags(np.asarray(magnitude.sum(axis=0)).ravel() + 1.0)
        cholmod.numeric(_cvxopt_lower(sp.csc_matrix(dominant)), self._factor)
        return int(np.flatnonzero(self.permutation() == column)[0])

    def solve(self, b: np.ndarray, trans: str = "N") -> np.ndarray:
        """x (n,) or (n, k) of ``A x = b`` (``trans`` asks for the transpose's, the same: A is
        symmetric)."""
        if self._ldl is not None:  # handing L over left CHOLMOD's factor symbolic: make it again
            cholmod.numeric(self._lower, self._factor)
            self._ldl = None
        b = np.asarray(b, dtype=float)
        x = matrix(np.asfortranarray(b.reshape(b.shape[0], -1)))
        cholmod.solve(self._factor, x)
        return np.asarray(x).reshape(b.shape)

    def permutation(self) -> np.ndarray:
        """(n,) int64 ``perm`` with ``A[u, v] = (L L^T)[perm[u], perm[v]]``."""
        position = matrix(np.arange(self.shape[0], dtype=float))
        cholmod.solve(self._factor, position, sys=8)  # P x: x[u] lands at u's place in the factor
        return np.rint(np.asarray(position).ravel()).astype(np.int64)

    def ldl(self) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        """``(L_1, D, perm)``: ``P A P^T = L_1 diag(D) L_1^T``, ``L_1`` (n, n) unit lower triangular
        CSC with sorted rows (explicit zeros where a supernode pads its columns), ``perm`` as
        ``permutation``. A solve after it factors A again (CHOLMOD hands its L over by moving it)."""
        if self._ldl is None:
            perm = self.permutation()
            indptr, indices, values = (np.asarray(part).ravel() for part in cholmod.getfactor(self._factor).CCS)
            L = sp.csc_matrix((values, indices, indptr), shape=self.shape)
            L.sort_indices()
            diagonal = L.diagonal()
            L.data /= np.repeat(diagonal, np.diff(L.indptr))  # L = L_1 diag(l), its pattern kept
            self._ldl = (L, diagonal**2, perm)
        return self._ldl


def _cvxopt_lower(A: sp.csc_matrix) -> spmatrix:
    """The lower triangle of A (CSC) as cvxopt's sparse matrix (triplets, 64-bit indices)."""
    column = np.repeat(np.arange(A.shape[1], dtype=np.int64), np.diff(A.indptr))
    lower = A.indices >= column
    return spmatrix(matrix(A.data[lower]), matrix(A.indices[lower].astype(np.int64)), matrix(column[lower]), A.shape)
