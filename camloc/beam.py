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
point they back-project to (``PairGating.in_best_coordinates``): a point is linear in the
robot's position, so with noisy odometry in a dense map a right landmark predicted decimetres off
still gates there while its pixels have bent out of the gate.

Keeping it fast (most poses are not ambiguous):
- a hypothesis branches on an observation only into the options within ``branch_delta`` of that
  observation's best option; the observations with a single such option, whose landmark no other
  observation could take, are taken in one stacked update (the same cost, computed jointly), and
  only the ambiguous rest are explained one by one, each re-gated under the hypothesis conditioned
  on the pairs before it among its pool of nearby landmarks (no new search of the map);
- after each pose the beam keeps the ``beam_width`` cheapest hypotheses within ``beam_delta`` of
  the best (more, and further, at a pose of a few rays: ``camloc.sparse_poses``), and merges hypotheses whose states coincide (within ``merge_sigma`` standard
  deviations on every axis), so in unambiguous stretches it collapses to one filter;
- where every observation of a pose is ambiguous (large measurement noise in a dense map) the
  partial explanations grown from all the beam's hypotheses share a budget of ``partial_budget``
  (``PoseExpansion.explain_all``), instead of beam_width each.

Robustness to odometry slips: when the best hypothesis leaves most of a pose's observations
unassigned (at least two observations, more than half of them, and more than the recent poses'
share of unassigned observations makes likely: clutter), the pose is explained again from
that hypothesis' prediction with its covariance inflated ``slip_inflation`` times, at an extra
``slip_cost``, grown from each of a few seed pairs in turn (one right pair pins the pose, and the
rest follow); if the odometry really slipped, that hypothesis explains the observations and wins.
It is searched too where the plain seeded explanation (below) beat the prediction's with fewer
pairs: the prediction's pairs cost more than leaving them unexplained, so the prior is off.
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

from dataclasses import replace
from typing import Callable, Optional

import numpy as np

from camloc import ekf
from camloc.diagnostics import divergence_cause
from camloc.beam_expansion import PoseExpansion
from camloc.beam_seeded import SeededSearch
from camloc.beam_types import BeamContext, BeamSettings, BeamStatistics, Hypothesis
from camloc.constants import SLIP_MIN_OBSERVATIONS
from camloc.dataset import observations_by_pose
from camloc.pair_options import PairGating
from camloc.sparse_poses import carried, pose_beam, sparse_poses


