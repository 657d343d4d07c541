"""The mapping localizer's per-pose arithmetic compiled (numba), each step one call a pose from
``camloc.slam_run``'s Python loop: the prediction (``predicted``: ``slam.predict``), the iterated
update (``iterated_update``: ``ekf.update`` over ``slam.observe_columns``, ``slam.retract`` and
``slam.difference`` with ``ekf.ColumnGain``), the association's candidates and costs
(``candidate_costs``: ``PoseAssociation.landmark_costs``), a new landmark's entry
(``augmented_inverse``: ``slam.inverse_observation`` and ``slam.augmented``), retiring landmarks'
world covariances (``world_covs``), the pose's right covariance (``right_cov``) and the scans of
the added landmarks and of what is surely in view (``live_within``, ``in_sure_view``), and the
doubt in the beam's pairs where the map lacks landmarks (``fixed_spread_into``:
``lacking_spread.fixed_landmark_spread`` added into P in place; in one file with
``observe_columns``, which it calls: numba's cache checks a function against its own file only).

Why: the state is small (the pose and some 10-80 landmarks under an exact map), so the numpy
steps' cost was their ~1,400 numpy calls a pose, not their arithmetic. The numpy steps stay the
reference (``engine="numpy"``, and runs under 300 poses): ``tests/test_slam_compiled.py`` compares
each with its twin on depth, pixel and disparity cameras and whole runs, and the Jacobian with
finite differences. Small products are written as loops: numba's ``@`` of 3x3 matrices and
3-vectors allocates and calls BLAS each time.

Not in ``camloc/kernels``: that folder's sources decide when the localizer's kernels are compiled
again (``kernels.stale_cache``), and these compile only where mapping runs (``cache=True``: once,
beside this file; about 22 s of CPU, ``camloc.warmup.compile_mapping_kernels``). The functions read
nothing but their arguments (no module constant is compiled in): a camera's measurement kind
arrives as its third row's form (``THIRD_*``, set in Python).

Pure: no I/O.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numba
import numpy as np

from camloc import measurement

# The kernels' options (``camloc.kernels._jit``), without their cache checks: these functions
# read nothing but their arguments.
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")

# A camera's third measurement row: none (a pixel's inert row), the depth, or its inverse.
THIRD_NONE, THIRD_DEPTH, THIRD_INVERSE = 0, 1, 2


def cache_folder() -> Optional[Path]:
    """Where numba caches these kernels; None where that cannot be told (numba's cache objects
    are not public API)."""
    try:
        return Path(iterated_update._cache._cache_path)
    except Exception:
        return None


def cache_is_warm() -> bool:
    """Whether these kernels are in numba's cache (a first compile takes ~25 s of CPU, loading
    them under a second); True where that cannot be told."""
    try:
        kernels = (iterated_update, candidate_costs, predicted, right_cov, augmented_inverse, world_covs, live_within,
                   fixed_spread_into)
        return all(Path(kernel._cache._cache_file._index_path).exists() for kernel in kernels)
    except Exception:
        return True


@_jit
def exp_and_left_jacobian(phi, small):
    """``geometry.so3_exp_and_left_jacobian_one``: Exp(phi) and J_l(phi) (3, 3)."""
    x, y, z = phi[0], phi[1], phi[2]
    a2 = x * x + y * y + z * z
    a = math.sqrt(a2)
    if a < small:
        s, c, j = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
    else:
        s, c, j = math.sin(a) / a, (1.0 - math.cos(a)) / a2, (a - math.sin(a)) / (a2 * a)
    xx, yy, zz, xy, xz, yz = x * x - a2, y * y - a2, z * z - a2, x * y, x * z, y * z
    E = np.empty((3, 3))
    J = np.empty((3, 3))
    E[0, 0], E[0, 1], E[0, 2] = 1.0 + c * xx, -s * z + c * xy, s * y + c * xz
    E[1, 0], E[1, 1], E[1, 2] = s * z + c * xy, 1.0 + c * yy, -s * x + c * yz
    E[2, 0], E[2, 1], E[2, 2] = -s * y + c * xz, s * x + c * yz, 1.0 + c * zz
    J[0, 0], J[0, 1], J[0, 2] = 1.0 + j * xx, -c * z + j * xy, c * y + j * xz
    J[1, 0], J[1, 1], J[1, 2] = c * z + j * xy, 1.0 + j * yy, -c * x + j * yz
    J[2, 0], J[2, 1], J[2, 2] = -c * y + j * xz, c * x + j * yz, 1.0 + j * zz
    return E, J


@_jit
def log_and_left_jacobian_inverse(Rm, small):
    """``geometry.so3_log_one`` and ``so3_left_jacobian_inverse_one`` of its result; ok False
    near a half turn (the numpy update, which switches formula there, then takes the pose)."""
    cos_a = min(1.0, max(-1.0, 0.5 * (Rm[0, 0] + Rm[1, 1] + Rm[2, 2] - 1.0)))
    a = math.acos(cos_a)
    phi = np.zeros(3)
    Ji = np.eye(3)
    if a > math.pi - 1e-3:
        return phi, Ji, False
    factor = 0.5 + a * a / 12.0 if a < small else a / (2.0 * math.sin(a))
    x, y, z = factor * (Rm[2, 1] - Rm[1, 2]), factor * (Rm[0, 2] - Rm[2, 0]), factor * (Rm[1, 0] - Rm[0, 1])
    phi[0], phi[1], phi[2] = x, y, z
    a2 = x * x + y * y + z * z
    a = math.sqrt(a2)
    c = 1.0 / 12.0 + a2 / 720.0 if a < small else 1.0 / a2 - (1.0 + math.cos(a)) / (2.0 * a * math.sin(a))
    xx, yy, zz, xy, xz, yz = x * x - a2, y * y - a2, z * z - a2, x * y, x * z, y * z
    Ji[0, 0], Ji[0, 1], Ji[0, 2] = 1.0 + c * xx, 0.5 * z + c * xy, -0.5 * y + c * xz
    Ji[1, 0], Ji[1, 1], Ji[1, 2] = -0.5 * z + c * xy, 1.0 + c * yy, 0.5 * x + c * yz
    Ji[2, 0], Ji[2, 1], Ji[2, 2] = 0.5 * y + c * xz, -0.5 * x + c * yz, 1.0 + c * zz
    return phi, Ji, True


@_jit
def retract(R, t, L, delta, small):
    """``slam.retract``: the estimate (R, t, L) moved by the error delta (6 + 3 m,)."""
    E, J = exp_and_left_jacobian(delta[3:6], small)
    m = L.shape[0]
    L_new = np.empty((m, 3))
    for i in range(m):
        for r in range(3):
            L_new[i, r] = (L[i, 0] * E[r, 0] + L[i, 1] * E[r, 1] + L[i, 2] * E[r, 2]
                           + delta[6 + 3 * i] * J[r, 0] + delta[7 + 3 * i] * J[r, 1] + delta[8 + 3 * i] * J[r, 2])
    R_new, t_new = np.empty((3, 3)), np.empty(3)
    for r in range(3):
        for c in range(3):
            R_new[r, c] = E[r, 0] * R[0, c] + E[r, 1] * R[1, c] + E[r, 2] * R[2, c]
        t_new[r] = (E[r, 0] * t[0] + E[r, 1] * t[1] + E[r, 2] * t[2]) + (J[r, 0] * delta[0] + J[r, 1] * delta[1] + J[r, 2] * delta[2])
    return R_new, t_new, L_new


@_jit
def difference_columns(R_a, t_a, L_a, R_b, t_b, L_b, landmarks, small):
    """``slam.difference(a, b)`` on the pose's columns and those of ``landmarks`` (state rows)
    only; ok False near a half turn."""
    turn = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            turn[r, c] = R_a[r, 0] * R_b[c, 0] + R_a[r, 1] * R_b[c, 1] + R_a[r, 2] * R_b[c, 2]
    phi, Ji, ok = log_and_left_jacobian_inverse(turn, small)
    E, _ = exp_and_left_jacobian(phi, small)
    d = np.empty(6 + 3 * landmarks.size)
    _moved_into(d, 0, Ji, E, t_a, t_b)
    d[3], d[4], d[5] = phi[0], phi[1], phi[2]
    for n in range(landmarks.size):
        _moved_into(d, 6 + 3 * n, Ji, E, L_a[landmarks[n]], L_b[landmarks[n]])
    return d, ok


@_jit
def _moved_into(d, at, Ji, E, a, b):
    """d[at:at + 3] = Ji (a - E b): a point's error in ``slam.difference``."""
    v0 = a[0] - (E[0, 0] * b[0] + E[0, 1] * b[1] + E[0, 2] * b[2])
    v1 = a[1] - (E[1, 0] * b[0] + E[1, 1] * b[1] + E[1, 2] * b[2])
    v2 = a[2] - (E[2, 0] * b[0] + E[2, 1] * b[1] + E[2, 2] * b[2])
    for r in range(3):
        d[at + r] = Ji[r, 0] * v0 + Ji[r, 1] * v1 + Ji[r, 2] * v2


