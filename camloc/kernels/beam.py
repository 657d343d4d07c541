"""The beam over association hypotheses, compiled: the hypotheses of a pose are arrays, and a
pose's work is one call. The reasoning (why a beam, the costs, the seeds of a slip, why two
explanations per seed) is in ``docs/beam.md``; the numpy reference it was checked against is
``camloc.beam`` (``BeamSearch``).

A generation of hypotheses is a tuple of arrays (``new_generation``): states X (n, d), covariances
P (n, d, d) (d the state's size: 6 for the Euler state, 3 for the planar one), costs (n,) (twice the negative log-likelihood of all they explain), the index of the
hypothesis each grew from at the previous pose, observations left unassigned at this pose, whether
it was explained from a slip's widened prior, and its pairs at this pose (n, cap, 2) of
(observation, landmark) with their count.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import FALSE, FIRST, ONE, called, entry, inlined, jit
from camloc.constants import (
    MISS_COST, RAY_STEP_SIGMA, SEEDED_MIN_UNASSIGNED, SEEDED_UNUSUAL_PROBABILITY, SLIP_MIN_OBSERVATIONS, UNEXPLAINED_RATE_CAP, UNEXPLAINED_WINDOW,
)
from camloc.kernels.beam_chain import checked_at, wide_for_rays
from camloc.kernels.camera import camera_pose, camera_position_jacobian, cameras_of, in_front_of, predict_candidates, robot_frame
from camloc.kernels.planar import SE2_DIM
from camloc.kernels.motion import predict
from camloc.kernels.rotation import wrap_angle
from camloc.kernels.state import difference
from camloc.kernels.sym3 import quadratic_and_det, spread
from camloc.kernels.update import innovation_cost, pair_model, updated_at
from camloc.kernels.view import sensor_candidates
from camloc.measurement import DEPTH, MARKER, PIXEL
from camloc.miss_term import miss_charge
from camloc.sparse_poses import carried, copy_sigma, pose_beam

AMBIGUOUS, UNASSIGNED = -2, -1
DONE, SLIP, GROW = 0, 1, 2

# the miss term's charge (plain numpy, shared with the numpy beam), compiled for a scalar
compiled_miss_charge = inlined(miss_charge)
compiled_pose_beam = inlined(pose_beam)
compiled_carried = inlined(carried)
compiled_copy_sigma = inlined(copy_sigma)


@entry
def new_generation(n, cap, dim):
    """n hypotheses of states of size dim (6: Euler, 3: planar), room for cap pairs each. (No
    default size: a call without one compiled a second signature, ``omitted(default=6)``.)"""
    return (np.empty((n, dim)), np.empty((n, dim, dim)), np.empty(n), np.full(n, -1, np.int64), np.zeros(n, np.int64),
            np.zeros(n, np.bool_), np.zeros(n, np.int64), np.empty((n, max(cap, 1), 2), np.int64))


@inlined
def put_state(gen, j, x, P):
    """Hypothesis j's state x (n,) and covariance P (n, n), entry by entry (as every copy into a
    slice: see ``_jit``); the state's size as a constant, its loops unrolled (every child of
    every hypothesis is a copy; ``sym3.spread``)."""
    if x.shape[0] == 6:
        put_state_of_size(gen, j, x, P, 6)
    else:
        put_state_of_size(gen, j, x, P, SE2_DIM)


@inlined
def put_state_of_size(gen, j, x, P, n):
    """``put_state`` of a state of n entries."""
    for a in range(n):
        gen[0][j, a] = x[a]
        for b in range(n):
            gen[1][j, a, b] = P[a, b]


@entry
def copy_hypothesis(src, i, dst, j):
    """dst[j] = src[i], every field."""
    put_state(dst, j, src[0][i], src[1][i])
    dst[2][j], dst[3][j], dst[4][j], dst[5][j], dst[6][j] = src[2][i], src[3][i], src[4][i], src[5][i], src[6][i]
    for q in range(src[6][i]):
        dst[7][j, q, 0], dst[7][j, q, 1] = src[7][i, q, 0], src[7][i, q, 1]


@entry
def carry(gen, indices):
    """The hypotheses at indices as the next pose's beam: states, covariances and costs (their
    pairs are in the history)."""
    out = new_generation(indices.size, ONE, gen[0].shape[1])
    for j in range(indices.size):
        put_state(out, j, gen[0][indices[j]], gen[1][indices[j]])
        out[2][j] = gen[2][indices[j]]
    return out


@entry
def gather(gen, indices, cap):
    out = new_generation(indices.size, cap, gen[0].shape[1])
    for j in range(indices.size):
        copy_hypothesis(gen, indices[j], out, j)
    return out


# ---------------------------------------------------------------------------------------------
# A pair's cost, in the coordinates where its linearization explains it best

@jit
def spread_row(spreads, q):
    return spreads[q, 0], spreads[q, 1], spreads[q, 2], spreads[q, 3], spreads[q, 4], spreads[q, 5]


@jit
def as_point(z_hat, q, K):
    """The camera-frame point prediction q (z_hat[q] of u, v, depth) back-projects to through
    intrinsics K, and the nonzero entries (j00, j02, j11, j12) of its Jacobian by (u, v, depth),
    J = [[j00, 0, j02], [0, j11, j12], [0, 0, 1]]: (p0, p1, p2, j00, j02, j11, j12). A sensor
    whose pairs are not judged as points (``measurement.judged_as_point``: not depth) gives
    zeros, a point of no spread, which fits nothing."""
    if K[4] != DEPTH:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    x_over_z, y_over_z, depth = (z_hat[q, 0] - K[2]) / K[0], (z_hat[q, 1] - K[3]) / K[1], z_hat[q, 2]
    return x_over_z * depth, y_over_z * depth, depth, depth / K[0], x_over_z, depth / K[1], y_over_z


@jit
def point_spread(spread_q, j00, j02, j11, j12):
    """The upper triangle of J (H P H') J' (``as_point``'s J) from that of H P H' (``spread_q``)."""
    a00, a01, a02, a11, a12, a22 = spread_q
    b00 = j00 * j00 * a00 + 2.0 * j00 * j02 * a02 + j02 * j02 * a22
    b01 = j00 * j11 * a01 + j00 * j12 * a02 + j02 * j11 * a12 + j02 * j12 * a22
    b02 = j00 * a02 + j02 * a22
    b11 = j11 * j11 * a11 + 2.0 * j11 * j12 * a12 + j12 * j12 * a22
    b12 = j11 * a12 + j12 * a22
    return b00, b01, b02, b11, b12, a22


@inlined
def pair_in_best_coordinates(scene, o, z_hat, H, q, spread_q, y, Hc, n, gate):
    """(d^2, cost ``d^2 + ln det S - ln det R``, judged as a point) of observation o against
    prediction q (z_hat[q] (3,), H[q] (3, d), ``spread_q`` the upper triangle of H[q] P H[q]'
    (``sym3.spread``): one per prediction, whatever the observation) under P, in the measured
    (u, v, depth) or in the camera-frame point they back-project to, whichever is likelier (a
    point is linear in the robot's position; pixels can fit better where the spread is
    rotation); writes the innovation y[n] (3,) and its Jacobian Hc[n] (3, d) in the chosen
    coordinates. (inf, inf, False), nothing written, where d^2 exceeds ``gate`` in both: most
    pairs a screen lets through, whose logarithms need not be paid for."""
    K = scene.camera_K[scene.obs_camera[o]]
    p0, p1, p2, j00, j02, j11, j12 = as_point(z_hat, q, K)
    a00, a01, a02, a11, a12, a22 = spread_q                                # H P H'
    R, C = scene.R_assoc, scene.point_cov
    r2 = scene.z[o, 2] - z_hat[q, 2]
    if K[4] == MARKER:                                                     # a marker's psi wrapped (``planar.wrapped_residual``)
        r2 = wrap_angle(r2)
    quadratic_pixels, det_pixels = quadratic_and_det(
        a00 + R[o, 0, 0], a01 + R[o, 0, 1], a02 + R[o, 0, 2], a11 + R[o, 1, 1], a12 + R[o, 1, 2], a22 + R[o, 2, 2],
        scene.z[o, 0] - z_hat[q, 0], scene.z[o, 1] - z_hat[q, 1], r2)
    b00, b01, b02, b11, b12, b22 = point_spread(spread_q, j00, j02, j11, j12)
    p0, p1, p2 = scene.point[o, 0] - p0, scene.point[o, 1] - p1, scene.point[o, 2] - p2
    quadratic_point, det_point = quadratic_and_det(
        b00 + C[o, 0, 0], b01 + C[o, 0, 1], b02 + C[o, 0, 2], b11 + C[o, 1, 1], b12 + C[o, 1, 2], b22 + C[o, 2, 2], p0, p1, p2)
    # as sym3.mahalanobis_components: a spread rounding left without a positive determinant fits nothing
    d2_pixels = quadratic_pixels / det_pixels if det_pixels > 0.0 else np.inf
    d2_point = quadratic_point / det_point if det_point > 0.0 else np.inf
    if not (d2_pixels <= gate or d2_point <= gate):
        return np.inf, np.inf, False
    cost_pixels = d2_pixels + math.log(det_pixels) - scene.log_det_R[o] if det_pixels > 0.0 else np.inf
    cost_point = d2_point + math.log(det_point) - scene.log_det_point_cov[o] if det_point > 0.0 else np.inf
    # loops of the larger state's count, the smaller's columns skipped: a loop over a count known
    # only when it runs would be a cycle across which the scene's references are not pruned (``sym3.spread``)
    dim = H.shape[2]
    if cost_point < cost_pixels:
        y[n, 0], y[n, 1], y[n, 2] = p0, p1, p2
        for i in range(6):
            if i < dim:
                Hc[n, 0, i] = j00 * H[q, 0, i] + j02 * H[q, 2, i]
                Hc[n, 1, i] = j11 * H[q, 1, i] + j12 * H[q, 2, i]
                Hc[n, 2, i] = H[q, 2, i]
        return d2_point, cost_point, True
    y[n, 0], y[n, 1], y[n, 2] = scene.z[o, 0] - z_hat[q, 0], scene.z[o, 1] - z_hat[q, 1], r2
    for a in range(3):
        for i in range(6):
            if i < dim:
                Hc[n, a, i] = H[q, a, i]
    return d2_pixels, cost_pixels, False


@entry
def options_for(scene, settings, x, P, obs, margin, max_angle):
    """What each observation (obs (m,)) may be under (x, P): its pool of landmarks within
    ``pool_gate_factor`` gates, with their costs (inf outside the gate), predictions, innovations
    and Jacobians in their best coordinates. CSR over the observations: (start (m + 1,), landmark,
    cost, z_hat (g, 3), H (g, 3, d), y (g, 3), Hc (g, 3, d), in_point, pool_cost: the cost inside
    the gate or not, for the miss term, ``expected_landmarks``). Among the landmarks in the
    view of half-angle ``max_angle``, and ``margin`` metres around it (``view.widened_view``);
    those x puts behind a pixel or disparity camera at inf (``pair_options.PairGating.in_front``)."""
    m = obs.size
    dim = x.shape[0]                            # the state's size: 6 (Euler), 3 (planar)
    cameras = cameras_of(scene.obs_camera, obs, scene.camera_R.shape[0])
    # every camera's candidates, their predictions and spreads, concatenated
    found, total = [], 0
    for c in cameras:
        found.append(sensor_candidates(scene, x, c, max_angle, margin))
        total += found[-1].size
    cand, cand_camera = np.empty(total, np.int64), np.empty(total, np.int64)
    z_hat, H = np.empty((total, 3)), np.empty((total, 3, dim))
    p_hat, diagonal_pixels, diagonal_point = np.empty((total, 3)), np.empty((total, 3)), np.empty((total, 3))
    spreads, front = np.empty((total, 6)), np.empty(total, np.bool_)  # the upper triangles of each H P H' (3, 3)
    R, E, t = robot_frame(x)
    d_position = np.empty((3, 3))
    at = FIRST    # a counter passed to kernels: int64 from the start (see FIRST)
    for g in range(cameras.size):
        c, f = cameras[g], found[g]
        R_rc, t_rc, K = scene.camera_R[c], scene.camera_t[c], scene.camera_K[c]
        camera_position_jacobian(R, R_rc, d_position)
        predict_candidates(R, E, t, R_rc, t_rc, K, scene.landmark_xyz, f, z_hat, H, at, d_position)
        for q in range(f.size):
            cand[at], cand_camera[at] = f[q], c
            front[at] = K[4] == DEPTH or in_front_of(R, t, R_rc, t_rc, K[4], scene.landmark_xyz, f[q])
            p_hat[at, 0], p_hat[at, 1], p_hat[at, 2], j00, j02, j11, j12 = as_point(z_hat, at, K)
            spread_q = spread(H, at, P)
            spreads[at, 0], spreads[at, 1], spreads[at, 2], spreads[at, 3], spreads[at, 4], spreads[at, 5] = spread_q
            # the screen's bound on every pair with this prediction: the diagonals of its spreads
            b00, _, _, b11, _, b22 = point_spread(spread_q, j00, j02, j11, j12)
            diagonal_pixels[at, 0], diagonal_pixels[at, 1], diagonal_pixels[at, 2] = spread_q[0], spread_q[3], spread_q[5]
            diagonal_point[at, 0], diagonal_point[at, 1], diagonal_point[at, 2] = b00, b11, b22
            at += 1
    cap = max(m * total, 1)
    start = np.zeros(m + 1, np.int64)
    lm, cost, in_point = np.empty(cap, np.int64), np.empty(cap), np.empty(cap, np.bool_)
    pool_cost = np.empty(cap)
    zh, Hs, ys, Hcs = np.empty((cap, 3)), np.empty((cap, 3, dim)), np.empty((cap, 3)), np.empty((cap, 3, dim))
    n = FIRST    # a counter passed to kernels: int64 from the start (see FIRST)
    for r in range(m):
        o = obs[r]
        c = scene.obs_camera[o]
        gate = scene.obs_gate[o]
        pool_gate = settings.pool_gate_factor * gate
        as_points = scene.camera_K[c, 4] == DEPTH
        marker = scene.camera_K[c, 4] == MARKER
        for q in range(total):
            if cand_camera[q] != c:
                continue
            # y' S^-1 y >= y_a^2 / S_aa on every axis a: most of a dense view's pairs are surely
            # beyond the pool on one axis in both coordinates (depth, often); a sensor without
            # points is judged in its own coordinates alone
            beyond_pixels, beyond_point = False, not as_points
            for a in range(3):
                e = scene.z[o, a] - z_hat[q, a]
                if marker and a == 2:           # a marker's psi wrapped (``planar.wrapped_residual``)
                    e = wrap_angle(e)
                beyond_pixels |= e * e > pool_gate * (diagonal_pixels[q, a] + scene.R_assoc[o, a, a])
                e = scene.point[o, a] - p_hat[q, a]
                beyond_point |= e * e > pool_gate * (diagonal_point[q, a] + scene.point_cov[o, a, a])
            if beyond_pixels and beyond_point:
                continue
            d2, pair_cost, point = pair_in_best_coordinates(scene, o, z_hat, H, q, spread_row(spreads, q), ys, Hcs, n, pool_gate)
            if not d2 <= pool_gate:
                continue
            lm[n], cost[n], in_point[n], pool_cost[n] = cand[q], pair_cost if d2 <= gate and front[q] else np.inf, point, pair_cost if front[q] else np.inf
            for a in range(3):
                zh[n, a] = z_hat[q, a]
                for b in range(6):              # unrolled, the smaller state's columns skipped (``same_state``)
                    if b < dim:
                        Hs[n, a, b] = H[q, a, b]
            n += 1
        start[r + 1] = n
    return start, lm[:n], cost[:n], zh[:n], Hs[:n], ys[:n], Hcs[:n], in_point[:n], pool_cost[:n]


@jit
def taken_by(pairs, count, h):
    """The landmarks hypothesis h of a generation has taken: pass its pairs and their count
    (``gen[7]``, ``gen[6]``), not the generation: a call counts a reference to every array it is
    passed, and this runs for every partial explanation branched."""
    return pairs[h, :count[h], 1]


@jit
def is_taken(landmark, taken):
    for t in taken:
        if t == landmark:
            return True
    return False


@jit
def condition_into(scene, settings, x, P, o, pool, taken, cost, z_hat, H, ys, Hcs, in_point, at):
    """The options of observation o over its pool (g,) under a hypothesis (x, P) conditioned on
    some of the pose's pairs, less the landmarks it has taken, written into rows at..at + g - 1 of
    cost, z_hat, H, ys, Hcs and in_point. The pool is kept; its predictions are made again (moving
    the old ones to first order is not enough: a pair's correction moves a landmark a metre away
    by pixels more than that). ``scene``: what the pairs' costs read of it (``update.pair_model``)."""
    c = scene.obs_camera[o]
    R_rc, t_rc, K = scene.camera_R[c], scene.camera_t[c], scene.camera_K[c]
    R, E, t = robot_frame(x)
    d_position = np.empty((3, 3))
    camera_position_jacobian(R, R_rc, d_position)
    predict_candidates(R, E, t, R_rc, t_rc, K, scene.landmark_xyz, pool, z_hat, H, at, d_position)
    for q in range(pool.size):
        r = at + q
        d2, pair_cost, point = pair_in_best_coordinates(scene, o, z_hat, H, r, spread(H, r, P), ys, Hcs, r, scene.obs_gate[o])
        front = K[4] == DEPTH or in_front_of(R, t, R_rc, t_rc, K[4], scene.landmark_xyz, pool[q])
        cost[r] = pair_cost if d2 <= scene.obs_gate[o] and front and not is_taken(pool[q], taken) else np.inf
        in_point[r] = point


@inlined
def condition(scene, settings, x, P, o, pool, taken):
    """``condition_into`` with fresh arrays: (cost, z_hat, H, y, Hc, in_point) of the pool's g landmarks."""
    g = pool.size
    cost, in_point = np.empty(g), np.empty(g, np.bool_)
    dim = x.shape[0]
    z_hat, H, ys, Hcs = np.empty((g, 3)), np.empty((g, 3, dim)), np.empty((g, 3)), np.empty((g, 3, dim))
    condition_into(scene, settings, x, P, o, pool, taken, cost, z_hat, H, ys, Hcs, in_point, FIRST)
    return cost, z_hat, H, ys, Hcs, in_point


@jit
def least_cost(costs, null_cost):
    best = null_cost
    for c in costs:
        if c < best:
            best = c
    return best


@jit
def clear_choices(settings, null_cost, start, lm, cost, positions):
    """Per position (an observation of the pose): the option index of its only viable landmark,
    UNASSIGNED when leaving it so is its only viable option, AMBIGUOUS when several options lie
    within ``branch_delta`` of its best or its one landmark is viable for another observation."""
    n = positions.size
    choice = np.full(n, AMBIGUOUS, np.int64)
    viable_landmarks = np.empty(lm.size, np.int64)
    viable = 0
    for k in range(n):
        i = positions[k]
        null_before = null_cost[k] + settings.null_offset   # viability at the null cost before its offset
        limit = least_cost(cost[start[i]:start[i + 1]], null_before) + settings.branch_delta
        count, last = 0, -1
        for j in range(start[i], start[i + 1]):
            if cost[j] <= limit:
                count += 1
                last = j
                viable_landmarks[viable] = lm[j]
                viable += 1
        null = null_before <= limit
        if count + int(null) == 1:
            choice[k] = UNASSIGNED if null else last
    for k in range(n):
        if choice[k] >= 0:
            claims = 0
            for v in viable_landmarks[:viable]:
                if v == lm[choice[k]]:
                    claims += 1
            if claims > 1:
                choice[k] = AMBIGUOUS
    return choice


@inlined
def after_clear(scene, settings, gen, h, obs, child, model, root_x, root_P, root_count):
    """Hypothesis h of gen after its stacked updates with the pose's clear observations, written
    into row h of ``child``: the clear ones are taken in one stacked update; conditioned on them
    the others are gated again, and those that became clear are taken in the next, until none does
    (an observation is often ambiguous only until a neighbour's pair pins the pose). Returns (its
    options, the ambiguous rest in the order to branch on them: fewest gated options first, and
    the least each can cost, whether the root's prior (root_x, root_P, with root_count pairs) is
    wide for the rays: its chains are then checked, ``beam_chain``)."""
    opt = options_for(scene, settings, gen[0][h], gen[1][h], obs, 0.0, scene.view_limits[2])
    start, lm, cost, zh, Hs, ys, Hcs, in_point, _ = opt
    taken = taken_by(gen[7], gen[6], h)          # a seeded explanation's seed pair: its landmark is not free
    for j in range(lm.size):
        if is_taken(lm[j], taken):
            cost[j] = np.inf
    wide = wide_for_rays(model, root_P, obs, start, cost, Hs)
    copy_hypothesis(gen, h, child, h)
    x, P = gen[0][h], gen[1][h]                  # read, never written: each update returns new arrays
    pending = np.arange(obs.size)                # positions still ambiguous: the first n_pending
    n_pending = obs.size
    while n_pending:
        positions = pending[:n_pending]
        null_cost = np.empty(n_pending)
        for k in range(n_pending):
            null_cost[k] = scene.null_cost[obs[positions[k]]]
        choice = clear_choices(settings, null_cost, start, lm, cost, positions)
        n_taken, n_clear = 0, 0
        for k in range(n_pending):
            n_taken += choice[k] >= 0
            n_clear += choice[k] != AMBIGUOUS
        if n_clear == 0:
            break
        # the clear ones leave: unassigned, or taken in one stacked update; the others stay, in order
        options, o = np.empty(n_taken, np.int64), np.empty(n_taken, np.int64)
        t = rest = 0
        for k in range(n_pending):
            if choice[k] == UNASSIGNED:
                child[2][h] += null_cost[k]
                child[4][h] += 1
            elif choice[k] >= 0:
                options[t], o[t] = choice[k], obs[positions[k]]
                t += 1
            else:
                pending[rest] = positions[k]     # rest <= k: positions[k] is read before its slot is reused
                rest += 1
        n_pending = rest
        if n_taken:
            before = child[6][h]
            x, P = take_clear_pairs(scene, settings, child, h, x, P, o, options, opt, model)
            if wide and before > root_count:     # a chain: pairs since the root before this round
                x, P = checked_at(model, settings.iterations, x, P, root_x, root_P, child[7][h], root_count, child[6][h])
        for k in range(n_pending):
            i = pending[k]
            if start[i + 1] > start[i]:
                claimed = taken_by(child[7], child[6], h)
                condition_into(model, settings, x, P, obs[i], lm[start[i]:start[i + 1]], claimed, cost, zh, Hs, ys, Hcs, in_point,
                               start[i])
    put_state(child, h, x, P)
    order, least = branch_order(scene, obs, pending[:n_pending], start, cost)
    return opt, order, least, wide


@inlined
def take_clear_pairs(scene, settings, child, h, x, P, o, options, opt, model):
    """(x, P) updated with the clear pairs of observations o (their chosen options of ``opt``), in
    one stacked update; their joint cost, each pair in the coordinates its option chose, and the
    pairs themselves are added to hypothesis h of ``child``. ``model``: ``update.pair_model``."""
    start, lm, cost, zh, Hs, ys, Hcs, in_point, _ = opt
    n_taken = o.size
    no_start = x[:0]                             # ``updated``'s start: none (a view, not an array allocated)
    landmarks = np.empty(n_taken, np.int64)
    dim = x.shape[0]
    z_hat, H, y, Hc = np.empty((n_taken, 3)), np.empty((n_taken, 3, dim)), np.empty((n_taken, 3)), np.empty((n_taken, 3, dim))
    R, R_inverse = np.empty((n_taken, 3, 3)), np.empty((n_taken, 3, 3))
    for t in range(n_taken):
        j = options[t]
        landmarks[t] = lm[j]
        point = in_point[j]
        for a in range(3):
            z_hat[t, a], y[t, a] = zh[j, a], ys[j, a]
            for b in range(6):                  # unrolled, the smaller state's columns skipped (``same_state``)
                if b < dim:
                    H[t, a, b], Hc[t, a, b] = Hs[j, a, b], Hcs[j, a, b]
            for b in range(3):
                R[t, a, b] = scene.point_cov[o[t], a, b] if point else scene.R_assoc[o[t], a, b]
                R_inverse[t, a, b] = scene.point_cov_inverse[o[t], a, b] if point else scene.R_assoc_inverse[o[t], a, b]
    x_new, P_new = updated_at(model, settings.iterations, x, P, o, landmarks, z_hat, H, scene.R_assoc, scene.R_assoc_inverse,
                           no_start, FALSE, 0.0)[:2]
    # the joint cost of the pairs, each in the coordinates its option chose, at the prior
    child[2][h] += innovation_cost(P, Hc, R, R_inverse, y)
    for t in range(n_taken):
        child[7][h, child[6][h], 0], child[7][h, child[6][h], 1] = o[t], landmarks[t]
        child[6][h] += 1
    return x_new, P_new


# numba's merge sort (``np.argsort(kind="mergesort")``) sorts this many or fewer by insertion
# (numba.misc.mergesort.SMALL_MERGESORT)
SMALL_MERGESORT = 20


@jit
def sort_by(keys, items):
    """``items`` put in place in the order ``items[np.argsort(keys[items], kind="mergesort")]``, by the
    same comparisons: up to ``SMALL_MERGESORT`` items numba's merge sort is an insertion sort, done
    here on the items themselves, without the keys' copy, the index array, the merge's workspace and
    the gather it allocates (four arrays a sort; the beam sorts each root's partial explanations
    every step). Past it, that merge sort, copied back."""
    n = items.size
    if n > SMALL_MERGESORT:
        order = items[np.argsort(keys[items], kind="mergesort")]
        for k in range(n):
            items[k] = order[k]
        return
    for i in range(1, n):
        item = items[i]
        j = i
        while j > 0 and keys[item] < keys[items[j - 1]]:
            items[j] = items[j - 1]
            j -= 1
        items[j] = item


@inlined
def branch_order(scene, obs, pending, start, cost):
    """The ambiguous observations (positions ``pending``, sorted in place) in the order to branch on
    them, fewest gated options first, and the least each can cost (obs.size,)."""
    counts = np.empty(obs.size)                 # by position; float: the merge sort the other kernels compile
    for k in range(pending.size):
        i = pending[k]
        counts[i] = 0.0
        for j in range(start[i], start[i + 1]):
            counts[i] += np.isfinite(cost[j])
    sort_by(counts, pending)
    order = pending
    least = np.zeros(obs.size)
    for i in order:
        least[i] = least_cost(cost[start[i]:start[i + 1]], scene.null_cost[obs[i]])
    return order, least


@inlined
def same_state(X, P, a, b, merge_sigma):
    """Whether hypotheses a and b differ by less than merge_sigma standard deviations of b on
    every axis (the cheaper is kept). Its loop counts to the larger state's size, the smaller's
    entries skipped: a loop to a size read when it runs is a cycle, across which numba does not
    prune the references counted to the arrays an inlined step is passed (``sym3.spread``), and
    this runs for every pair of partial explanations compared. (X, P: a generation's states and
    covariances.)"""
    d = difference(X[a], X[b])
    n = d.size
    for i in range(6):
        if i < n and d[i] * d[i] > merge_sigma * merge_sigma * P[b][i, i]:
            return False
    return True


@inlined
def settle(settings, X, P, c, parent_X, parent_P, pending, model, chain):
    """Compute the state of child c (X[c], P[c]), whose pair (observation, landmark, prediction
    z_hat and H at its parent) was added to parent ``pending[0][c]`` (of states ``parent_X``,
    ``parent_P``) when it was branched: at an ambiguous pose many children are pruned on their cost
    alone and never need their update. ``model``: what the update reads of the scene
    (``update.pair_model``), its noise too. Passed the arrays it reads, not the generations nor the
    scene: an inlined step counts a reference to each array of every tuple it binds, and the beam
    settles about 35 children a pose. ``chain``: (the children's pairs, their counts, their roots,
    the roots' states, covariances, pair counts and whether each is wide for the rays), against
    which a chain of two pairs or more is checked (``beam_chain``)."""
    source, obs, landmark, z_hat, H, waiting = pending
    if not waiting[c]:
        return
    p = source[c]
    # a ray's iterations also stop once a step is negligible against the prior's sigma (``RAY_STEP_SIGMA``)
    step_sigma = RAY_STEP_SIGMA if model.camera_K[model.obs_camera[obs[c]], 4] == PIXEL else 0.0
    x, P_new = updated_at(model, settings.iterations, parent_X[p], parent_P[p], obs[c:c + 1], landmark[c:c + 1],
                       z_hat[c:c + 1], H[c:c + 1], model.R_assoc, model.R_assoc_inverse, parent_X[p][:0], FALSE, step_sigma)[:2]
    r = chain[2][c]                              # the tuple read entry by entry: bound whole, its 7 arrays counted
    if chain[6][r] and chain[1][c] - chain[5][r] >= 2:
        x, P_new = checked_at(model, settings.iterations, x, P_new, chain[3][r], chain[4][r], chain[0][c], chain[5][r], chain[1][c])
    put_state((X, P), c, x, P_new)
    waiting[c] = False


@inlined
def nothing_pending(settings, X, P, c, parent_X, parent_P, pending, model, chain):
    """``settle`` where every state is settled (``prune``'s generation): its pruning compiled
    without the update that settling calls (its ``model``: None)."""
    return


@inlined
def prune_indices_into(settings, width, delta, X, P, costs, candidates, parent_X, parent_P, pending, settle_one, model, chain, kept,
                       at):
    """The cheapest of ``candidates`` (of a generation's states X, covariances P and costs; sorted
    in place by cost) within ``delta`` of the best, at most ``width`` (the pose's: ``pose_beam``),
    none within merge_sigma standard deviations of a cheaper one kept (beyond the run's width and
    delta, ``settings``', within ``copy_sigma``), whose states are settled by ``settle_one``
    (``settle``, or ``nothing_pending``) as a comparison first needs them, passed ``model`` and
    ``chain``: written into ``kept`` from index ``at``; returns the index after the last (no array
    of their own: this runs for each root every step)."""
    sort_by(costs, candidates)
    if candidates.size == 0:
        return at
    best = costs[candidates[0]]
    limit = best + delta
    n = 0
    for c in candidates:
        if costs[c] > limit or n >= width:
            break
        # the run's width and delta are settings'; beyond them only a distinct hypothesis is kept
        sigma = compiled_copy_sigma(costs[c], best, n, settings.beam_width, settings.beam_delta, settings.merge_sigma)
        merged = False
        for q in range(at, at + n):
            # the two compared, c first; settle inlined at one site (each site is compiled again)
            for h in (c, kept[q]):
                if pending[5][h]:
                    settle_one(settings, X, P, h, parent_X, parent_P, pending, model, chain)
            if same_state(X, P, c, kept[q], sigma):
                merged = True
                break
        if not merged:
            kept[at + n] = c
            n += 1
    return at + n


@inlined
def settled(n, dim):
    """The pending-state record of n settled hypotheses (of states of size dim)."""
    return (np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3, dim)),
            np.zeros(n, np.bool_))


