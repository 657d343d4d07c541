"""The re-check of a pose's accepted pairs: each observation judged by the posterior of the pose's
other pairs (its own left out), and a pair kept only when no single change of the assignment comes
close; and what the chance that a kept pair is clutter adds to the estimate's covariance. The numpy
twins are ``camloc.association.leave_one_out_costs``, ``assignment_margins`` and ``rival_margins``, and
``camloc.ekf.leave_one_out_spread``.

Leaving pair i out of an update linearized at the posterior (the MAP, where the gradient vanishes):

    L_i = information + sum_{j != i} H_j' R_j^-1 H_j,   L_i delta_i = -H_c' R_i^-1 (z_i - z_hat_c)

and every candidate j's prediction moves to ``z_hat_j + H_j delta_i`` with ``S = H_j L_i^-1 H_j' + R_i``.
Information is summed from the prior, never subtracted from the posterior, so L_i stays positive definite.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.constants import NEGLIGIBLE_MARGIN, RESTORE_LIMIT
from camloc.kernels._jit import inlined, jit
from camloc.kernels.camera import observe_pairs
from camloc.kernels.planar import onto_measured_branch, wrapped_residual
from camloc.kernels.small import mm, mtm, mv, solve
from camloc.kernels.sym3 import innovation_mahalanobis, inverse_components, mahalanobis, mahalanobis_components, spread
from camloc.kernels.update import innovation_cost


@inlined
def leave_one_out_costs(z, R, R_inverse, log_det_R, z_hat, H, chosen, information, gate, kind=-1):
    """Costs (n, m) ``d^2 + ln det S - ln det R`` of n observations (z (n, 3), R, R^-1 (n, 3, 3),
    ln det R (n,)) against m candidates (z_hat (m, 3), H (m, 3, n)) at the posterior, each judged
    with its own pair (chosen (n,): candidate column, -1 for none) left out; inf beyond the gate.
    ``information``: the prior's plus that of the update's pairs outside these observations;
    ``kind``: the observations' (a sensor's), whose angle row is wrapped (``wrapped_residual``; -1: none)."""
    n, m = z.shape[0], z_hat.shape[0]
    dim = information.shape[0]              # the state's size: 6 (Euler), 3 (planar)
    pair_information = np.zeros((n, dim, dim))
    total = information.copy()
    for i in range(n):
        if chosen[i] >= 0:
            Hc = H[chosen[i]]
            information_i = mtm(Hc, mm(R_inverse[i], Hc))
            for a in range(dim):
                for b in range(dim):
                    pair_information[i, a, b] = information_i[a, b]
            total += information_i
    cost = np.full((n, m), np.inf)
    # Every L_i >= information, so each S is at most H_j information^-1 H_j' + r_max I (r_max: the
    # largest eigenvalue of any R_i): d^2 under that bound is a lower bound, and the pairs it puts
    # beyond the gate (most of a view's) need no factorization.
    P_bound = solve(information, np.eye(dim))
    r_max = 0.0
    for i in range(n):                      # the trace bounds the largest eigenvalue: a valid, looser screen
        r_max = max(r_max, R[i, 0, 0] + R[i, 1, 1] + R[i, 2, 2])
    bound_inverse = np.empty((m, 6))        # the upper triangle of each bound's inverse
    screened = np.ones(m, np.bool_)
    for j in range(m):
        a, b, c, d, e, f = spread(H, j, P_bound)
        a, d, f = a + r_max, d + r_max, f + r_max
        # rounding can leave the bound indefinite (information 1e12 beside a prior of 1e2): no screen
        screened[j] = np.isfinite(mahalanobis_components(a, b, c, d, e, f, 0.0, 0.0, 0.0)[1]) and a > 0.0 and d > 0.0
        if screened[j]:
            (bound_inverse[j, 0], bound_inverse[j, 1], bound_inverse[j, 2], bound_inverse[j, 3], bound_inverse[j, 4],
             bound_inverse[j, 5]) = inverse_components(a, b, c, d, e, f)
    for i in range(n):
        L = total - pair_information[i]
        P_i = solve(L, np.eye(dim))
        P_i = 0.5 * (P_i + P_i.T)
        delta = np.zeros(dim)
        if chosen[i] >= 0:
            Hc = H[chosen[i]]
            e = z[i] - z_hat[chosen[i]]
            e[2] = wrapped_residual(kind, 2, e[2])
            delta = -mv(P_i, mv(Hc.T.copy(), mv(R_inverse[i], e)))   # copied: mv is compiled for C arrays only
        for j in range(m):
            r0 = z[i, 0] - z_hat[j, 0]
            r1 = z[i, 1] - z_hat[j, 1]
            r2 = wrapped_residual(kind, 2, z[i, 2] - z_hat[j, 2])
            for b in range(6):              # the larger state's count, unrolled; the smaller's columns skipped
                if b < dim:
                    r0 -= H[j, 0, b] * delta[b]
                    r1 -= H[j, 1, b] * delta[b]
                    r2 -= H[j, 2, b] * delta[b]
            if screened[j]:
                w = bound_inverse[j]
                bound = (w[0] * r0 * r0 + w[3] * r1 * r1 + w[5] * r2 * r2
                         + 2.0 * (w[1] * r0 * r1 + w[2] * r0 * r2 + w[4] * r1 * r2))
                if not bound <= gate:
                    continue
            d2, log_det = innovation_mahalanobis(H, j, P_i, R, i, r0, r1, r2)
            if d2 <= gate:
                cost[i, j] = d2 + log_det - log_det_R[i]
    return cost


@inlined
def assignment_margins(cost, null_cost, chosen):
    """(row (n,), steal (n,)): how much costlier the nearest single change that undoes each chosen
    pair is. row: the observation takes another landmark or none; steal: another observation takes
    its landmark (giving up what it holds, or going unassigned) while it takes its next best.
    inf for unassigned observations and where no alternative exists."""
    n, m = cost.shape
    current = null_cost.copy()
    for i in range(n):
        if chosen[i] >= 0:
            current[i] = cost[i, chosen[i]]
    row = np.full(n, np.inf)
    steal = np.full(n, np.inf)
    for i in range(n):
        c = chosen[i]
        if c < 0:
            continue
        other = null_cost[i]
        for j in range(m):
            if j != c and cost[i, j] < other:
                other = cost[i, j]
        row[i] = other - current[i]
        rival = np.inf
        for i2 in range(n):
            if i2 != i:
                taking = cost[i2, c] - min(current[i2], null_cost[i2])
                if taking < rival:
                    rival = taking
        if np.isfinite(rival):
            steal[i] = row[i] + rival
    return row, steal


@inlined
def rival_margins(cost, chosen):
    """(n,): how much costlier each chosen pair's nearest rival landmark is (another candidate of
    its observation, not the null option); inf for unassigned observations and where no other
    landmark gates. The numpy twin is ``camloc.association.rival_margins``."""
    n, m = cost.shape
    margin = np.full(n, np.inf)
    for i in range(n):
        c = chosen[i]
        if c < 0:
            continue
        rival = np.inf
        for j in range(m):
            if j != c and cost[i, j] < rival:
                rival = cost[i, j]
        margin[i] = rival - cost[i, c]
    return margin


@jit
def restored_pairs(residuals, H, P, R, R_inverse, null_cost):
    """Which of the pairs the re-check dropped against leaving them unassigned to take back (d,):
    ``camloc.association.restored_pairs``, the subsets in the same order, each's joint cost the
    stacked ``update.innovation_cost`` as the beam's explanations."""
    d = residuals.shape[0]
    best, best_mask = 0.0, 0
    for i in range(d):
        best += null_cost[i]
    restore = np.zeros(d, np.bool_)
    if d > RESTORE_LIMIT:
        return restore
    chosen = np.empty(d, np.int64)
    for mask in range(1, 1 << d):
        k, rest = 0, 0.0
        for i in range(d):
            if (mask >> i) & 1 == 1:
                chosen[k] = i
                k += 1
            else:
                rest += null_cost[i]
        subset = chosen[:k]
        total = innovation_cost(P, H[subset], R[subset], R_inverse[subset], residuals[subset]) + rest
        if total < best:
            best, best_mask = total, mask
    for i in range(d):
        restore[i] = (best_mask >> i) & 1 == 1
    return restore


