"""Beam search over association hypotheses: the association that does not lock onto a wrong
alignment when the filter's uncertainty is larger than the spacing of landmarks.

A hypothesis is a filter (x, P) plus the assignments that produced it and their cost, twice the
negative log-likelihood of everything it has explained. At each pose every hypothesis is
predicted with the odometry; then each of the pose's observations either stays unassigned (a
fixed ``null_cost``, what a clutter detection costs) or pairs with a landmark whose prediction
gates it. Explaining observations one at a time, conditioning on each pair before looking at the
next, sums by the chain rule to the joint likelihood of the stacked innovation:

    cost += d^2 + ln det S - ln det R        for a pair (d^2 = y' S^-1 y)
    cost += null_cost                        for an unassigned observation

``ln det S - ln det R`` charges a pair for the spread of its prediction, so that a vague
hypothesis does not win by gating everything. Each pair is judged in the coordinates where its
linearization at the hypothesis explains it best, the measured (u, v, depth) or the camera-frame
point they back-project to (``BeamSearch._in_best_coordinates``): a point is linear in the
robot's position, so with noisy odometry in a dense map a right landmark predicted decimetres off
still gates there while its pixels have bent out of the gate.

Keeping it fast (most poses are not ambiguous):
- a hypothesis branches on an observation only into the options within ``branch_delta`` of that
  observation's best option; the observations with a single such option, whose landmark no other
  observation could take, are taken in one stacked update (the same cost, computed jointly), and
  only the ambiguous rest are explained one by one, each re-gated under the hypothesis conditioned
  on the pairs before it among its pool of nearby landmarks (no new search of the map);
- after each pose the beam keeps the ``beam_width`` cheapest hypotheses within ``beam_delta`` of
  the best, and merges hypotheses whose states coincide (within ``merge_sigma`` standard
  deviations on every axis), so in unambiguous stretches it collapses to one filter;
- where every observation of a pose is ambiguous (large measurement noise in a dense map) the
  partial explanations grown from all the beam's hypotheses share a budget of ``partial_budget``
  (``BeamSearch._explain_all``), instead of beam_width each.

Robustness to odometry slips: when the best hypothesis leaves most of a pose's observations
unassigned (at least two observations, more than half of them, and more than the recent poses'
share of unassigned observations makes likely: clutter), the pose is explained again from
that hypothesis' prediction with its covariance inflated ``slip_inflation`` times, at an extra
``slip_cost``, grown from each of a few seed pairs in turn (one right pair pins the pose, and the
rest follow); if the odometry really slipped, that hypothesis explains the observations and wins.
The same seeded explanation is tried from the prediction as it is, without the slip's inflation
and cost: where the odometry is merely noisy and the map dense, explaining the observations one
by one can lock onto a shifted alignment that a right seed pair avoids. Seeds are ranked by the
cost of the whole explanation each implies (``association.seeded_explanation_costs``), not by
their own cost, which under a wide prior barely separates right pairs from wrong ones in a dense
map. The pairs ranked are the individually cheapest and those whose implied shift of the robot
the most other pairs share (``association.shift_agreement``, a Hough vote: a pose's right pairs
all imply its one true shift), found among the landmarks within three standard deviations of the
predicted view, not only in it.

The beam returns the association of the best final hypothesis; the localizer then runs its
ordinary filter with those pairs (stacked, iterated updates), so that the estimate, covariance and
NIS are computed exactly as for any other association method. Per pose these are the pairs a
per-pose method of ``camloc.associators`` returns, ``(observation indices, landmark rows)``, but
the beam is not one of them: a pose's pairs are final only once the poses after it have
confirmed them (every hypothesis left descends from one there), so it searches the whole run and
the localizer looks each pose's pairs up in its result.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Callable, NamedTuple, Optional, Protocol

import numpy as np

from camloc import association, ekf, geometry, measurement, models
from camloc.kernels.beam_settings import MISS_COST, SLIP_MIN_OBSERVATIONS
from camloc.tails import binomial_tail, chi2_quantile

if TYPE_CHECKING:
    from camloc.associators import CameraModel
    from camloc.dataset import Dataset
    from camloc.filters import EulerFilter, SE3Filter


# A seeded explanation whose state leaves its prior's 99.9% region is dropped (``BeamSettings.state_gate``,
# ``BeamSearch._within_prior``): the chi^2 quantile with 6 degrees of freedom.
STATE_GATE = float(chi2_quantile(6, 0.001))


@dataclass(frozen=True)
class BeamSettings:
    """Parameters of the beam (costs are 2 x negative log-likelihoods).

    beam_width : hypotheses kept after each pose.
    beam_delta : drop hypotheses this much costlier than the best.
    branch_delta : options of an observation this much costlier than its best are not explored.
    merge_sigma : hypotheses whose states differ by less than this many standard deviations on
        every axis are merged (the cheaper kept).
    slip_inflation, slip_cost : covariance factor and cost of the odometry-slip hypothesis.
    slip_candidates : how many of its individually cheapest pairs the slip hypothesis ranks as
        first pairs (by the cost of the explanation each implies).
    slip_seeds : how many of the best ranked it explains in full.
    seed_explanations : how many of each seed's cheapest explanations it keeps. One pose may not
        tell the right explanation from one that pairs a clutter detection the right one leaves
        unassigned (a few cost units apart); the poses after it do, if both are kept.
    partial_budget : most partial explanations of a pose kept across all the beam's hypotheses,
        past each one's own best (``BeamSearch._explain_all``).
    state_gate : a seeded explanation whose state is further than this from its prior (its
        squared Mahalanobis distance, 6 dof) is dropped (``BeamSearch._within_prior``); inf keeps
        every one.
    miss_cost : what an explanation pays for each landmark near a pixel observation's ray, within
        the range where a camera surely detects what it sees (``detection_range``), that it
        leaves unclaimed (``BeamSearch._missed``); 0: no such term.
    """

    beam_width: int = 16
    beam_delta: float = 14.0
    branch_delta: float = 8.0
    merge_sigma: float = 0.3
    slip_inflation: float = 25.0
    slip_cost: float = 10.0
    slip_candidates: int = 256
    slip_seeds: int = 8
    seed_explanations: int = 2
    partial_budget: int = 64
    state_gate: float = STATE_GATE
    miss_cost: float = MISS_COST


class PartialPruning(NamedTuple):
    """One pruning of a pose's partial explanations (``BeamSearch._prune_partials``): ``grown``
    of them, from ``parents`` of the hypotheses the pose started from, of which ``kept`` were kept."""

    pose: int
    parents: int
    grown: int
    kept: int


@dataclass
class BeamStatistics:
    """What a ``BeamSearch`` did, counted as it runs (``BeamSearch.statistics``); nothing reads
    them back, they are for tests and measurements.

    Attributes
    ----------
    slip_search_poses : the poses explained again from a slip's widened prior (the seeded
        search under ``slip_inflation``), in order.
    seeded_search_poses : the poses explained again from seed pairs under the plain prediction.
    partial_prunings : every pruning of partial explanations (``PartialPruning``), in order.
    children_created : children paired with a landmark (``BeamSearch._branches``), whose state
        is computed only when first read.
    children_settled : of those, the ones whose state was computed.
    """

    slip_search_poses: list[int] = field(default_factory=list)
    seeded_search_poses: list[int] = field(default_factory=list)
    partial_prunings: list[PartialPruning] = field(default_factory=list)
    children_created: int = 0
    children_settled: int = 0


class _Hypothesis:
    """A filter (x, P), the assignments at this pose that produced it and their cost.

    A child grown by one more pair (``BeamSearch._branches``) has its cost at once, from the
    pair's options, but its state only when something first reads x or P (``pending``, a
    function returning both): at an ambiguous pose many children are pruned on their cost alone
    (a fifth, where every observation is ambiguous), and their filter updates are never needed.
    """

    __slots__ = ("_x", "_P", "cost", "parent", "pairs", "unassigned", "slipped", "_pending")

    def __init__(
        self, x: Optional[np.ndarray], P: Optional[np.ndarray], cost: float, parent: int, pairs: tuple = (),
        unassigned: int = 0, slipped: bool = False, *, pending: Optional[Callable[[], tuple[np.ndarray, np.ndarray]]] = None,
    ):
        self._x, self._P = x, P
        self.cost = cost
        self.parent = parent              # index of the hypothesis it grew from, at the previous pose
        self.pairs = pairs                # ((observation, landmark index), ...) at this pose
        self.unassigned = unassigned
        self.slipped = slipped            # explained from the widened (odometry-slip) prior
        self._pending = pending

    @property
    def x(self) -> np.ndarray:
        if self._pending is not None:
            self._settle()
        return self._x

    @property
    def P(self) -> np.ndarray:
        if self._pending is not None:
            self._settle()
        return self._P

    def _settle(self) -> None:
        self._x, self._P = self._pending()
        self._pending = None


@dataclass
class _Options:
    """What one observation may be under one hypothesis: its pool of nearby landmarks (d^2 within
    ``POOL_GATE_FACTOR`` gates) with their pair costs, infinite where the pair fails the gate."""

    landmarks: np.ndarray   # (g,) landmark indices
    costs: np.ndarray       # (g,) d^2 + ln det S - ln det R, inf outside the gate
    z_hat: np.ndarray       # (g, 3) predicted u, v, depth (for the filter's update)
    H: np.ndarray           # (g, 3, 6) their Jacobian
    y: np.ndarray           # (g, 3) the innovation in the pair's coordinates (``_in_best_coordinates``)
    Hc: np.ndarray          # (g, 3, 6) its Jacobian
    Rc: np.ndarray          # (g, 3, 3) the observation's covariance in them


@dataclass
class _Partial:
    """A hypothesis that has explained some of a pose's observations (``BeamSearch._explain_all``)."""

    h: _Hypothesis
    order: tuple                      # observations (positions in the pose's obs) still to explain, in order
    options: list                     # _Options of every observation under base_x
    base_x: np.ndarray                # the state the options were computed under
    least: dict                       # position -> the least its explanation costs under base_x
    rest: float                       # sum of least over order
    root: int                         # which parent it grew from