@entry
def prune(scene, settings, gen, n, width, delta):
    """``prune_indices_into`` over the first n hypotheses of a settled generation, to the pose's width
    and delta (``pose_beam``)."""
    kept = np.empty(min(n, width), np.int64)
    count = prune_indices_into(settings, width, delta, gen[0], gen[1], gen[2], np.arange(n), gen[0], gen[1],
                               settled(n, gen[0].shape[1]), nothing_pending, None, None, kept, FIRST)
    return kept[:count]


@inlined
def prune_partials(settings, gen, root, rest, parents, pending, model, chain):
    """Each root's partial explanations pruned as ``prune`` does (they have explained the same
    observations, so their costs compare); past ``partial_budget`` in all, the best of each root
    and the rest of the budget by cost plus ``rest``, the least what they still have to explain
    can cost. Roots are taken in the order they first appear."""
    n = root.size
    seen = np.zeros(root.max() + 1 if n else 1, np.bool_)
    X, P, costs, parent_X, parent_P = gen[0], gen[1], gen[2], parents[0], parents[1]
    # each root's children and those kept, in two arrays a step, not three or four arrays a root
    # (``root == r``, its nonzero entries, a concatenation)
    members, kept = np.empty(n, np.int64), np.empty(n, np.int64)
    n_kept = 0
    for c in range(n):
        r = root[c]
        if seen[r]:
            continue
        seen[r] = True
        g = 0
        for q in range(c, n):                   # the root first appears at c
            if root[q] == r:
                members[g] = q
                g += 1
        n_kept = prune_indices_into(settings, settings.beam_width, settings.beam_delta, X, P, costs, members[:g], parent_X, parent_P,
                                    pending, settle, model, chain, kept, n_kept)
    kept = kept[:n_kept]
    if kept.size > settings.partial_budget:
        ranked = kept[np.argsort(costs[kept] + rest[kept], kind="mergesort")]
        first = np.zeros(ranked.size, np.bool_)
        seen[:] = False
        for q in range(ranked.size):
            if not seen[root[ranked[q]]]:
                seen[root[ranked[q]]] = True
                first[q] = True
        others = ranked[~first][:max(0, settings.partial_budget - first.sum())]
        kept = np.concatenate((ranked[first], others))
    for c in kept:
        if pending[5][c]:
            settle(settings, X, P, c, parent_X, parent_P, pending, model, chain)
    return kept


