"""Entries of the inverse of a sparse symmetric positive definite matrix on the pattern of its
factor (selected inversion), for the smoother's landmark covariances.

With ``P A P^T = L D L^T`` (L unit lower triangular, D diagonal), ``Z = (L D L^T)^-1`` satisfies
``L^T Z = D^-1 L^-1``, whose strictly upper part is zero and whose diagonal is ``1 / D``. Read
column by column from the last, that gives Takahashi's recurrence (Takahashi, Fagan and Chin,
1973; Erisman and Tinney, 1975):

    Z[i, j] = - sum_{k in struct(j)} Z[i, k] L[k, j]                     i in struct(j)
    Z[j, j] = 1 / D[j] - sum_{k in struct(j)} Z[k, j] L[k, j]

where struct(j) are the rows below the diagonal of L's column j. Every Z[i, k] it reads lies on
L's symbolic pattern (its rows form a clique of the filled graph), so Z is computed there only,
at about the cost of the factorization, never the dense inverse. L and D are SuperLU's in
symmetric mode (``camloc.schur.factor``: the same permutation of rows and columns, diagonal
pivots), where ``U = D L^T``. SuperLU's L as scipy hands it over leaves out entries that came out
exactly zero, so its pattern is first closed again (``_closed_pattern``: each column's rows
include its elimination-tree children's, Liu 1990) with zeros where entries were missing.

The loops are compiled with numba (a few seconds the first time, cached beside this file).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

# The kernels' options (``camloc.kernels._jit``), without their cache checks: these two functions
# read nothing but their arguments.
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


class PatternError(RuntimeError):
    """The factor's pattern lacks an entry the recurrence needs (a factor that dropped zeros)."""


def selected_inverse(lu) -> tuple[sp.csc_matrix, np.ndarray]:
    """``Z`` (lower triangle, on L's pattern, CSC) of the inverse of ``P A P^T``, and ``perm``
    (n,) with ``A^-1[u, v] = Z[perm[u], perm[v]]`` (read the lower triangle: max row, min column).

    Parameters
    ----------
    lu : scipy's SuperLU of a symmetric positive definite A in symmetric mode.

    Raises
    ------
    PatternError : the factor is not of that kind (other row and column permutations, or a
        pattern the recurrence cannot run on).
    """
    if not np.array_equal(lu.perm_r, lu.perm_c):
        raise PatternError("the factor permutes rows and columns differently")
    L = sp.csc_matrix(lu.L)
    L.sort_indices()
    D = lu.U.diagonal()
    indptr, indices, data = _closed_pattern(L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data)
    Z = np.zeros(len(data))
    if not _takahashi(indptr, indices, data, D, Z):
        raise PatternError("the factor's pattern is not closed under the recurrence")
    return sp.csc_matrix((Z, indices, indptr), shape=L.shape), np.asarray(lu.perm_c)


