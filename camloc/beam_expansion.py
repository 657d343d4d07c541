"""The numpy beam's explanation of one pose (``camloc.beam``): every hypothesis' children that
explain all of the pose's observations, the clear ones in stacked updates and the ambiguous rest
branched on one at a time (``PoseExpansion.explain_all``), pruned to the beam and merged
(``PoseExpansion.prune``)."""

from __future__ import annotations

from collections import Counter
from functools import partial
from typing import Callable, Optional, Sequence

import numpy as np

from camloc import beam_chain, ekf, measurement
from camloc.beam_types import BeamContext, BeamSettings, BeamStatistics, Hypothesis, Partial, PartialPruning
from camloc.constants import RAY_STEP_SIGMA
from camloc.miss_term import miss_charge
from camloc.pair_options import PairGating, PairOptions, member
from camloc.sparse_poses import copy_sigma


class PoseExpansion:
    """Explains a pose's observations from hypotheses of the run ``ctx``: ``explain_all`` grows
    them, ``prune`` keeps the beam. ``history`` is the search's list of each pose's beam (its
    length is the pose being explained), ``statistics`` what it counts."""

    def __init__(self, context: BeamContext, settings: BeamSettings, gating: PairGating, statistics: BeamStatistics,
                 history: list[list[Hypothesis]]):
        self.ctx = context
        self.settings = settings     # the run's
        # the pose's beam (``sparse_poses.pose_beam``), set per pose by the search
        self.width, self.delta = settings.beam_width, settings.beam_delta
        self.gating = gating
        self.statistics = statistics
        self.history = history
        self.null_cost = context.null_cost      # cost of leaving each observation unassigned

    def explain(self, h: Hypothesis, obs: np.ndarray) -> list[Hypothesis]:
        """Children of h that explain all of obs, pruned to the beam."""
        return self.explain_all([h], obs)

    def explain_all(self, parents: list[Hypothesis], obs: np.ndarray, roots: Optional[list] = None) -> list[Hypothesis]:
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
        Each chain of pairs is checked against its parent's prior, the parent itself, where
        ``roots`` is None, or its entry of ``roots`` (the seeded search's: the prior it started
        from; ``camloc.beam_chain``).
        """
        roots = parents if roots is None else roots
        partials = [self.after_clear(h, obs, root, roots[root]) for root, h in enumerate(parents)]
        expected = [self.expected(h, obs, p.options) for h, p in zip(parents, partials)]
        while any(p.order for p in partials):
            grown: list[Partial] = []
            for p in partials:
                if not p.order:
                    grown.append(p)
                    continue
                i, order = p.order[0], p.order[1:]
                options = p.options[i] if p.h.x is p.base_x else self.gating.conditioned(p.h, obs[i : i + 1], [p.options[i]])[0]
                rest = p.rest - p.least[i]
                # the landmark of each observation still to explain that gates only one
                contested = [gated for gated in (p.options[later].landmarks[np.isfinite(p.options[later].costs)] for later in order)
                             if gated.size == 1]
                grown += [Partial(child, order, p.options, p.base_x, p.least, rest, p.root, p.chain_root)
                          for child in self.branches(p.h, int(obs[i]), options, contested, p.chain_root)]
            partials = self.prune_partials(grown)
        return [self.missed(p.h, expected[p.root], parents[p.root]) for p in partials]

    def expected(self, h: Hypothesis, obs: np.ndarray, options: list[PairOptions]) -> tuple[np.ndarray, np.ndarray]:
        """The landmarks a pose's explanation grown from h is expected to claim (``expected_landmarks``)."""
        return expected_landmarks(self.ctx, self.settings, self.null_cost, h, obs, options)

    def missed(self, h: Hypothesis, expected: tuple[np.ndarray, np.ndarray], parent: Hypothesis) -> Hypothesis:
        """h (an explanation grown from ``parent``) charged for each of the ``expected``
        landmarks it leaves unclaimed (``camloc.miss_term.miss_charge`` of its least excess)."""
        landmarks, excess = expected
        if landmarks.size == 0:
            return h
        unclaimed = ~member(landmarks, np.array([lm for _, lm in h.pairs], dtype=np.int64))
        if not unclaimed.any():
            return h
        if h is parent:  # never the parent's own cost
            h = Hypothesis(h.x, h.P, h.cost, h.parent, h.pairs, h.unassigned, h.slipped)
        h.cost += float(miss_charge(excess[unclaimed], self.settings.miss_cost).sum())
        return h

    def after_clear(self, h: Hypothesis, obs: np.ndarray, root: int, prior: Hypothesis) -> Partial:
        """h after its stacked updates with the clear observations (see ``explain_all``), with
        the ambiguous rest in the order to branch on them (fewest gated options first); ``prior``:
        the pose's prior h grew from (h itself, or the seeded search's start), its chains checked
        against it."""
        options = self.gating.options(h, obs)
        if h.pairs:  # a seeded explanation's seed pair
            taken = np.array([lm for _, lm in h.pairs], dtype=np.int64)
            for o in options:
                o.costs = np.where(member(o.landmarks, taken), np.inf, o.costs)
        chain_root = beam_chain.root_if_wide(self.ctx, prior, obs, options)
        child, pending = h, np.arange(obs.size)
        while pending.size:
            choice = self.clear_choices(obs[pending], [options[i] for i in pending])
            clear = [k for k, c in enumerate(choice) if c is not None]
            if not clear:
                break
            child = self.stacked_child(child, obs[pending[clear]], [options[pending[k]] for k in clear], [choice[k] for k in clear],
                                       chain_root)
            pending = pending[[k for k, c in enumerate(choice) if c is None]]
            if pending.size:
                conditioned = self.gating.conditioned(child, obs[pending], [options[i] for i in pending])
                for i, o in zip(pending, conditioned):
                    options[i] = o
        order = tuple(sorted((int(i) for i in pending), key=lambda i: int(np.isfinite(options[i].costs).sum())))
        least = {i: min(float(self.null_cost[obs[i]]), float(options[i].costs.min(initial=np.inf))) for i in order}
        return Partial(child, order, options, child.x, least, sum(least.values()), root, chain_root)

    def prune_partials(self, partials: list[Partial]) -> list[Partial]:
        """Each parent's partial explanations pruned as ``prune`` does, to the run's beam (they
        have explained the same observations, so their costs compare); then, if together they are more than
        ``partial_budget``, the best of each parent and the rest of the budget by cost plus
        ``rest``, the least their observations still to explain can cost."""
        by_root: dict[int, list[Partial]] = {}
        for p in partials:
            by_root.setdefault(p.root, []).append(p)
        kept = [p for group in by_root.values() for p in self.prune(group, lambda p: p.h, self.settings.beam_width, self.settings.beam_delta)]
        if len(kept) > self.settings.partial_budget:
            kept.sort(key=lambda p: p.h.cost + p.rest)
            firsts = {}
            for p in kept:
                firsts.setdefault(p.root, p)
            others = [p for p in kept if firsts[p.root] is not p]
            kept = list(firsts.values()) + others[: max(0, self.settings.partial_budget - len(firsts))]
        self.statistics.partial_prunings.append(PartialPruning(len(self.history), len(by_root), len(partials), len(kept)))
        return kept

    def viable(self, costs: np.ndarray, null_cost: float) -> tuple[np.ndarray, bool]:
        """Which pair options (inf: excluded) and whether the null option lie within branch_delta
        of the best, the null option at its cost before ``null_offset``."""
        null_cost = null_cost + self.settings.null_offset
        best = min(null_cost, float(costs.min()) if costs.size else np.inf)
        limit = best + self.settings.branch_delta
        return costs <= limit, null_cost <= limit

    def clear_choices(self, obs: np.ndarray, options: list[PairOptions]) -> list[Optional[int]]:
        """Per observation: the index of its only viable landmark option, -1 when leaving it
        unassigned is its only viable option, None when it is ambiguous (several viable options,
        or its landmark is viable for another observation too)."""
        # each observation's viable options (their positions) and whether its null option is viable
        viable = [(np.flatnonzero(pairs), null) for pairs, null in
                  (self.viable(o.costs, c) for o, c in zip(options, self.null_cost[obs].tolist()))]
        claims = Counter(lm for o, (at, _) in zip(options, viable) for lm in o.landmarks[at].tolist())
        shared = {lm for lm, count in claims.items() if count > 1}
        choice: list[Optional[int]] = []
        for o, (at, null) in zip(options, viable):
            if at.size + int(null) != 1:
                choice.append(None)
            elif null:
                choice.append(-1)
            else:
                j = int(at[0])
                choice.append(None if int(o.landmarks[j]) in shared else j)
        return choice

    def stacked_child(self, h: Hypothesis, obs: np.ndarray, options: list[PairOptions], choice: list[int],
                      chain_root: Optional[Hypothesis] = None) -> Hypothesis:
        """h updated with all chosen pairs at once; the cost of the stacked innovation is the same
        chain-rule sum the one-by-one path computes. ``chain_root``: ``beam_chain.checked``'s."""
        taken = [i for i, j in enumerate(choice) if j >= 0]
        unassigned = len(choice) - len(taken)
        cost = h.cost + float(sum(self.null_cost[obs[i]] for i, j in enumerate(choice) if j < 0))
        if not taken:
            return Hypothesis(h.x, h.P, cost, h.parent, h.pairs, h.unassigned + unassigned)
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
        if chain_root is not None and len(h.pairs) > len(chain_root.pairs):   # a chain: h has pairs since the prior
            x, P = beam_chain.checked(self.ctx, x, P, chain_root, h.pairs + pairs)
        return Hypothesis(x, P, cost, h.parent, h.pairs + pairs, h.unassigned + unassigned)

    def branches(self, h: Hypothesis, o: int, options: PairOptions, contested: Sequence[np.ndarray] = (),
                 chain_root: Optional[Hypothesis] = None) -> list[Hypothesis]:
        """Children of h for one observation (``options`` under h): unassigned, or paired with a
        viable landmark. ``contested``: the landmarks of the observations still to explain after
        it that gate only one; where one of its viable landmarks is among them it may also stay
        unassigned whatever its null cost ("Contested landmarks" in docs/beam.md)."""
        costs = options.costs
        if h.pairs:  # the landmarks h has taken are not free
            costs = np.where(member(options.landmarks, np.array([lm for _, lm in h.pairs], dtype=np.int64)), np.inf, costs)
        null_cost = float(self.null_cost[o])
        pairs, null = self.viable(costs, null_cost)
        if not null and any(member(options.landmarks[pairs], later).any() for later in contested):
            # Another observation gates this landmark alone: branch_delta judges each observation
            # alone, but the explanation that leaves this one unassigned pairs the landmark with
            # the other (a clutter detection beside a landmark's own: both near-equal), so keep it.
            null = True
        out = []
        if null:
            out.append(Hypothesis(h.x, h.P, h.cost + null_cost, h.parent, h.pairs, h.unassigned + 1))
        paired = np.flatnonzero(pairs)
        self.statistics.children_created += paired.size
        for j in paired:
            out.append(Hypothesis(None, None, h.cost + float(options.costs[j]), h.parent, h.pairs + ((o, int(options.landmarks[j])),),
                                  h.unassigned, pending=partial(self.paired_state, h.x, h.P, o, options, int(j), chain_root, h.pairs)))
        return out

    def paired_state(self, x: np.ndarray, P: np.ndarray, o: int, options: PairOptions, j: int,
                     chain_root: Optional[Hypothesis] = None, before: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
        """(x, P) updated with observation o paired with its option j; ``before``: the pairs x has,
        its chain checked against ``chain_root`` (``beam_chain.checked``)."""
        self.statistics.children_settled += 1
        # a ray's iterations also stop once a step is negligible against the prior's sigma (``RAY_STEP_SIGMA``)
        ray = bool(measurement.is_ray(self.ctx.dataset.obs_kind[o]))
        result = self.ctx.updated(x, P, np.array([o]), options.landmarks[j : j + 1],
                                  at_prior=(options.z_hat[j : j + 1], options.H[j : j + 1]), for_association=True,
                                  step_sigma=RAY_STEP_SIGMA if ray else 0.0)
        return beam_chain.checked(self.ctx, result.state, result.cov, chain_root, before + ((o, int(options.landmarks[j])),))

    def prune(self, children: list, hypothesis: Callable = lambda c: c, width: Optional[int] = None,
              delta: Optional[float] = None) -> list:
        """The cheapest children within ``delta`` of the best, merged, at most ``width`` (by default
        the pose's, ``sparse_poses.pose_beam``; a sparse pose's extra ones distinct: ``copy_sigma``).
        ``hypothesis(child)`` is the child's Hypothesis (children may be Partial)."""
        width, delta = (self.width if width is None else width), (self.delta if delta is None else delta)
        children = sorted(children, key=lambda c: hypothesis(c).cost)
        best = hypothesis(children[0]).cost
        limit = best + delta
        s = self.settings
        differences = getattr(self.ctx.filter, "differences", None)  # a filter's batched ``difference``, where it has one
        kept = _KeptAtOnce(hypothesis, differences, min(width, len(children))) if differences else _Kept(hypothesis, self.same_state)
        for c in children:
            if hypothesis(c).cost > limit or len(kept.children) >= width:
                break
            # beyond the run's width and delta (a sparse pose's extra ones) only a distinct one
            sigma = copy_sigma(hypothesis(c).cost, best, len(kept.children), s.beam_width, s.beam_delta, s.merge_sigma)
            if not kept.any_same(hypothesis(c), sigma):
                kept.children.append(c)
        return kept.children

    def same_state(self, a: Hypothesis, b: Hypothesis, sigma: Optional[float] = None) -> bool:
        """Whether a lies within ``sigma`` (default merge_sigma) standard deviations of b on every axis."""
        sigma = self.settings.merge_sigma if sigma is None else sigma
        d = self.ctx.filter.difference(a.x, b.x)
        return bool(np.all(d * d <= sigma**2 * b.P.diagonal()))


def expected_landmarks(ctx, settings: BeamSettings, null_cost: np.ndarray, h: Hypothesis, obs: np.ndarray,
                       options: list[PairOptions]) -> tuple[np.ndarray, np.ndarray]:
    """The landmarks (distinct, sorted) that a pose's explanation grown from h is expected to
    claim, and each one's least excess (its pair's cost under h over the observation's null
    cost): those in the pool of one of its pixel observations (near the ray) whose distance
    from that observation's camera under h lies within ``detect_range``, where a camera
    surely detects what it sees. A pixel gives a ray, and the landmarks along it are told
    apart by their predicted spread, which favours a far one (its prediction is tighter);
    but a near landmark on the ray would have been detected, and left unclaimed it is a
    miss, charged by the chance that it is on the ray (``missed``, ``camloc.miss_term``)."""
    low, high = ctx.detect_range
    none = (np.zeros(0, np.int64), np.zeros(0))
    if settings.miss_cost <= 0.0 or high <= 0.0:
        return none
    ds = ctx.dataset
    pixel = measurement.is_ray(ds.obs_kind[obs])
    found, excess = [], []
    T_world_robot = ctx.filter.pose(h.x)
    for i in np.flatnonzero(pixel):
        landmarks = options[i].landmarks
        if landmarks.size == 0:
            continue
        centre = T_world_robot[:3, :3] @ ctx.cameras[int(ctx.obs_sensor[obs[i]])].T_robot_camera[:3, 3] + T_world_robot[:3, 3]
        distance = np.linalg.norm(ds.landmark_xyz[landmarks] - centre, axis=1)
        near = (distance >= low) & (distance <= high)
        found.append(landmarks[near])
        excess.append(options[i].pool_costs[near] - null_cost[obs[i]])
    if not found:
        return none
    landmarks, which = np.unique(np.concatenate(found), return_inverse=True)
    least = np.full(landmarks.size, np.inf)
    np.minimum.at(least, which, np.concatenate(excess))
    return landmarks, least


class _Kept:
    """The children a ``prune`` has kept, and whether a candidate's state is one of theirs
    (``PoseExpansion.same_state`` of each in turn)."""

    def __init__(self, hypothesis: Callable, same_state: Callable):
        self.children: list = []
        self.hypothesis, self.same_state = hypothesis, same_state

    def any_same(self, h: Hypothesis, sigma: float) -> bool:
        return any(self.same_state(h, self.hypothesis(k), sigma) for k in self.children)


class _KeptAtOnce(_Kept):
    """``_Kept`` of a filter with a batched ``differences`` (the Euler filter's), a candidate tested
    against all the kept states in one numpy step: on a dense pixel world a pruning compares a
    candidate with up to the beam's width of them, and one comparison at a time (a Python call, a
    ``difference`` and a diagonal each) held ``prune``'s own time, its children's updates aside, at
    3.1 s of a 33 s numpy run (2.0 s in one step; the 50-pose dense pixel world of
    ``tests/test_kernels.py``, 2026-12-06). The same answers to the bit as ``same_state``; and a
    state is read (a pending child's update computed) only where the loop read it: a kept one once
    a candidate is compared with it, a candidate only where one is kept before it."""

    def __init__(self, hypothesis: Callable, differences: Callable, width: int):
        super().__init__(hypothesis, same_state=None)
        self.differences, self.width = differences, width
        self.filled = 0

    def any_same(self, h: Hypothesis, sigma: float) -> bool:
        """Whether h's state lies within ``sigma`` standard deviations of a kept one's on every
        axis (``PoseExpansion.same_state`` of each)."""
        n = len(self.children)
        if not n:
            return False
        if not self.filled:
            self.x, self.variance = np.empty((self.width, h.x.size)), np.empty((self.width, h.x.size))
        for k in self.children[self.filled :]:
            kh = self.hypothesis(k)
            self.x[self.filled], self.variance[self.filled] = kh.x, kh.P.diagonal()
            self.filled += 1
        d = self.differences(h.x, self.x[:n])
        return bool(np.any(np.all(d * d <= sigma**2 * self.variance[:n], axis=1)))