def explain_all(scene, settings, parents, n_parents, obs):
    """Children of the first n_parents hypotheses of ``parents`` that explain all of obs (m,);
    each step's partial explanations pruned to the run's beam (a sparse pose's wider one,
    ``pose_beam``, is the pose's last pruning's: settling every extra partial explanation to
    compare it would cost more than the few it keeps).

    Under each parent the clear observations are taken first (``after_clear``). Then the
    observations still ambiguous are branched on one at a time: unassigned (``null_cost``), or
    paired with each landmark within ``branch_delta`` of its best option; each parent's partial
    explanations are pruned to a beam of their own, so that a costlier parent's best explanation
    is grown to the end (where observations are few it is often the right one), and past
    ``partial_budget`` they share one budget (``prune_partials``). Each parent's chains of pairs
    are checked against its own prior (``explain_from``, ``beam_chain``).

    A Python function, not a kernel: ``run_poses`` calls ``explain_from`` itself. As an ``entry``
    of its own over ``explain_from``, its module held a copy of the whole beam's tree, which LLVM
    optimized and generated again (6 s of a first compile's 106 s of CPU, docs/performance.md,
    2026-12-06 (seventeenth session))."""
    return explain_from(scene, settings, parents, n_parents, obs, parents)


@entry
def explain_from(scene, settings, parents, n_parents, obs, roots):
    """``explain_all``, each parent's chains of pairs checked against its row of ``roots`` (the
    pose's prior it grew from: the parent itself in the beam, the prior the search started from
    in the seeded search, ``seeds.from_seeds``; ``beam_chain``)."""
    m = obs.size
    cap = parents[6][:n_parents].max() + m if n_parents else m
    dim = parents[0].shape[1]                   # the state's size: 6 (Euler), 3 (planar)
    gen = new_generation(n_parents, cap, dim)
    model = pair_model(scene)                   # what the updates read of the scene
    options, orders, leasts = [], [], []
    root = np.arange(n_parents)
    # each partial explanation's row of gen: a step's kept children stay where they were branched,
    # not gathered into a generation of their own (a copy of every field of each, every step)
    live = np.arange(n_parents)
    rest = np.zeros(n_parents)
    moved = np.zeros(n_parents, np.bool_)
    expected = []
    wide = np.zeros(n_parents, np.bool_)
    for h in range(n_parents):
        opt, order, least, wide[h] = after_clear(scene, settings, parents, h, obs, gen, model, roots[0][h], roots[1][h], roots[6][h])
        options.append(opt)
        expected.append(expected_landmarks(scene, parents[0][h], obs, opt))
        orders.append(order)
        leasts.append(least)
        rest[h] = least[order].sum()
    step = room_even = room_odd = 0
    while True:
        growing = False
        for r in root:
            growing = growing or step < orders[r].size
        if not growing:
            if step:
                gen = gather(gen, live, cap)
            for c in range(root.size):
                gen[2][c] += missed(expected[root[c]][0], expected[root[c]][1], taken_by(gen[7], gen[6], c))
            return gen, root.size
        # the children of every partial explanation for its next observation, into one of two sets
        # of a step's arrays in turn (gen is the other's), each grown as a step needs more room:
        # 17 arrays allocated a step before, about 100 a pose of the 20k pixel world
        n = root.size
        total = step_room(root, orders, options, step)
        if step % 2 == 0:
            if total > room_even:
                even, room_even = step_arrays(total, cap, dim), total
            children, c_root, c_rest, c_moved, pending = even
        else:
            if total > room_odd:
                odd, room_odd = step_arrays(total, cap, dim), total
            children, c_root, c_rest, c_moved, pending = odd
        for c in range(total):
            pending[5][c] = False                # a new child is settled unless branch pairs it
        at = FIRST    # a counter passed to kernels: int64 from the start (see FIRST)
        for p in range(n):
            r = root[p]
            if step >= orders[r].size:
                copy_hypothesis(gen, live[p], children, at)
                c_root[at], c_rest[at], c_moved[at] = r, rest[p], moved[p]
                at += 1
                continue
            i, q = orders[r][step], live[p]
            start, lm, cost, zh, Hs = options[r][:5]
            part = slice(start[i], start[i + 1])
            taken = taken_by(gen[7], gen[6], q)
            # here, not in branch: an inlined step would count the model's 16 arrays as it binds them
            options_i = options_of(model, settings, gen[0][q], gen[1][q], taken, obs[i], lm[part], cost[part], zh[part], Hs[part],
                                   moved[p])
            at = branch(scene.null_cost, settings, gen, q, r, obs[i], options_i, taken, start, lm, cost, moved[p],
                        orders[r][step + 1:], rest[p] - leasts[r][i], children, at, c_root, c_rest, c_moved, pending)
        c_root, c_rest, c_moved = c_root[:at], c_rest[:at], c_moved[:at]
        chain = (children[7], children[6], c_root, roots[0], roots[1], roots[6], wide)
        live = prune_partials(settings, children, c_root, c_rest, gen, pending, model, chain)
        gen = children
        root, rest, moved = c_root[live], c_rest[live], c_moved[live]
        step += 1