@_jit
def observe_columns(R, t, L, xyz, rows, block, sensor, cam_R, cam_t, cam_K, cam_third, width):
    """``slam.observe_columns`` of every pair at once (each its own sensor): predictions (p, 3)
    and the Jacobian (3 p, width) on the columns of ``block`` (0: the pose's translation, 1: its
    rotation, >= 2: a landmark of the state; -1 a point held fixed)."""
    p = xyz.shape[0]
    z_hat = np.zeros((p, 3))
    H = np.zeros((3 * p, width))
    M = np.empty((3, 3))  # Rc' R': d p_camera / d p_world (loops, not @: numba's @ of 3x3s allocates and calls BLAS)
    pc = np.empty(3)
    for o in range(p):
        s = sensor[o]
        Rc, tc = cam_R[s], cam_t[s]
        point = L[rows[o]] if rows[o] >= 0 else xyz[o]
        v0, v1, v2 = point[0] - t[0], point[1] - t[1], point[2] - t[2]
        r0 = R[0, 0] * v0 + R[1, 0] * v1 + R[2, 0] * v2 - tc[0]
        r1 = R[0, 1] * v0 + R[1, 1] * v1 + R[2, 1] * v2 - tc[1]
        r2 = R[0, 2] * v0 + R[1, 2] * v1 + R[2, 2] * v2 - tc[2]
        for r in range(3):
            pc[r] = Rc[0, r] * r0 + Rc[1, r] * r1 + Rc[2, r] * r2
            for c in range(3):
                M[r, c] = Rc[0, r] * R[c, 0] + Rc[1, r] * R[c, 1] + Rc[2, r] * R[c, 2]
        fx, fy, cx, cy = cam_K[s, 0], cam_K[s, 1], cam_K[s, 2], cam_K[s, 3]
        zc = pc[2]
        z_hat[o, 0] = fx * pc[0] / zc + cx
        z_hat[o, 1] = fy * pc[1] / zc + cy
        # d z / d p_camera (Jh): its rows 0, 1 and the third by the camera's kind
        j00, j02, j11, j12, j22 = fx / zc, -fx * pc[0] / zc**2, fy / zc, -fy * pc[1] / zc**2, 0.0
        if cam_third[s] == 1:  # THIRD_DEPTH
            z_hat[o, 2], j22 = zc, 1.0
        elif cam_third[s] == 2:  # THIRD_INVERSE
            z_hat[o, 2], j22 = 1.0 / zc, -1.0 / zc**2
        row = 3 * o
        col = 3 * block[o]
        for c in range(3):
            a0 = j00 * M[0, c] + j02 * M[2, c]
            a1 = j11 * M[1, c] + j12 * M[2, c]
            a2 = j22 * M[2, c]
            H[row, c], H[row + 1, c], H[row + 2, c] = -a0, -a1, -a2
            if block[o] >= 0:
                H[row, col + c], H[row + 1, col + c], H[row + 2, col + c] = a0, a1, a2
        if block[o] < 0:  # held fixed: the heading's lever arm, A [xyz]x
            x0, x1, x2 = point[0], point[1], point[2]
            for r in range(3):
                A0, A1, A2 = -H[row + r, 0], -H[row + r, 1], -H[row + r, 2]
                H[row + r, 3] = A1 * x2 - A2 * x1
                H[row + r, 4] = -A0 * x2 + A2 * x0
                H[row + r, 5] = A0 * x1 - A1 * x0
    return z_hat, H


