"""The numpy beam's search from seed pairs (``camloc.beam``), where a pose's best explanation
leaves most of its observations unassigned: under the prediction as it is, and, where that many
unassigned is unusual for this data even then, under the widened prior of an odometry slip. The
reasoning is in ``docs/beam.md`` and in ``camloc.beam``'s docstring."""

from __future__ import annotations

import numpy as np

from camloc import association, geometry
from camloc.beam_expansion import PoseExpansion
from camloc.beam_types import BeamContext, BeamSettings, Hypothesis
from camloc.constants import (
    AGREEMENT_DEPTH_FRACTION, AGREEMENT_SIGMAS, SEEDED_MIN_UNASSIGNED, SEEDED_UNUSUAL_PROBABILITY, UNEXPLAINED_RATE_CAP,
    UNEXPLAINED_RUN, UNEXPLAINED_WINDOW, UNUSUAL_PROBABILITY,
)
from camloc.pair_options import PairGating
from camloc.tails import binomial_tail


class SeededSearch:
    """Explanations of a pose grown from seed pairs (``explain_from_seeds``), whether a pose is
    unusually unexplained for this data (``unusually_unexplained``, from ``unexplained``: the
    record of each pose's best explanation), and the beam's last place for a seeded explanation
    (``with_a_seeded_one``)."""

    def __init__(self, context: BeamContext, settings: BeamSettings, gating: PairGating, expansion: PoseExpansion):
        self.ctx = context
        self.settings = settings
        self.gating = gating
        self.expansion = expansion
        self.point, self.point_cov = context.point, context.point_cov  # every observation in its camera's frame
        self.null_cost = context.null_cost      # cost of leaving each observation unassigned
        self.unexplained: list[tuple[int, int]] = []  # (unassigned, observations) of each pose's best explanation

    def with_a_seeded_one(self, kept: list[Hypothesis], seeded: list[Hypothesis]) -> list[Hypothesis]:
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
        if candidate.cost > kept[0].cost + self.settings.beam_delta or any(self.expansion.same_state(candidate, k) for k in kept):
            return kept
        return sorted(kept[:-1] + [candidate], key=lambda c: c.cost)

    def worth_trying(self, unassigned: int, observed: int) -> bool:
        """Whether a pose whose best explanation leaves at most half its observations unassigned
        is searched from seeds all the same (``seeds_worth_trying``)."""
        recent = self.unexplained[-UNEXPLAINED_WINDOW:]  # all the rule reads
        return seeds_worth_trying(unassigned, observed, np.array(recent, dtype=np.int64).reshape(-1, 2))

    def unusually_unexplained(self, unassigned: int, observed: int) -> bool:
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

    def explain_from_seeds(self, h: Hypothesis, obs: np.ndarray, slipped: bool = True) -> list[Hypothesis]:
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
        options = self.gating.options(h, obs, widened_view=True)
        pair_obs = np.concatenate([np.full(o.landmarks.size, i) for i, o in enumerate(options)]).astype(np.int64)
        pair_landmark = np.concatenate([o.landmarks for o in options])
        pair_cost = np.concatenate([o.costs for o in options])
        gated = np.isfinite(pair_cost)
        if not gated.any():
            return self.expansion.explain(h, obs)
        pair_obs, pair_landmark, pair_cost = pair_obs[gated], pair_landmark[gated], pair_cost[gated]
        candidates = np.argsort(pair_cost, kind="stable")[: self.settings.slip_candidates]
        # and the pairs whose implied shift of the robot most others share: a right pair's own
        # cost under a wide prior may rank it far down
        # (a pixel is a ray: it implies no one shift; only pairs judged as points vote)
        ranged = self.gating.ranged[obs[pair_obs]]
        agreement = np.zeros(pair_obs.size, np.int64)
        if ranged.any():
            agreement[ranged] = association.shift_agreement(
                self.implied_shifts(h, obs, pair_obs[ranged], pair_landmark[ranged]), self.agreement_radius(obs[self.gating.ranged[obs]]))
        crowded = np.argsort(-agreement, kind="stable")[: self.settings.slip_candidates // 4]
        crowded = crowded[agreement[crowded] >= 3]  # fewer than three agreeing pairs is no crowd
        candidates = np.concatenate([candidates, crowded[~np.isin(crowded, candidates)]])
        ranked = association.seeded_explanation_costs(
            np.concatenate([o.y for o in options])[gated], np.concatenate([o.Hc for o in options])[gated],
            np.concatenate([o.Rc for o in options])[gated], h.P,
            pair_obs, pair_landmark, self.null_cost[obs], candidates, gate=self.ctx.obs_gate[obs[pair_obs]],
        )
        children: list[Hypothesis] = []
        for seed in candidates[np.argsort(ranked, kind="stable")[: self.settings.slip_seeds]]:
            i, landmark = int(pair_obs[seed]), int(pair_landmark[seed])
            result = self.ctx.updated(h.x, h.P, obs[i : i + 1], np.array([landmark]), for_association=True)
            seeded = Hypothesis(result.state, result.cov, h.cost + float(pair_cost[seed]), h.parent, ((int(obs[i]), landmark),))
            # its chains checked against the prior the search started from (``camloc.beam_chain``): a seed
            # pair's state under a wide prior is as far off as a branched one's; on 3x-noise worlds it gains w9 and
            # w11 and holds the default-noise ones (docs/performance.md, 2026-12-06 seventeenth session, seeded-chain2)
            explained = self.expansion.explain_all([seeded], np.delete(obs, i), [h])[: self.settings.seed_explanations]
            children += [c for c in explained if self.within_prior(c, h)]
        children = self.expansion.prune(children) if children else self.expansion.explain(h, obs)
        for child in children:
            child.slipped = slipped
        return children

    def within_prior(self, child: Hypothesis, h: Hypothesis) -> bool:
        """Whether child's state lies within h's prior's 99.9% region (``BeamSettings.state_gate``).

        A child's cost sums its pairs' innovations, each linearized where the hypothesis was
        before it. Under a wide prior in a dense map, a seed pair can fit a landmark metres from
        the right one by turning the camera, and the iterated update then carries the state
        there: every innovation looked likely, yet the state moved many standard deviations. The
        chain rule's sum equals the state's own cost only for a linear model; this gate catches
        the explanations for which it does not hold at all."""
        d = self.ctx.filter.difference(child.x, h.x)
        return float(d @ np.linalg.solve(h.P, d)) <= self.settings.state_gate

    def implied_shifts(self, h: Hypothesis, obs: np.ndarray, pair_obs: np.ndarray, pair_landmark: np.ndarray) -> np.ndarray:
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

    def agreement_radius(self, obs: np.ndarray) -> float:
        """How close two implied shifts must be to agree: three standard deviations of a measured
        point, plus a tenth of the depth for the orientation's error (about 6 deg)."""
        point_sigma = np.sqrt(np.trace(self.point_cov[obs], axis1=1, axis2=2) / 3.0)
        return float(AGREEMENT_SIGMAS * np.median(point_sigma) + AGREEMENT_DEPTH_FRACTION * np.median(np.abs(self.point[obs, 2])))


def seeds_worth_trying(unassigned: int, observed: int, history: np.ndarray) -> bool:
    """Whether a pose whose best explanation leaves ``unassigned`` of its ``observed``
    observations unassigned (at most half) is searched from seeds: at least
    ``SEEDED_MIN_UNASSIGNED`` are, and that many is less likely than
    ``SEEDED_UNUSUAL_PROBABILITY`` at the rate of the last poses' best explanations (``history``
    (h, 2) of unassigned, observed; every pose's until there is one). One wrong pair taken first
    can pull a hypothesis off the right landmarks of the pose's other observations, which then
    stay unassigned. The compiled beam's ``kernels.beam.seeds_worth_trying`` is this rule
    (``tests/test_kernel_formulas.py``)."""
    if unassigned < SEEDED_MIN_UNASSIGNED:
        return False
    recent = history[-UNEXPLAINED_WINDOW:]
    if recent.shape[0] == 0:
        return True
    rate = min(float(recent[:, 0].sum() / recent[:, 1].sum()), UNEXPLAINED_RATE_CAP)
    return bool(binomial_tail(unassigned - 1, observed, rate) < SEEDED_UNUSUAL_PROBABILITY)  # P(X >= unassigned)
