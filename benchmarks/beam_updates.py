"""What a pose costs the beam, counted: per pose, the iterated updates the beam runs (stacked ones
of a hypothesis' clear pairs, one-pair ones settling a branched child's state), their
linearizations, the hypotheses, the clear pairs every hypothesis takes alike, the children settled
and then pruned, the branchings by their options, the pools predicted again, how far each
linearization moved the state (docs/performance.md, 2026-12-05, "Fewer updates a pose").

The numpy engine's beam (``camloc.beam``, which the compiled one equals pair for pair,
``tests/test_engine_parity.py``) run with counters wrapped around its steps (nothing of the
product changes): the compiled beam runs the same updates, so the counts are its too (where it
settles a child the numpy beam leaves lazy, it says so: "doomed", what a cut of those would save;
such a cut, ``doomed_above``, was tried and taken out: performance.md), and what cuts of the
partials would leave out: those a bound of the pose's best explanation puts past the pose's delta
(with the best known, and with a bound known at the step), and those grown from a hypothesis whose
predicted state lies within ``merge_sigma`` of a cheaper one's (docs/performance.md, 2026-12-07
twentieth session, "The beam's partial explanations counted again"). Figures per pose over the run's
last pass from pose ``--skip`` (a pixel-only run's first 300 poses are a pass of their own, which
learns the reach). Numpy is slow on pixels: 1,000 poses take a few minutes.

    nice python benchmarks/beam_updates.py WORLD.g2o [--poses 400] [--skip 300]
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np

import camloc
import camloc.beam_types
import camloc.miss_term
from camloc import beam_expansion, ekf, stacked_update
from camloc.beam_expansion import PoseExpansion
from camloc.dataset import first_poses


class PoseCounter(collections.Counter):
    """Counts, also kept per pose of the last pass (``where``: [pass, pose] of the beam's latest
    explanation; a pixel-only run's first 300 poses are a pass of their own, learning the reach)."""

    def __init__(self):
        super().__init__()
        self.where = [0, -1]
        self.per_pose: dict = collections.defaultdict(collections.Counter)

    def __setitem__(self, key, value):
        self.per_pose[tuple(self.where)][key] += value - self[key]
        super().__setitem__(key, value)


counts = PoseCounter()
phase = ["filter"]            # who is updating: "stacked", "settle", or the filter's replay
pose_pairs: dict = {}         # per (pose, root): the clear pairs of its stacked updates
settled_ids: set = set()      # ids of children whose state was computed
fresh_ids: set = set()        # ids of the children paired at the step being pruned
last_step: list = []          # (cost before the misses, settled) of the children paired at a pose's last step
root_options: set = set()     # ids of the options after_clear left (a partial that has paired nothing since branches on them)
grown_at_pose: list = []      # (cost, rest, hypothesis, kept) of every partial grown at the pose's steps before its last
clear_at_pose: list = []      # per root: whether after_clear left it nothing ambiguous
pose_context: list = []       # (expansion, parents, obs) of the pose being explained
mergeable_roots: set = set()  # the pose's hypotheses within merge_sigma of a cheaper one after the prediction


def bucket(moved: float) -> str:
    for bound in ("1e-4", "1e-3", "1e-2", "3e-2", "1e-1", "3e-1"):
        if moved < float(bound):
            return f"<{bound}"
    return ">=3e-1"


def counted_update(original):
    """``ekf.update`` counted: its linearizations (the first at the prior's given prediction, one
    more per call of ``measure``, less the MAP cost's), and what the later ones moved the state,
    in standard deviations (an angle's difference wrapped)."""
    def update(x, P, z, R, measure, **options):
        seen = []

        def counting(state):
            seen.append(state)
            return measure(state)

        result = original(x, P, z, R, counting, **options)
        who = phase[0]
        if len(seen) >= 2 and options.get("start") is None:
            last = np.abs(np.angle(np.exp(1j * (result.state - seen[1])))) / np.sqrt(np.diagonal(result.cov))
            counts[f"{who} last linearization moved {bucket(float(last.max()))} sigma"] += 1
            second = np.abs(np.angle(np.exp(1j * (seen[1] - seen[0])))) / np.sqrt(np.diagonal(P))
            counts[f"{who} second linearization moved {bucket(float(second.max()))} prior sigma"] += 1
            third = np.abs(np.angle(np.exp(1j * (result.state - seen[1])))) / np.sqrt(np.diagonal(P))
            counts[f"{who} second moved {bucket(float(second.max()))}, the third {bucket(float(third.max()))} prior sigma"] += 1
        linearizations = 1 + len(seen) - (1 if options.get("map_cost") else 0)
        counts[f"{who} updates"] += 1
        counts[f"{who} linearizations"] += linearizations
        counts[f"{who} pairs"] += z.size // 3
        counts[f"{who} updates of {linearizations} linearizations"] += 1
        return result
    return update


def wrap(cls, name, before=None, after=None, set_phase=None):
    original = getattr(cls, name)

    def wrapped(self, *args, **kwargs):
        if before:
            before(self, *args, **kwargs)
        saved = phase[0]
        if set_phase:
            phase[0] = set_phase
        try:
            result = original(self, *args, **kwargs)
        finally:
            phase[0] = saved
        if after:
            after(self, result, *args, **kwargs)
        return result
    setattr(cls, name, wrapped)


def on_explain_all(self, parents, obs, *rest):
    root_options.clear()
    pose = len(self.history)
    if pose < counts.where[1]:
        counts.where[0] += 1
    counts.where[1] = pose
    counts["explain_all calls"] += 1
    counts["hypotheses"] += len(parents)
    counts["observations x hypotheses"] += len(parents) * obs.size
    grown_at_pose.clear()
    clear_at_pose.clear()
    pose_context[:] = [self, parents, obs]
    # the hypotheses a merge right after the prediction would drop (as ``prune`` merges: by cost,
    # the cheaper kept, within merge_sigma of a kept one's standard deviations on every axis)
    kept_roots: list = []
    mergeable_roots.clear()
    for r in sorted(range(len(parents)), key=lambda r: parents[r].cost):
        if any(self.same_state(parents[r], parents[q]) for q in kept_roots):
            mergeable_roots.add(r)
        else:
            kept_roots.append(r)
    counts["hypotheses a merge after the prediction would drop"] += len(mergeable_roots)
    # near duplicates among the pose's hypotheses: the largest axis difference in sigma of each pair's
    if len(parents) > 1:
        for a in range(len(parents)):
            for b in range(a + 1, len(parents)):
                d = self.ctx.filter.difference(parents[a].x, parents[b].x)
                sigma = float(np.max(np.abs(d) / np.sqrt(np.minimum(parents[a].P.diagonal(), parents[b].P.diagonal()))))
                near = "<0.3" if sigma < 0.3 else "<1" if sigma < 1 else "<3" if sigma < 3 else ">=3"
                counts[f"pairs of a pose's hypotheses {near} sigma apart"] += 1


def after_explain_all(self, result, parents, obs, *rest):
    counts["explanations left unsettled by explain_all"] += sum(1 for h in result if h._pending is not None)
    if result and last_step:
        # the pose's pruning drops what lies beam_delta above its best: a cut that left such
        # children of the last step unsettled (``doomed_above``, tried and taken out) would save
        # at most these
        limit = min(h.cost for h in result) + self.settings.beam_delta
        doomed = [settled for cost, settled in last_step if cost > limit]
        counts["last step's paired children doomed (at most)"] += len(doomed)
        counts["  of them settled by the partials' pruning"] += sum(doomed)
    last_step.clear()
    # what a bound would prune before its update: a partial grown before the last step whose cost
    # (a) alone, rigorous (every later pair and miss costs >= 0), (b) plus its rest (the least its
    # observations still to explain cost under its root's state: not a bound, conditioning can
    # lower a pair's cost), lies above the pose's best explanation plus the pose's delta
    counts["poses explained"] += 1
    if clear_at_pose and all(clear_at_pose):
        counts["poses every hypothesis of which after_clear left nothing ambiguous"] += 1
        if len(clear_at_pose) == 1:
            counts["  of them with a single hypothesis"] += 1
    if result:
        limit = min(h.cost for h in result) + self.delta
        for cost, rest, h, was_kept in grown_at_pose:
            settled = id(h) in settled_ids
            if cost > limit:
                counts["partials grown before the last step, cost > best + delta (a bound would drop)"] += 1
                counts["  of them settled"] += settled
                counts["  of them kept by the partials' pruning (branched on next)"] += was_kept
            if cost + rest > limit:
                counts["partials grown before the last step, cost + rest > best + delta"] += 1
                counts["  of them settled (cost + rest)"] += settled
    grown_at_pose.clear()


def on_after_clear(self, result, h, obs, root, prior=None):
    root_options.update(id(o) for o in result.options)
    clear_at_pose.append(not result.order)
    counts["pending after clear"] += len(result.order)
    pose = len(self.history)
    pose_pairs.setdefault(pose, {})[root] = set(result.h.pairs) - set(h.pairs)


def on_prune_partials(self, kept, partials):
    counts["partials grown"] += len(partials)
    counts["partials kept"] += len(kept)
    kept_now = {id(p.h) for p in kept}
    counts["children settled, then pruned"] += sum(1 for p in partials if id(p.h) in settled_ids and id(p.h) not in kept_now)
    if partials and not any(p.order for p in partials):     # the pose's last step: its children, before their misses
        last_step[:] = [(p.h.cost, id(p.h) in settled_ids) for p in partials if id(p.h) in fresh_ids]
    else:
        kept_ids = {id(p.h) for p in kept}
        grown_at_pose.extend((p.h.cost, p.rest, p.h, id(p.h) in kept_ids) for p in partials)
    counts["partials grown and dropped by the same pruning"] += len(partials) - len(kept)
    counts["  partials grown from a hypothesis a merge after the prediction would drop"] += sum(
        1 for p in partials if p.root in mergeable_roots)
    counts["  partials grown from a hypothesis a merge after the prediction would drop, paired (an update each)"] += sum(
        1 for p in partials if p.root in mergeable_roots and id(p.h) in fresh_ids)
    if kept and pose_context and any(p.order for p in kept):
        # a bound known at this step without any update: each root's cheapest partial (always kept)
        # completed by leaving every observation still to explain unassigned (its cheapest child is
        # never dearer than its null child) and charged every miss it could pay
        expansion, parents, obs = pose_context
        s = expansion.settings
        upper = np.inf
        for p in kept:
            nulls = sum(float(expansion.null_cost[obs[i]]) + max(0.0, s.null_offset - s.branch_delta) for i in p.order)
            landmarks, excess = expansion.expected(parents[p.root], obs, p.options)
            misses = float(camloc.miss_term.miss_charge(excess, s.miss_cost).sum()) if landmarks.size else 0.0
            upper = min(upper, p.h.cost + nulls + misses)
        doomed = [p for p in kept if p.h.cost > upper + expansion.delta]
        counts["partials kept past a bound known then (best + nulls + misses + delta)"] += len(doomed)
        counts["  of them settled (then)"] += sum(1 for p in doomed if id(p.h) in settled_ids)
    fresh_ids.clear()


def on_prune(self, kept, children, *rest):
    if children and not hasattr(children[0], "root"):   # the pose's own pruning (Hypothesis, not Partial)
        ordered = sorted(children, key=lambda c: c.cost)
        limit = ordered[0].cost + self.settings.beam_delta
        within = sum(1 for c in ordered if c.cost <= limit)
        # the children prune looks at (compares, or keeps); past them none needs a state
        looked = within if len(kept) < self.settings.beam_width else 1 + max(i for i, c in enumerate(ordered) if c in kept)
        counts["explanations a pose's pruning never looks at"] += len(children) - looked
        counts["explanations never settled"] += sum(1 for c in children if c._pending is not None)
        counts["explanations of a pose"] += len(children)
        counts["explanations pruned at the pose's end"] += len(children) - len(kept)
        counts["kept hypotheses"] += len(kept)


def settle_counted(original):
    def settle(self):
        settled_ids.add(id(self))
        original(self)
    return settle


def on_paired_state(self, result, x, P, o, options, j, *rest, **kw):
    counts["children settled"] += 1


def on_branches(self, result, h, o, options, contested=(), *rest, **kw):
    fresh_ids.update(id(c) for c in result if c._pending is not None)
    paired = sum(1 for c in result if c._pending is not None)
    null = len(result) - paired
    counts[f"branchings into {'null + ' if null else ''}{paired} pair(s)"] += 1
    if paired == 1 and not null:
        if id(options) in root_options:
            counts["  of the one-pair branchings: on the root's options (contested landmark)"] += 1
        else:
            counts["  of the one-pair branchings: clear only once conditioned on the partial's pairs"] += 1


def on_conditioned(self, result, h, obs, options):
    counts["conditionings"] += 1
    counts["pool landmarks predicted again"] += sum(o.landmarks.size for o in options)


def on_options(self, result, h, obs, **kw):
    counts["option searches"] += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("world")
    parser.add_argument("--poses", type=int, default=400)
    parser.add_argument("--skip", type=int, default=300, help="the last pass's poses before this are not in its figures")
    args = parser.parse_args()
    world = camloc.load(args.world)
    world = first_poses(world, args.poses)
    camloc.beam_types.Hypothesis._settle = settle_counted(camloc.beam_types.Hypothesis._settle)
    ekf.update = counted_update(ekf.update)
    stacked_update.ekf.update = ekf.update
    wrap(PoseExpansion, "explain_all", before=on_explain_all, after=after_explain_all)
    wrap(PoseExpansion, "after_clear", after=on_after_clear)
    wrap(PoseExpansion, "stacked_child", set_phase="stacked")
    wrap(PoseExpansion, "paired_state", after=on_paired_state, set_phase="settle")
    wrap(PoseExpansion, "prune_partials", after=on_prune_partials)
    wrap(PoseExpansion, "prune", after=on_prune)
    wrap(PoseExpansion, "branches", after=on_branches)
    wrap(beam_expansion.PairGating, "conditioned", after=on_conditioned)
    wrap(beam_expansion.PairGating, "options", after=on_options)
    start = time.time()
    camloc.localize(world, camloc.LocalizerConfig(), engine="numpy")
    n = world.num_poses
    print(f"{args.world}: {n} poses, {time.time() - start:.0f} s in numpy; every pass")
    for key in sorted(counts):
        print(f"  {key:44s} {counts[key]:9d}")
    last = max(p for p, _ in counts.per_pose)
    steady = [c for (p, k), c in counts.per_pose.items() if p == last and k >= args.skip]
    print(f"the last pass's poses {args.skip}-{n - 1} ({len(steady)} explained), a pose:")
    for key in sorted(counts):
        if "filter" not in key:
            print(f"  {key:44s} {sum(c[key] for c in steady) / max(len(steady), 1):8.2f}")
    # clear pairs common to every hypothesis of a pose (its roots' stacked updates)
    common = total = 0
    for roots in pose_pairs.values():
        sets = list(roots.values())
        total += sum(len(s) for s in sets)
        if len(sets) > 1:
            common += len(set.intersection(*sets)) * len(sets)
    print(f"  clear pairs in stacked updates {total} ({total / n:.2f} a pose), of them taken alike by every one of "
          f"a pose's several hypotheses {common} ({common / max(total, 1):.0%})")


if __name__ == "__main__":
    main()