@_jit
def state_columns(rows):
    """``slam.state_columns``: the error's columns the pairs touch and each pair's block."""
    in_state = np.unique(rows[rows >= 0])
    columns = np.empty(6 + 3 * in_state.size, np.int64)
    columns[0:6] = np.arange(6)
    for n in range(in_state.size):
        columns[6 + 3 * n:9 + 3 * n] = 6 + 3 * in_state[n] + np.arange(3)
    block = np.full(rows.size, -1, np.int64)
    for o in range(rows.size):
        if rows[o] >= 0:
            block[o] = 2 + np.searchsorted(in_state, rows[o])
    return in_state, columns, block


@_jit
def column_gain(P_columns, columns, H, R_full):
    """``ekf.ColumnGain``: U = P H' (n, m) and S = H P H' + R (m, m), exactly symmetric;
    raises numpy's LinAlgError where S is not positive definite (its Cholesky check)."""
    U = P_columns @ H.T
    HU = H @ U[columns]
    S = 0.5 * ((HU + R_full) + (HU + R_full).T)
    np.linalg.cholesky(S)
    return U, S


@_jit
def iterated_update(R, t, L, P, z, R_z, R_inverse, xyz, rows, sensor, cam_R, cam_t, cam_K, cam_third,
                    iterations, converged, small, monotone):
    """``ekf.update(..., map_cost=True, columns=...)`` of p pairs (z (p, 3), their noise R_z and
    its inverse (p, 3, 3), the fixed points xyz (p, 3) or state rows ``rows`` (p,), each pair's
    sensor) on the estimate (R, t, L) with covariance P: (ok, R, t, L, P, the innovation at the
    prior (3 p,), S's diagonal blocks (p, 3, 3), NIS, MAP cost, each pair's squared Mahalanobis
    distance (p,) in its block). ok False: a step near a half
    turn, which the numpy update takes instead (its logarithm switches formula there).
    ``monotone``: the update is the iterate of least MAP cost, not the last one (``ekf.update``'s
    ``monotone``)."""
    p = z.shape[0]
    in_state, columns, block = state_columns(rows)
    width = columns.size
    R_full = np.zeros((3 * p, 3 * p))
    for o in range(p):
        R_full[3 * o:3 * o + 3, 3 * o:3 * o + 3] = R_z[o]
    P_columns = np.ascontiguousarray(P[:, columns])
    z_flat = z.ravel()
    z_hat, H = observe_columns(R, t, L, xyz, rows, block, sensor, cam_R, cam_t, cam_K, cam_third, width)
    y_prior = z_flat - z_hat.ravel()
    U, S = column_gain(P_columns, columns, H, R_full)
    w = np.linalg.solve(S, y_prior)
    nis = y_prior @ w
    S_prior = S
    delta = U @ w
    R_i, t_i, L_i = retract(R, t, L, delta, small)
    last = y_prior
    # the cheapest iterate yet, its gain and its MAP cost once known (``monotone``)
    kept_R, kept_t, kept_L, kept_U, kept_S, kept_w, kept_cost = R_i, t_i, L_i, U, S, w, np.inf
    for _ in range(iterations - 1):
        z_hat_i, H_i = observe_columns(R_i, t_i, L_i, xyz, rows, block, sensor, cam_R, cam_t, cam_K, cam_third, width)
        if monotone:
            cost_i = w @ ((S - R_full) @ w) + _residual_cost(z, z_hat_i, R_inverse)
            if cost_i < kept_cost:
                kept_R, kept_t, kept_L, kept_U, kept_S, kept_w, kept_cost = R_i, t_i, L_i, U, S, w, cost_i
        U, S = column_gain(P_columns, columns, H_i, R_full)
        moved, ok = difference_columns(R_i, t_i, L_i, R, t, L, in_state, small)
        if not ok:
            return False, R, t, L, P, y_prior, np.zeros((p, 3, 3)), 0.0, 0.0, np.zeros(p)
        last = z_flat - z_hat_i.ravel() + H_i @ moved
        w = np.linalg.solve(S, last)
        step = U @ w
        R_i, t_i, L_i = retract(R, t, L, step, small)
        if np.max(np.abs(step - delta)) < converged:
            break  # the linearization no longer moves (``ekf.update``)
        delta = step
    # the MAP cost: d' P^-1 d = w' (S - R) w of the last gain, and the posterior's residual
    z_post, _ = observe_columns(R_i, t_i, L_i, xyz, rows, block, sensor, cam_R, cam_t, cam_K, cam_third, width)
    cost = w @ ((S - R_full) @ w) + _residual_cost(z, z_post, R_inverse)
    if monotone and cost > kept_cost:  # Gauss-Newton overshot: the cheapest iterate, with its gain
        R_i, t_i, L_i, U, S, w, cost = kept_R, kept_t, kept_L, kept_U, kept_S, kept_w, kept_cost
    K = np.linalg.solve(S, U.T).T
    KM = K @ (0.5 * (K @ S) - U).T
    S_blocks = np.empty((p, 3, 3))
    d2 = np.empty(p)
    for o in range(p):
        S_blocks[o] = S_prior[3 * o:3 * o + 3, 3 * o:3 * o + 3]
        d2[o] = block_distance(S_blocks[o], y_prior[3 * o:3 * o + 3])
    return True, R_i, t_i, L_i, P + (KM + KM.T), y_prior, S_blocks, nis, cost, d2


