"""The filter's pass over the poses once the association is known or trivial: predict, take the
pose's pairs (given by an associator, or the file's ids for the oracle), update with all of them
stacked, re-check each pair by the others, record. One compiled loop over a block of poses."""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import FALSE, TRUE, called, entry, inlined, jit
from camloc.kernels.camera import camera_pose, cameras_of, in_front_of, observe, robot_frame
from camloc.kernels.motion import predict
from camloc.kernels.planar import SE2_DIM
from camloc.constants import RESTORE_LIMIT
from camloc.kernels.recheck import (add_leave_one_out_spread, assignment_margins, leave_one_out_costs, predict_pairs, restored_pairs,
                                     rival_margins)
from camloc.kernels.small import check_covariance, mm, mtm, solve
from camloc.kernels.sym3 import innovation_mahalanobis
from camloc.kernels.update import pair_model, updated_at
from camloc.kernels.view import sensor_candidates
from camloc.measurement import MARKER, PIXEL, POINT2

GIVEN, ORACLE = 0, 1


@inlined
def oracle_pairs(scene, settings, x, P, obs):
    """The file's landmark of each observation (obs (m,)) where it is in the map, x puts it in
    front of its camera (``in_front``) and the pair passes the gate at (x, P): a gross outlier
    keeps its true id but is no evidence to take."""
    mapped = obs[scene.true_index[obs] >= 0]
    landmarks = scene.true_index[mapped]
    # each pair predicted and gated on its own: the pairs behind the camera are predicted with the
    # others and left out with the gate's, not by copies of their arrays first
    front = in_front(scene, x, mapped, landmarks)
    z_hat, H = predict_pairs(scene, x, mapped, landmarks)
    keep = np.zeros(mapped.size, np.bool_)
    for r in range(mapped.size):
        keep[r] = front[r] and pair_distance(scene.R_assoc, mapped[r], scene.z, z_hat, H, r, P) <= scene.obs_gate[mapped[r]]
    return mapped[keep], landmarks[keep]


@jit
def pair_distance(R, o, z, z_hat, H, i, P):
    """d^2 of observation o (z[o], noise R[o]) against prediction i (z_hat[i], H[i]) under P."""
    return innovation_mahalanobis(H, i, P, R, o, z[o, 0] - z_hat[i, 0], z[o, 1] - z_hat[i, 1], z[o, 2] - z_hat[i, 2])[0]


