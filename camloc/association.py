"""Data association between a pose's observations and the map's landmarks: pure functions of arrays.

Pipeline for one camera at one pose:
1. ``candidate_indices``: map landmarks in front of the camera within the depth range (and distance), found through
   a ``PointIndex`` of the map (the slab of a map sorted along its widest axis, a k-d tree over a
   large map);
2. ``pair_statistics``: for every (observation, candidate) pair, the squared Mahalanobis distance of
   the innovation and the pair's negative log-likelihood ``d^2 + ln det S``;
3. ``best_friends``: keep a pair only when each is the other's cheapest, the pair passes the chi^2
   gate, and no rival comes within ``margin`` of it ("lonely best friends").

Why ``d^2 + ln det S`` and not ``d^2``: plain Mahalanobis distance favours the landmarks whose
prediction is most uncertain (far, large S) because their d^2 is small for everything; the log
determinant charges for that spread, making the cost a proper likelihood comparison.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right

import numpy as np

from camloc import ekf, planar, sym3
from camloc.constants import RESTORE_LIMIT

# Up to this many points a ball query searches a strip of the points sorted along their widest
# axis (``PointIndex``), as quickly as scipy's k-d tree on maps of the numpy engine's sizes (45
# against 47 us a query on the 3,314 landmarks of a 3,000-pose world, EPYC): scipy.spatial, whose
# import is 0.5 s of CPU on that machine (1.5% of such a first run), stays unloaded. Past it the
# strip holds too many points (twice the tree's time at 16,384 landmarks of the same density).
STRIP_MAX_POINTS = 8192
# shift_agreement compares every pair of shifts directly up to this many (an n x n table), and
# more in blocks of this many.
SCAN_MAX_SHIFTS = 256


class PointIndex:
    """The points (N, 3) within a ball of any centre: a strip search over up to
    ``STRIP_MAX_POINTS`` points, a k-d tree (scipy's ``cKDTree``) over more; both exact, indices
    in increasing order."""

    def __init__(self, points: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=float)
        self._tree = None
        if self.points.shape[0] > STRIP_MAX_POINTS:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points)
            return
        # the points sorted along the axis of their widest extent: a ball's points lie in the
        # slab of that axis within its radius, found by bisection
        extent = np.ptp(self.points, axis=0) if self.points.shape[0] else np.zeros(3)
        self._axis = int(np.argmax(extent))
        self._order = np.argsort(self.points[:, self._axis], kind="stable")
        self._sorted = self.points[self._order]
        self._keys = self._sorted[:, self._axis].tolist()

    def within(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """(m,) int64 indices of the points at most ``radius`` from ``centre`` (3,)."""
        if self._tree is not None:
            return np.asarray(self._tree.query_ball_point(centre, radius, return_sorted=True), dtype=np.int64)
        middle = float(centre[self._axis])
        reach = _slab_reach(radius, abs(middle))  # the distance test below decides
        start = bisect_left(self._keys, middle - reach)
        stop = bisect_right(self._keys, middle + reach, lo=start)
        offset = self._sorted[start:stop] - centre
        near = self._order[start:stop][np.einsum("ij,ij->i", offset, offset) <= radius * radius]
        near.sort()
        return near


def _slab_reach(radius: float, largest: float) -> float:
    """How far from a centre a slab along one axis reaches to hold every point within ``radius``
    of it, coordinates up to ``largest`` in magnitude: a hair wider than the ball, so that the
    rounding of the slab's bounds never leaves out a point the distance test would accept."""
    return radius + (largest + radius) * 1e-9


def candidate_indices(
    index: PointIndex,
    landmark_xyz: np.ndarray,
    T_world_camera: np.ndarray,
    *,
    min_depth: float,
    max_depth: float,
    max_angle_rad: float,
    margin: float = 0.0,
    max_distance: float = np.inf,
) -> np.ndarray:
    """Indices (m,) of landmarks that may be visible from a camera.

    Parameters
    ----------
    index : ``PointIndex`` over ``landmark_xyz`` (L, 3), world frame.
    T_world_camera : (4, 4) the camera's pose.
    min_depth, max_depth : range of depth (camera z) in metres.
    max_angle_rad : largest angle between the optical axis and a visible landmark's direction.
    margin : metres the camera's position may be off: landmarks this close to the view (the depth
        range widened by it, the cone's apex moved back along the axis by ``margin / sin`` of its
        half-angle, which holds every point within ``margin`` of the cone) count too.
    max_distance : only landmarks within this distance of the camera's centre (+ ``margin``).
    """
    centre, axis = T_world_camera[:3, 3], T_world_camera[:3, 2]
    back = margin / np.sin(max_angle_rad) if margin > 0.0 else 0.0
    ball_centre, radius = view_cone_ball(centre - back * axis, axis, max_depth + margin + back, max_angle_rad)
    near = index.within(ball_centre, radius)
    if near.size == 0:
        return near
    p_camera = (landmark_xyz[near] - centre) @ T_world_camera[:3, :3]
    depth = p_camera[:, 2]
    off_axis = np.hypot(p_camera[:, 0], p_camera[:, 1])
    visible = (depth > min_depth - margin) & (depth < max_depth + margin) & (off_axis <= (depth + back) * np.tan(max_angle_rad))
    if np.isfinite(max_distance):
        visible &= np.einsum("ij,ij->i", p_camera, p_camera) <= (max_distance + margin) ** 2
    return near[visible]


def shift_agreement(shifts: np.ndarray, radius: float) -> np.ndarray:
    """How many pairs (counting itself) imply nearly the same shift of the robot as each pair.

    A pair (measured point p in the camera frame, landmark l) says the camera sits at
    ``l - R_wc p``: with the orientation about right, it implies that the robot is off its
    predicted position by ``l - (c + R_wc p)`` (c, R_wc: the predicted camera's centre and
    rotation). The right pairs of a pose all imply its one true shift; wrong pairs scatter theirs
    over the prior's spread. Under a wide prior, where a pair's own cost cannot tell them apart,
    the size of its crowd can (a Hough vote).

    shifts : (N, 3) the shift each pair implies; radius : how close two shifts must be to agree.
    Returns (N,) counts.
    """
    if shifts.shape[0] <= SCAN_MAX_SHIFTS:
        return _agreeing(shifts, shifts, radius)
    # more: the shifts sorted along their widest axis, each block of SCAN_MAX_SHIFTS compared with
    # the slab of that axis within the radius of it (no scipy import, as ``PointIndex``)
    axis = int(np.argmax(np.ptp(shifts, axis=0)))
    order = np.argsort(shifts[:, axis], kind="stable")
    ordered = shifts[order]
    keys = ordered[:, axis]
    reach = _slab_reach(radius, float(np.abs(keys).max()))
    counts = np.empty(shifts.shape[0], dtype=np.int64)
    for start in range(0, shifts.shape[0], SCAN_MAX_SHIFTS):
        block = ordered[start : start + SCAN_MAX_SHIFTS]
        low = int(np.searchsorted(keys, block[0, axis] - reach, side="left"))
        high = int(np.searchsorted(keys, block[-1, axis] + reach, side="right"))
        counts[order[start : start + SCAN_MAX_SHIFTS]] = _agreeing(block, ordered[low:high], radius)
    return counts


def _agreeing(shifts: np.ndarray, others: np.ndarray, radius: float) -> np.ndarray:
    """(N,) how many of ``others`` (M, 3) lie within ``radius`` of each of ``shifts`` (N, 3)."""
    offset = shifts[:, None, :] - others[None, :, :]
    return np.count_nonzero(np.einsum("ijk,ijk->ij", offset, offset) <= radius * radius, axis=1).astype(np.int64)


def view_cone_ball(apex: np.ndarray, axis: np.ndarray, depth: float, half_angle_rad: float) -> tuple[np.ndarray, float]:
    """The smallest ball holding the cone of a camera's view, (centre (3,), radius): the cone's
    apex at ``apex``, unit ``axis``, points up to ``depth`` along the axis and within
    ``half_angle_rad`` of it. A ball query's cost grows with the points the ball returns, and the
    ball around the apex that holds the cone holds 1.7x (57 deg) to 5x (30 deg) more.

    Up to 45 deg the ball passes through the apex and the base's rim (centre ``depth / (2
    cos^2)`` along the axis); wider, it is the base's rim ball, centred on the base.
    """
    half_angle_rad = min(half_angle_rad, np.radians(89.9))
    cos = np.cos(half_angle_rad)
    if cos * cos >= 0.5:
        along = depth / (2.0 * cos * cos)
        radius = along
    else:
        along = depth
        radius = depth * np.tan(half_angle_rad)
    return apex + along * axis, radius * (1.0 + 1e-9) + 1e-9  # a hair larger: points on the rim stay in


def pair_statistics(
    z: np.ndarray, R_obs: np.ndarray, z_hat: np.ndarray, HPH: np.ndarray, kinds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Squared Mahalanobis distance and negative log-likelihood of every (observation, candidate).

    Parameters
    ----------
    z : (n, 3) measurements; R_obs : (n, 3, 3) their covariances.
    z_hat : (m, 3) predicted measurements; HPH : (m, 3, 3) ``H P H'`` of each prediction.
    kinds : (n,) the measurements' kinds, whose angle rows' residuals are wrapped
        (``planar.wrap_residuals``); None: no angle.

    Returns
    -------
    d2 : (n, m) ``y' S^-1 y`` with ``S = H P H' + R`` and ``y = z - z_hat``.
    nll : (n, m) ``d2 + ln det S``.
    """
    S = HPH[None, :, :, :] + R_obs[:, None, :, :]
    y = z[:, None, :] - z_hat[None, :, :]
    if kinds is not None:
        y = planar.wrap_residuals(y, np.asarray(kinds)[:, None])
    d2, log_det = mahalanobis_3x3(S, y)
    return d2, d2 + log_det


def best_friends(
    cost: np.ndarray, d2: np.ndarray, *, gate: float | np.ndarray, margin: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual-best pairs that pass the gate and have no close rival.

    Parameters
    ----------
    cost : (n, m) pair costs (lower is better); d2 : (n, m) squared Mahalanobis distances.
    gate : accept only pairs with ``d2 <= gate`` (a chi^2 quantile; or (n, m), each pair's).
    margin : reject a pair when a rival in its row or column costs less than ``cost + margin``.

    Returns
    -------
    obs_index, cand_index : (p,) int arrays of accepted pairs.
    gap : (p,) how much more the closest rival of each pair costs (inf when there is none): the
        pair's confidence.
    """
    n, m = cost.shape
    if n == 0 or m == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0)
    rows = np.arange(n)
    best_cand = np.argmin(cost, axis=1)
    best_obs = np.argmin(cost, axis=0)
    best_cost = cost[rows, best_cand]
    mutual = best_obs[best_cand] == rows
    gated = d2[rows, best_cand] <= np.broadcast_to(gate, d2.shape)[rows, best_cand]
    gap = np.minimum(_runner_up(cost, axis=1), _runner_up(cost, axis=0)[best_cand]) - best_cost
    keep = mutual & gated & (gap >= margin)
    return rows[keep], best_cand[keep], gap[keep]


def _runner_up(cost: np.ndarray, *, axis: int) -> np.ndarray:
    """Second smallest value along an axis (inf when there is only one)."""
    if cost.shape[axis] < 2:
        return np.full(cost.shape[1 - axis], np.inf)
    return np.partition(cost, 1, axis=axis).take(1, axis=axis)


def assignment_margins(cost: np.ndarray, null_cost: np.ndarray, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much costlier the nearest alternatives to each chosen pair are: its confidence.

    For a pair (i, c) the alternatives are the single changes of the pose's assignment that undo
    it. ``row``: observation i takes another landmark or none. ``steal``: another observation i2
    takes landmark c (leaving what it has now) while i takes its next best; its margin is the row
    margin plus ``cost[i2, c] - current[i2]``. A margin of ``delta`` means the chosen pair is
    ``exp(delta / 2)`` times likelier than that alternative.

    Parameters
    ----------
    cost : (n, m) pair costs of the pose's observations against the candidates (2 x negative
        log-likelihood, inf where a pair fails the gate).
    null_cost : (n,) cost of leaving each observation unassigned.
    chosen : (n,) chosen candidate column of each observation, -1 when unassigned.

    Returns
    -------
    row, steal : (n,) margins; inf for unassigned observations and where no alternative exists.
    """
    n = cost.shape[0]
    rows = np.flatnonzero(chosen >= 0)
    columns = chosen[rows]
    current = null_cost.astype(float).copy()
    current[rows] = cost[rows, columns]
    row = np.full(n, np.inf)
    steal = np.full(n, np.inf)
    if rows.size == 0:
        return row, steal
    others = cost[rows].copy()
    others[np.arange(rows.size), columns] = np.inf
    row[rows] = np.minimum(null_cost[rows], others.min(axis=1)) - current[rows]
    # a rival gives up what it holds now, or less: any observation may go unassigned
    taking = cost[:, columns] - np.minimum(current, null_cost)[:, None]   # (n, p)
    taking[rows, np.arange(rows.size)] = np.inf                          # not itself
    rival = taking.min(axis=0)
    able = np.isfinite(rival)                                            # some rival could take it
    steal[rows[able]] = row[rows[able]] + rival[able]
    return row, steal


def restored_pairs(residuals: np.ndarray, H: np.ndarray, P: np.ndarray, R: np.ndarray, null_cost: np.ndarray) -> np.ndarray:
    """Which of the pairs the re-check dropped against leaving them unassigned to take back (d,):
    the subset whose joint cost under the posterior of the pairs kept (residuals (d, 3), Jacobians
    (d, 3, n) at its state, P its covariance, R (d, 3, 3) the noise association judges with: the
    stacked ``ekf.innovation_cost``, as the beam's explanations) plus the null costs of the rest is
    least (none restored on a tie). The re-check judges each pair by the others' posterior
    linearized, and its costs stop at the gate: a right pair where the prior is off, or with a
    partner as doubtful as itself (two rays, one a camera), fails it whatever leaving it costs.
    More than ``RESTORE_LIMIT`` pairs: none. The compiled twin is ``kernels.recheck.restored_pairs``."""
    d, n = residuals.shape[0], P.shape[0]
    best, best_mask = float(null_cost.sum()), 0
    if d > RESTORE_LIMIT:
        return np.zeros(d, dtype=bool)
    for mask in range(1, 1 << d):            # in increasing order, as the compiled twin
        chosen = np.array([(mask >> i) & 1 == 1 for i in range(d)])
        total = (ekf.innovation_cost(P, H[chosen].reshape(-1, n), R[chosen], residuals[chosen].reshape(-1))
                 + float(null_cost[~chosen].sum()))
        if total < best:
            best, best_mask = total, mask
    return np.array([(best_mask >> i) & 1 == 1 for i in range(d)])


def rival_margins(cost: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """How much costlier each chosen pair's nearest rival landmark is: the cheapest other
    candidate of its observation (not the null option) minus the pair's cost.

    ``assignment_margins``' row margin takes the cheaper of that rival and leaving the observation
    unassigned; this one looks at landmarks alone, for a ray (a pixel observation) that passes
    near several of them: a small margin says which of them it is is not known, whatever leaving
    it unassigned would cost.

    Parameters
    ----------
    cost : (n, m) pair costs (inf where a pair fails the gate).
    chosen : (n,) chosen candidate column of each observation, -1 when unassigned.

    Returns
    -------
    (n,) margins; inf for unassigned observations and where no other landmark gates.
    """
    margin = np.full(cost.shape[0], np.inf)
    rows = np.flatnonzero(chosen >= 0)
    if rows.size == 0 or cost.shape[1] < 2:
        return margin
    others = cost[rows].copy()
    others[np.arange(rows.size), chosen[rows]] = np.inf
    with np.errstate(invalid="ignore"):    # a chosen pair beyond its gate: inf - inf (its row margin drops it)
        margin[rows] = others.min(axis=1) - cost[rows, chosen[rows]]
    return margin


def leave_one_out_costs(
    z: np.ndarray, R_obs: np.ndarray, z_hat: np.ndarray, H: np.ndarray, chosen: np.ndarray,
    *, information: np.ndarray, gate: float, kinds: np.ndarray | None = None,
) -> np.ndarray:
    """Pair costs of every observation against every candidate, each observation judged by the
    posterior of all the other pairs (its own pair left out).

    After an update that used pair (i, c), the posterior has partly fitted observation i, so its
    costs there flatter the chosen landmark. Linearized at the posterior (the MAP, where the
    cost's gradient vanishes), leaving pair i out gives the information and correction

        L_i = information + sum_{j != i} H_j' R_j^-1 H_j,   L_i delta_i = -H_c' R_i^-1 (z_i - z_hat_c)

    and the candidates' predictions move to ``z_hat_j + H_j delta_i`` with
    ``S = H_j L_i^-1 H_j' + R_i``. Unpaired observations are judged against the full posterior.
    Information is summed from the prior, never subtracted from the posterior, so every L_i
    stays positive definite.

    Parameters
    ----------
    z : (n, 3) measurements; R_obs : (n, 3, 3) their covariances.
    z_hat : (m, 3), H : (m, 3, 6) candidates' predictions and Jacobians at the posterior.
    chosen : (n,) candidate column paired with each observation in the update, -1 for none.
    information : (6, 6) prior information (P_prior^-1) plus that of the update's pairs outside
        these observations (another camera's).
    gate : chi^2 gate on d^2; pairs beyond it cost inf.
    kinds : (n,) the measurements' kinds, for their angle rows (``planar.wrap_residuals``).

    Returns
    -------
    (n, m) costs ``d^2 + ln det S - ln det R`` (the beam's units), inf beyond the gate.
    """
    n, dim = z.shape[0], information.shape[0]
    kinds = np.zeros(n, np.int64) if kinds is None else np.asarray(kinds)
    paired = np.flatnonzero(chosen >= 0)
    Hc = H[chosen[paired]]                                            # (p, 3, n_x)
    HtRinv = ekf.solve(R_obs[paired], Hc).swapaxes(1, 2)             # (p, n_x, 3) H' R^-1
    J = HtRinv @ Hc                                                   # (p, n_x, n_x) each pair's information
    L_rows = np.broadcast_to(information + J.sum(axis=0), (n, dim, dim)).copy()
    rhs = np.zeros((n, dim))
    if paired.size:
        L_rows[paired] = information[None] + (J.sum(axis=0)[None] - J)   # the other pairs' information
        y_paired = planar.wrap_residuals(z[paired] - z_hat[chosen[paired]], kinds[paired])
        rhs[paired] = -(HtRinv @ y_paired[..., None])[..., 0]
    P_rows = ekf.solve(L_rows, np.broadcast_to(ekf.identity(dim), (n, dim, dim)))
    P_rows = 0.5 * (P_rows + P_rows.swapaxes(1, 2))
    delta = np.einsum("nij,nj->ni", P_rows, rhs)
    y = planar.wrap_residuals(z[:, None, :] - z_hat[None, :, :], kinds[:, None])
    residual = y - np.einsum("mij,nj->nmi", H, delta)  # (n, m, 3)

    # Screen before the (n, m) factorizations: every L_i >= information, so each S is at most
    # S_bound_j = H_j information^-1 H_j' + r_max I (r_max: the largest eigenvalue of any R_i),
    # and d^2 under S_bound is a lower bound on the true d^2. Pairs whose bound fails the gate
    # fail it for certain; only the few others are factored.
    P_bound = ekf.solve(information, ekf.identity(dim))
    r_max = float(np.linalg.eigvalsh(R_obs).max())
    S_bound = H @ P_bound @ H.swapaxes(1, 2) + r_max * np.eye(3)
    try:
        inverse_factor = np.linalg.solve(np.linalg.cholesky(S_bound), np.broadcast_to(np.eye(3), S_bound.shape))
    except np.linalg.LinAlgError:  # information too far beyond the prior's for rounding: no screen, judge every pair
        rows, columns = np.nonzero(np.ones(residual.shape[:2], dtype=bool))
    else:
        w_bound = np.einsum("mij,nmj->nmi", inverse_factor, residual)
        rows, columns = np.nonzero(np.einsum("nmi,nmi->nm", w_bound, w_bound) <= gate)

    cost = np.full((n, z_hat.shape[0]), np.inf)
    if rows.size == 0:
        return cost
    Hq = H[columns]
    S = Hq @ P_rows[rows] @ Hq.swapaxes(1, 2) + R_obs[rows]
    d2, log_det = mahalanobis_3x3(S, residual[rows, columns])
    cost[rows, columns] = np.where(d2 <= gate, d2 + log_det - np.linalg.slogdet(R_obs[rows])[1], np.inf)
    return cost


def seeded_explanation_costs(
    y: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    P: np.ndarray,
    pair_obs: np.ndarray,
    pair_landmark: np.ndarray,
    null_cost: np.ndarray,
    seeds: np.ndarray,
    *,
    gate: float,
) -> np.ndarray:
    """What a pose's whole explanation costs if each seed pair is taken first: for ranking seeds.

    Under a wide prior most observations gate many landmarks, and a pair's own cost says little
    about whether it is right. A right pair pins the pose, after which the other observations'
    right pairs fit well; a wrong pair leaves most of them unexplained. So each seed s is scored
    by the cost of explaining everything given s, linearized at the prior:

        cost_s + sum over the other observations i of min(null_i, min_q c_q|s)

    where q runs over i's pairs (not sharing s's landmark) and ``c_q|s = d^2 + ln det S - ln det R``
    of q's innovation conditioned on s (the Schur complement of the two pairs' joint innovation
    covariance, so ``d^2_s + d^2_q|s`` is their joint compatibility statistic). Observations do not
    compete for landmarks here: this ranks seeds, the beam then explains the best ones exactly.

    Parameters
    ----------
    y : (N, 3) innovation of every candidate pair; H : (N, 3, n) its Jacobian; R : (N, 3, 3) the
        observation's covariance (each pair may be in coordinates of its own: pixels and depth,
        or a camera-frame point); P : (n, n) the prior covariance.
    pair_obs, pair_landmark : (N,) the pair's observation (0..m-1) and landmark.
    null_cost : (m,) per observation.
    seeds : (M,) indices of the pairs to score.
    gate : chi^2 gate on a conditioned pair's d^2.

    Returns
    -------
    (M,) the approximate cost of each seed's explanation (lower is better).
    """
    seeds = np.asarray(seeds, dtype=np.int64)
    # in chunks of seeds: the work is (seeds x pairs) 3x3 blocks, which a dense pose with a few
    # thousand pairs would otherwise hold in memory all at once
    chunks = [seeds[i : i + SEED_CHUNK] for i in range(0, seeds.size, SEED_CHUNK)] or [seeds]
    HP = H @ P                                                    # (N, 3, n)
    S = HP @ H.swapaxes(1, 2) + R                                 # (N, 3, 3) each pair's own S
    log_det_R = np.linalg.slogdet(R)[1]                           # (N,)
    return np.concatenate([
        _seeded_explanation_costs(y, H, HP, S, pair_obs, pair_landmark, null_cost, log_det_R, chunk, gate=gate)
        for chunk in chunks
    ])


# Eight seeds a chunk keep a chunk's (pairs x seeds) arrays small enough to stay in cache on a dense
# pose: on 22 slip searches of a dense map with 4x odometry noise (up to 13,000 pairs and 320
# seeds), 3.3 s against 4.6 s with 16 and 5.4 s with 64, the costs equal to 3e-14.
SEED_CHUNK = 8


def _seeded_explanation_costs(y, H, HP, S, pair_obs, pair_landmark, null_cost, log_det_R, seeds, *, gate):
    """``seeded_explanation_costs`` for one chunk of seeds, given every pair's ``H P``, S and
    ``ln det R``."""
    N, M, n = y.shape[0], seeds.size, H.shape[-1]
    S_seed, y_seed = S[seeds], y[seeds]
    L_seed = np.linalg.cholesky(S_seed)
    # Conditioning on seed s: P_s = P - U_s U_s' with U_s = P H_s' L_s^-T (rank 3), and the
    # correction is K_s y_s = U_s L_s^-1 y_s. Both reach every pair through one matrix product.
    U = np.swapaxes(np.linalg.solve(L_seed, HP[seeds]), 1, 2)     # (M, n, 3)
    correction = (U @ np.linalg.solve(L_seed, y_seed[..., None]))[..., 0]  # (M, n)
    # (N, 3, M, 3) and (N, 3, M): pairs first, so that the components below are contiguous
    H_rows = H.reshape(N * 3, n)
    V = (H_rows @ U.transpose(1, 0, 2).reshape(n, M * 3)).reshape(N, 3, M, 3)   # H_q U_s
    moved = (H_rows @ correction.T).reshape(N, 3, M)                             # H_q K_s y_s
    S_cond = [S[:, i, j][:, None] - np.einsum("qsk,qsk->qs", V[:, i], V[:, j]) for i, j in sym3.UPPER]
    y_cond = [y[:, i][:, None] - moved[:, i] for i in range(3)]
    d2, log_det = _mahalanobis_sym3(*S_cond, *y_cond)
    d2, log_det = d2.T, log_det.T                                 # (M, N)
    cost = d2 + log_det - log_det_R[None]
    excluded = (d2 > gate) | (pair_landmark[None] == pair_landmark[seeds][:, None]) | (pair_obs[None] == pair_obs[seeds][:, None])
    cost = np.where(excluded, np.inf, cost)
    best = np.full((M, null_cost.size), np.inf)                   # per seed and observation
    np.minimum.at(best, (np.arange(M)[:, None], pair_obs[None]), cost)
    best = np.minimum(best, null_cost[None])
    best[np.arange(M), pair_obs[seeds]] = 0.0                     # the seed's own observation
    d2_seed, log_det_seed = mahalanobis_3x3(S_seed, y_seed)
    own = d2_seed + log_det_seed - log_det_R[seeds]
    return own + best.sum(axis=1)


def mahalanobis_3x3(S: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``y' S^-1 y`` and ``ln det S`` for stacks of symmetric positive definite 3x3 matrices, in
    closed form (adjugate and determinant) so that a million of them cost a few array passes
    instead of a LAPACK call each. Its relative error is about cond(S) x 1e-16; the gates' S (a
    prediction's spread plus the sensor's noise) stay far from singular.

    S : (..., 3, 3); y : (..., 3). Returns two (...) arrays, both inf where rounding left S without
    a positive determinant (its pair fits nothing). Reads only the upper triangle.
    """
    return _mahalanobis_sym3(S[..., 0, 0], S[..., 0, 1], S[..., 0, 2], S[..., 1, 1], S[..., 1, 2], S[..., 2, 2],
                             y[..., 0], y[..., 1], y[..., 2])


def _mahalanobis_sym3(a, b, c, d, e, f, y1, y2, y3):
    """``mahalanobis_3x3`` from the components of S = [[a, b, c], [b, d, e], [c, e, f]] and y."""
    A11, A12, A13, A22, A23, A33, det = sym3.adjugate(a, b, c, d, e, f)
    quadratic = A11 * y1 * y1 + A22 * y2 * y2 + A33 * y3 * y3 + 2.0 * (A12 * y1 * y2 + A13 * y1 * y3 + A23 * y2 * y3)
    with np.errstate(divide="ignore", invalid="ignore"):
        d2, log_det = quadratic / det, np.log(det)
    # an S that rounding left without a positive determinant (information matrices many orders of
    # magnitude apart) is no spread at all: its pair fits nothing, rather than a NaN or negative d^2 passing a gate
    broken = ~(det > 0.0)
    if broken.any():
        d2, log_det = np.where(broken, np.inf, d2), np.where(broken, np.inf, log_det)
    return d2, log_det
