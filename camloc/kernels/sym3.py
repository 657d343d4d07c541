"""Closed-form algebra of one symmetric 3x3 matrix (adjugate and determinant): the pair tests
factor thousands of them a pose, where a LAPACK call each costs more than the arithmetic. The
numpy twin is ``camloc.association.mahalanobis_3x3``."""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import jit


@jit
def mahalanobis(S, y):
    """(y' S^-1 y, ln det S) of a symmetric positive definite S (3, 3) (upper triangle read) and y
    (3,); both inf where rounding left S without a positive determinant: its pair fits nothing."""
    return mahalanobis_components(S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2], y[0], y[1], y[2])


@jit
def mahalanobis_components(a, b, c, d, e, f, y1, y2, y3):
    """``mahalanobis`` of S = [[a, b, c], [b, d, e], [c, e, f]] and y = (y1, y2, y3), given as scalars."""
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A11 + b * A12 + c * A13
    if not det > 0.0:
        return np.inf, np.inf
    quadratic = A11 * y1 * y1 + A22 * y2 * y2 + A33 * y3 * y3 + 2.0 * (A12 * y1 * y2 + A13 * y1 * y3 + A23 * y2 * y3)
    return quadratic / det, math.log(det)


@jit
def inverse(S):
    """S^-1 (3, 3) of a symmetric S (upper triangle read), exactly symmetric, by the adjugate
    (scaled by the largest entry first, as ``camloc.sym3.inverse``); inf/nan where S is singular."""
    scale = 0.0
    for i in range(3):
        for j in range(i, 3):
            scale = max(scale, abs(S[i, j]))
    if scale == 0.0:
        scale = 1.0
    a, b, c = S[0, 0] / scale, S[0, 1] / scale, S[0, 2] / scale
    d, e, f = S[1, 1] / scale, S[1, 2] / scale, S[2, 2] / scale
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = (a * A11 + b * A12 + c * A13) * scale
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = A11 / det, A12 / det, A13 / det
    out[1, 0], out[1, 1], out[1, 2] = A12 / det, A22 / det, A23 / det
    out[2, 0], out[2, 1], out[2, 2] = A13 / det, A23 / det, A33 / det
    return out


@jit
def log_det(S):
    """ln det S of a symmetric positive definite S (3, 3); inf where the determinant is not positive."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    det = a * (d * f - e * e) + b * (c * e - b * f) + c * (b * e - c * d)
    return math.log(det) if det > 0.0 else np.inf