# Compiled on its own, not inlined: numba's inlining pass over ``filter_poses`` took 6.9 s with this
# step's body (and the three it inlines) in it, 0.1 s without; compiled alone it costs 5.5 s, so the
# first compile of the world is 99 -> 85 s of CPU (``_jit``; run once a pose: no slower)
@jit
def recheck(scene, settings, obs, pair_obs, pair_landmarks, P_prior, x_post):
    """Which of a pose's pairs (p,) keep more than ``recheck_margin`` over their nearest
    alternative, more than ``recheck_steal_margin`` over a rival taking their landmark and, a pixel
    observation's, more than ``recheck_ray_margin`` over its nearest rival landmark, each
    observation of the pose (obs (m,)) judged by the posterior of the other pairs; and whose
    landmark lies within the candidates' distance of its camera at x_post (``within_reach``) and in
    front of it (``in_front``); and
    which of those dropped are rays that failed only against leaving them unassigned (``rechecked``
    weighs them again). The numpy twin is ``camloc.localizer._Localizer._recheck``."""
    # the candidates' distance (``view_limits[6]``, a pixel-only file's learned reach; inf: none)
    reach = scene.view_limits[6] if scene.view_limits.shape[0] > 6 else np.inf
    # and in front of it there (``in_front``): a pair the beam judged at a state conditioned on some
    # of the pose's pairs may lie behind the camera at the posterior of all of them
    keep = within_reach(scene, x_post, pair_obs, pair_landmarks, reach) & in_front(scene, x_post, pair_obs, pair_landmarks)
    doubtful = np.zeros(pair_obs.size, np.bool_)
    cameras = cameras_of(scene.obs_camera, obs, scene.camera_R.shape[0])
    n = x_post.shape[0]                          # the state's size: 6 (Euler), 3 (planar)
    information = np.zeros((cameras.size, n, n))
    groups = []
    for g in range(cameras.size):
        c = cameras[g]
        mine = obs[scene.obs_camera[obs] == c]
        candidates = sensor_candidates(scene, x_post, c, scene.view_limits[2], 0.0)
        z_hat, H = observe(x_post, scene.camera_R[c], scene.camera_t[c], scene.camera_K[c], scene.landmark_xyz[candidates])
        chosen = np.full(mine.size, -1, np.int64)
        for r in range(mine.size):
            for q in range(pair_obs.size):
                if pair_obs[q] == mine[r]:
                    j = np.searchsorted(candidates, pair_landmarks[q])    # candidates are sorted
                    if j < candidates.size and candidates[j] == pair_landmarks[q]:
                        chosen[r] = j
            if chosen[r] >= 0:
                Hc = H[chosen[r]]
                pair_information = mtm(Hc, mm(scene.R_assoc_inverse[mine[r]], Hc))
                for a in range(n):
                    for b in range(n):
                        information[g, a, b] += pair_information[a, b]
        groups.append((mine, z_hat, H, chosen))
    prior_information = solve(P_prior, np.eye(n))
    for g in range(cameras.size):
        mine, z_hat, H, chosen = groups[g]
        if z_hat.shape[0] == 0:
            continue
        others = prior_information.copy()
        for g2 in range(cameras.size):
            if g2 != g:
                others += information[g2]
        cost = leave_one_out_costs(scene.z[mine], scene.R_assoc[mine], scene.R_assoc_inverse[mine], scene.log_det_R[mine],
                                   z_hat, H, chosen, others, scene.obs_gate[mine[0]], scene.camera_K[cameras[g], 4])  # a sensor's observations share their dof and kind
        row, steal = assignment_margins(cost, scene.null_cost[mine], chosen)
        # a ray passes near several landmarks; judged by its rivals only within the camera's reach:
        # beyond it, landmarks the camera cannot see crowd every ray
        ray = scene.camera_K[cameras[g], 4] == PIXEL and reach < np.inf
        rival = rival_margins(cost, chosen)
        for r in range(mine.size):
            others_hold = steal[r] > settings.recheck_steal_margin and not (ray and rival[r] <= settings.recheck_ray_margin)
            for q in range(pair_obs.size):
                if pair_obs[q] == mine[r] and not (row[r] > settings.recheck_margin and others_hold):
                    # a ray dropped against the null option alone (or its own cost beyond the
                    # gate, where no other test means anything) is weighed again (``rechecked``)
                    doubtful[q] = keep[q] and ray and not row[r] > settings.recheck_margin and (not np.isfinite(row[r]) or others_hold)
                    keep[q] = False
    return keep, doubtful


# The filter's big callees by their address (``_jit.called``): linked, ``recheck``'s module (20,175
# LLVM instructions) and ``add_leave_one_out_spread``'s (7,227) were generated again in
# ``filter_poses``'; ``restored_pairs`` runs only where the re-check doubts a ray (never on the
# issue's 3,000-pose world), so it is compiled where a run first reaches it (``deferred``; a
# compile's second process compiles it for the runs after: ``warmup.deferred_kernels``)
recheck_at = called(recheck)
restored_pairs_at = called(restored_pairs, deferred=True)
add_leave_one_out_spread_at = called(add_leave_one_out_spread)


