"""Joint compatibility over one pose's pairs, for the mapping localizer (``camloc.slam_run``).

Per pose: each observation's candidates (landmarks within its own chi^2 gate, with their
innovation y, Jacobian H on the filter's error, and the covariance of a landmark held outside the
state) are searched depth first for the largest set of pairs that is **jointly** compatible
(Neira & Tardos 2001: the stacked innovation's Mahalanobis distance within the chi^2 gate of
its dimension), ties broken by the lower joint cost. Jointly means through the shared pose error:
two pairs that each fit alone but pull the pose two ways do not fit together, which is what keeps
a wrong pair of a poorly predicted pose out (the per-pose least-cost assignment took such pairs).
The search stops after ``max_nodes`` nodes and keeps the best set found. Without a map a pair
over its cost limit alone may be kept in a set of three or more where its cost given the others
is within it (``joint_pairs``): a loop closure's returns, each alone paying the pose's spread.

``PoseAssociation`` (a mix-in of the mapping localizer) gathers each observation's candidates
among the landmarks in view and runs that search. Every ``H P H'`` here is taken from the columns
the Jacobians touch (the pose and the candidates' landmarks), never from the whole state.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Optional

import numpy as np

from camloc import measurement, slam
from camloc.association import mahalanobis_3x3
from camloc.dataset import landmark_kind_of
from camloc.planar import wrap_residuals
from camloc.slam_landmarks import TENTATIVE_GAP, UNPAIRED, kept_longer, places_point, with_state_estimates
from camloc.tails import chi2_quantile


@dataclass(frozen=True)
class Candidate:
    """One gated pair: observation index, landmark (table index), innovation y (3,), Jacobian
    H (3, n), the extra covariance (3, 3) of a landmark outside the state (zeros: in it or exact),
    the observation's noise R (3, 3), its degrees of freedom, its cost alone and the sensor that
    made the observation (each sensor sees a landmark once a pose; two cameras, twice)."""

    obs: int
    landmark: int
    y: np.ndarray
    H: np.ndarray
    extra: np.ndarray
    R: np.ndarray
    dof: int
    cost: float
    sensor: int = 0
    # the cost the pair must stay within, alone or given the other pairs of its set (``joint_pairs``;
    # inf: no such test, the pair taken as ``jcbb`` takes it)
    limit: float = float("inf")
    alone: bool = True  # may be taken on its own cost (False: only given the others)


def joint_distance(P: np.ndarray, pairs: list[Candidate]) -> float:
    """The stacked innovation's squared Mahalanobis distance ``y' S^-1 y`` with
    ``S = H P H' + blockdiag(R_i + extra_i)`` (the plain statement of what ``jcbb`` computes from
    its precomputed blocks)."""
    S, y = stacked_innovation(P, pairs)
    return float(y @ np.linalg.solve(S, y))


def stacked_innovation(P: np.ndarray, pairs: list[Candidate]) -> tuple[np.ndarray, np.ndarray]:
    """The pairs' stacked innovation covariance ``S = H P H' + blockdiag(R_i + extra_i)`` (3p, 3p)
    and innovation y (3p,); ``H P H'`` over the state's columns some pair's H reads."""
    H = np.vstack([c.H for c in pairs])
    cols = np.flatnonzero(np.any(H != 0.0, axis=0))
    S = H[:, cols] @ P[np.ix_(cols, cols)] @ H[:, cols].T
    for i, c in enumerate(pairs):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] += c.R + c.extra
    return S, np.concatenate([c.y for c in pairs])


@lru_cache(maxsize=256)
def _gate(dof: int, probability: float) -> float:
    return chi2_quantile(dof, 1.0 - probability)


def _gate_at_tail(dofs: np.ndarray, tail: float) -> np.ndarray:
    """The chi^2 gates (M,) of ``dofs`` (M,) at ``tail``."""
    return np.array([_gate(int(d), 1.0 - tail) if d else 0.0 for d in np.asarray(dofs).tolist()])