@_jit
def _closed_pattern(indptr, indices, data):  # pragma: no cover - compiled
    """L (CSC, rows sorted, diagonal first) on the smallest pattern that holds its entries and is
    closed under elimination: column j's rows are its own and those of every child c (parent(c)
    = the first row below c's diagonal) beyond j; entries L lacked are zero."""
    n = indptr.shape[0] - 1
    capacity = max(2 * indices.shape[0], 16)
    out_indices = np.empty(capacity, dtype=np.int64)
    out_ptr = np.zeros(n + 1, dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    head = np.full(n, -1, dtype=np.int64)  # children of each column, as linked lists
    next_child = np.full(n, -1, dtype=np.int64)
    rows = np.empty(n, dtype=np.int64)
    for j in range(n):
        count = 0
        for p in range(indptr[j], indptr[j + 1]):
            rows[count] = indices[p]
            mark[indices[p]] = j
            count += 1
        c = head[j]
        while c != -1:
            for p in range(out_ptr[c] + 1, out_ptr[c + 1]):
                row = out_indices[p]
                if row > j and mark[row] != j:
                    mark[row] = j
                    rows[count] = row
                    count += 1
            c = next_child[c]
        column = np.sort(rows[:count])
        start = out_ptr[j]
        if start + count > capacity:
            capacity = 2 * (start + count)
            grown = np.empty(capacity, dtype=np.int64)
            grown[:start] = out_indices[:start]
            out_indices = grown
        for q in range(count):
            out_indices[start + q] = column[q]
        out_ptr[j + 1] = start + count
        if count > 1:  # the parent: the first row below the diagonal
            parent = column[1]
            next_child[j] = head[parent]
            head[parent] = j
    out_indices = out_indices[: out_ptr[n]].copy()
    out_data = np.zeros(out_ptr[n])
    for j in range(n):
        q = out_ptr[j]
        for p in range(indptr[j], indptr[j + 1]):
            while out_indices[q] < indices[p]:
                q += 1
            out_data[q] = data[p]
    return out_ptr, out_indices, out_data


@_jit
def _takahashi(indptr, indices, L, D, Z):  # pragma: no cover - compiled
    """Fill Z (nnz,) on L's pattern; False when a needed entry is missing from the pattern."""
    n = indptr.shape[0] - 1
    acc = np.zeros(n)
    for j in range(n - 1, -1, -1):
        start, end = indptr[j], indptr[j + 1]
        if indices[start] != j:  # the diagonal first
            return False
        first = start + 1
        m = end - first
        for b in range(m):
            acc[b] = 0.0
        for a in range(m):
            k = indices[first + a]
            L_kj = L[first + a]
            acc[a] += Z[indptr[k]] * L_kj  # Z[k, k]
            p, stop = indptr[k] + 1, indptr[k + 1]
            for b in range(a + 1, m):
                row = indices[first + b]
                while p < stop and indices[p] < row:
                    p += 1
                if p == stop or indices[p] != row:
                    return False
                acc[b] += Z[p] * L_kj  # Z[row, k] L[k, j] toward Z[row, j]
                acc[a] += Z[p] * L[first + b]  # Z[k, row] L[row, j] toward Z[k, j]
        diagonal = 1.0 / D[j]
        for a in range(m):
            Z[first + a] = -acc[a]
            diagonal += acc[a] * L[first + a]
        Z[start] = diagonal
    return True


def quadratic_forms(Z: sp.csc_matrix, perm: np.ndarray, W: sp.csc_matrix, width: int) -> np.ndarray:
    """``W_l^T A^-1 W_l`` (count, width, width) for each block of ``width`` columns of W, with
    A^-1 given on a pattern by ``selected_inverse`` (it must hold every pair of rows a block
    touches, as the factor of ``A = S`` does for ``W = Hpl Hll^-1``).

    Raises
    ------
    PatternError : a pair of rows off Z's pattern.
    """
    W = sp.csc_matrix(W)
    W.sort_indices()
    count = W.shape[1] // width
    out = np.zeros((count, width, width))
    ok = _quadratic_forms(Z.indptr.astype(np.int64), Z.indices.astype(np.int64), Z.data, perm.astype(np.int64),
                          W.indptr.astype(np.int64), W.indices.astype(np.int64), W.data, width, out)
    if not ok:
        raise PatternError("a landmark couples poses whose inverse entry is off the factor's pattern")
    return out


@_jit
def _quadratic_forms(Zp, Zi, Zd, perm, Wp, Wi, Wd, width, out):  # pragma: no cover - compiled
    for block in range(out.shape[0]):
        for a in range(width):
            ca = block * width + a
            for b in range(a, width):
                cb = block * width + b
                total = 0.0
                for x in range(Wp[ca], Wp[ca + 1]):
                    u = perm[Wi[x]]
                    for y in range(Wp[cb], Wp[cb + 1]):
                        v = perm[Wi[y]]
                        col, row = min(u, v), max(u, v)
                        lo, hi = Zp[col], Zp[col + 1]
                        while lo < hi:  # binary search of the row in the column
                            mid = (lo + hi) // 2
                            if Zi[mid] < row:
                                lo = mid + 1
                            else:
                                hi = mid
                        if lo == Zp[col + 1] or Zi[lo] != row:
                            return False
                        total += Wd[x] * Zd[lo] * Wd[y]
                out[block, a, b] = total
                out[block, b, a] = total
    return True