@inlined
def step_room(root, orders, options, step):
    """Room for every child the partial explanations (of roots ``root``) may have at ``step``: one
    per landmark of the observation's pool and the unassigned one (counting the viable ones would
    make each partial's options twice)."""
    total = FIRST    # a counter passed to kernels: int64 from the start (see FIRST)
    for p in range(root.size):
        if step >= orders[root[p]].size:
            total += 1
        else:
            i = orders[root[p]][step]
            total += options[root[p]][0][i + 1] - options[root[p]][0][i] + 1
    return total


@inlined
def step_arrays(n, cap, dim):
    """A step's children (a generation), their roots, rests, whether moved, and pending record
    (``settled``'s), room for n."""
    return new_generation(n, cap, dim), np.empty(n, np.int64), np.empty(n), np.empty(n, np.bool_), settled(n, dim)


# ``explain_from`` as ``run_poses`` calls it: by its address, compiled once in its own module, where
# linked the beam's whole tree was optimized and generated again in ``run_poses``' (``_jit.called``)
explain_from_at = called(explain_from)

@jit
def expected_landmarks(scene, x, obs, opt):
    """The landmarks (distinct, sorted) a pose's explanation grown from a hypothesis at x is
    expected to claim, and each one's least excess (its pair's cost over the observation's null
    cost): those in the pool (``opt``, its options) of one of its pixel observations whose distance
    from that observation's camera lies within the scene's detection range (``view_limits[3:5]``,
    ``observation_space.detection_range``). The charge itself (``camloc.miss_term``) is computed by
    ``missed``, for the landmarks an explanation leaves unclaimed only: most are claimed.
    ``camloc.beam_expansion.PoseExpansion.expected``."""
    low, high = scene.view_limits[3], scene.view_limits[4]
    start, lm, pool_cost = opt[0], opt[1], opt[8]
    found = np.empty(lm.size, np.int64)
    excess = np.empty(lm.size)
    n = 0
    if MISS_COST <= 0.0 or high <= 0.0:
        return found[:0], excess[:0]
    last = -1                                   # the camera whose centre is ``centre``: a pose's are grouped
    for i in range(obs.size):
        c = scene.obs_camera[obs[i]]
        if scene.camera_K[c, 4] != PIXEL:
            continue
        if c != last:                           # once a camera, not once an observation (four arrays each)
            centre = camera_pose(x, scene.camera_R[c], scene.camera_t[c])[1]
            last = c
        null_cost = scene.null_cost[obs[i]]
        for j in range(start[i], start[i + 1]):
            d = 0.0
            for a in range(3):
                e = scene.landmark_xyz[lm[j], a] - centre[a]
                d += e * e
            d = math.sqrt(d)
            if low <= d <= high:
                found[n], excess[n] = lm[j], pool_cost[j] - null_cost
                n += 1
    # distinct landmarks, each at its least excess (its largest chance of being on a ray)
    return distinct_least_in_place(found, excess, n)


