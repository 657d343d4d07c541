"""Products of small matrices as plain loops: ``@`` on 3x3 and 6x6 operands goes through BLAS,
whose call costs more than the arithmetic (the twins are numpy's own products)."""

from __future__ import annotations

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
def mtv(A, v):
    """A' @ v."""
    out = np.zeros(A.shape[1])
    for q in range(A.shape[0]):
        a = v[q]
        for i in range(A.shape[1]):
            out[i] += A[q, i] * a
    return out


@jit
def sandwich(H, P):
    """H P H' of H (r, n) and symmetric P (n, n)."""
    HP = mm(H, P)
    r = H.shape[0]
    out = np.empty((r, r))
    for i in range(r):
        for j in range(i, r):
            s = 0.0
            for q in range(H.shape[1]):
                s += HP[i, q] * H[j, q]
            out[i, j] = s
            out[j, i] = s
    return out