@inlined
def predict_pairs(scene, x, obs, landmarks):
    """(z_hat (p, 3), H (p, 3, n)) of the pairs (obs (p,), landmarks (p,)) at x, each angle
    prediction on its observation's branch (``planar.onto_measured_branch``): ``pairs_predicted``
    passed the six arrays of the scene it reads, not the scene (whose 31 arrays a compiled step
    counts a reference to on entry and on return, at every update)."""
    return pairs_predicted(x, obs, landmarks, scene.z, scene.obs_camera, scene.landmark_xyz, scene.camera_R, scene.camera_t,
                           scene.camera_K)


@jit
def pairs_predicted(x, obs, landmarks, z, obs_camera, landmark_xyz, camera_R, camera_t, camera_K):
    """``predict_pairs`` of the scene's arrays it reads. One compiled step for the filter's five
    sites: each site's fancy indexing and calls were compiled again inline."""
    z_hat, H = observe_pairs(x, landmark_xyz[landmarks], obs_camera[obs], camera_R, camera_t, camera_K)
    onto_measured_branch(z, obs_camera, camera_K, obs, z_hat)
    return z_hat, H


@inlined
def positive_definite_3x3(B):
    """Whether the symmetric B (3, 3) is positive definite (its leading minors, Sylvester)."""
    minor2 = B[0, 0] * B[1, 1] - B[0, 1] * B[0, 1]
    det = (B[0, 0] * (B[1, 1] * B[2, 2] - B[1, 2] * B[1, 2]) - B[0, 1] * (B[0, 1] * B[2, 2] - B[1, 2] * B[0, 2])
           + B[0, 2] * (B[0, 1] * B[1, 2] - B[1, 1] * B[0, 2]))
    return B[0, 0] > 0.0 and minor2 > 0.0 and det > 0.0


