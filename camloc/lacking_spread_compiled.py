"""``lacking_spread.fixed_landmark_spread`` of a pose's pairs with fixed landmarks, compiled (numba),
with their predictions and Jacobians at the posterior, added into P in place: one call a pose from
``slam_run.MappingLocalizer._doubt_given`` where the mapping localizer's steps are compiled
(``camloc.slam_compiled``).

Why: in numpy the spread's ~40 small calls cost about 0.3 ms a pose, a third of the compiled
mapping pass's whole time on a 4,000-pose world with a fifth of its map withheld. The numpy
function stays the reference: ``tests/test_lacking_spread.py`` compares the two. A module of its
own (not ``slam_compiled``): its kernels' cache is kept beside their source, and a change here
compiles this kernel only.

Pure: no I/O.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.slam_compiled import _jit, observe_columns

POSE_COLUMNS = 6


@_jit
def _inverse3(A, out):
    """out = A^-1 of a 3x3 A by its adjugate; False where A is not positive definite (leading minors)."""
    m0 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    m1 = A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0]
    m2 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * m0 - A[0, 1] * m1 + A[0, 2] * m2
    if A[0, 0] <= 0.0 or A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0] <= 0.0 or det <= 0.0:
        return False, 0.0
    out[0, 0], out[0, 1], out[0, 2] = m0 / det, -(A[0, 1] * A[2, 2] - A[0, 2] * A[2, 1]) / det, (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) / det
    out[1, 0], out[1, 1], out[1, 2] = -m1 / det, (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) / det, -(A[0, 0] * A[1, 2] - A[0, 2] * A[1, 0]) / det
    out[2, 0], out[2, 1], out[2, 2] = m2 / det, -(A[0, 0] * A[2, 1] - A[0, 1] * A[2, 0]) / det, (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) / det
    return True, det


@_jit
def _product3(A, B, out):
    """out = A B of 3x3s (loops: numba's @ of small matrices allocates and calls BLAS)."""
    for r in range(3):
        for c in range(3):
            out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c]


@_jit
def _alternative(P, H, i, r, R_z, judged, log_det_judged, null, inner):
    """Pair i's alternative (its rows ``H[3 i:3 i + 3]`` (3 p, 6), residual r (3,), noise R_z, the
    noise association judges with, its ln det, the alternative's cost ``null``): its margin over the
    update (inf where B or S is not positive definite), and ``inner`` = ``B^-1 + B^-1 r r' B^-1``."""
    PHt = np.zeros((6, 3))
    A, B, B_inverse = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    S, S_inverse, T = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    for a in range(6):  # P66 H'
        for c in range(3):
            for q in range(6):
                PHt[a, c] += P[a, q] * H[3 * i + c, q]
    for a in range(3):
        for c in range(3):
            A[a, c] = 0.0
            for q in range(6):
                A[a, c] += H[3 * i + a, q] * PHt[q, c]
    for a in range(3):
        for c in range(3):
            B[a, c] = R_z[a, c] - 0.5 * (A[a, c] + A[c, a])
    ok, _ = _inverse3(B, B_inverse)
    if not ok:  # not positive definite by rounding: the pair adds nothing
        return np.inf
    B_inverse_r = B_inverse @ r
    e = R_z @ B_inverse_r                                             # the residual at the others' posterior
    _product3(A, B_inverse, T)
    _product3(T, A, S)
    for a in range(3):
        for c in range(3):
            S[a, c] += A[a, c] + judged[a, c]                         # H P_i H' + R_judged
    ok, det = _inverse3(S, S_inverse)
    if not ok:
        return np.inf
    d2 = e @ (S_inverse @ e)
    for a in range(3):
        for c in range(3):
            inner[a, c] = B_inverse[a, c] + B_inverse_r[a] * B_inverse_r[c]
    return null - (d2 + math.log(det) - log_det_judged)