# The slip's search runs where a pose's best explanation leaves an unusual share of its observations
# unassigned for this data (``BeamSearch._unusually_unexplained``).
UNEXPLAINED_WINDOW = 50
UNUSUAL_PROBABILITY = 0.01
UNEXPLAINED_RATE_CAP = 0.6
UNEXPLAINED_RUN = 3

# A hypothesis conditioned on some of a pose's pairs re-gates each remaining observation among the
# landmarks that were within this many gates before: its predictions moved by about H dx, with dx
# drawn from the variance it lost, so a landmark it gates was within the (wider) earlier gate with
# the same probability; twice the gate (about 99.996% for the default) makes a miss negligible.
POOL_GATE_FACTOR = 2.0


class BeamContext(Protocol):
    """What the beam reads of the run, all of it fixed for the run; ``camloc.localizer._Localizer``
    provides it (``visible`` and ``observe`` through its ``camloc.associators.AssociationScene``)."""

    dataset: Dataset
    filter: EulerFilter | SE3Filter
    map_index: Optional[association.PointIndex]  # over dataset.landmark_xyz; None for an empty map
    cameras: dict[int, CameraModel]      # by sensor (``sensors.sensors_of``)
    obs_sensor: np.ndarray               # (K,) each observation's sensor
    obs_gate: np.ndarray                 # (K,) each observation's chi^2 gate, at its dof
    obs_of_pose: list[np.ndarray]        # each pose's observations (indices into the dataset's)
    T_increments: np.ndarray             # (N - 1, 4, 4) the odometry increments
    null_cost: np.ndarray                # (K,) cost of leaving each observation unassigned
    association_cov: np.ndarray          # (K, 3, 3) the noise association judges each observation by
    log_det_R: np.ndarray                # (K,) its ln det     (``association.noise_floored``)
    point: np.ndarray                    # (K, 3) each observation as a point in its camera's frame,
    point_cov: np.ndarray                # (K, 3, 3) its covariance
    log_det_point_cov: np.ndarray        # (K,) and that covariance's ln det
    detect_range: tuple[float, float]    # distances from a camera within which it surely detects a landmark
                                         # it sees (``scene.detection_range``; (0, 0): no pixel observations)

    def visible(self, x: np.ndarray, camera_id: int, P: Optional[np.ndarray] = None) -> np.ndarray:
        """The landmarks camera ``camera_id`` may see from x; with P, from within three standard
        deviations of x."""

    def observe(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (m, 3) of the landmarks by camera ``camera_id`` from x, and their Jacobians."""

    def updated(
        self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray, *,
        at_prior: tuple[np.ndarray, np.ndarray] | None = None, for_association: bool = False,
    ) -> ekf.UpdateResult:
        """The filter's stacked, iterated update of (x, P) with the given pairs."""


class BeamSearch:
    """Runs the beam over a whole dataset, reading the run through ``context`` (``BeamContext``)."""

    def __init__(self, context: BeamContext, settings: BeamSettings):
        self.ctx = context
        self.settings = settings
        self.R = context.association_cov        # the noise association judges each observation by
        self.log_det_R = context.log_det_R      # ln det R of every observation
        self.point, self.point_cov = context.point, context.point_cov  # every observation in its camera's frame
        self.log_det_point_cov = context.log_det_point_cov
        self.null_cost = context.null_cost      # cost of leaving each observation unassigned
        # which observations have a point (``measurement.judged_as_point``; a pixel is a ray)
        self._ranged = measurement.judged_as_point(context.dataset.obs_kind)
        self.history: list[list[_Hypothesis]] = []  # each pose's beam; during a pose, those before it
        self.statistics = BeamStatistics()
        self.unexplained: list[tuple[int, int]] = []  # (unassigned, observations) of each pose's best explanation

    def run(
        self, x0: np.ndarray, P0: np.ndarray, *,
        on_pose: Optional[Callable[[int], None]] = None,
        on_decided: Optional[Callable[[int, list[np.ndarray], np.ndarray], None]] = None,
        decided_stride: int = 64,
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Process every pose; returns, per pose, a (p, 2) int array of chosen (obs, landmark), and
        (n,) bool: the pose was explained from the widened prior of an odometry slip (the filter
        that replays the pairs must widen its prior there too).

        ``on_decided(first, pairs, slipped)``, when given, is called every ``decided_stride`` poses
        with the association of the poses from ``first`` on that no later pose can change any more
        (every hypothesis in the beam descends from the same one there), in order and each pose
        once, so that a consumer can filter them while the beam goes on; the last call comes
        before ``run`` returns and covers every pose.
        """
        beam = [_Hypothesis(x0, P0, 0.0, -1)]
        decided = 0  # poses before this one have been passed to on_decided
        n = self.ctx.dataset.num_poses
        for k in range(n):
            try:
                if k > 0:
                    beam = [self._predicted(h, k - 1, parent) for parent, h in enumerate(beam)]
                beam = self._explain_pose(k, beam, self.ctx.obs_of_pose[k])
            except ekf.NUMERICAL_FAILURES as error:
                raise ekf.as_divergence(error).at_pose(int(self.ctx.dataset.pose_ids[k])) from None
            self.history.append(beam)
            if on_pose is not None:
                on_pose(k)
            if on_decided is not None and (k + 1) % decided_stride == 0:
                decided = self._pass_decided(decided, on_decided)
        chosen, slipped = self._backtrack()
        if on_decided is not None and decided < n:
            on_decided(decided, chosen[decided:], slipped[decided:])
        return chosen, slipped

    def _pass_decided(self, first: int, on_decided: Callable[[int, list[np.ndarray], np.ndarray], None]) -> int:
        """Hand the newly decided poses (from ``first`` on) to on_decided; returns the first pose
        still undecided. Pose k is decided once all the current hypotheses share their ancestor
        there."""
        last = len(self.history) - 1
        indices = set(range(len(self.history[last])))
        k = last
        while len(indices) > 1 and k > first:
            indices = {self.history[k][i].parent for i in indices}
            k -= 1
        if len(indices) > 1:
            return first
        chosen, slipped = self._chain(k, indices.pop(), first)
        on_decided(first, chosen, slipped)
        return k + 1

    def _chain(self, k: int, index: int, first: int) -> tuple[list[np.ndarray], np.ndarray]:
        """The association of poses first..k along the ancestors of hypothesis ``index`` at pose k."""
        chosen: list[np.ndarray] = [np.zeros((0, 2), np.int64)] * (k + 1 - first)
        slipped = np.zeros(k + 1 - first, dtype=bool)
        for j in range(k, first - 1, -1):
            h = self.history[j][index]
            chosen[j - first] = np.asarray(h.pairs, dtype=np.int64).reshape(-1, 2)
            slipped[j - first] = h.slipped
            index = h.parent
        return chosen, slipped

    def _predicted(self, h: _Hypothesis, edge: int, parent: int) -> _Hypothesis:
        x, F, G = self.ctx.filter.predict(h.x, self.ctx.T_increments[edge])
        P = ekf.predict(h.P, F, G, self.ctx.dataset.odom_cov[edge])  # P = F P F' + G Q G'
        return _Hypothesis(x, P, h.cost, parent)

    def _explain_pose(self, k: int, beam: list[_Hypothesis], obs: np.ndarray) -> list[_Hypothesis]:
        if obs.size == 0 or self.ctx.map_index is None:
            return beam
        children = self._explain_all(beam, obs)
        if not children:  # every option's cost is NaN: a covariance that is not one
            raise ekf.FilterDivergedError("no explanation of the pose's observations has a finite cost")
        best = min(children, key=lambda c: c.cost)
        seeded: list[list[_Hypothesis]] = []
        if obs.size >= SLIP_MIN_OBSERVATIONS and 2 * best.unassigned > obs.size:
            origin = beam[0]
            self.statistics.seeded_search_poses.append(k)
            seeded.append(self._explain_from_seeds(origin, obs, slipped=False))  # noisy odometry, not a slip
            # a slip is the explanation of last resort: its search (the costliest, under the
            # widest prior) runs only where the pose stays unusually unexplained after the plain one's
            best_with_seeds = min(children + seeded[0], key=lambda c: c.cost)
            if (self._unusually_unexplained(best.unassigned, obs.size)
                    and self._unusually_unexplained(best_with_seeds.unassigned, obs.size)):
                slipped = _Hypothesis(origin.x, origin.P * self.settings.slip_inflation,
                                      origin.cost + self.settings.slip_cost, origin.parent)
                self.statistics.slip_search_poses.append(k)
                seeded.insert(0, self._explain_from_seeds(slipped, obs))
        kept = self._prune(children + [c for group in seeded for c in group])
        for group in seeded:
            kept = self._with_a_seeded_one(kept, group)
        self.unexplained.append((kept[0].unassigned, obs.size))
        return kept

    def _with_a_seeded_one(self, kept: list[_Hypothesis], seeded: list[_Hypothesis]) -> list[_Hypothesis]:
        """The pruned beam with its last place given to the cheapest seeded explanation, when that
        is within beam_delta of the best and only the beam's width kept it out.

        A pose of few observations says little: under a slip's wide prior the right explanation
        of three observations pays for its first pair's spread and the slip, about what leaving
        two of them unassigned costs a wrong hypothesis, and a full beam of that hypothesis' near
        copies crowds it out. Kept, it explains the next poses' observations where the wrong one
        goes on leaving them unassigned, and it wins within a pose or two."""
        if len(kept) < self.settings.beam_width or any(c in kept for c in seeded):
            return kept  # not crowded out: too costly, or a copy of a kept hypothesis
        candidate = min(seeded, key=lambda c: c.cost)
        if candidate.cost > kept[0].cost + self.settings.beam_delta or any(self._same_state(candidate, k) for k in kept):
            return kept
        return sorted(kept[:-1] + [candidate], key=lambda c: c.cost)

    def _unusually_unexplained(self, unassigned: int, observed: int) -> bool:
        """Whether leaving ``unassigned`` of a pose's ``observed`` observations unexplained is
        unlikely for this data: a binomial tail below ``UNUSUAL_PROBABILITY`` at the rate of the
        last ``UNEXPLAINED_WINDOW`` poses' best explanations (at most ``UNEXPLAINED_RATE_CAP``),
        for this pose alone or pooled with the ``UNEXPLAINED_RUN - 1`` poses before it.

        Where a third of the detections are clutter, most poses leave half their observations
        unassigned, and re-explaining each of them from seeds (the slip's search) costs up to
        half a second a pose, finds nothing better, and now and then a wrong alignment that
        explains some clutter. A rate learnt from the recent poses keeps that search for poses that explain
        less than the data usually lets them. A pose of three observations says little (all
        three unexplained at a rate of 0.4: 6%), but a slip leaves every pose after it
        unexplained: pooled over three poses, 9 of 9 is 0.03%. The cap keeps a filter that has
        lost its way (nothing explained for many poses) from learning that this is normal: at
        0.6, three poses of four observations none of which fits are unusual (0.2%).
        """
        if not self.unexplained:
            return True
        recent = np.array(self.unexplained[-UNEXPLAINED_WINDOW:], dtype=np.int64)
        rate = min(float(recent[:, 0].sum() / recent[:, 1].sum()), UNEXPLAINED_RATE_CAP)
        run = recent[len(recent) - (UNEXPLAINED_RUN - 1):].sum(axis=0)
        tails = binomial_tail(np.array([unassigned, unassigned + run[0]]) - 1, np.array([observed, observed + run[1]]), rate)
        return bool(tails.min() < UNUSUAL_PROBABILITY)  # P(X >= unassigned), alone or pooled

    def _explain_from_seeds(self, h: _Hypothesis, obs: np.ndarray, slipped: bool = True) -> list[_Hypothesis]:
        """Explanations of obs under h (the widened prior of a slip, or the plain prediction with
        ``slipped=False``), each grown from one seed pair.

        Under a wide prior every observation gates many landmarks and explaining them one by
        one from the prior goes astray. One right pair pins the pose's position, after which the
        others fall into place; so the ``slip_seeds`` pairs whose conditioned explanation of the
        pose looks cheapest (``association.seeded_explanation_costs``, among the
        ``slip_candidates`` individually cheapest pairs and the ``slip_candidates // 4`` with
        the largest crowds of pairs implying the same shift of the robot) are each tried as the
        first, the hypothesis conditioned on it, and the rest explained as usual; each seed gives
        its ``seed_explanations`` cheapest explanations.
        """
        # the seeds are looked for in all the view the wide prior allows, not only the mean's
        options = self._options(h, obs, widened_view=True)
        pair_obs = np.concatenate([np.full(o.landmarks.size, i) for i, o in enumerate(options)]).astype(np.int64)
        pair_landmark = np.concatenate([o.landmarks for o in options])
        pair_cost = np.concatenate([o.costs for o in options])
        gated = np.isfinite(pair_cost)
        if not gated.any():
            return self._explain(h, obs)
        pair_obs, pair_landmark, pair_cost = pair_obs[gated], pair_landmark[gated], pair_cost[gated]
        candidates = np.argsort(pair_cost, kind="stable")[: self.settings.slip_candidates]
        # and the pairs whose implied shift of the robot most others share: a right pair's own
        # cost under a wide prior may rank it far down
        # (a pixel is a ray: it implies no one shift; only pairs judged as points vote)
        ranged = self._ranged[obs[pair_obs]]
        agreement = np.zeros(pair_obs.size, np.int64)
        if ranged.any():
            agreement[ranged] = association.shift_agreement(
                self._implied_shifts(h, obs, pair_obs[ranged], pair_landmark[ranged]), self._agreement_radius(obs[self._ranged[obs]]))
        crowded = np.argsort(-agreement, kind="stable")[: self.settings.slip_candidates // 4]
        crowded = crowded[agreement[crowded] >= 3]  # fewer than three agreeing pairs is no crowd
        candidates = np.concatenate([candidates, crowded[~np.isin(crowded, candidates)]])
        ranked = association.seeded_explanation_costs(
            np.concatenate([o.y for o in options])[gated], np.concatenate([o.Hc for o in options])[gated],
            np.concatenate([o.Rc for o in options])[gated], h.P,
            pair_obs, pair_landmark, self.null_cost[obs], candidates, gate=self.ctx.obs_gate[obs[pair_obs]],
        )
        children: list[_Hypothesis] = []
        for seed in candidates[np.argsort(ranked, kind="stable")[: self.settings.slip_seeds]]:
            i, landmark = int(pair_obs[seed]), int(pair_landmark[seed])
            result = self.ctx.updated(h.x, h.P, obs[i : i + 1], np.array([landmark]), for_association=True)
            seeded = _Hypothesis(result.state, result.cov, h.cost + float(pair_cost[seed]), h.parent, ((int(obs[i]), landmark),))
            explained = self._explain(seeded, np.delete(obs, i))[: self.settings.seed_explanations]
            children += [c for c in explained if self._within_prior(c, h)]
        children = self._prune(children) if children else self._explain(h, obs)
        for child in children:
            child.slipped = slipped
        return children

    def _within_prior(self, child: _Hypothesis, h: _Hypothesis) -> bool:
        """Whether child's state lies within h's prior's 99.9% region (``BeamSettings.state_gate``).

        A child's cost sums its pairs' innovations, each linearized where the hypothesis was
        before it. Under a wide prior in a dense map, a seed pair can fit a landmark metres from
        the right one by turning the camera, and the iterated update then carries the state
        there: every innovation looked likely, yet the state moved many standard deviations. The
        chain rule's sum equals the state's own cost only for a linear model; this gate catches
        the explanations for which it does not hold at all."""
        d = self.ctx.filter.difference(child.x, h.x)
        return float(d @ np.linalg.solve(h.P, d)) <= self.settings.state_gate

    def _implied_shifts(self, h: _Hypothesis, obs: np.ndarray, pair_obs: np.ndarray, pair_landmark: np.ndarray) -> np.ndarray:
        """(N, 3) the shift of the robot from h each pair implies (``association.shift_agreement``)."""
        ds = self.ctx.dataset
        T_world_robot = self.ctx.filter.pose(h.x)
        measured_world = np.empty((pair_obs.size, 3))
        cameras = self.ctx.obs_sensor[obs][pair_obs]
        for camera_id in np.unique(cameras):
            mine = cameras == camera_id
            T_world_camera = T_world_robot @ self.ctx.cameras[int(camera_id)].T_robot_camera
            measured_world[mine] = geometry.transform_points(T_world_camera, self.point[obs[pair_obs[mine]]])
        return ds.landmark_xyz[pair_landmark] - measured_world

    def _agreement_radius(self, obs: np.ndarray) -> float:
        """How close two implied shifts must be to agree: three standard deviations of a measured
        point, plus a tenth of the depth for the orientation's error (about 6 deg)."""
        point_sigma = np.sqrt(np.trace(self.point_cov[obs], axis1=1, axis2=2) / 3.0)
        return float(3.0 * np.median(point_sigma) + 0.1 * np.median(np.abs(self.point[obs, 2])))

    def _explain(self, h: _Hypothesis, obs: np.ndarray) -> list[_Hypothesis]:
        """Children of h that explain all of obs, pruned to the beam."""
        return self._explain_all([h], obs)

    def _explain_all(self, parents: list[_Hypothesis], obs: np.ndarray) -> list[_Hypothesis]:
        """Children of all parents that explain all of obs.

        Under each parent the clear observations are taken in one stacked update; conditioned on
        them, the others are gated again, and those that became clear are taken in the next
        stacked update, until none does (an observation is often ambiguous only until a
        neighbour's pair pins the pose). Then the observations still ambiguous are branched on
        one at a time, each parent's partial explanations pruned to a beam of their own, so that
        a costlier parent's best explanation is grown to the end: where observations are few it
        is often the right one. Where every observation is ambiguous and the beam is full, that
        is beam_width^2 partial explanations per observation, mostly near copies (the parents of
        a pose differ in a pair or two); so past ``partial_budget`` the parents share one budget,
        ranked by cost plus the least the observations they have still to explain can cost.
        """
        partials = [self._after_clear(h, obs, root) for root, h in enumerate(parents)]
        expected = [self._expected(h, obs, p.options) for h, p in zip(parents, partials)]
        while any(p.order for p in partials):
            grown: list[_Partial] = []
            for p in partials:
                if not p.order:
                    grown.append(p)
                    continue
                i, order = p.order[0], p.order[1:]
                options = p.options[i] if p.h.x is p.base_x else self._conditioned(p.h, obs[i : i + 1], [p.options[i]])[0]
                rest = p.rest - p.least[i]
                grown += [_Partial(child, order, p.options, p.base_x, p.least, rest, p.root)
                          for child in self._branches(p.h, int(obs[i]), options)]
            partials = self._prune_partials(grown)
        return [self._missed(p.h, expected[p.root], parents[p.root]) for p in partials]

    def _expected(self, h: _Hypothesis, obs: np.ndarray, options: list[_Options]) -> np.ndarray:
        """The landmarks (distinct, sorted) that a pose's explanation grown from h is expected to
        claim: those in the pool of one of its pixel observations (near the ray) whose distance
        from that observation's camera under h lies within ``detect_range``, where a camera
        surely detects what it sees. A pixel gives a ray, and the landmarks along it are told
        apart by their predicted spread, which favours a far one (its prediction is tighter);
        but a near landmark on the ray would have been detected, and left unclaimed it is a
        miss (``_missed``)."""
        low, high = self.ctx.detect_range
        if self.settings.miss_cost <= 0.0 or high <= 0.0:
            return np.zeros(0, np.int64)
        ds = self.ctx.dataset
        pixel = ~measurement.measures_range(ds.obs_kind[obs])
        found = []
        T_world_robot = self.ctx.filter.pose(h.x)
        for i in np.flatnonzero(pixel):
            landmarks = options[i].landmarks
            if landmarks.size == 0:
                continue
            centre = T_world_robot[:3, :3] @ self.ctx.cameras[int(self.ctx.obs_sensor[obs[i]])].T_robot_camera[:3, 3] + T_world_robot[:3, 3]
            distance = np.linalg.norm(ds.landmark_xyz[landmarks] - centre, axis=1)
            found.append(landmarks[(distance >= low) & (distance <= high)])
        return np.unique(np.concatenate(found)) if found else np.zeros(0, np.int64)

    def _missed(self, h: _Hypothesis, expected: np.ndarray, parent: _Hypothesis) -> _Hypothesis:
        """h (an explanation grown from ``parent``) charged ``miss_cost`` for each of the
        ``expected`` landmarks it leaves unclaimed."""
        if expected.size == 0:
            return h
        missed = int((~_member(expected, np.array([lm for _, lm in h.pairs], dtype=np.int64))).sum())
        if missed and h is parent:  # never the parent's own cost
            h = _Hypothesis(h.x, h.P, h.cost, h.parent, h.pairs, h.unassigned, h.slipped)
        h.cost += self.settings.miss_cost * missed
        return h

    def _after_clear(self, h: _Hypothesis, obs: np.ndarray, root: int) -> _Partial:
        """h after its stacked updates with the clear observations (see ``_explain_all``), with
        the ambiguous rest in the order to branch on them (fewest gated options first)."""
        options = self._options(h, obs)
        taken = np.array([lm for _, lm in h.pairs], dtype=np.int64)  # a seeded explanation's seed pair
        if taken.size:
            for o in options:
                o.costs = np.where(_member(o.landmarks, taken), np.inf, o.costs)
        child, pending = h, np.arange(obs.size)
        while pending.size:
            choice = self._clear_choices(obs[pending], [options[i] for i in pending])
            clear = [k for k, c in enumerate(choice) if c is not None]
            if not clear:
                break
            child = self._stacked_child(child, obs[pending[clear]], [options[pending[k]] for k in clear], [choice[k] for k in clear])
            pending = pending[[k for k, c in enumerate(choice) if c is None]]
            if pending.size:
                conditioned = self._conditioned(child, obs[pending], [options[i] for i in pending])
                for i, o in zip(pending, conditioned):
                    options[i] = o
        order = tuple(sorted((int(i) for i in pending), key=lambda i: int(np.isfinite(options[i].costs).sum())))
        least = {i: min(float(self.null_cost[obs[i]]), float(options[i].costs.min(initial=np.inf))) for i in order}
        return _Partial(child, order, options, child.x, least, sum(least.values()), root)

    def _prune_partials(self, partials: list[_Partial]) -> list[_Partial]:
        """Each parent's partial explanations pruned as ``_prune`` does (they have explained the
        same observations, so their costs compare); then, if together they are more than
        ``partial_budget``, the best of each parent and the rest of the budget by cost plus
        ``rest``, the least their observations still to explain can cost."""
        by_root: dict[int, list[_Partial]] = {}
        for p in partials:
            by_root.setdefault(p.root, []).append(p)
        kept = [p for group in by_root.values() for p in self._prune(group, lambda p: p.h)]
        if len(kept) > self.settings.partial_budget:
            kept.sort(key=lambda p: p.h.cost + p.rest)
            firsts = {}
            for p in kept:
                firsts.setdefault(p.root, p)
            others = [p for p in kept if firsts[p.root] is not p]
            kept = list(firsts.values()) + others[: max(0, self.settings.partial_budget - len(firsts))]
        self.statistics.partial_prunings.append(PartialPruning(len(self.history), len(by_root), len(partials), len(kept)))
        return kept

    def _options(self, h: _Hypothesis, obs: np.ndarray, *, widened_view: bool = False) -> list[_Options]:
        """Gated landmarks of every observation under h, computed in one batch per camera; with
        ``widened_view``, among the landmarks within three standard deviations of h's view."""
        out: list[_Options] = [None] * obs.size  # type: ignore[list-item]
        cameras = self.ctx.obs_sensor[obs]
        for camera_id in np.unique(cameras):
            rows = np.flatnonzero(cameras == camera_id)
            gate = float(self.ctx.obs_gate[obs[rows[0]]])  # a sensor's observations share their dof
            pool_gate = POOL_GATE_FACTOR * gate
            candidates = self.ctx.visible(h.x, camera_id, h.P if widened_view else None)
            if candidates.size == 0:
                for r in rows:
                    out[r] = _empty_options()
                continue
            z_hat, H = self.ctx.observe(h.x, camera_id, candidates)
            o = obs[rows]
            spread = self._spread(h.P, camera_id, z_hat, H)
            j, g = self._plausible_pairs(o, z_hat, spread, pool_gate)  # row by row
            p_hat, Hp, HPH, JHPHJ = (part[g] for part in spread)
            d2, costs, in_point = self._in_best_coordinates(o[j], z_hat[g], p_hat, HPH, JHPHJ)
            pool = d2 <= pool_gate  # each observation's pool
            j, g, d2, costs, in_point, p_hat, Hp = (part[pool] for part in (j, g, d2, costs, in_point, p_hat, Hp))
            costs = np.where(d2 <= gate, costs, np.inf)
            y, Hc, Rc = self._chosen(in_point, o[j], z_hat[g], H[g], p_hat, Hp)
            bounds = np.searchsorted(j, np.arange(rows.size + 1))
            for k, r in enumerate(rows):
                part = slice(bounds[k], bounds[k + 1])
                pool = g[part]
                out[r] = _Options(candidates[pool], costs[part], z_hat[pool], H[pool], y[part], Hc[part], Rc[part])
        return out

    def _spread(
        self, P: np.ndarray, camera_id: int, z_hat: np.ndarray, H: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predictions (z_hat (m, 3), H (m, 3, n)) of camera camera_id under covariance P, also
        as camera-frame points: (p_hat (m, 3), their Jacobian Hp (m, 3, n), the spread of the
        predictions H P H' (m, 3, 3) and of the points Hp P Hp' (m, 3, 3)). A sensor that does not
        measure range has no point: zeros, a singular spread, which fits nothing
        (``_in_best_coordinates`` keeps its pixels)."""
        camera = self.ctx.cameras[int(camera_id)]
        HPH = H @ P @ np.swapaxes(H, -1, -2)
        if not measurement.judged_as_point(camera.kind):
            return np.zeros_like(z_hat), np.zeros_like(H), HPH, np.zeros_like(HPH)
        p_hat, J = models.back_project(z_hat, camera.intrinsics, camera.kind)
        return p_hat, J @ H, HPH, J @ HPH @ np.swapaxes(J, -1, -2)

    def _plausible_pairs(self, o: np.ndarray, z_hat: np.ndarray, spread: tuple, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """(rows into o, rows into z_hat) of the pairs whose d^2 may be within ``limit`` in either
        coordinates of ``_in_best_coordinates``, row-major; the others are surely beyond it. For
        S positive definite, ``y' S^-1 y >= |y|^2 / trace(S)``, and the trace of S = H P H' + R
        is a sum of traces: a bound for every pair from a few numbers per observation and per
        prediction, where d^2 itself needs a 3x3 system per pair (most of a dense view's pairs
        are far out of every gate)."""
        ds = self.ctx.dataset
        p_hat, _, HPH, JHPHJ = spread
        spread_pixels = np.trace(HPH, axis1=1, axis2=2)[None, :] + np.trace(self.R[o], axis1=1, axis2=2)[:, None]
        spread_point = np.trace(JHPHJ, axis1=1, axis2=2)[None, :] + np.trace(self.point_cov[o], axis1=1, axis2=2)[:, None]
        y_pixels = ds.obs_z[o][:, None, :] - z_hat[None, :, :]
        y_point = self.point[o][:, None, :] - p_hat[None, :, :]
        near = ((np.einsum("ijk,ijk->ij", y_pixels, y_pixels) <= limit * spread_pixels)
                | ((np.einsum("ijk,ijk->ij", y_point, y_point) <= limit * spread_point) & self._ranged[o][:, None]))
        return np.nonzero(near)

    def _in_best_coordinates(
        self, o: np.ndarray, z_hat: np.ndarray, p_hat: np.ndarray, HPH: np.ndarray, JHPHJ: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pairs of observations o (g,) with predictions z_hat (g, 3) (``_spread``: as points
        p_hat, their spreads HPH and JHPHJ), each judged in the coordinates where its
        linearization explains it best: the measured (u, v, depth), or the camera-frame point
        they back-project to.

        The two agree to first order and part where the prior is wide. A point is linear in the
        robot's position, so a prediction a few decimetres off (noisy odometry in a dense map)
        keeps a Gaussian spread there while in pixels it bends; pixels can fit better where the
        spread is mostly rotation. The likelier of the two (the smaller
        ``d^2 + ln det S - ln det R``, the same quantity in either) is kept; a joint cost of
        several pairs may take each in its own coordinates.

        Returns d^2 and the cost of each pair, and whether it is judged as a point.
        """
        ds = self.ctx.dataset
        d2_pixels, log_det_pixels = association.mahalanobis_3x3(HPH + self.R[o], ds.obs_z[o] - z_hat)
        d2_point, log_det_point = association.mahalanobis_3x3(JHPHJ + self.point_cov[o], self.point[o] - p_hat)
        cost_pixels = d2_pixels + log_det_pixels - self.log_det_R[o]
        cost_point = d2_point + log_det_point - self.log_det_point_cov[o]
        in_point = cost_point < cost_pixels
        return np.where(in_point, d2_point, d2_pixels), np.where(in_point, cost_point, cost_pixels), in_point

    def _chosen(
        self, in_point: np.ndarray, o: np.ndarray, z_hat: np.ndarray, H: np.ndarray, p_hat: np.ndarray, Hp: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The innovation (g, 3), its Jacobian (g, 3, n) and the observation's covariance (g, 3, 3)
        of g pairs (observations o, predictions z_hat, H and as points p_hat, Hp), each in the
        coordinates ``_in_best_coordinates`` chose for it."""
        ds = self.ctx.dataset
        point = in_point[:, None]
        y = np.where(point, self.point[o] - p_hat, ds.obs_z[o] - z_hat)
        Hc = np.where(point[:, :, None], Hp, H)
        Rc = np.where(point[:, :, None], self.point_cov[o], self.R[o])
        return y, Hc, Rc

    def _conditioned(self, h: _Hypothesis, obs: np.ndarray, options: list[_Options]) -> list[_Options]:
        """Options of observations obs under h, a hypothesis conditioned on some of the pose's
        pairs, from their options before: the same pools of landmarks predicted again from h, one
        batch per camera, less the landmarks h has taken. (Moving the old predictions to first
        order is not enough: with landmarks a metre away, a pair's correction moves the
        predictions by pixels more than the linear term says.)"""
        taken = np.array([lm for _, lm in h.pairs], dtype=np.int64)
        out = list(options)
        cameras = self.ctx.obs_sensor[obs]
        for camera_id in np.unique(cameras):
            rows = [r for r in np.flatnonzero(cameras == camera_id) if options[r].landmarks.size]
            if not rows:
                continue
            sizes = [options[r].landmarks.size for r in rows]
            landmarks = np.concatenate([options[r].landmarks for r in rows])
            z_hat, H = self.ctx.observe(h.x, int(camera_id), landmarks)
            owner = np.repeat(obs[rows], sizes)
            p_hat, Hp, HPH, JHPHJ = self._spread(h.P, camera_id, z_hat, H)
            d2, costs, in_point = self._in_best_coordinates(owner, z_hat, p_hat, HPH, JHPHJ)
            costs = np.where((d2 <= self.ctx.obs_gate[owner]) & ~_member(landmarks, taken), costs, np.inf)
            y, Hc, Rc = self._chosen(in_point, owner, z_hat, H, p_hat, Hp)
            for r, start, stop in zip(rows, np.cumsum([0] + sizes[:-1]), np.cumsum(sizes)):
                part = slice(start, stop)
                out[r] = _Options(landmarks[part], costs[part], z_hat[part], H[part], y[part], Hc[part], Rc[part])
        return out

    def _viable(self, costs: np.ndarray, null_cost: float) -> tuple[np.ndarray, bool]:
        """Which pair options (inf: excluded) and whether the null option lie within branch_delta
        of the best."""
        best = min(null_cost, float(costs.min()) if costs.size else np.inf)
        limit = best + self.settings.branch_delta
        return costs <= limit, null_cost <= limit

    def _clear_choices(self, obs: np.ndarray, options: list[_Options]) -> list[Optional[int]]:
        """Per observation: the index of its only viable landmark option, -1 when leaving it
        unassigned is its only viable option, None when it is ambiguous (several viable options,
        or its landmark is viable for another observation too)."""
        viable = [self._viable(o.costs, float(c)) for o, c in zip(options, self.null_cost[obs])]
        claims = Counter(int(lm) for o, (pairs, _) in zip(options, viable) for lm in o.landmarks[pairs])
        shared = {lm for lm, count in claims.items() if count > 1}
        choice: list[Optional[int]] = []
        for o, (pairs, null) in zip(options, viable):
            if int(pairs.sum()) + int(null) != 1:
                choice.append(None)
            elif null:
                choice.append(-1)
            else:
                j = int(np.flatnonzero(pairs)[0])
                choice.append(None if int(o.landmarks[j]) in shared else j)
        return choice

    def _stacked_child(self, h: _Hypothesis, obs: np.ndarray, options: list[_Options], choice: list[int]) -> _Hypothesis:
        """h updated with all chosen pairs at once; the cost of the stacked innovation is the same
        chain-rule sum the one-by-one path computes."""
        taken = [i for i, j in enumerate(choice) if j >= 0]
        unassigned = len(choice) - len(taken)
        cost = h.cost + float(sum(self.null_cost[obs[i]] for i, j in enumerate(choice) if j < 0))
        if not taken:
            return _Hypothesis(h.x, h.P, cost, h.parent, h.pairs, h.unassigned + unassigned)
        o = obs[taken]
        landmarks = np.array([options[i].landmarks[choice[i]] for i in taken])
        at_prior = (np.array([options[i].z_hat[choice[i]] for i in taken]), np.array([options[i].H[choice[i]] for i in taken]))
        result = self.ctx.updated(h.x, h.P, o, landmarks, at_prior=at_prior, for_association=True)  # stacked, iterated as configured
        # the joint cost of the pairs, each in the coordinates its option chose, at h
        y = np.array([options[i].y[choice[i]] for i in taken]).reshape(-1)
        Hc = np.array([options[i].Hc[choice[i]] for i in taken]).reshape(-1, h.P.shape[0])
        Rc = np.array([options[i].Rc[choice[i]] for i in taken])
        cost += ekf.innovation_cost(h.P, Hc, Rc, y)
        x, P = result.state, result.cov
        pairs = tuple((int(obs[i]), int(options[i].landmarks[choice[i]])) for i in taken)
        return _Hypothesis(x, P, cost, h.parent, h.pairs + pairs, h.unassigned + unassigned)

    def _branches(self, h: _Hypothesis, o: int, options: _Options) -> list[_Hypothesis]:
        """Children of h for one observation (``options`` under h): unassigned, or paired with a
        viable landmark."""
        free = ~_member(options.landmarks, np.array([lm for _, lm in h.pairs], dtype=np.int64))
        null_cost = float(self.null_cost[o])
        pairs, null = self._viable(np.where(free, options.costs, np.inf), null_cost)
        out = []
        if null:
            out.append(_Hypothesis(h.x, h.P, h.cost + null_cost, h.parent, h.pairs, h.unassigned + 1))
        paired = np.flatnonzero(pairs)
        self.statistics.children_created += paired.size
        for j in paired:
            out.append(_Hypothesis(None, None, h.cost + float(options.costs[j]), h.parent, h.pairs + ((o, int(options.landmarks[j])),),
                                   h.unassigned, pending=partial(self._paired_state, h.x, h.P, o, options, int(j))))
        return out

    def _paired_state(self, x: np.ndarray, P: np.ndarray, o: int, options: _Options, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, P) updated with observation o paired with its option j."""
        self.statistics.children_settled += 1
        result = self.ctx.updated(x, P, np.array([o]), options.landmarks[j : j + 1],
                                  at_prior=(options.z_hat[j : j + 1], options.H[j : j + 1]), for_association=True)
        return result.state, result.cov

    def _prune(self, children: list, hypothesis: Callable = lambda c: c) -> list:
        """The cheapest children within beam_delta of the best, merged, at most beam_width.
        ``hypothesis(child)`` is the child's _Hypothesis (children may be _Partial)."""
        children = sorted(children, key=lambda c: hypothesis(c).cost)
        limit = hypothesis(children[0]).cost + self.settings.beam_delta
        kept: list = []
        for c in children:
            if hypothesis(c).cost > limit or len(kept) >= self.settings.beam_width:
                break
            if not any(self._same_state(hypothesis(c), hypothesis(k)) for k in kept):
                kept.append(c)
        return kept

    def _same_state(self, a: _Hypothesis, b: _Hypothesis) -> bool:
        d = self.ctx.filter.difference(a.x, b.x)
        return bool(np.all(d * d <= self.settings.merge_sigma**2 * np.diagonal(b.P)))

    def _backtrack(self) -> tuple[list[np.ndarray], np.ndarray]:
        # each pose's beam is sorted by cost: the first is the best
        return self._chain(len(self.history) - 1, 0, 0)


def _member(values: np.ndarray, few: np.ndarray) -> np.ndarray:
    """``np.isin(values, few)`` for the handful of landmarks a hypothesis has taken at a pose,
    by direct comparison (isin sorts, which costs more than comparing with a few)."""
    if few.size == 0:
        return np.zeros(values.shape, dtype=bool)
    return (values[:, None] == few[None, :]).any(axis=1)


def _empty_options() -> _Options:
    return _Options(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 6)), np.zeros((0, 3)),
                    np.zeros((0, 3, 6)), np.zeros((0, 3, 3)))