@jit
def distinct_least_in_place(found, excess, n):
    """The distinct landmarks of found[:n] and each one's least excess, written over found and
    excess in ascending order of landmark: sorted in place by a stable insertion (the merge sort's
    order, no array allocated) up to ``SMALL_EXPECTED_SORT`` of them, else by the merge sort."""
    if n > SMALL_EXPECTED_SORT:
        order = np.argsort(found[:n].astype(np.float64), kind="mergesort")   # the merge sort the other kernels compile
        found[:n], excess[:n] = found[order], excess[order]
    else:
        for i in range(1, n):
            landmark, e = found[i], excess[i]
            j = i
            while j > 0 and landmark < found[j - 1]:
                found[j], excess[j] = found[j - 1], excess[j - 1]
                j -= 1
            found[j], excess[j] = landmark, e
    u = 0
    for k in range(n):                          # u <= k: found[k] is read before its slot is reused
        if u and found[u - 1] == found[k]:
            excess[u - 1] = min(excess[u - 1], excess[k])
        else:
            found[u], excess[u] = found[k], excess[k]
            u += 1
    return found[:u], excess[:u]


# Up to this many, ``expected_landmarks`` sorts its landmarks in place by insertion; more, by merge sort
SMALL_EXPECTED_SORT = 64


@jit
def missed(expected, excess, taken):
    """What leaving the expected landmarks that are not taken costs (``camloc.miss_term``)."""
    total = 0.0
    for k in range(expected.size):
        if not is_taken(expected[k], taken):
            total += compiled_miss_charge(excess[k], MISS_COST)
    return total


