"""Closed-form algebra of one symmetric 3x3 matrix (adjugate and determinant): the pair tests
factor thousands of them a pose, where a LAPACK call each costs more than the arithmetic. The
numpy twin is ``camloc.association.mahalanobis_3x3``."""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import inlined, jit
from camloc.kernels.planar import SE2_DIM


@jit
def mahalanobis(S, y):
    """(y' S^-1 y, ln det S) of a symmetric positive definite S (3, 3) (upper triangle read) and y
    (3,); both inf where rounding left S without a positive determinant: its pair fits nothing."""
    return mahalanobis_components(S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2], y[0], y[1], y[2])


@jit
def mahalanobis_components(a, b, c, d, e, f, y1, y2, y3):
    """``mahalanobis`` of S = [[a, b, c], [b, d, e], [c, e, f]] and y = (y1, y2, y3), given as scalars."""
    quadratic, det = quadratic_and_det(a, b, c, d, e, f, y1, y2, y3)
    if not det > 0.0:
        return np.inf, np.inf
    return quadratic / det, math.log(det)


@jit
def quadratic_and_det(a, b, c, d, e, f, y1, y2, y3):
    """(y' adj(S) y, det S) of S = [[a, b, c], [b, d, e], [c, e, f]]: d^2 = quadratic / det where
    det > 0, for a caller that tests d^2 against a gate before it pays for a logarithm."""
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A11 + b * A12 + c * A13
    quadratic = A11 * y1 * y1 + A22 * y2 * y2 + A33 * y3 * y3 + 2.0 * (A12 * y1 * y2 + A13 * y1 * y3 + A23 * y2 * y3)
    return quadratic, det


@jit
def inverse_components(a, b, c, d, e, f):
    """The upper triangle of S^-1 of a symmetric S = [[a, b, c], [b, d, e], [c, e, f]], given as
    scalars, by the adjugate (scaled by the largest entry first, as ``camloc.sym3.inverse``);
    inf/nan where S is singular."""
    scale = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f))
    if scale == 0.0:
        scale = 1.0
    a, b, c, d, e, f = a / scale, b / scale, c / scale, d / scale, e / scale, f / scale
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = (a * A11 + b * A12 + c * A13) * scale
    return A11 / det, A12 / det, A13 / det, A22 / det, A23 / det, A33 / det


@jit
def log_det(S):
    """ln det S of a symmetric positive definite S (3, 3); inf where the determinant is not positive."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    det = a * (d * f - e * e) + b * (c * e - b * f) + c * (b * e - c * d)
    return math.log(det) if det > 0.0 else np.inf


@inlined
def spread(H, i, P):
    """The upper triangle (a, b, c, d, e, f) of H[i] P H[i]' for H (m, 3, n) and symmetric P (n, n):
    a column of H[i] P at a time, then its products with H[i]'s rows (144 products, not 324 for
    n = 6). It runs for every candidate of every hypothesis: either state's size is passed as a
    constant, whose loops the compiler unrolls. A loop over a size known only when it runs is a
    cycle in the caller's code, across which numba's reference-count pruning gives up: every array
    of the candidate's loop was then counted once more per candidate (``_jit``)."""

    if P.shape[0] == 6:
        return spread_of_size(H, i, P, 6)
    return spread_of_size(H, i, P, SE2_DIM)


@inlined
def spread_of_size(H, i, P, n):
    """``spread`` of a state of n entries."""
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for c in range(n):
        g0 = g1 = g2 = 0.0
        for k in range(n):
            p = P[k, c]
            g0 += H[i, 0, k] * p
            g1 += H[i, 1, k] * p
            g2 += H[i, 2, k] * p
        h0, h1, h2 = H[i, 0, c], H[i, 1, c], H[i, 2, c]
        a00 += g0 * h0
        a01 += g0 * h1
        a02 += g0 * h2
        a11 += g1 * h1
        a12 += g1 * h2
        a22 += g2 * h2
    return a00, a01, a02, a11, a12, a22


@jit
def innovation_mahalanobis(H, i, P, R, o, y1, y2, y3):
    """``mahalanobis`` of a pair's innovation y = (y1, y2, y3) under S = H[i] P H[i]' + R[o]
    (H (m, 3, n), P (n, n), R (K, 3, 3)), without forming S."""
    a, b, c, d, e, f = spread(H, i, P)
    return mahalanobis_components(a + R[o, 0, 0], b + R[o, 0, 1], c + R[o, 0, 2], d + R[o, 1, 1], e + R[o, 1, 2],
                                  f + R[o, 2, 2], y1, y2, y3)