@_jit
def _add_spread(P, H, w, inner):
    """P += P[:, :6] M P[:6, :], M = sum_i w_i H_i' inner_i H_i (symmetric by construction)."""
    n = P.shape[0]
    M = np.zeros((POSE_COLUMNS, POSE_COLUMNS))
    for i in range(w.size):
        if w[i] > 0.0:
            for a in range(6):
                for c in range(6):
                    acc = 0.0
                    for u in range(3):
                        for v in range(3):
                            acc += H[3 * i + u, a] * inner[i, u, v] * H[3 * i + v, c]
                    M[a, c] += w[i] * acc
    C = P[:, :POSE_COLUMNS].copy()  # read before P's own columns change below
    CM = np.zeros((n, POSE_COLUMNS))
    for a in range(n):
        for c in range(6):
            for q in range(6):
                CM[a, c] += C[a, q] * M[q, c]
    for a in range(n):
        for c in range(a, n):
            v = 0.0
            for q in range(6):
                v += CM[a, q] * C[c, q]
            P[a, c] += v
            if c != a:
                P[c, a] += v


@_jit
def fixed_spread_into(P, R, t, L, obs, xyz, obs_sensor, obs_z, obs_cov, judged_cov, log_det_judged, null_cost, offset,
                      cam_R, cam_t, cam_K, cam_third, negligible):
    """P += the spread that the chance of each pair (observation ``obs[i]`` of the fixed point
    ``xyz[i]``) being of another landmark adds to the posterior (R, t, L) with covariance P:
    ``lacking_spread.fixed_landmark_spread`` of the pairs' residuals and Jacobians on the pose's
    columns (``slam_compiled.observe_columns``), each alternative priced at ``null_cost[o] -
    offset``; ``negligible``: ``constants.NEGLIGIBLE_MARGIN``. The per-observation arrays are the
    run's (K, ...), read at ``obs``."""
    p = obs.size
    fixed = np.full(p, -1, np.int64)
    z_hat, H = observe_columns(R, t, L, xyz, fixed, fixed, obs_sensor[obs], cam_R, cam_t, cam_K, cam_third, POSE_COLUMNS)
    margin = np.full(p, np.inf)
    inner = np.zeros((p, 3, 3))
    for i in range(p):
        o = obs[i]
        margin[i] = _alternative(P, H, i, obs_z[o] - z_hat[i], obs_cov[o], judged_cov[o], log_det_judged[o],
                                 null_cost[o] - offset, inner[i])
    lowest = min(0.0, np.min(margin))
    total = math.exp(lowest / 2.0) if -lowest <= negligible else 0.0  # the update's own weight, 1 before shifting
    w = np.zeros(p)
    for i in range(p):
        if margin[i] - lowest <= negligible:
            w[i] = math.exp(-(margin[i] - lowest) / 2.0)
            total += w[i]
    if total > 0.0 and np.any(w > 0.0):
        _add_spread(P, H, w / total, inner)


def compiled_fixed_spread_into(update, x, P, obs, xyz, obs_sensor, obs_z, obs_cov, judged_cov, log_det_judged, null_cost,
                               offset: float, negligible: float) -> None:
    """``fixed_spread_into`` (P, C-contiguous float64, widened in place) from the mapping
    localizer's arrays and its ``slam_compiled.CompiledUpdate`` (``update``: the cameras as the
    compiled steps take them)."""
    c = np.ascontiguousarray
    fixed_spread_into(P, c(x.R, float), c(x.t, float), c(x.L, float), c(obs, np.int64), c(xyz, float), obs_sensor, obs_z,
                      obs_cov, judged_cov, log_det_judged, null_cost, float(offset), update.cam_R, update.cam_t,
                      update.cam_K, update.cam_third, float(negligible))


def cache_is_warm() -> bool:
    """Whether ``fixed_spread_into`` is in numba's cache (``slam_compiled.cache_is_warm`` asks the same
    of the other mapping kernels); True where that cannot be told."""
    from pathlib import Path

    try:
        return all(Path(kernel._cache._cache_file._index_path).exists() for kernel in (fixed_spread_into, _alternative, _add_spread, _inverse3, _product3))
    except Exception:
        return True