# Inlined into its one caller: compiled on its own, its module generates ``updated``'s tree once more
# (4.7 s of LLVM): the first compile of the world 93.6 s of CPU against 85-87 inlined
@inlined
def rechecked(scene, settings, model, x, P, obs_k, obs, landmarks, result):
    """A pose's pairs (obs, landmarks) after the re-check and their update from (x, P) (result:
    the update with all of them): ``recheck``'s drops, then the rays it dropped against leaving
    them unassigned alone restored where their joint cost under the kept pairs' posterior says so
    (``restored_pairs``). The numpy twin is ``camloc.localizer._rechecked``."""
    keep, doubtful = recheck_at(scene, settings, obs_k, obs, landmarks, P, result[0])
    if keep.all():
        return obs, landmarks, result
    no_start = np.empty(0)
    kept_obs, kept_landmarks = obs[keep], landmarks[keep]
    x_kept, P_kept = x, P
    if kept_obs.size:
        z_hat, H = predict_pairs(scene, x, kept_obs, kept_landmarks)
        result = updated_at(model, settings.iterations, x, P, kept_obs, kept_landmarks, z_hat, H, scene.R_file, scene.R_file_inverse,
                         no_start, TRUE, 0.0)
        x_kept, P_kept = result[0], result[1]
    weighed = np.flatnonzero(doubtful)
    if weighed.size == 0 or weighed.size > RESTORE_LIMIT:
        return kept_obs, kept_landmarks, result
    weighed_obs = obs[weighed]
    z_hat, H = predict_pairs(scene, x_kept, weighed_obs, landmarks[weighed])
    restore = restored_pairs_at(scene.z[weighed_obs] - z_hat, H, P_kept, scene.R_assoc[weighed_obs], scene.R_assoc_inverse[weighed_obs],
                             scene.null_cost[weighed_obs])
    if not restore.any():
        return kept_obs, kept_landmarks, result
    for i in range(weighed.size):
        if restore[i]:
            keep[weighed[i]] = True
    obs, landmarks = obs[keep], landmarks[keep]
    z_hat, H = predict_pairs(scene, x, obs, landmarks)
    result = updated_at(model, settings.iterations, x, P, obs, landmarks, z_hat, H, scene.R_file, scene.R_file_inverse, no_start, TRUE, 0.0)
    return obs, landmarks, result


@inlined
def within_reach(scene, x, pair_obs, pair_landmarks, reach):
    """Which pairs' landmarks lie within ``reach`` (``recheck``'s candidates' distance; inf: every
    one) of their camera at x (a planar sensor's: every one). The numpy twin is
    ``AssociationScene.within_reach``."""
    within = np.ones(pair_obs.size, np.bool_)
    if not reach < np.inf:
        return within
    for q in range(pair_obs.size):
        c = scene.obs_camera[pair_obs[q]]
        kind = scene.camera_K[c, 4]
        if kind == POINT2 or kind == MARKER:
            continue
        _, centre = camera_pose(x, scene.camera_R[c], scene.camera_t[c])
        distance2 = 0.0
        for a in range(3):
            d = scene.landmark_xyz[pair_landmarks[q], a] - centre[a]
            distance2 += d * d
        within[q] = distance2 <= reach * reach
    return within


@inlined
def in_front(scene, x, pair_obs, pair_landmarks):
    """Which pairs' landmarks lie in front of their camera at x (depth > 0; a planar sensor's:
    every one: ``camera.in_front_of``): ``pairs_in_front`` passed the five arrays of the scene it
    reads (as ``recheck.predict_pairs``). The numpy twin is ``AssociationScene.in_front``, which
    says why."""
    return pairs_in_front(x, pair_obs, pair_landmarks, scene.obs_camera, scene.landmark_xyz, scene.camera_R, scene.camera_t,
                          scene.camera_K)


@jit
def pairs_in_front(x, pair_obs, pair_landmarks, obs_camera, landmark_xyz, camera_R, camera_t, camera_K):
    """``in_front`` of the scene's arrays it reads."""
    front = np.ones(pair_obs.size, np.bool_)
    R, _, t = robot_frame(x)
    for q in range(pair_obs.size):
        c = obs_camera[pair_obs[q]]
        front[q] = in_front_of(R, t, camera_R[c], camera_t[c], camera_K[c, 4], landmark_xyz, pair_landmarks[q])
    return front


@jit
def record_state(states, covs, k, x, P):
    """states[k] = x, covs[k] = P, entry by entry (as every copy into a slice: see ``_jit``)."""
    if x.shape[0] == 6:                          # the Euler state's size as a constant (``sym3.spread``)
        record_state_of_size(states, covs, k, x, P, 6)
    else:
        record_state_of_size(states, covs, k, x, P, SE2_DIM)


@inlined
def record_state_of_size(states, covs, k, x, P, n):
    """``record_state`` of a state of n entries."""
    for a in range(n):
        states[k, a] = x[a]
        for b in range(n):
            covs[k, a, b] = P[a, b]


