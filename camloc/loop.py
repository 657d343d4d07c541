"""The localizer's loop over compiled kernels (the Euler filter; beam and oracle association).

    scene = build_scene(dataset, config)            # what never changes during the run
    pairs = associate(scene, ...)                   # the beam decides every pose's pairs
    filter(scene, pairs)                            # predict, update, re-check, record
    result(...)                                     # the run, as camloc.results.RunResult

The beam runs over every pose first (``search_beam``: a compiled loop that hands the rare poses
needing a search from seed pairs to ``camloc.seeds``), then the filter replays its association
(``filter_poses``), so that estimate, covariance and NIS are computed as for any other method.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from camloc.kernels import beam as kb
from camloc.kernels.filtering import GIVEN, ORACLE, filter_poses
from camloc.scene import build_scene, build_settings
from camloc.tails import chi2_quantile

ProgressCallback = Callable[[int, int], None]

# The progress callback is called this many times per run at most (between compiled blocks).
PROGRESS_STEPS = 200


def run_compiled(dataset, config, on_progress: Optional[ProgressCallback] = None, *, initial_x, initial_P):
    """Localize every pose of ``dataset``; returns the arrays ``camloc.localizer`` assembles into
    a RunResult: (states, covs, chosen landmark index per observation, Mahalanobis distance per
    observation, update pose indices, NIS, MAP costs, NIS dof, slipped pose indices)."""
    scene = build_scene(dataset, config)
    settings = build_settings(config, float(chi2_quantile(3, 1.0 - config.gate)))
    n, K = dataset.num_poses, dataset.num_observations
    progress = _Progress(n, on_progress, halves=2 if config.association == "beam" else 1)
    if config.association == "beam":
        pair_start, pairs, slipped = search_beam(scene, settings, initial_x, initial_P, progress)
        method = GIVEN
    else:
        pair_start, pairs, slipped = np.zeros(n + 1, np.int64), np.zeros((0, 2), np.int64), np.zeros(n, np.bool_)
        method = ORACLE
    states, covs = np.zeros((n, 6)), np.zeros((n, 6, 6))
    chosen, distance = np.full(K, -1, np.int64), np.full(K, np.nan)
    update_pose, nis, map_cost, dof = np.zeros(n, np.int64), np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
    counters = np.zeros(3, np.int64)
    x, P = initial_x.copy(), initial_P.copy()
    pair_obs, pair_landmark = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    for first, last in progress.blocks():
        x, P = _at_pose(counters, filter_poses, scene, settings, method, first, last, x, P, pair_start, pair_obs,
                        pair_landmark, slipped, states, covs, chosen, distance, update_pose, nis, map_cost, dof, counters)
        progress.done(last)
    u = int(counters[0])
    return states, covs, chosen, distance, update_pose[:u], nis[:u], map_cost[:u], dof[:u], np.flatnonzero(slipped)


def search_beam(scene, settings, x0, P0, progress):
    """Every pose's pairs as the beam decides them: (pair_start (N + 1,), pairs (p, 2) of
    (observation, landmark), the seed pair first at a slip; slipped (N,))."""
    n = scene.pose_obs_start.size - 1
    width = settings.beam_width
    history = (np.zeros(n, np.int64), np.zeros((n, width), np.int64), np.zeros((n, width), np.bool_),
               np.zeros((n, width + 1), np.int64), np.zeros((max(4 * scene.z.shape[0], 64), 2), np.int64), np.zeros(1, np.int64))
    unexplained = np.zeros((n, 2), np.int64)
    counters = np.zeros(3, np.int64)
    beam = kb.new_generation(1, 1)
    beam[0][0], beam[1][0], beam[2][0] = x0, P0, 0.0
    size = 1
    for first, last in progress.blocks():
        k = first
        while k < last:
            status, k, parents, n_parents, children, count = _at_pose(counters, kb.run_poses, scene, settings, k, last, beam, size,
                                                                     history, unexplained, counters)
            if status in (kb.GROW, kb.SLIP):
                obs = scene.pose_obs[scene.pose_obs_start[k]:scene.pose_obs_start[k + 1]]
                if status == kb.SLIP:
                    from camloc.seeds import explain_with_seeds

                    gen, kept = _at_pose(counters, explain_with_seeds, scene, settings, parents, n_parents, children, count, obs,
                                         unexplained[:counters[2]])
                else:  # the pose was explained, but its record did not fit
                    gen, kept = children, kb.prune(scene, settings, children, count)
                while not kb.commit(history, k, gen, kept):
                    history = history[:4] + (np.concatenate([history[4], np.zeros_like(history[4])]),) + history[5:]
                unexplained[counters[2]] = (gen[4][kept[0]], obs.size)
                counters[2] += 1
                beam, size = kb.carry(gen, kept), kept.size
                k += 1
                continue
            beam, size = parents, n_parents
        progress.done(last)
    return _backtrack(history, n)


def _backtrack(history, n):
    """The pairs of every pose along the ancestors of the last pose's best hypothesis."""
    count, parent, slipped_flag, pair_start, pairs, _ = history
    chosen, slipped = [None] * n, np.zeros(n, np.bool_)
    index = 0
    for k in range(n - 1, -1, -1):
        chosen[k] = pairs[pair_start[k, index]:pair_start[k, index + 1]]
        slipped[k] = slipped_flag[k, index]
        index = parent[k, index]
    sizes = np.array([c.shape[0] for c in chosen], dtype=np.int64)
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64), np.concatenate(chosen or [np.zeros((0, 2), np.int64)]), slipped


class PoseFailure(Exception):
    """A kernel's numerical failure at pose index ``k`` (the caller names the pose by its id)."""

    def __init__(self, k: int, detail: str):
        super().__init__(detail)
        self.k = k


def _at_pose(counters, kernel, *args):
    """Call a kernel; a numerical failure is a PoseFailure at the pose it stopped at."""
    try:
        return kernel(*args)
    except (FloatingPointError, ZeroDivisionError, np.linalg.LinAlgError) as error:
        raise PoseFailure(int(counters[1]), str(error)) from None


class _Progress:
    """Blocks of poses between progress reports; with the beam, the search and the filter each
    count for half of the bar."""

    def __init__(self, n: int, callback: Optional[ProgressCallback], *, halves: int):
        self.n, self.callback, self.halves, self.pass_ = n, callback, halves, 0
        self.stride = max(1, n // (PROGRESS_STEPS // halves)) if callback else max(n, 1)

    def blocks(self):
        for first in range(0, self.n, self.stride):
            yield first, min(first + self.stride, self.n)
        self.pass_ += 1

    def done(self, last: int) -> None:
        if self.callback is not None:
            self.callback(min(self.n, (self.pass_ * self.n + last) // self.halves), self.n)
