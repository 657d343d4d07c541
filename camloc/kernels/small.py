"""Products and solves of small matrices as plain loops: ``@`` on 3x3 and 6x6 operands goes
through BLAS and ``np.linalg.solve`` through LAPACK, whose calls cost more than the arithmetic (the
twins are numpy's own). ``solve`` is ``lu_factor`` then ``lu_solve``, which callers that solve
with one matrix several times use themselves."""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import jit


@jit
def mm(A, B):
    """A @ B."""
    n, k, m = A.shape[0], A.shape[1], B.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for q in range(k):
            a = A[i, q]
            if a != 0.0:
                for j in range(m):
                    out[i, j] += a * B[q, j]
    return out


@jit
def mtm(A, B):
    """A' @ B."""
    k, n, m = A.shape[0], A.shape[1], B.shape[1]
    out = np.zeros((n, m))
    for q in range(k):
        for i in range(n):
            a = A[q, i]
            if a != 0.0:
                for j in range(m):
                    out[i, j] += a * B[q, j]
    return out


@jit
def mv(A, v):
    """A @ v."""
    out = np.zeros(A.shape[0])
    for i in range(A.shape[0]):
        s = 0.0
        for j in range(A.shape[1]):
            s += A[i, j] * v[j]
        out[i] = s
    return out


@jit
def lu_factor(M, pivots):
    """Factor M (n, n) in place by Gaussian elimination with partial pivoting: U on and above the
    diagonal, the multipliers below it, pivots[col] the row swapped with col. Raises
    FloatingPointError where M is singular."""
    n = M.shape[0]
    for col in range(n):
        pivot, best = col, abs(M[col, col])
        for r in range(col + 1, n):
            if abs(M[r, col]) > best:
                pivot, best = r, abs(M[r, col])
        if not best > 0.0:
            raise FloatingPointError("a singular matrix in a filter step")
        pivots[col] = pivot
        if pivot != col:
            for j in range(n):
                M[col, j], M[pivot, j] = M[pivot, j], M[col, j]
        inverse_pivot = 1.0 / M[col, col]
        for r in range(col + 1, n):
            factor = M[r, col] * inverse_pivot
            M[r, col] = factor
            if factor != 0.0:
                for j in range(col + 1, n):
                    M[r, j] -= factor * M[col, j]


@jit
def lu_solve(M, pivots, B):
    """B (n, k) <- A^-1 B in place, with A factored into (M, pivots) by ``lu_factor``."""
    n, k = B.shape
    for col in range(n):                 # the rows in their final order: the multipliers moved with them
        pivot = pivots[col]
        if pivot != col:
            for j in range(k):
                B[col, j], B[pivot, j] = B[pivot, j], B[col, j]
    for col in range(n):
        for r in range(col + 1, n):
            factor = M[r, col]
            if factor != 0.0:
                for j in range(k):
                    B[r, j] -= factor * B[col, j]
    for col in range(n - 1, -1, -1):
        for j in range(k):
            s = B[col, j]
            for q in range(col + 1, n):
                s -= M[col, q] * B[q, j]
            B[col, j] = s / M[col, col]


@jit
def lu_log_det(M, pivots):
    """(sign, ln |det A|) of A factored into (M, pivots) by ``lu_factor``."""
    sign, total = 1.0, 0.0
    for i in range(M.shape[0]):
        if pivots[i] != i:
            sign = -sign
        if M[i, i] < 0.0:
            sign = -sign
        total += math.log(abs(M[i, i]))
    return sign, total


@jit
def solve(A, B):
    """A^-1 B for a small square A (n, n) and B (n, k) or (n,) (the result (n, k) or (n, 1)), by
    Gaussian elimination with partial pivoting (LAPACK's call costs more than a 6x6 system);
    raises FloatingPointError where A is singular."""
    n = A.shape[0]
    M, pivots = A.copy(), np.empty(n, np.int64)
    lu_factor(M, pivots)
    X = B.reshape(n, -1).copy() if B.ndim != 1 else B.copy().reshape(n, 1)
    lu_solve(M, pivots, X)
    return X


# A covariance with a variance below this fraction of its largest has left what double precision
# can filter: information of 1e300 beside a prior of 1e2 leaves variances of 1e-290 beside 1e-4,
# whose products underflow. Exact data legitimately reaches 1e-14 of the largest (the simulator's
# noise-free files, information 1e12), far above the bound.
VARIANCE_RATIO_FLOOR = 1e-100


@jit
def check_covariance(P):
    """Raise FloatingPointError where the covariance P (n, n) is not finite or its variances are
    not all positive and within VARIANCE_RATIO_FLOOR of the largest."""
    n = P.shape[0]
    largest = 0.0
    for i in range(n):
        for j in range(n):
            if not np.isfinite(P[i, j]):
                raise FloatingPointError("a covariance is no longer finite")
        largest = max(largest, P[i, i])
    for i in range(n):
        if not P[i, i] > VARIANCE_RATIO_FLOOR * largest:
            raise FloatingPointError("a covariance is no longer positive definite")


@jit
def sorted_ints(values):
    """values (int64) in increasing order, by the float merge sort the kernels' other sorts use:
    ``np.sort`` of an int64 array compiles numba's quicksort for it alone (with ``np.argsort`` of
    int64 and of float, its three kinds took ~4 s of a first compile). Exact below 2^53."""
    return values[np.argsort(values.astype(np.float64), kind="mergesort")]