def jcbb(P: np.ndarray, candidates: list[list[Candidate]], probability: float, max_nodes: int = 2000) -> list[Candidate]:
    """The largest jointly compatible set of pairs (one candidate or none per observation, each
    landmark once per sensor), ties by the lower sum of the pairs' own costs. Every candidate's H P H' block
    against every other's is computed once (``H P H'`` over all of them), so that a node's joint
    test costs what its few pairs do, not the state's size."""
    with_options = [options for options in candidates if options]
    if len(with_options) == 1:
        # one observation with candidates (most poses under an exact map): the search takes its
        # cheapest (the first of the cheapest: a stable sort's), with no joint test to make
        return [min(with_options[0], key=lambda c: c.cost)]
    return jcbb_search(P, candidates, probability, max_nodes)


def jcbb_search(P: np.ndarray, candidates: list[list[Candidate]], probability: float, max_nodes: int = 2000) -> list[Candidate]:
    """``jcbb``'s depth-first search (every case: ``jcbb`` answers a lone observation itself)."""
    order = sorted(range(len(candidates)), key=lambda i: (len(candidates[i]) == 0, len(candidates[i])))
    lists = [sorted(candidates[i], key=lambda c: c.cost) for i in order]
    flat = [c for options in lists for c in options]
    if not flat:
        return []
    slot = {id(c): n for n, c in enumerate(flat)}
    H = np.vstack([c.H for c in flat])
    cols = np.flatnonzero(np.any(H != 0.0, axis=0))  # the pose and the candidates' landmarks: not the whole state
    H = H[:, cols]
    cross = H @ P[np.ix_(cols, cols)] @ H.T  # (3C, 3C): every pair of candidates' H P H'
    for n, c in enumerate(flat):
        cross[3 * n:3 * n + 3, 3 * n:3 * n + 3] += c.R + c.extra
    y_all = np.concatenate([c.y for c in flat])
    best: list[Candidate] = []
    best_cost = np.inf
    nodes = 0
    # a node's rows of cross and its degrees of freedom are its parent's and one pair's (the search
    # visits up to max_nodes nodes a pose: under a prior, most of a 20,000-pose run's time)
    block_rows = [np.arange(3 * n, 3 * n + 3) for n in range(len(flat))]
    remaining_from = np.cumsum([bool(rest) for rest in lists[::-1]])[::-1].tolist() + [0]  # lists not empty from depth on

    def compatible(rows: np.ndarray, dof: int) -> bool:
        y = y_all[rows]
        d2 = float(y @ np.linalg.solve(cross[rows[:, None], rows], y))
        return d2 <= _gate(dof, probability)

    def search(depth: int, chosen: list[Candidate], used: set, cost: float, rows: np.ndarray, dof: int) -> None:
        nonlocal best, best_cost, nodes
        nodes += 1
        remaining = remaining_from[depth]
        if len(chosen) + remaining < len(best) or (len(chosen) + remaining == len(best) and cost >= best_cost) or nodes > max_nodes:
            return
        if depth == len(lists):
            if len(chosen) > len(best) or (len(chosen) == len(best) and cost < best_cost):
                best, best_cost = list(chosen), cost
            return
        for c in lists[depth]:
            if (c.landmark, c.sensor) in used:
                continue
            trial_rows, trial_dof = np.concatenate([rows, block_rows[slot[id(c)]]]), dof + c.dof
            if chosen and not compatible(trial_rows, trial_dof):
                continue
            search(depth + 1, chosen + [c], used | {(c.landmark, c.sensor)}, cost + c.cost, trial_rows, trial_dof)
        search(depth + 1, chosen, used, cost, rows, dof)

    search(0, [], set(), 0.0, np.zeros(0, np.int64), 0)
    return best