@jit
def options_of(model, settings, x, P, taken, o, lm, cost, zh, Hs, moved):
    """The options of observation o, its pool ``lm`` and their costs, predictions and Jacobians
    at its root's base state (``zh``, ``Hs``), under a partial at (x, P) that has taken ``taken``:
    those of the base state, or made again under the partial's own where it has paired something
    since (``model``: ``update.pair_model``). Passed the arrays it reads, not the generation and
    the options: every array a call is passed is counted on entry and on return. The base state's
    are the root's own arrays, not copies: ``viable_limit`` and ``branch`` write nothing into them."""
    if not moved:
        return lm, cost, zh, Hs
    cost, z_hat, H, _, _, _ = condition(model, settings, x, P, o, lm, taken)
    return lm, cost, z_hat, H


@jit
def viable_limit(taken, landmarks, cost, null_cost, branch_delta):
    """The cost within which an option is viable: branch_delta over the best of the options (those
    of landmarks not taken: ``untaken_cost``) and the null one. Option j is viable where
    ``untaken_cost(cost, landmarks, j, taken) <= limit`` (a test, not an array of them: one array
    allocated per partial explanation branched). Writes nothing: ``cost`` may be the root's options' own."""
    best = null_cost                            # ``least_cost`` of the untaken costs
    for j in range(cost.size):
        c = untaken_cost(cost, landmarks, j, taken)
        if c < best:
            best = c
    return best + branch_delta


