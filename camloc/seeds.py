"""The beam's search from seed pairs, where a pose's best explanation leaves most of its
observations unassigned (an odometry slip, or noisy odometry in a dense map): rare, so it runs in
Python over the compiled kernels. The reasoning is in ``docs/beam.md``.

Under a wide prior every observation gates many landmarks, and explaining them one by one goes
astray; one right pair pins the pose, after which the others fall into place. So the seed pairs
whose conditioned explanation of the pose looks cheapest (``association.seeded_explanation_costs``)
among the individually cheapest pairs and those whose implied shift of the robot most other pairs
share (``association.shift_agreement``) are each tried first, and the rest explained as usual.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry, planar
from camloc.constants import (
    AGREEMENT_DEPTH_FRACTION, AGREEMENT_SIGMAS, SLIP_CANDIDATES, SLIP_MIN_OBSERVATIONS, SLIP_SEEDS, STATE_GATE, UNEXPLAINED_RATE_CAP,
    UNEXPLAINED_RUN, UNEXPLAINED_WINDOW, UNUSUAL_PROBABILITY,
)
from camloc.kernels import beam as kb
from camloc.kernels import seeds as ranking
from camloc.kernels.state import difference
from camloc.kernels.view import widened_view
from camloc.measurement import DEPTH
from camloc.tails import binomial_tail


def explain_with_seeds(scene, settings, parents, n, children, count, obs, unexplained, width, delta):
    """The kept hypotheses of a pose whose best explanation (of ``children``) left most of its
    observations unassigned, or an unusual number of them (``kernels.beam.seeds_worth_trying``):
    the children, and the explanations grown from seeds under the beam's best prediction
    (``parents``' first), as it is and, where most were left and leaving that many unassigned is
    unusual for this data even with those, widened as after an odometry slip.
    ``settings`` are the run's; ``width`` and ``delta`` the pose's beam (``sparse_poses.pose_beam``).
    Returns (the generation they are in, the kept indices)."""
    origin = kb.gather(parents, np.array([0]), 1)
    plain = from_seeds(scene, settings, origin, obs, width, delta, slipped=False)  # noisy odometry, not a slip
    groups = [plain]
    # a slip is the explanation of last resort: its search (the costliest, under the widest prior)
    # runs only where the pose stays unusually unexplained after the plain prediction's, or where a
    # seed's explanation beat the prior's with fewer pairs (the prior's pairs cost more than leaving
    # them unexplained: the prior is off)
    cost, left = best_of([(children, count)])
    cost_with_seeds, left_with_seeds = best_of([(children, count), plain])
    most = obs.size >= SLIP_MIN_OBSERVATIONS and 2 * left > obs.size
    unusual = (most and unusually_unexplained(left, obs.size, unexplained)
               and unusually_unexplained(left_with_seeds, obs.size, unexplained))
    if unusual or (obs.size >= SLIP_MIN_OBSERVATIONS and cost_with_seeds < cost and left_with_seeds > left):
        slipped = kb.gather(parents, np.array([0]), 1)
        slipped[1][0] *= settings.slip_inflation
        slipped[2][0] += settings.slip_cost
        groups.insert(0, from_seeds(scene, settings, slipped, obs, width, delta, slipped=True))
    everything, sizes = concatenated([(children, count)] + groups)
    kept = list(kb.prune(scene, settings, everything, sizes.sum(), width, delta))
    offsets = np.cumsum(sizes)
    for g in range(len(groups)):
        kept = with_a_seeded_one(scene, settings, everything, kept, range(offsets[g], offsets[g + 1]), width, delta)
    return everything, np.asarray(kept, dtype=np.int64)


def best_of(generations) -> tuple[float, int]:
    """The cost of the cheapest hypothesis of [(generation, count), ...] (the first of equal
    costs), and how many of the pose's observations it leaves unassigned."""
    best_cost, unassigned = np.inf, 0
    for gen, n in generations:
        if n:
            i = int(np.argmin(gen[2][:n]))
            if gen[2][i] < best_cost:
                best_cost, unassigned = float(gen[2][i]), int(gen[4][i])
    return best_cost, unassigned


def concatenated(generations):
    """One generation of [(generation, count), ...], and the counts. Field by field, a slice of
    each: a compiled ``copy_hypothesis`` per hypothesis from Python cost more (its wrapper unboxes
    two generations) than the copy; the pairs past a hypothesis' count are never read."""
    cap = max(g[7].shape[1] for g, _ in generations)
    sizes = np.array([n for _, n in generations], dtype=np.int64)
    out = kb.new_generation(int(sizes.sum()), cap, generations[0][0][0].shape[1])
    at = 0
    for g, n in generations:
        for field in range(7):
            out[field][at:at + n] = g[field][:n]
        out[7][at:at + n, :g[7].shape[1]] = g[7][:n]
        at += n
    return out, sizes


def with_a_seeded_one(scene, settings, gen, kept, seeded, width, delta):
    """The pruned beam with its last place given to the cheapest seeded explanation, when that is
    within ``delta`` of the best and only the ``width`` kept it out (the pose's beam): a full beam of a wrong
    hypothesis' near copies can crowd out the right explanation of a pose of few observations,
    which the next poses confirm."""
    seeded = list(seeded)
    if len(kept) < width or not seeded or any(c in kept for c in seeded):
        return kept
    candidate = min(seeded, key=lambda c: gen[2][c])
    if gen[2][candidate] > gen[2][kept[0]] + delta or any(kb.same_state(gen[0], gen[1], candidate, k, settings.merge_sigma)
                                                                        for k in kept):
        return kept
    return sorted(kept[:-1] + [candidate], key=lambda c: gen[2][c])


def unusually_unexplained(unassigned: int, observed: int, history: np.ndarray) -> bool:
    """Whether leaving ``unassigned`` of ``observed`` observations unexplained is unlikely at the
    rate of the last poses' best explanations (history (h, 2) of unassigned, observed), for this
    pose alone or pooled with the two before it: where a third of the detections are clutter,
    most poses leave half unassigned, and searching each from seeds finds nothing better."""
    if history.shape[0] == 0:
        return True
    recent = history[-UNEXPLAINED_WINDOW:]
    rate = min(float(recent[:, 0].sum() / recent[:, 1].sum()), UNEXPLAINED_RATE_CAP)
    run = recent[len(recent) - (UNEXPLAINED_RUN - 1):].sum(axis=0)
    tails = binomial_tail(np.array([unassigned, unassigned + run[0]]) - 1, np.array([observed, observed + run[1]]), rate)
    return bool(tails.min() < UNUSUAL_PROBABILITY)


def from_seeds(scene, settings, h, obs, width, delta, *, slipped: bool):
    """Explanations of obs under hypothesis h (a generation of one), each grown from one seed pair;
    each seed gives its SEED_EXPLANATIONS cheapest (``kernels.seeds.seeded_explanations``, one
    compiled call for all the seeds), of which those within the prior are kept. Returns (generation, count)."""
    x, P = h[0][0], h[1][0]
    # among the landmarks within three standard deviations of the view, not only in it
    margin, max_angle = widened_view(P, scene.view_limits[2])
    start, landmark, cost, z_hat, H, y, Hc, in_point, _ = kb.options_for(scene, settings, x, P, obs, margin, max_angle)
    pair_obs = np.repeat(np.arange(obs.size), np.diff(start))
    gated = np.isfinite(cost)
    if not gated.any():
        out = kb.explain_all(scene, settings, h, 1, obs)
        return _flagged(out, slipped)
    pair_obs, pair_landmark, pair_cost = pair_obs[gated], landmark[gated], cost[gated]
    candidates = np.argsort(pair_cost, kind="stable")[:SLIP_CANDIDATES]
    # and the pairs whose implied shift of the robot most others share: a right pair's own cost
    # under a wide prior may rank it far down
    # (a pixel is a ray: it implies no one shift; only pairs judged as points vote)
    obs_as_point = scene.camera_K[scene.obs_camera[obs], 4] == DEPTH
    as_point = obs_as_point[pair_obs]
    agreement = np.zeros(pair_obs.size, np.int64)
    if as_point.any():
        agreement[as_point] = ranking.shift_agreement(implied_shifts(scene, x, obs, pair_obs[as_point], pair_landmark[as_point]),
                                                      agreement_radius(scene, obs[obs_as_point]))
    crowded = np.argsort(-agreement, kind="stable")[: SLIP_CANDIDATES // 4]
    crowded = crowded[agreement[crowded] >= 3]
    # (a few dozen of each: one comparison of all with all costs less than np.isin's sort)
    candidates = np.concatenate([candidates, crowded[~(crowded[:, None] == candidates[None, :]).any(axis=1)]])
    pair_in_point, pair_z_hat, pair_H = in_point[gated], z_hat[gated], H[gated]
    o = obs[pair_obs]
    noise = np.where(pair_in_point[:, None, None], scene.point_cov[o], scene.R_assoc[o])
    ranked = ranking.seeded_explanation_costs(y[gated], Hc[gated], noise, P, pair_obs, pair_landmark,
                                              scene.null_cost[obs], candidates.astype(np.int64), scene.obs_gate[o])
    seeds = candidates[np.argsort(ranked, kind="stable")[:SLIP_SEEDS]]
    found, n = ranking.seeded_explanations(scene, settings, h, obs, seeds, pair_obs, pair_landmark, pair_cost, pair_z_hat, pair_H)
    within = np.flatnonzero(within_prior(found[0][:n], x, P)).astype(np.int64)
    if not within.size:
        return _flagged(kb.explain_all(scene, settings, h, 1, obs), slipped)
    gen = kb.gather(found, within, found[7].shape[1])
    kept = kb.prune(scene, settings, gen, within.size, width, delta)
    return _flagged((kb.gather(gen, kept, gen[7].shape[1]), kept.size), slipped)


def _flagged(generation, slipped: bool):
    gen, n = generation
    gen[5][:n] = slipped
    return gen, n


def within_prior(X, x, P) -> np.ndarray:
    """(k,) whether each state of X (k, n) lies within the 99.9% region of its prior (x, P): under
    a wide prior in a dense map a seed can fit a landmark metres from the right one by turning the
    camera, every innovation looking likely while the state moved many standard deviations.
    One stacked solve for all (numpy's solve calls LAPACK's gesv for each matrix of a stack as
    it does for one, and matmul's product of a row and a column is the dot of two vectors: the
    same bits as a solve and a dot per state, ``tests/test_seeds_steps.py``), where a call
    each was the search's costliest step in Python."""
    if X.shape[0] == 0:
        return np.zeros(0, np.bool_)
    D = np.array([difference(X[c], x) for c in range(X.shape[0])])
    solved = np.linalg.solve(np.broadcast_to(P, (D.shape[0],) + P.shape), D[:, :, None])
    return np.matmul(D[:, None, :], solved)[:, 0, 0] <= STATE_GATE


def implied_shifts(scene, x, obs, pair_obs, pair_landmark):
    """(N, 3) the shift of the robot from x each pair implies (``association.shift_agreement``)."""
    T_world_robot = planar.lift(x) if x.size == planar.STATE_SIZE else geometry.pose_from_euler(x)
    measured_world = np.empty((pair_obs.size, 3))
    cameras = scene.obs_camera[obs][pair_obs]
    for c in np.unique(cameras):
        mine = cameras == c
        T_world_camera = T_world_robot @ geometry.make_pose(scene.camera_R[c], scene.camera_t[c])
        measured_world[mine] = geometry.transform_points(T_world_camera, scene.point[obs[pair_obs[mine]]])
    return scene.landmark_xyz[pair_landmark, :3] - measured_world


def agreement_radius(scene, obs) -> float:
    """How close two implied shifts must be to agree: three standard deviations of a measured
    point, plus a tenth of the depth for the orientation's error (about 6 deg)."""
    point_sigma = np.sqrt(np.trace(scene.point_cov[obs], axis1=1, axis2=2) / 3.0)
    return float(AGREEMENT_SIGMAS * median(point_sigma) + AGREEMENT_DEPTH_FRACTION * median(np.abs(scene.point[obs, 2])))


def median(values: np.ndarray) -> float:
    """np.median of a few finite values (the middle one, or the mean of the middle two: the same
    bits), by a sort: np.median's checks and partition cost four times as much on a pose's few."""
    ordered = np.sort(values)
    half = ordered.size // 2
    return float(ordered[half]) if ordered.size % 2 else float((ordered[half - 1] + ordered[half]) / 2.0)