def conditional_costs(P: np.ndarray, pairs: list[Candidate]) -> np.ndarray:
    """(p,) each pair's cost given the other pairs of the set: ``J(set) - J(set without it)`` with
    ``J = y' S^-1 y + ln det S - sum ln det R`` over the stacked pairs (``stacked_innovation``), in
    the units of a pair's own cost (for a set of one, its own cost). Against the observation's
    null cost it is the likelihood ratio of "this pair" over "clutter or a new landmark" given the
    rest of the set: where the pairs share an uncertain pose, each one alone pays that pose's
    spread in its ``ln det S``, and the set pays it once."""
    p = len(pairs)
    if p == 1:
        return np.array([pairs[0].cost])
    S, y = stacked_innovation(P, pairs)

    def j(rows: np.ndarray) -> float:
        block = S[np.ix_(rows, rows)]
        return float(y[rows] @ np.linalg.solve(block, y[rows]) + np.linalg.slogdet(block)[1])

    every = np.arange(3 * p)
    whole = j(every)
    out = np.empty(p)
    for i, c in enumerate(pairs):
        own = every[3 * i:3 * i + 3]
        # J(set) - J(set \ i) - J(i) + cost_i: the ln det R of the others cancels, pair i's is in its cost
        out[i] = whole - j(np.delete(every, own)) - j(own) + c.cost
    return out


def joint_pairs(P: np.ndarray, candidates: list[list[Candidate]], probability: float,
                max_nodes: int = 2000) -> list[Candidate]:
    """``jcbb``'s set with every pair within its ``limit``, alone (its own cost) or, in a set of
    ``JOINT_MIN`` pairs or more, ``JOINT_MARGIN`` within it given the others
    (``conditional_costs``): while one is over both, the pair most over stops being a candidate
    and the search runs again. Pairs with no limit are taken as ``jcbb`` takes them; a pair not
    ``alone`` only given the others. (Two pairs can agree by chance: among landmarks a few tenths
    of a metre apart, seen from a pose unsure by as much, wrong pairs that vouched for each other
    were 6 of the 18 taken so in sets of two, 4 of 33 in sets of three or more, on 16 100-pose grid
    worlds.)"""
    candidates = [list(options) for options in candidates]
    while True:
        chosen = jcbb(P, candidates, probability, max_nodes)
        limits = np.array([c.limit for c in chosen])
        if not np.any(np.isfinite(limits)):
            return chosen
        excess = np.array([c.cost - c.limit if c.alone else np.inf for c in chosen])
        if len(chosen) >= JOINT_MIN:  # each within its limit alone or given the others
            excess = np.minimum(excess, conditional_costs(P, chosen) + JOINT_MARGIN - limits)
        worst = int(np.argmax(excess))
        if excess[worst] < 0.0:
            return chosen
        candidates = [[c for c in options if c is not chosen[worst]] for options in candidates]


# A pair is ambiguous where another jointly compatible set as large explains its observation
# otherwise at a cost at most this much higher (the best less than e^(9.2 / 2) = 100 times as
# likely): neither is taken (``unambiguous``).
AMBIGUITY_MARGIN = 2.0 * float(np.log(100.0))


