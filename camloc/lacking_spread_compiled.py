"""``lacking_spread.fixed_landmark_spread`` of a pose's pairs with fixed landmarks, compiled (numba),
with their predictions and Jacobians at the posterior: one call a pose from
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
def fixed_spread(R, t, L, P, z, R_z, R_judged, log_det_judged, null_cost, xyz, sensor, cam_R, cam_t, cam_K, cam_third,
                 negligible):
    """The spread (n, n) that the chance of each pair (z (p, 3) of the fixed points xyz (p, 3),
    each with its sensor) being of another landmark adds to the posterior (R, t, L) with covariance
    P: ``lacking_spread.fixed_landmark_spread`` of the pairs' residuals and Jacobians on the pose's
    columns (``slam_compiled.observe_columns``); ``negligible``: ``constants.NEGLIGIBLE_MARGIN``."""
    p, n = z.shape[0], P.shape[0]
    fixed = np.full(p, -1, np.int64)
    z_hat, H = observe_columns(R, t, L, xyz, fixed, fixed, sensor, cam_R, cam_t, cam_K, cam_third, POSE_COLUMNS)
    P_pose = np.ascontiguousarray(P[:POSE_COLUMNS, :POSE_COLUMNS])
    margin = np.full(p, np.inf)
    usable = np.zeros(p, np.bool_)
    inner = np.zeros((p, 3, 3))
    for o in range(p):
        Ho = np.ascontiguousarray(H[3 * o:3 * o + 3])
        A = Ho @ P_pose @ Ho.T                                        # H P H'
        B = R_z[o] - A
        if np.linalg.eigvalsh(0.5 * (B + B.T))[0] <= 0.0:  # not positive definite by rounding: adds nothing
            continue
        usable[o] = True
        B_inverse = np.linalg.inv(B)
        B_inverse_r = B_inverse @ (z[o] - z_hat[o])
        e = R_z[o] @ B_inverse_r                                      # the residual at the others' posterior
        S = A + A @ B_inverse @ A + R_judged[o]                       # H P_i H' + R_judged
        cost = e @ np.linalg.solve(S, e) + math.log(np.linalg.det(S)) - log_det_judged[o]
        margin[o] = null_cost[o] - cost
        inner[o] = B_inverse + np.outer(B_inverse_r, B_inverse_r)
    spread = np.zeros((n, n))
    if not usable.any():
        return spread
    lowest = min(0.0, np.min(margin))
    total = math.exp(lowest / 2.0) if -lowest <= negligible else 0.0  # the update's own weight, 1 before shifting
    w = np.zeros(p)
    for o in range(p):
        if usable[o] and margin[o] - lowest <= negligible:
            w[o] = math.exp(-(margin[o] - lowest) / 2.0)
            total += w[o]
    M = np.zeros((POSE_COLUMNS, POSE_COLUMNS))
    for o in range(p):
        if w[o] > 0.0:
            Ho = np.ascontiguousarray(H[3 * o:3 * o + 3])
            M += (w[o] / total) * (Ho.T @ inner[o] @ Ho)
    C = np.ascontiguousarray(P[:, :POSE_COLUMNS])
    spread = C @ M @ C.T
    return 0.5 * (spread + spread.T)


def compiled_fixed_spread(update, x, P, z, R_z, R_judged, log_det_judged, null_cost, xyz, sensor, negligible: float):
    """``fixed_spread`` from the mapping localizer's arrays and its ``slam_compiled.CompiledUpdate``
    (``update``: the cameras as the compiled steps take them)."""
    c = np.ascontiguousarray
    return fixed_spread(c(x.R, float), c(x.t, float), c(x.L, float), c(P, float), c(z, float), c(R_z, float),
                        c(R_judged, float), c(log_det_judged, float), c(null_cost, float), c(xyz, float),
                        c(sensor, np.int64), update.cam_R, update.cam_t, update.cam_K, update.cam_third, float(negligible))


def cache_is_warm() -> bool:
    """Whether ``fixed_spread`` is in numba's cache (``slam_compiled.cache_is_warm`` asks the same
    of the other mapping kernels); True where that cannot be told."""
    from pathlib import Path

    try:
        return Path(fixed_spread._cache._cache_file._index_path).exists()
    except Exception:
        return True