@_jit
def _residual_cost(z, z_hat, R_inverse):
    """``r' R^-1 r`` of the residuals r = z - z_hat (p, 3) of p pairs, each with its own block."""
    cost = 0.0
    for o in range(z.shape[0]):
        r = z[o] - z_hat[o]
        cost += r @ (R_inverse[o] @ r)
    return cost


@_jit
def block_distance(S, y):
    """``y' S^-1 y`` of a symmetric 3x3 S from its upper triangle in closed form, inf where S has
    no positive determinant (``association.mahalanobis_3x3``'s formula)."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A11 + b * A12 + c * A13
    if not det > 0.0:
        return np.inf
    y1, y2, y3 = y[0], y[1], y[2]
    return (A11 * y1 * y1 + A22 * y2 * y2 + A33 * y3 * y3 + 2.0 * (A12 * y1 * y2 + A13 * y1 * y3 + A23 * y2 * y3)) / det



@_jit
def candidate_costs(R, t, L, P, xyz, rows, cov, sensor, cam_R, cam_t, cam_K, cam_third, near, far, cos_angle,
                    z, R_z, log_det_R, gate, unpaired):
    """``PoseAssociation.landmark_costs`` after its search by place: of the points xyz (C, 3)
    (rows (C,): the state's landmark, -1 outside it with world covariance ``cov`` (C, 3, 3)),
    those in camera ``sensor``'s view (``seen`` (C,)), their predictions (c, 3), Jacobians
    (c, 3, n), extra covariance (c, 3, 3) and the costs (O, c) of observations z (O, 3) of noise
    R_z with ``ln det`` log_det_R and gates ``gate`` (O,): ``unpaired`` outside the gate. S's
    ``H P H'`` from each point's own columns (the pose's, its landmark's), the Mahalanobis
    distance and ln det S in closed form (``association.mahalanobis_3x3``)."""
    Rc, tc = cam_R[sensor], cam_t[sensor]
    C = xyz.shape[0]
    seen = np.zeros(C, np.bool_)
    pc = np.empty(3)
    for c in range(C):  # in loops: numba's @ of 3-vectors allocates and calls BLAS, per point
        v0, v1, v2 = xyz[c, 0] - t[0], xyz[c, 1] - t[1], xyz[c, 2] - t[2]
        r0 = R[0, 0] * v0 + R[1, 0] * v1 + R[2, 0] * v2 - tc[0]
        r1 = R[0, 1] * v0 + R[1, 1] * v1 + R[2, 1] * v2 - tc[1]
        r2 = R[0, 2] * v0 + R[1, 2] * v1 + R[2, 2] * v2 - tc[2]
        for r in range(3):
            pc[r] = Rc[0, r] * r0 + Rc[1, r] * r1 + Rc[2, r] * r2
        norm = math.sqrt(pc[0] * pc[0] + pc[1] * pc[1] + pc[2] * pc[2])
        seen[c] = pc[2] > near and pc[2] <= far and pc[2] >= cos_angle * norm
    index = np.flatnonzero(seen)
    m = index.size
    n = P.shape[0]
    points, own = xyz[index], rows[index]
    z_hat, H_flat = observe_columns(R, t, L, points, own, np.where(own >= 0, 2 + own, -1),
                                    np.full(m, sensor, np.int64), cam_R, cam_t, cam_K, cam_third, n)
    H = H_flat.reshape(m, 3, n)
    extra = np.zeros((m, 3, 3))
    cost = np.full((z.shape[0], m), unpaired)
    columns = np.empty(9, np.int64)
    for c in range(m):
        k = 6
        columns[0:6] = np.arange(6)
        if own[c] >= 0:
            columns[6:9] = 6 + 3 * own[c] + np.arange(3)
            k = 9
        S = np.zeros((3, 3))
        for i in range(3):
            for j in range(i, 3):
                total = 0.0
                for a in range(k):
                    inner = 0.0
                    for b in range(k):
                        inner += P[columns[a], columns[b]] * H[c, j, columns[b]]
                    total += H[c, i, columns[a]] * inner
                S[i, j] = total
        if own[c] < 0:  # outside the state: its own covariance through the translation's block, A cov A' (A = -H_t)
            W = cov[index[c]]
            for i in range(3):
                AW = np.zeros(3)
                for b in range(3):
                    AW[b] = -H[c, i, 0] * W[0, b] - H[c, i, 1] * W[1, b] - H[c, i, 2] * W[2, b]
                for j in range(3):
                    extra[c, i, j] = -(AW[0] * H[c, j, 0] + AW[1] * H[c, j, 1] + AW[2] * H[c, j, 2])
        for o in range(z.shape[0]):
            cost[o, c] = pair_cost(S, extra[c], R_z[o], z[o] - z_hat[c], log_det_R[o], gate[o], unpaired)
    return seen, z_hat, H, extra, cost


@_jit
def pair_cost(S, extra, R_z, y, log_det_R, gate, unpaired):
    """One pair's cost ``d2 + ln det S - ln det R`` from S's upper triangle (``H P H'``, then the
    landmark's extra and the observation's noise added), ``unpaired`` outside the gate or where S
    has no positive determinant (``association._mahalanobis_sym3``'s formula)."""
    a = (S[0, 0] + extra[0, 0]) + R_z[0, 0]
    b = (S[0, 1] + extra[0, 1]) + R_z[0, 1]
    c = (S[0, 2] + extra[0, 2]) + R_z[0, 2]
    d = (S[1, 1] + extra[1, 1]) + R_z[1, 1]
    e = (S[1, 2] + extra[1, 2]) + R_z[1, 2]
    f = (S[2, 2] + extra[2, 2]) + R_z[2, 2]
    A11, A12, A13 = d * f - e * e, c * e - b * f, b * e - c * d
    A22, A23, A33 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A11 + b * A12 + c * A13
    if not det > 0.0:
        return unpaired
    y1, y2, y3 = y[0], y[1], y[2]
    quadratic = A11 * y1 * y1 + A22 * y2 * y2 + A33 * y3 * y3 + 2.0 * (A12 * y1 * y2 + A13 * y1 * y3 + A23 * y2 * y3)
    d2 = quadratic / det
    cost = d2 + math.log(det) - log_det_R
    if not (math.isfinite(cost) and d2 <= gate):
        return unpaired
    return cost


@_jit
def predicted(R, t, L, T_increment, Q):
    """``slam.predict``'s estimate (R, t) after the odometry increment and W = G chol(Q) (n, 6),
    G its noise coefficients (``slam.noise_coefficients``); raises numpy's LinAlgError where Q
    has no Cholesky factor. ``P + W W'`` is numpy's (``CompiledUpdate.predict``): its symmetric
    product beat numba's here from n ~ 300 on (a prior's state)."""
    C = np.linalg.cholesky(Q)
    R_next = R @ np.ascontiguousarray(T_increment[:3, :3])
    t_next = t + R @ np.ascontiguousarray(T_increment[:3, 3])
    n = 6 + 3 * L.shape[0]
    G = np.zeros((n, 6))
    for r in range(3):
        for c in range(3):
            G[r, c] = R_next[r, c]
            G[3 + r, 3 + c] = R_next[r, c]
    _lever_into(G, 0, t_next, R_next)
    for i in range(L.shape[0]):
        _lever_into(G, 6 + 3 * i, L[i], R_next)
    return R_next, t_next, G @ C


@_jit
def right_cov(R, t, P):
    """``slam.pose_right_cov``: the pose block as the SE(3) filter's right perturbation's
    covariance, J P J' symmetrized (J = [[R', -R' [t]x], [0, R']])."""
    J = np.zeros((6, 6))
    Rt = np.ascontiguousarray(R.T)
    lever = np.zeros((3, 3))
    lever[0, 1], lever[0, 2], lever[1, 0], lever[1, 2], lever[2, 0], lever[2, 1] = -t[2], t[1], t[2], -t[0], -t[1], t[0]
    J[0:3, 0:3] = Rt
    J[0:3, 3:6] = -(Rt @ lever)
    J[3:6, 3:6] = Rt
    C = J @ np.ascontiguousarray(P[:6, :6]) @ J.T
    return 0.5 * (C + C.T)


@_jit
def _lever_into(G, at, v, R):
    """G[at:at + 3, 3:6] = [v]x R: a point's error under the robot's turn (``noise_coefficients``)."""
    for c in range(3):
        G[at, 3 + c] = -v[2] * R[1, c] + v[1] * R[2, c]
        G[at + 1, 3 + c] = v[2] * R[0, c] - v[0] * R[2, c]
        G[at + 2, 3 + c] = -v[1] * R[0, c] + v[0] * R[1, c]


@_jit
def live_within(xyz, live, centre, radius):
    """The entries of ``live`` (indices into xyz (N, 3)) whose points are within ``radius`` of
    ``centre``, in order (``LandmarkTable.in_range``'s scan of the added landmarks)."""
    out = np.empty(live.size, np.int64)
    count = 0
    r2 = radius * radius
    for n in range(live.size):
        i = live[n]
        d0, d1, d2 = xyz[i, 0] - centre[0], xyz[i, 1] - centre[1], xyz[i, 2] - centre[2]
        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
            out[count] = i
            count += 1
    return out[:count]


@_jit
def augmented_inverse(P, R, t, Rc, tc, K, inverse, z, R_z):
    """``slam.inverse_observation`` of one measurement z (3,) with range (the depth, or its
    inverse where ``inverse``) and noise R_z, then ``slam.augmented``: the new landmark's position
    (3,) and the covariance with it (n + 3, n + 3). Its error is the robot's translation error
    plus the measurement's (B = [I, 0]): its rows are P's first three, exactly."""
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    x_over_z, y_over_z = (z[0] - cx) / fx, (z[1] - cy) / fy
    if inverse:
        depth = 1.0 / z[2] if z[2] > 0.0 else -1.0
        d_depth = -depth * depth
    else:
        depth, d_depth = z[2], 1.0
    p_camera = np.array([x_over_z * depth, y_over_z * depth, depth])
    G = np.zeros((3, 3))
    G[0, 0], G[0, 2] = depth / fx, x_over_z * d_depth
    G[1, 1], G[1, 2] = depth / fy, y_over_z * d_depth
    G[2, 2] = d_depth
    xyz = t + R @ (tc + Rc @ p_camera)
    W = R @ Rc @ G
    N = W @ R_z @ W.T
    n = P.shape[0]
    P_new = np.empty((n + 3, n + 3))
    P_new[:n, :n] = P
    P_new[n:, :n] = P[0:3, :]
    P_new[:n, n:] = P[0:3, :].T
    for i in range(3):
        for j in range(3):
            # symmetrize(P_tt + symmetrize(N)), as slam.augmented_many
            a = P[i, j] + 0.5 * (N[i, j] + N[j, i])
            b = P[j, i] + 0.5 * (N[j, i] + N[i, j])
            P_new[n + i, n + j] = 0.5 * (a + b)
    return xyz, P_new


@_jit
def world_covs(L, P, rows):
    """``slam.landmark_world_cov`` of the state's landmarks ``rows`` (q,): (q, 3, 3), each
    ``A P_rows A'`` with A = [-[l]x, I] on the heading's and the landmark's rows."""
    out = np.empty((rows.size, 3, 3))
    A = np.zeros((3, 6))
    index = np.empty(6, np.int64)
    for n in range(rows.size):
        i = rows[n]
        l0, l1, l2 = L[i, 0], L[i, 1], L[i, 2]
        A[0, 0], A[0, 1], A[0, 2] = 0.0, l2, -l1
        A[1, 0], A[1, 1], A[1, 2] = -l2, 0.0, l0
        A[2, 0], A[2, 1], A[2, 2] = l1, -l0, 0.0
        A[0, 3], A[1, 4], A[2, 5] = 1.0, 1.0, 1.0
        index[0], index[1], index[2] = 3, 4, 5
        index[3], index[4], index[5] = 6 + 3 * i, 7 + 3 * i, 8 + 3 * i
        block = np.empty((6, 6))
        for a in range(6):
            for b in range(6):
                block[a, b] = P[index[a], index[b]]
        C = A @ block @ A.T
        out[n] = 0.5 * (C + C.T)
    return out


@_jit
def in_sure_view(R, t, xyz, cam_R, cam_t, near, far, cos_angle):
    """``slam_landmarks.surely_in_view``: which points xyz (M, 3) some camera sees from (R, t)
    within distances [near, far] and the angle whose cosine is ``cos_angle``."""
    out = np.zeros(xyz.shape[0], np.bool_)
    for c in range(xyz.shape[0]):
        v0, v1, v2 = xyz[c, 0] - t[0], xyz[c, 1] - t[1], xyz[c, 2] - t[2]
        r0 = R[0, 0] * v0 + R[1, 0] * v1 + R[2, 0] * v2
        r1 = R[0, 1] * v0 + R[1, 1] * v1 + R[2, 1] * v2
        r2 = R[0, 2] * v0 + R[1, 2] * v1 + R[2, 2] * v2
        for s in range(cam_R.shape[0]):
            Rc, tc = cam_R[s], cam_t[s]
            q0, q1, q2 = r0 - tc[0], r1 - tc[1], r2 - tc[2]
            p0 = Rc[0, 0] * q0 + Rc[1, 0] * q1 + Rc[2, 0] * q2
            p1 = Rc[0, 1] * q0 + Rc[1, 1] * q1 + Rc[2, 1] * q2
            p2 = Rc[0, 2] * q0 + Rc[1, 2] * q1 + Rc[2, 2] * q2
            distance = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
            if distance >= near and distance <= far and p2 >= cos_angle * distance:
                out[c] = True
                break
    return out

# -- the doubt in the beam's pairs (``camloc.lacking_spread``) ------------------------------------

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
    M = np.zeros((6, 6))
    for i in range(w.size):
        if w[i] > 0.0:
            for a in range(6):
                for c in range(6):
                    acc = 0.0
                    for u in range(3):
                        for v in range(3):
                            acc += H[3 * i + u, a] * inner[i, u, v] * H[3 * i + v, c]
                    M[a, c] += w[i] * acc
    C = P[:, :6].copy()  # read before P's own columns change below
    CM = np.zeros((n, 6))
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
    z_hat, H = observe_columns(R, t, L, xyz, fixed, fixed, obs_sensor[obs], cam_R, cam_t, cam_K, cam_third, 6)
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


class CompiledUpdate:
    """The cameras of a run as the compiled update takes them (arrays indexed by sensor id), and
    the call of ``iterated_update`` from the mapping localizer's arrays; ``usable`` False where a
    sensor is not a camera of depth, pixels or disparity (the numpy update then runs)."""

    def __init__(self, sensors: dict, small_angle: float, converged: float):
        thirds = {measurement.DEPTH: THIRD_DEPTH, measurement.PIXEL: THIRD_NONE, measurement.DISPARITY: THIRD_INVERSE}
        count = max(sensors) + 1 if sensors else 0
        self.cam_R, self.cam_t = np.zeros((count, 3, 3)), np.zeros((count, 3))
        self.cam_K, self.cam_third = np.zeros((count, 4)), np.zeros(count, np.int64)
        self.usable = bool(sensors)
        for s, sensor in sensors.items():
            self.usable &= sensor.kind in thirds and sensor.camera_id >= 0
            self.cam_R[s], self.cam_t[s] = sensor.T_robot_camera[:3, :3], sensor.T_robot_camera[:3, 3]
            self.cam_K[s], self.cam_third[s] = np.asarray(sensor.intrinsics, float), thirds.get(sensor.kind, THIRD_NONE)
        self.small_angle, self.converged = small_angle, converged

    def __call__(self, R, t, L, P, z, R_z, R_inverse, xyz, rows, sensor, iterations: int, monotone: bool = False):
        c = np.ascontiguousarray
        return iterated_update(c(R, float), c(t, float), c(L, float), c(P, float), c(z, float), c(R_z, float),
                               c(R_inverse, float), c(xyz, float), c(rows, np.int64), c(sensor, np.int64),
                               self.cam_R, self.cam_t, self.cam_K, self.cam_third, int(iterations),
                               float(self.converged), float(self.small_angle), bool(monotone))

    def costs(self, x, P, xyz, rows, cov, sensor: int, near: float, far: float, cos_angle: float, z, R_z, log_det_R, gate,
              unpaired: float):
        """``candidate_costs`` of camera ``sensor`` from the mapping localizer's arrays."""
        c = np.ascontiguousarray
        return candidate_costs(c(x.R, float), c(x.t, float), c(x.L, float), c(P, float), c(xyz, float), c(rows, np.int64),
                               c(cov, float), int(sensor), self.cam_R, self.cam_t, self.cam_K, self.cam_third, float(near),
                               float(far), float(cos_angle), c(z, float), c(R_z, float), c(log_det_R, float), c(gate, float),
                               float(unpaired))

    def predict(self, x, P, T_increment, Q):
        """``slam.predict`` with its estimate and noise coefficients compiled (``predicted``) and
        ``P + W W'`` numpy's symmetric product, as there; None where Q has no Cholesky factor
        (``slam.predict`` then takes the pose, as it does)."""
        c = np.ascontiguousarray
        try:
            R, t, W = predicted(c(x.R, float), c(x.t, float), c(x.L, float), c(T_increment, float), c(Q, float))
        except np.linalg.LinAlgError:
            return None
        return R, t, P + W @ W.T

    def augmented(self, x, P, sensor, z, R_z):
        """``augmented_inverse`` of camera model ``sensor`` (its kind: depth or disparity)."""
        c = np.ascontiguousarray
        T = sensor.T_robot_camera
        return augmented_inverse(c(P, float), c(x.R, float), c(x.t, float), c(T[:3, :3], float), c(T[:3, 3], float),
                                 np.asarray(sensor.intrinsics, float), sensor.kind == measurement.DISPARITY, c(z, float),
                                 c(R_z, float))

    def world_covs(self, x, P, rows):
        """``world_covs`` of the state's landmarks ``rows``."""
        return world_covs(np.ascontiguousarray(x.L, float), np.ascontiguousarray(P, float), np.asarray(rows, np.int64))

    @staticmethod
    def live_within(xyz, live, centre, radius: float):
        return live_within(xyz, live, np.ascontiguousarray(centre, float), float(radius))

    def pose_right_cov(self, x, P):
        """``right_cov``: ``slam.pose_right_cov`` compiled."""
        return right_cov(np.ascontiguousarray(x.R, float), np.ascontiguousarray(x.t, float), P)

    def surely_in_view(self, x, xyz, view):
        """``in_sure_view`` of every camera (``view``: ``slam_landmarks.sure_view``'s)."""
        near, far, angle = view
        return in_sure_view(np.ascontiguousarray(x.R, float), np.ascontiguousarray(x.t, float), np.ascontiguousarray(xyz, float),
                            self.cam_R, self.cam_t, float(near), float(far), float(np.cos(angle)))

    def spread_into(self, x, P, obs, xyz, obs_sensor, obs_z, obs_cov, judged_cov, log_det_judged, null_cost,
                    offset: float, negligible: float) -> None:
        """``fixed_spread_into`` (P, C-contiguous float64, widened in place) from the mapping
        localizer's arrays (``lacking_spread.GivenPairsDoubt``)."""
        c = np.ascontiguousarray
        fixed_spread_into(P, c(x.R, float), c(x.t, float), c(x.L, float), c(obs, np.int64), c(xyz, float), obs_sensor,
                          obs_z, obs_cov, judged_cov, log_det_judged, null_cost, float(offset), self.cam_R, self.cam_t,
                          self.cam_K, self.cam_third, float(negligible))