def unambiguous(P: np.ndarray, candidates: list[list[Candidate]], chosen: list[Candidate], probability: float,
                margin: float, obs_sensor: np.ndarray, max_nodes: int = 2000, search=None) -> list[Candidate]:
    """The pairs of ``chosen`` (``jcbb``'s set) that no other jointly compatible set explains
    otherwise: a pair is left out where the best set without it is as large and costs at most
    ``margin`` more, unless that set gives its landmark an observation of another sensor
    (``obs_sensor`` (K,): each observation's; two cameras seeing one landmark give it two
    observations, one sensor cannot). What is left is a subset of a jointly compatible set, so
    jointly compatible. ``search``: the search of the other sets (``jcbb`` by default; the one
    that made ``chosen``). (Measured against it: leaving out only a pair whose observation the other
    set pairs otherwise, 74 landmarks added twice on 8 planar points worlds against 38; without
    the exception, a still robot's two pixel cameras' landmark was never updated, 0.15 m of spread
    after 40 views.)"""
    total = sum(c.cost for c in chosen)
    kept = []
    for c in chosen:
        without = [[option for option in options if option is not c] for options in candidates]
        alternative = jcbb(P, without, probability, max_nodes) if search is None else search(P, without, probability, max_nodes)
        # (a set that gives the landmark another sensor's observation instead is no doubt about it)
        otherwise = not any(a.landmark == c.landmark and obs_sensor[a.obs] != obs_sensor[c.obs] for a in alternative)
        if not otherwise or len(alternative) < len(chosen) or sum(a.cost for a in alternative) > total + margin:
            kept.append(c)
    return kept


# Without a map a pair must be likelier than clutter (its cost below the observation's null cost)
# to be tried: JCBB takes the largest jointly compatible set, so any pair tried that fits is taken.
# (Pairs up to _NULL_SLACK costlier than clutter were tried for added landmarks; with no map such
# a pair, less likely than clutter, moved the robot 0.7-1.1 m on two of 24 worlds measured, planar
# points seed 3 at pose 159 and grid seed 1 at pose 106, and the map seen before no longer fitted
# where the robot came back to it: landmarks were added twice.) With a map, added landmarks keep
# the slack (``PoseAssociation._slack``): the odds below e^-10 / 2.
_NULL_SLACK = 20.0
# Without a map, a landmark unseen for more than RETURN_GAP poses is paired again only where the
# pair is RETURN_PENALTY likelier than clutter (its cost that much below the null cost). Why: a
# return after a gap is where the wrong pairs were, most of them an observation of a landmark not
# yet mapped paired with a neighbour (an unexplained observation is far likelier to be a new
# landmark than rare clutter there, and the drift since the last view spreads the gate over the
# neighbours). Pairs made by the old rules, wrong of all (300-pose grid worlds, seeds 0-3): with
# landmarks unseen 20 poses or more and a cost within 4 of the null cost, 17 of 27 (10-19 poses:
# 10 of 15); with landmarks unseen under 10 poses, 61 of 1,338. Measured (docs/performance.md, 2026-12-05, "No map on sparse worlds"):
# gaps 10, 20, 30 and penalties 2, 4 (and 2 on every pair): 20 and 4 kept; landmarks added twice
# on 300-pose worlds fell on every kind; the 100-pose grid worlds (the real file's kind) lost 2-6%
# of RMSE with each setting, the loop closures refused among them mostly right.
RETURN_GAP = 20
RETURN_PENALTY = 4.0
# Without a map, a point's pair up to JOINT_SLACK costlier than its limit alone (the null cost,
# RETURN_PENALTY below it after RETURN_GAP) is tried too, and kept where, in a set of JOINT_MIN
# pairs or more, its cost given the pose's other pairs is JOINT_MARGIN within the limit
# (``joint_pairs``). Why: where the robot comes back to a place seen long ago its pose is unsure by
# as much as the landmarks are apart, each return alone pays that spread in its ln det S, and every
# return of the loop closure was refused together (a 100-pose grid world: 5-8 returns a pose, each
# 0.5-3.5 over its limit alone, 10-14 under it given the others; 0.79 m after an SE(3) alignment
# against the true association's 0.21). Two pairs can agree by chance, and the set the search
# found is the best of many: wrong pairs taken so were 6 of 18 in sets of two, and within 3 of
# their limits given the others on the whole (right ones mostly 4-14 within). Measured on 72
# 100-pose worlds and 300-pose ones (docs/performance.md, 2026-12-05, "No map: a loop closure's
# returns judged together").
JOINT_SLACK = 4.0
JOINT_MIN = 3
JOINT_MARGIN = 3.0
# Under a prior, an observation the beam left out is tried against the map's landmarks again (one
# may have moved) where the pair is likelier than clutter, and only against a landmark the beam has
# not paired within BEAM_RECENT poses but missed where it was surely in view: one it pairs is where
# the map says, and an observation left near it is of another landmark or clutter (on simulated worlds: moved landmarks' error 0.09-0.13 m after the
# run instead of 0.28 m, and half-withheld maps' RMSE within 4% of never trying the map again).
BEAM_RECENT = 30
BEAM_MISSES = 1  # ... and that the beam left out at least this many times where it was surely in view