@jit
def untaken_cost(cost, landmarks, j, taken):
    """Option j's cost, inf where its landmark is taken."""
    return np.inf if is_taken(landmarks[j], taken) else cost[j]


@jit
def contested(start, lm, cost, later, landmarks, option_cost, taken, limit):
    """Whether a viable landmark of an observation (its options ``landmarks``, ``option_cost``,
    ``viable_limit``'s limit) is the only landmark in the gate of one still
    to explain after it (``later``): then that observation may stay unassigned whatever its null
    cost, since the explanation that leaves it gives the landmark to the other
    (``PoseExpansion.branches``). Passed the options' arrays it reads (``options_of``)."""
    for i in later:
        gated, only = 0, -1
        for g in range(start[i], start[i + 1]):
            if math.isfinite(cost[g]):
                gated += 1
                only = lm[g]
        if gated != 1:
            continue
        for j in range(landmarks.size):
            if untaken_cost(option_cost, landmarks, j, taken) <= limit and landmarks[j] == only:
                return True
    return False


@inlined
def branch(null_cost, settings, gen, p, r, o, options, taken, start, lm, all_cost, moved, later, rest, children, at, c_root,
           c_rest, c_moved, pending):
    """Write the children of partial p (which has taken ``taken``) for observation o from index
    ``at``: unassigned, or paired with a viable landmark of its ``options`` (``options_of``) (its
    state pending); returns the next free index. Passed the arrays it reads of the scene
    (``null_cost``) and of its root's options (``options_for``'s first three), not the tuples: an
    inlined step counts a reference to every array of the tuples it binds, per partial explanation
    branched."""
    landmarks, cost, z_hat, H = options
    null_option = null_cost[o] + settings.null_offset
    limit = viable_limit(taken, landmarks, cost, null_option, settings.branch_delta)
    null = null_option <= limit or contested(start, lm, all_cost, later, landmarks, cost, taken, limit)
    if null:
        copy_hypothesis(gen, p, children, at)
        children[2][at] += null_cost[o]
        children[4][at] += 1
        c_root[at], c_rest[at], c_moved[at] = r, rest, moved
        at += 1
    for j in range(landmarks.size):             # not np.flatnonzero: two arrays a partial explanation
        if not untaken_cost(cost, landmarks, j, taken) <= limit:
            continue
        copy_hypothesis(gen, p, children, at)
        children[2][at] += untaken_cost(cost, landmarks, j, taken)
        children[7][at, children[6][at], 0], children[7][at, children[6][at], 1] = o, landmarks[j]
        children[6][at] += 1
        c_root[at], c_rest[at], c_moved[at] = r, rest, True
        pending[0][at], pending[1][at], pending[2][at] = p, o, landmarks[j]
        for a in range(3):
            pending[3][at, a] = z_hat[j, a]
            for b in range(6):                  # unrolled, the smaller state's columns skipped (``same_state``)
                if b < H.shape[2]:
                    pending[4][at, a, b] = H[j, a, b]
        pending[5][at] = True
        at += 1
    return at


