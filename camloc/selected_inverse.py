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
at about the cost of the factorization, never the dense inverse. L and D come from the sparse
Cholesky ``P A P^T = L_c L_c^T`` (``camloc.cholesky``: ``L = L_c diag(L_c)^-1``, ``D =
diag(L_c)^2``). Its pattern is closed already (CHOLMOD's supernodes), but the pairs asked for
(``needed``) may lie off it, so the pattern with them is closed again (``_closed_pattern``: each
column's rows include its elimination-tree children's, Liu 1990) with zeros where entries were
missing.

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


def selected_inverse(L: sp.csc_matrix, D: np.ndarray, perm: np.ndarray, needed: sp.spmatrix | None = None, *,
                     closed: bool = False) -> tuple[sp.csc_matrix, np.ndarray]:
    """``Z`` (lower triangle, on L's pattern, CSC) of the inverse of ``P A P^T = L diag(D) L^T``,
    and ``perm`` (n,) with ``A^-1[u, v] = Z[perm[u], perm[v]]`` (read the lower triangle: max row,
    min column).

    Parameters
    ----------
    L : (n, n) unit lower triangular, CSC with sorted rows (``Cholesky.ldl``).
    D : (n,) positive.
    perm : (n,) int, A's index u is row and column ``perm[u]`` of the factor.
    needed : (n, n) a pattern (A's indices) whose entries of A^-1 are wanted: added to the
        pattern where L lacks them, and the pattern closed again. scipy's sparse arithmetic
        drops entries that come out exactly zero (a grid world's axis-aligned poses can give
        such), so A's own pattern, and so L's, can lack a pair of poses that see a common landmark.
    closed : L's pattern is closed under elimination already (a supernodal factor's is), so
        that, where it holds every needed pair, it is used as it is.

    Raises
    ------
    PatternError : a pattern the recurrence cannot run on (a column without its diagonal first).
    """
    L = sp.csc_matrix(L)
    perm = np.asarray(perm, dtype=np.int64)
    if needed is not None:
        E = sp.coo_matrix(needed)
        u, v = perm[E.row], perm[E.col]
        rows, cols = np.maximum(u, v), np.minimum(u, v)
        if not _holds(L.indptr.astype(np.int64), L.indices.astype(np.int64), rows, cols):
            L = _with_zeros_at(L, rows, cols)
            closed = False
    indptr, indices, data = L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data
    Z = np.zeros(len(data))
    if closed and _takahashi(indptr, indices, data, D, Z):
        return sp.csc_matrix((Z, indices, indptr), shape=L.shape), perm
    indptr, indices, data = _closed_pattern(indptr, indices, data)  # a pattern said closed that was not, too
    Z = np.zeros(len(data))
    if not _takahashi(indptr, indices, data, D, Z):
        raise PatternError("the factor's pattern is not closed under the recurrence")
    return sp.csc_matrix((Z, indices, indptr), shape=L.shape), perm


def _with_zeros_at(L: sp.csc_matrix, rows: np.ndarray, cols: np.ndarray) -> sp.csc_matrix:
    """L (CSC, sorted rows) with explicit zeros added at (rows, cols) where it has no entry."""
    Lc = L.tocoo()
    L = sp.coo_matrix((np.concatenate([Lc.data, np.zeros(len(rows))]),
                       (np.concatenate([Lc.row, rows]), np.concatenate([Lc.col, cols]))), shape=L.shape).tocsc()
    L.sum_duplicates()  # zeros added to an entry L has leave its value as it is
    L.sort_indices()
    return L


@_jit
def _holds(indptr, indices, rows, cols):  # pragma: no cover - compiled
    """Whether the pattern (CSC, sorted rows) has every entry (rows[k], cols[k]): binary search."""
    for k in range(rows.shape[0]):
        lo, hi = indptr[cols[k]], indptr[cols[k] + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if indices[mid] < rows[k]:
                lo = mid + 1
            else:
                hi = mid
        if lo == indptr[cols[k] + 1] or indices[lo] != rows[k]:
            return False
    return True


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
def _supernode_widths(indptr, indices):  # pragma: no cover - compiled
    """(n,) columns from j to the end of j's supernode: j joins j+1's when its pattern is j then j+1's."""
    n = indptr.shape[0] - 1
    width = np.ones(n, dtype=np.int64)  # columns from j to the end of j's supernode
    for j in range(n - 2, -1, -1):  # j joins j+1's supernode when its pattern is j then j+1's
        size, next_size = indptr[j + 1] - indptr[j], indptr[j + 2] - indptr[j + 1]
        same = size == next_size + 1
        if same:
            for q in range(next_size):
                if indices[indptr[j] + 1 + q] != indices[indptr[j + 1] + q]:
                    same = False
                    break
        if same:
            width[j] = width[j + 1] + 1
    return width


@_jit
def _gather_upper(indptr, indices, Z, width, base, m, Z_RR, position):  # pragma: no cover - compiled
    """The upper triangle of Z_RR (m, m) for the rows R of a supernode
    (``indices[base:base + m]``), a row at a time (contiguous writes), an ancestor supernode K
    at a time; False when a needed entry is off the pattern."""
    a = 0
    while a < m:  # the upper triangle of Z_RR, a row at a time, an ancestor supernode K at a time
        k0 = indices[base + a]
        end = k0 + width[k0]  # K's columns k0..end-1 (k0 may be inside K)
        a1 = a
        while a1 < m and indices[base + a1] < end:
            a1 += 1
        # the rows of R beyond K's columns lie in K's rows below (closed pattern): where, once for K
        below, stop = indptr[k0] + (end - k0), indptr[k0 + 1]
        p = below
        for b in range(a1, m):
            row = indices[base + b]
            while p < stop and indices[p] < row:
                p += 1
            if p == stop or indices[p] != row:
                return False
            position[b] = p - below
        for r in range(a, a1):  # column k of K holds rows k..end-1, then K's rows below
            k = indices[base + r]
            column = indptr[k]
            Z_RR[r, r] = Z[column]
            for b in range(r + 1, a1):
                Z_RR[r, b] = Z[column + (indices[base + b] - k)]
            tail = column + (end - k)
            for b in range(a1, m):
                Z_RR[r, b] = Z[tail + position[b]]
        a = a1
    return True


@_jit
def _takahashi(indptr, indices, L, D, Z):  # pragma: no cover - compiled
    """Fill Z (nnz,) on L's closed pattern, a supernode at a time from the last; False when a
    needed entry is missing from the pattern.

    A supernode is a run of columns c0..c1-1 whose patterns nest (column c's is c and the next
    one's): a dense unit lower triangle L_JJ over rows R_J = c0..c1-1, and a block L_RJ over the
    rows R below, shared. Its part of Takahashi's recurrence in block form (Z = (L D L^T)^-1):

        Z_RJ = -Z_RR L_RJ L_JJ^-1,     Z_JJ = L_JJ^-T (D_J^-1 L_JJ^-1 - L_RJ^T Z_RJ)

    Z_RR is gathered from the columns of R (their entries below, on the pattern) once per
    supernode, into a dense block, so that the products are BLAS's (a column at a time, in
    scalar loops, took 35 s at 20,000 poses; this takes a few).
    """
    n = indptr.shape[0] - 1
    width = _supernode_widths(indptr, indices)
    # walk supernodes from the last: a supernode starts at c0 and spans width[c0] columns when
    # c0 - 1 does not join it
    c1 = n
    ZRR = np.empty(256)
    position = np.empty(n, dtype=np.int64)
    while c1 > 0:
        c0 = c1 - 1
        while c0 > 0 and width[c0 - 1] == width[c0] + 1:
            c0 -= 1
        w = c1 - c0
        base = indptr[c0] + w  # the rows R start here in the first column
        m = indptr[c0 + 1] - base
        if indices[indptr[c0]] != c0:
            return False
        LR = np.empty((m, w))  # L_RJ
        for t in range(w):
            off = indptr[c0 + t] + (w - t)
            for b in range(m):
                LR[b, t] = L[off + b]
        if ZRR.shape[0] < m * m:
            ZRR = np.empty(4 * m * m)
        Z_RR = ZRR[: m * m].reshape((m, m))  # contiguous, for BLAS
        if not _gather_upper(indptr, indices, Z, width, base, m, Z_RR, position):
            return False
        for r in range(m):  # the lower triangle mirrored, for one BLAS product (U + U^T took two)
            for b in range(r + 1, m):
                Z_RR[b, r] = Z_RR[r, b]
        Y = np.dot(Z_RR, LR)
        LinvT = _diagonal_block_inverse(indptr, L, c0, w)  # (L_JJ^-1)^T
        Linv = LinvT.T.copy()
        # Z_RJ = -Y L_JJ^-1, a BLAS product (a triangular solve in scalar loops, strided over the
        # m rows, took a third of the recurrence at 20,000 poses)
        X = -np.dot(Y, Linv)
        # Z_JJ = L_JJ^-T (D^-1 L_JJ^-1 - L_RJ^T Z_RJ), both products BLAS's
        B = -np.dot(LR.T.copy(), X)  # -L_RJ^T Z_RJ
        for s in range(w):
            for t in range(w):
                B[s, t] += Linv[s, t] / D[c0 + s]
        Z_JJ = np.dot(LinvT, B)
        for t in range(w):
            column = indptr[c0 + t]
            for s in range(t, w):  # the lower triangle, (s, t) with s >= t
                Z[column + (s - t)] = Z_JJ[s, t]
        for t in range(w):
            off = indptr[c0 + t] + (w - t)
            for b in range(m):
                Z[off + b] = X[b, t]
        c1 = c0
    return True



@_jit
def _diagonal_block_inverse(indptr, L, c0, w):  # pragma: no cover - compiled
    """``(L_JJ^-1)^T`` (w, w) for the unit lower triangle L_JJ of the supernode at columns
    c0..c0+w-1: row t (column t of L_JJ^-1) by forward substitution, reading L_JJ and the row
    along their rows (contiguous). The same recurrence down L's columns read L a column apart at
    every step: a cache miss each, and a supernode of CHOLMOD's is up to 1,566 columns wide at
    20,000 poses."""
    LJJ = np.zeros((w, w))
    for t in range(w):
        column = indptr[c0 + t]
        for s in range(t + 1, w):
            LJJ[s, t] = L[column + (s - t)]
    LinvT = np.zeros((w, w))
    for t in range(w):
        LinvT[t, t] = 1.0
        for s in range(t + 1, w):
            total = 0.0
            for r in range(t, s):  # L_JJ^-1[s, t] = -sum_r L_JJ[s, r] L_JJ^-1[r, t]
                total += LJJ[s, r] * LinvT[t, r]
            LinvT[t, s] = -total
    return LinvT


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
    """Each block's W_l (rows, width) made dense over the union of its columns' rows, the block
    of A^-1 over those rows looked up once (binary search in Z's columns), then W_l^T A^-1 W_l."""
    n = perm.shape[0]
    slot = np.full(n, -1, dtype=np.int64)  # row -> its place in the current block's row list
    rows = np.empty(n, dtype=np.int64)
    for block in range(out.shape[0]):
        m = 0
        for a in range(width):
            c = block * width + a
            for x in range(Wp[c], Wp[c + 1]):
                if slot[Wi[x]] < 0:
                    slot[Wi[x]] = m
                    rows[m] = Wi[x]
                    m += 1
        Wl = np.zeros((m, width))
        for a in range(width):
            c = block * width + a
            for x in range(Wp[c], Wp[c + 1]):
                Wl[slot[Wi[x]], a] = Wd[x]
        A = np.empty((m, m))
        for i in range(m):
            u = perm[rows[i]]
            for j in range(i, m):
                v = perm[rows[j]]
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
                A[i, j] = Zd[lo]
                A[j, i] = Zd[lo]
        out[block] = np.dot(Wl.T.copy(), np.dot(A, Wl))
        for i in range(m):
            slot[rows[i]] = -1
    return True