@jit
def add_leave_one_out_spread(scene, x, P, obs, landmarks, spread, k):
    """spread[k] += ``camloc.ekf.leave_one_out_spread`` of the pairs (obs, landmarks) that updated
    the pose into its posterior (x, P): what the chance that one of them is clutter adds to the
    estimate's covariance (each pair's alternative, the posterior of the others, weighed by its
    cost over leaving the observation unassigned)."""
    z_hat, H = predict_pairs(scene, x, obs, landmarks)
    p = obs.size
    n = x.shape[0]                                 # the state's size: 6 (Euler), 3 (planar)
    margin = np.full(p, np.inf)
    PHt = np.zeros((p, n, 3))
    B_inverse = np.zeros((p, 3, 3))
    B_inverse_r = np.zeros((p, 3))
    for i in range(p):
        o = obs[i]
        for a in range(n):                         # P H'
            for c in range(3):
                total = 0.0
                for b in range(n):
                    total += P[a, b] * H[i, c, b]
                PHt[i, a, c] = total
        A = mm(H[i], PHt[i])                       # H P H'
        B = scene.R_file[o] - A
        if not positive_definite_3x3(B):
            continue                               # rounding: the pair adds nothing
        # entry by entry, not ``B_inverse[i] = ...``: an array assigned to a row links numba's
        # shape-mismatch formatter into the kernel and every caller (``_jit``: ~4 s of a first compile)
        B_inverse_i = solve(B, np.eye(3))
        B_inverse_r_i = mv(B_inverse_i, scene.z[o] - z_hat[i])
        for a in range(3):
            B_inverse_r[i, a] = B_inverse_r_i[a]
            for b in range(3):
                B_inverse[i, a, b] = B_inverse_i[a, b]
        e = mv(scene.R_file[o], B_inverse_r[i])    # the residual at the others' posterior
        S = A + mm(A, mm(B_inverse[i], A)) + scene.R_assoc[o]
        d2, log_det_S = mahalanobis(S, e)
        margin[i] = scene.null_cost[o] - (d2 + log_det_S - scene.log_det_R[o])
    lowest = 0.0                                   # the update itself: cost 0
    for i in range(p):
        lowest = min(lowest, margin[i])
    total = math.exp(lowest / 2.0)                 # the update's own weight, exp(-(0 - lowest) / 2)
    for i in range(p):
        if margin[i] - lowest <= NEGLIGIBLE_MARGIN:
            total += math.exp(-(margin[i] - lowest) / 2.0)
    for i in range(p):
        if not margin[i] - lowest <= NEGLIGIBLE_MARGIN:
            continue
        w = math.exp(-(margin[i] - lowest) / 2.0) / total
        g = mv(PHt[i], B_inverse_r[i])             # x - x_i
        widen = mm(PHt[i], mm(B_inverse[i], PHt[i].T.copy()))   # copied: mm is compiled for C arrays only
        for a in range(n):
            for b in range(n):
                spread[k, a, b] += w * (widen[a, b] + g[a] * g[b])
    for a in range(n):                             # symmetric to rounding, as numpy's symmetrize
        for b in range(a + 1, n):
            mean = 0.5 * (spread[k, a, b] + spread[k, b, a])
            spread[k, a, b] = mean
            spread[k, b, a] = mean