class PoseAssociation:
    """The mapping localizer's association of one pose's observations (a mix-in of
    ``slam_run.MappingLocalizer``, whose state it reads: ``x``, ``P``, ``table``, ``sensors``,
    the beam's pairs): the candidates in view, their costs, and JCBB among them."""

    def _associated(self, obs: np.ndarray, added_only: bool = False, k: int = 0) -> list[tuple[int, int]]:
        """The pose's (observation, table index) pairs: the largest jointly compatible set among
        the landmarks in view (``slam_association.jcbb``; ``added_only``: the added ones), each
        observation free to stay unassigned."""
        if obs.size == 0:
            return []
        self._sync_positions()
        nearby = self.table.in_range(self.x.t, self.reach, None if added_only else self.mapped_index)
        if self.given_pairs is not None and not added_only:
            mapped = nearby < self.table.num_mapped
            trusted = np.zeros(nearby.size, bool)
            trusted[mapped] = ((self.beam_paired_at[nearby[mapped]] >= k - BEAM_RECENT)
                               | (self.beam_missed[nearby[mapped]] < BEAM_MISSES))
            nearby = nearby[~trusted]
        candidates = self._candidates(obs, nearby, k)
        if not any(candidates):
            return []
        chosen = joint_pairs(self.P, candidates, self.config.gate)
        if self.config.map == "none":  # without a map JCBB alone holds the robot (with one, the beam's pairs do)
            chosen = unambiguous(self.P, candidates, chosen, self.config.gate, AMBIGUITY_MARGIN, self.obs_sensor,
                                 search=joint_pairs)
        for c in chosen:
            if self.table.tentative[c.landmark]:
                self.table.score[c.landmark] += 0.5 * (self.null_cost[c.obs] - c.cost)
        return [(c.obs, c.landmark) for c in chosen]

    def _candidates(self, obs: np.ndarray, nearby: np.ndarray, k: int) -> list[list[Candidate]]:
        """Each observation's candidates among the landmarks ``nearby`` at pose k: their pairs
        within the gate, at most ``_slack`` costlier than clutter."""
        candidates: list[list[Candidate]] = []
        for sensor_id in np.unique(self.obs_sensor[obs]).tolist():
            mine = obs[self.obs_sensor[obs] == sensor_id]
            gated = self.landmark_costs(sensor_id, mine, nearby)
            if gated is None:
                continue
            landmarks, cost, z_hat, H, extra = gated
            cost = self._orientation_costs(mine, landmarks, cost, z_hat, H, extra)  # a tag's judged with its orientation
            placed = places_point(self.sensors[sensor_id].kind)
            slack = self._slack(landmarks, placed, k)
            # without a map a point's pair may also be judged given the pose's other pairs
            # (``joint_pairs``): tried up to JOINT_SLACK over its limit alone
            joint = self.config.map == "none" and placed and JOINT_SLACK > 0.0
            tried = slack + JOINT_SLACK if joint else slack
            # a tentative landmark unseen for TENTATIVE_GAP poses: only given the others, past the
            # return penalty (``slam_landmarks.TENTATIVE_KEEP``)
            stale = (self.table.tentative[landmarks] & (self.table.last_seen[landmarks] < k - TENTATIVE_GAP)
                     & kept_longer(self.config.map, self.table.kind[landmarks])) if joint else np.zeros(landmarks.size, bool)
            for i, o in enumerate(mine.tolist()):
                limits = self.null_cost[o] + np.where(stale, -RETURN_PENALTY, slack) if joint else np.full(slack.shape, np.inf)
                candidates.append([Candidate(o, int(landmarks[j]), self._innovation(o, z_hat[j], sensor_id), H[j], extra[j],
                                             self.association_cov[o], int(self.obs_dof[o]), float(cost[i, j]), int(sensor_id),
                                             float(limits[j]), not bool(stale[j]))
                                   for j in np.flatnonzero(cost[i] < self.null_cost[o] + tried).tolist()])
        return candidates

    def _slack(self, landmarks: np.ndarray, placed: bool, k: int) -> np.ndarray:
        """(C,) how much costlier than clutter a pair with each of ``landmarks`` may be and still be
        tried: nothing without a map for an observation that places its point (``placed``: with
        range, or a planar robot's), nor for a tentative landmark, nor for a mapped one where the
        beam already judged the map's pairs (it left this observation out); ``_NULL_SLACK`` for
        the other landmarks of a run with a map (there the beam's pairs hold the robot, and these
        rules were measured without one: with the three rules a prior's run lost the robot on 2
        of 24 worlds with half the map withheld) and for a ray (a still robot's two pixel
        cameras: the landmark's NEES over 20 seeds 4.09 with it, 4.99 without, the bound 4.16).
        Nor for an added landmark under an exact map whose pairs the beam gave (it lacks landmarks,
        so what the beam left is mostly their first sightings): with the slack, where the doubt
        in the beam's pairs had widened the pose (``lacking_spread``), an observation of a landmark
        not yet added was paired with an added one 1.4 m away (a 300-pose smooth3d world: mean NEES
        8.5 -> 17.3; docs/performance.md, 2026-12-05)."""
        if self.config.map == "none" and placed:
            return np.where(self.table.last_seen[landmarks] < k - RETURN_GAP, -RETURN_PENALTY, 0.0)
        given = self.given_pairs is not None
        if given and placed and self.config.map == "exact":
            return np.zeros(landmarks.size)
        strict = self.table.tentative[landmarks] | ((landmarks < self.table.num_mapped) & given)
        return np.where(strict, 0.0, _NULL_SLACK)

    def _innovation(self, o: int, z_hat: np.ndarray, sensor_id: int) -> np.ndarray:
        """Observation o's innovation against the prediction z_hat (a marker's heading wrapped)."""
        y = self.dataset.obs_z[o] - z_hat
        return wrap_residuals(y, measurement.MARKER) if self.sensors[sensor_id].kind == measurement.MARKER else y

    def _count_beam_misses(self, k: int) -> None:
        """The map's landmarks surely in view (``sure_view``) that the beam did not pair at pose k
        miss once more (``beam_missed``)."""
        if (self.sure_view is None and self.floor_view is None) or self.mapped_index is None:
            return
        far = max(view[1] for view in (self.sure_view, self.floor_view) if view is not None)
        nearby = self.mapped_index.within(self.x.t, far + 1.0)
        in_view = self._in_sure_view(nearby, self.table.xyz[nearby])
        missed = nearby[in_view & (self.beam_paired_at[nearby] != k)]
        self.beam_missed[missed] += 1

    def _sync_positions(self) -> None:
        """The table's positions of the landmarks in the state, for the search by place."""
        if self.state_landmark and self.x.orientation is not None:  # a tag's orientation rows are not positions
            position = ~self.x.orientation
            self.table.xyz[np.array(self.state_landmark)[position]] = self.x.L[position]
        elif self.state_landmark:
            self.table.xyz[np.array(self.state_landmark)] = self.x.L

    def landmark_costs(self, sensor_id: int, obs: np.ndarray, nearby: np.ndarray, tail: Optional[float] = None):
        """(candidates (C,), costs (O, C), predictions (C, 3), Jacobians (C, 3, n), the extra
        covariance (C, 3, 3) of a landmark held outside the state) of observations ``obs`` of one
        sensor against the landmarks of ``nearby`` in its view; costs ``UNPAIRED`` outside the
        gate. None: no candidate. ``tail``: gate at this tail where it is wider than the
        association's, every landmark in front of the sensor within its reach taken as in view
        (whether an observation could be of a landmark already known: ``_unexplained``)."""
        sensor = self.sensors[sensor_id]
        if self.dataset.planar:  # a planar robot's point sensor sees the floor's points, its marker sensor markers, a camera the others
            nearby = nearby[self.table.kind[nearby] == landmark_kind_of(sensor.kind)]
        if nearby.size == 0:
            return None
        rows = self.table.state_row[nearby]
        xyz = with_state_estimates(self.table.xyz, self.table.state_row, nearby, self.x.L)
        near, far, cos_angle, planar_far = max(self.min_depth, 1e-6), self.max_depth, np.cos(self.max_angle), self.planar_range
        gates = self._position_gates(obs)
        if tail is not None:  # any landmark in front of the sensor within its reach, at the wider gate
            near, far, cos_angle, planar_far = 1e-6, self.reach, 0.0, self.reach
            gates = np.maximum(gates, _gate_at_tail(self.obs_dof[obs], tail))
        if self.compiled is not None:  # the same costs compiled (camloc.slam_compiled); this numpy one is its reference
            seen, z_hat, H, extra, cost = self.compiled.costs(
                self.x, self.P, xyz, rows, self.table.cov[nearby], sensor_id, near, far, cos_angle, self.dataset.obs_z[obs],
                self.association_cov[obs], self.log_det_R[obs], gates, UNPAIRED)
            return (nearby[seen], cost, z_hat, H, extra) if np.any(seen) else None
        p_camera = slam.camera_points(self.x, sensor, xyz)
        norm = np.linalg.norm(p_camera, axis=1)
        if sensor.kind in measurement.PLANAR_KINDS:  # within the sensor's reach on the floor, any bearing (its view is not in the file)
            seen = np.hypot(p_camera[:, 0], p_camera[:, 1]) <= planar_far
        else:
            seen = (p_camera[:, 2] > near) & (p_camera[:, 2] <= far) & (p_camera[:, 2] >= cos_angle * norm)
        if not np.any(seen):
            return None
        candidates, xyz = nearby[seen], xyz[seen]
        rows = self.table.state_row[candidates]
        z_hat, H = slam.observe(self.x, sensor, xyz, rows)
        S = column_products(H, self.P)
        extra = np.zeros_like(S)
        outside = rows < 0
        if np.any(outside):  # a landmark outside the state adds its own covariance (zero: exact)
            A = -H[outside, :, 0:3]
            extra[outside] = A @ self.table.cov[candidates[outside]] @ np.swapaxes(A, 1, 2)
        S = S + extra
        y = wrap_residuals(self.dataset.obs_z[obs][:, None, :] - z_hat[None, :, :], sensor.kind)
        S_pair = S[None, :, :, :] + self.association_cov[obs][:, None, :, :]
        d2, log_det = mahalanobis_3x3(S_pair, y)
        cost = d2 + log_det - self.log_det_R[obs][:, None]
        return candidates, np.where(np.isfinite(cost) & (d2 <= gates[:, None]), cost, UNPAIRED), z_hat, H, extra


def column_products(H: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``H_i P H_i'`` (C, b, b) of Jacobians H (C, b, n) from the columns any of them touches (the
    pose and a few landmarks of the state): O(C k^2), not O(C n^2)."""
    cols = np.flatnonzero(np.any(H != 0.0, axis=(0, 1)))
    H_cols = H[:, :, cols]
    return H_cols @ P[np.ix_(cols, cols)] @ np.swapaxes(H_cols, 1, 2)