@entry
def filter_poses(scene, settings, method, first, last, x, P, pair_start, pair_obs, pair_landmark, slipped,
                 states, covs, chosen, mahalanobis_distance, update_pose, nis, map_cost, nis_dof, pair_spread, counters):
    """Filter poses first..last-1 from (x, P) (the state after pose first - 1, or the start).

    method: GIVEN (pose k's pairs are pair_obs/pair_landmark[pair_start[k]:pair_start[k + 1]], the
    first the seed of an explanation from a slip, and ``slipped[k]``: the prior is widened by
    ``slip_inflation`` there) or ORACLE. Writes states (N, n), covs (N, n, n), per observation the
    chosen landmark (-1 none) and the pair's Mahalanobis distance, per update its pose, NIS, MAP
    cost and degrees of freedom, and with GIVEN pairs what their chance of being clutter adds to
    the estimate's covariance (``add_leave_one_out_spread`` into pair_spread (N, n, n));
    counters[0] counts updates, counters[1] is the pose being filtered (where an error stopped
    it). Returns (x, P) after pose last - 1."""
    no_start = np.empty(0)                       # ``updated``'s start: none
    model = pair_model(scene)                    # what ``updated`` reads of the scene
    for k in range(first, last):
        counters[1] = k
        if k > 0:
            x, P = predict(x, P, scene.T_increment[k - 1], scene.odom_cov[k - 1])   # x <- x (+) odometry
        obs_k = scene.pose_obs[scene.pose_obs_start[k]:scene.pose_obs_start[k + 1]]
        if method == ORACLE:
            obs, landmarks = oracle_pairs(scene, settings, x, P, obs_k)
        else:                                                                       # in observation order
            given_obs = pair_obs[pair_start[k]:pair_start[k + 1]]
            order = np.argsort(given_obs.astype(np.float64), kind="mergesort")   # float: the beam's merge sort
            obs, landmarks = given_obs[order], pair_landmark[pair_start[k]:pair_start[k + 1]][order]
        start = no_start
        if method == GIVEN and slipped[k]:
            P = P * settings.slip_inflation                                         # as the beam did
            if obs.size:
                # the beam explained the pose from its seed pair, listed first: one right pair pins
                # the pose where Gauss-Newton from the slip's wide prior can settle metres away
                seed_obs, seed_landmark = pair_obs[pair_start[k]:pair_start[k] + 1], pair_landmark[pair_start[k]:pair_start[k] + 1]
                z_hat, H = predict_pairs(scene, x, seed_obs, seed_landmark)
                start = updated_at(model, settings.iterations, x, P, seed_obs, seed_landmark, z_hat, H, scene.R_file, scene.R_file_inverse,
                                no_start, FALSE, 0.0)[0]
        if obs.size == 0:
            record_state(states, covs, k, x, P)
            continue
        z_hat, H = predict_pairs(scene, x, obs, landmarks)
        result = updated_at(model, settings.iterations, x, P, obs, landmarks, z_hat, H, scene.R_file, scene.R_file_inverse, start, TRUE, 0.0)
        # A lone pair left out leaves the prior its association was judged by; after a slip, the
        # widened prior leaves each pair's partners too little to confirm it by
        if settings.recheck and method == GIVEN and obs.size >= 2 and not slipped[k]:
            obs, landmarks, result = rechecked(scene, settings, model, x, P, obs_k, obs, landmarks, result)
        if obs.size:
            x_post, P_post, nis_k, cost_k, y = result
            check_covariance(P_post)
            for i in range(obs.size):            # each pair's own 3x3 block of S = H P H' + R
                chosen[obs[i]] = landmarks[i]
                mahalanobis_distance[obs[i]] = math.sqrt(pair_distance(scene.R_file, obs[i], scene.z, z_hat, H, i, P))
            u = counters[0]
            # an iterated update's statistic is its MAP cost at the posterior: NIS at the prior's
            # linearization carries the second-order error the iterations removed
            recorded = cost_k if settings.iterations > 1 and np.isfinite(cost_k) else nis_k
            dof = 0
            for o in obs:
                dof += scene.obs_dof[o]
            update_pose[u], nis[u], map_cost[u], nis_dof[u] = k, recorded, cost_k, dof
            counters[0] = u + 1
            x, P = x_post, P_post
            if method == GIVEN:
                add_leave_one_out_spread_at(scene, x, P, obs, landmarks, pair_spread, k)
        record_state(states, covs, k, x, P)
    return x, P