# ---------------------------------------------------------------------------------------------
# The run over the poses

@inlined
def predicted(T_increment, odom_cov, beam, n, k):
    """The beam's first n hypotheses predicted to pose k (k > 0) with its odometry (the scene's
    ``T_increment``, ``odom_cov``: not the scene, whose 31 arrays an inlined step counts as it
    binds them): same costs, each remembering which it grew from, no pairs yet."""
    out = new_generation(n, ONE, beam[0].shape[1])
    for h in range(n):
        x, P = predict(beam[0][h], beam[1][h], T_increment[k - 1], odom_cov[k - 1])
        put_state(out, h, x, P)
        out[2][h], out[3][h] = beam[2][h], h
    return out


@entry
def commit(history, k, gen, kept):
    """Record pose k's kept hypotheses (parent, slipped, pairs, state, cost) for the backtrack;
    False where the pair buffer is full (the caller grows it and calls again)."""
    count, parent, slipped, pair_start, pairs, used, state, cost = history
    needed = 0
    for h in kept:
        needed += gen[6][h]
    if used[0] + needed > pairs.shape[0]:
        return False
    count[k] = kept.size
    for q in range(kept.size):
        h = kept[q]
        parent[k, q], slipped[k, q], cost[k, q] = gen[3][h], gen[5][h], gen[2][h]
        for a in range(gen[0].shape[1]):
            state[k, q, a] = gen[0][h, a]
        pair_start[k, q] = used[0]
        for i in range(gen[6][h]):
            pairs[used[0] + i, 0], pairs[used[0] + i, 1] = gen[7][h, i, 0], gen[7][h, i, 1]
        used[0] += gen[6][h]
        pair_start[k, q + 1] = used[0]
    return True


@inlined
def binomial_upper_tail(u, n, p):
    """P(X >= u) for X ~ Binomial(n, p), summed term by term (n is a pose's observations)."""
    if u <= 0:
        return 1.0
    if u > n or p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    total = 0.0
    for j in range(u, n + 1):
        total += math.exp(math.lgamma(n + 1.0) - math.lgamma(j + 1.0) - math.lgamma(n - j + 1.0)
                          + j * math.log(p) + (n - j) * math.log1p(-p))
    return min(total, 1.0)


@inlined
def seeds_worth_trying(unassigned, observed, unexplained, count):
    """``camloc.beam_seeded.seeds_worth_trying`` over the first ``count`` rows of ``unexplained`` (the
    poses' (unassigned, observed) so far)."""
    if unassigned < SEEDED_MIN_UNASSIGNED:
        return False
    first = max(count - UNEXPLAINED_WINDOW, 0)
    if count == first:
        return True
    left = seen = 0
    for r in range(first, count):
        left += unexplained[r, 0]
        seen += unexplained[r, 1]
    rate = min(left / seen, UNEXPLAINED_RATE_CAP)
    return binomial_upper_tail(unassigned, observed, rate) < SEEDED_UNUSUAL_PROBABILITY


@entry
def run_poses(scene, settings, sparse, first, last, beam, n, history, unexplained, counters):
    """The beam from pose first to last - 1, from ``beam`` (n hypotheses after pose first - 1, or
    the start), ``sparse`` (N,) the run's sparse poses (``sparse_poses.sparse_poses``). Per pose: predict every hypothesis, explain the pose's observations, keep the
    cheapest (``prune``), record them. Stops early with SLIP where the best explanation leaves
    most of a pose's observations unassigned (the caller decides whether to search from seeds),
    or GROW where the history's pair buffer is full. counters[1] is the pose being explained.

    Returns (status, pose, beam after it (or the predicted beam at it), its size, the pose's
    children, their count)."""
    for k in range(first, last):
        counters[1] = k
        parents = predicted(scene.T_increment, scene.odom_cov, beam, n, k) if k > 0 else beam
        obs = scene.pose_obs[scene.pose_obs_start[k]:scene.pose_obs_start[k + 1]]
        if obs.size == 0 or scene.grid_keys.size == 0:
            children, count, kept = parents, n, np.arange(n)
        else:
            # the extra hypotheses of a sparse pose before are not explained at one that is not
            n = compiled_carried(parents[2], n, sparse[k], settings.beam_width, settings.beam_delta)
            width, delta = compiled_pose_beam(sparse[k], settings.beam_width, settings.beam_delta)
            children, count = explain_from_at(scene, settings, parents, n, obs, parents)   # ``explain_all``
            if count == 0:
                raise FloatingPointError("no explanation of the pose's observations has a finite cost")
            best = np.argmin(children[2][:count])
            unassigned = children[4][best]
            if ((obs.size >= SLIP_MIN_OBSERVATIONS and 2 * unassigned > obs.size)
                    or seeds_worth_trying(unassigned, obs.size, unexplained, counters[2])):
                return SLIP, k, parents, n, children, count
            kept = prune(scene, settings, children, count, width, delta)
        if not commit(history, k, children, kept):
            return GROW, k, parents, n, children, count
        if obs.size and scene.grid_keys.size:
            u = counters[2]
            unexplained[u, 0], unexplained[u, 1] = children[4][kept[0]], obs.size
            counters[2] = u + 1
        beam, n = carry(children, kept), kept.size
    return DONE, last, beam, n, beam, n
