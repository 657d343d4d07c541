"""Closed-form algebra of stacks of symmetric 3x3 matrices (adjugate, determinant, inverse): a million
of them cost a few array passes instead of a LAPACK call each. Pure numpy, cheap to import.

A symmetric S = [[a, b, c], [b, d, e], [c, e, f]] is given by its upper triangle a..f, each an
array of any (common, broadcastable) shape. The relative error is about cond(S) x 1e-16, as for a
factorization.
"""

from __future__ import annotations

import numpy as np

UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the components a..f


def adjugate(a, b, c, d, e, f):
    """The upper triangle of adj(S) (A11, A12, A13, A22, A23, A33) and det(S)."""
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    return A11, A12, A13, A22, A23, A33, a * A11 + b * A12 + c * A13


def _scaled_components(S: np.ndarray):
    """The upper triangle a..f of S (..., 3, 3), each matrix divided by its largest entry, and
    that scale (1 for a zero matrix): the determinant is a cube of the entries, which overflows
    from about 1e103 and underflows below 1e-103 where what is asked of it is representable."""
    components = [S[..., i, j] for i, j in UPPER]
    scale = np.max(np.abs(np.stack(components)), axis=0)
    scale = np.where(scale > 0.0, scale, 1.0)
    return [c / scale for c in components], scale


def log_abs_det(S: np.ndarray) -> np.ndarray:
    """ln |det S| (...) of symmetric S (..., 3, 3), as ``np.linalg.slogdet(S)[1]`` (-inf where S
    is singular); reads only the upper triangle."""
    components, scale = _scaled_components(S)
    det = adjugate(*components)[-1]
    with np.errstate(divide="ignore"):
        return np.log(np.abs(det)) + 3.0 * np.log(scale)


def inverse(S: np.ndarray) -> np.ndarray:
    """S^-1 (..., 3, 3) of symmetric S (..., 3, 3), exactly symmetric; reads only the upper triangle
    (each matrix scaled by its largest entry first; a zero matrix stays singular: inf / nan)."""
    components, scale = _scaled_components(S)
    *upper, det = adjugate(*components)
    out = np.empty(S.shape, dtype=np.result_type(S, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        for (i, j), value in zip(UPPER, upper):
            out[..., i, j] = out[..., j, i] = value / det / scale
    return out