class BeamSearch:
    """Runs the beam over a whole dataset, reading the run through ``context`` (``BeamContext``):
    each pose's hypotheses predicted, explained (``PoseExpansion``), searched again from seed
    pairs where most observations stay unassigned (``SeededSearch``) and pruned; the association
    of the best final hypothesis traced back through its ancestors."""

    def __init__(self, context: BeamContext, settings: BeamSettings):
        self.ctx = context
        self.settings = settings
        self.history: list[list[Hypothesis]] = []  # each pose's beam; during a pose, those before it
        self.statistics = BeamStatistics()
        self.gating = PairGating(context)
        self.expansion = PoseExpansion(context, settings, self.gating, self.statistics, self.history)
        self.seeded = SeededSearch(context, settings, self.gating, self.expansion)

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
        beam = [Hypothesis(x0, P0, 0.0, -1)]
        # per pose, the spread of the beam's explanations about the chosen one (``_spread_about``):
        # what the replayed filter's covariance, which knows one explanation, leaves out
        self.association_spread = np.zeros((self.ctx.dataset.num_poses,) + P0.shape)
        decided = 0  # poses before this one have been passed to on_decided
        n = self.ctx.dataset.num_poses
        order, bounds = observations_by_pose(self.ctx.dataset)
        self.sparse = sparse_poses(self.ctx.dataset.obs_kind[order], bounds, x0.size)  # a few rays only
        for k in range(n):
            try:
                if k > 0:
                    beam = [self._predicted(h, k - 1, parent) for parent, h in enumerate(beam)]
                beam = self._explain_pose(k, beam, self.ctx.obs_of_pose[k])
            except ekf.NUMERICAL_FAILURES as error:
                raise ekf.as_divergence(error).at_pose(int(self.ctx.dataset.pose_ids[k]),
                                                       divergence_cause(self.ctx.dataset)) from None
            self.history.append(beam)
            if on_pose is not None:
                on_pose(k)
            if on_decided is not None and (k + 1) % decided_stride == 0:
                decided = self._pass_decided(decided, on_decided)
        chosen, slipped = self._backtrack(spread_from=decided)
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

    def _chain(self, k: int, index: int, first: int, spread_from: Optional[int] = None) -> tuple[list[np.ndarray], np.ndarray]:
        """The association of poses first..k along the ancestors of hypothesis ``index`` at pose k;
        records the ``association_spread`` about that chain's hypothesis of each pose from
        ``spread_from`` (default: first) on: the poses before it were recorded by a chain that
        was already decided there."""
        spread_from = first if spread_from is None else spread_from
        chosen: list[np.ndarray] = [np.zeros((0, 2), np.int64)] * (k + 1 - first)
        slipped = np.zeros(k + 1 - first, dtype=bool)
        for j in range(k, first - 1, -1):
            h = self.history[j][index]
            chosen[j - first] = np.asarray(h.pairs, dtype=np.int64).reshape(-1, 2)
            slipped[j - first] = h.slipped
            if j >= spread_from:
                self.association_spread[j] = self._spread_about(self.history[j], h)
            index = h.parent
        return chosen, slipped

    def _spread_about(self, beam: list[Hypothesis], chosen: Hypothesis) -> np.ndarray:
        """How far the pose's kept hypotheses, weighted by their likelihood there, spread about
        the chosen one (``ekf.mixture_spread``): zero where the beam held one explanation."""
        if len(beam) < 2:
            return np.zeros_like(self.association_spread[0])
        differences = np.array([self.ctx.filter.difference(h.x, chosen.x) for h in beam])
        return ekf.mixture_spread(differences, np.array([h.cost for h in beam]))

    def _predicted(self, h: Hypothesis, edge: int, parent: int) -> Hypothesis:
        x, F, G = self.ctx.filter.predict(h.x, self.ctx.T_increments[edge])
        P = ekf.predict(h.P, F, G, self.ctx.dataset.odom_cov[edge])  # P = F P F' + G Q G'
        return Hypothesis(x, P, h.cost, parent)

    def _explain_pose(self, k: int, beam: list[Hypothesis], obs: np.ndarray) -> list[Hypothesis]:
        if obs.size == 0 or self.ctx.map_index is None:
            return beam
        beam = self._use_pose_beam(bool(self.sparse[k]), beam)
        children = self.expansion.explain_all(beam, obs)
        if not children:  # every option's cost is NaN: a covariance that is not one
            raise ekf.FilterDivergedError("no explanation of the pose's observations has a finite cost")
        best = min(children, key=lambda c: c.cost)
        seeded: list[list[Hypothesis]] = []
        most = obs.size >= SLIP_MIN_OBSERVATIONS and 2 * best.unassigned > obs.size
        if most or self.seeded.worth_trying(best.unassigned, obs.size):
            origin = beam[0]
            self.statistics.seeded_search_poses.append(k)
            seeded.append(self.seeded.explain_from_seeds(origin, obs, slipped=False))  # noisy odometry, not a slip
            # a slip is the explanation of last resort: its search (the costliest, under the
            # widest prior) runs only where the pose stays unusually unexplained after the plain
            # one's, or where a seed's explanation beat the prior's with fewer pairs (the prior's
            # pairs cost more than leaving them unexplained: the prior is off)
            best_with_seeds = min(children + seeded[0], key=lambda c: c.cost)
            unusual = (most and self.seeded.unusually_unexplained(best.unassigned, obs.size)
                       and self.seeded.unusually_unexplained(best_with_seeds.unassigned, obs.size))
            if unusual or (obs.size >= SLIP_MIN_OBSERVATIONS and best_with_seeds.cost < best.cost
                           and best_with_seeds.unassigned > best.unassigned):
                slipped = Hypothesis(origin.x, origin.P * self.settings.slip_inflation,
                                     origin.cost + self.settings.slip_cost, origin.parent)
                self.statistics.slip_search_poses.append(k)
                seeded.insert(0, self.seeded.explain_from_seeds(slipped, obs))
        kept = self.expansion.prune(children + [c for group in seeded for c in group])
        for group in seeded:
            kept = self.seeded.with_a_seeded_one(kept, group)
        self.seeded.unexplained.append((kept[0].unassigned, obs.size))
        return kept

    def _use_pose_beam(self, sparse: bool, beam: list[Hypothesis]) -> list[Hypothesis]:
        """The pose's beam width and delta (``sparse_poses.pose_beam``: wider at a ``sparse`` pose,
        of a few rays) where its explanation, seeded search and pruning read them; returns the
        hypotheses the pose explains (``sparse_poses.carried``: a sparse pose's extra ones dropped
        before one that is not)."""
        width, delta = self.settings.beam_width, self.settings.beam_delta
        n = carried([h.cost for h in beam], len(beam), sparse, width, delta)
        width, delta = pose_beam(sparse, width, delta)
        self.expansion.width, self.expansion.delta = width, delta
        self.seeded.settings = replace(self.settings, beam_width=width, beam_delta=delta)
        return beam[:n]

    def _backtrack(self, spread_from: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
        # each pose's beam is sorted by cost: the first is the best
        return self._chain(len(self.history) - 1, 0, 0, spread_from)
