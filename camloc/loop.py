"""The localizer's loop over compiled kernels (the Euler and the planar SE(2) filter, the state's
size telling them apart; beam and oracle association).

    scene = build_scene(dataset, config)            # what never changes during the run
    pairs = associate(scene, ...)                   # the beam decides every pose's pairs
    filter(scene, pairs)                            # predict, update, re-check, record
    result(...)                                     # the run, as camloc.results.RunResult

The beam runs over the poses (``search_beam``: a compiled loop that hands the rare poses needing a
search from seed pairs to ``camloc.seeds``), and the filter replays its association
(``filter_poses``), so that estimate, covariance and NIS are computed as for any other method.
A pose's pairs are settled once the beam has narrowed to one hypothesis at it or after it (all
later hypotheses descend from that one), which on most data is most poses: with ``concurrent``,
the filter replays each settled stretch in a second thread while the beam goes on (the kernels
release the GIL), with the same result as one pass after the other.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional

import numpy as np

from camloc.ekf import mixture_spread
from camloc.filters import make_filter
from camloc.kernels import beam as kb
from camloc.kernels.filtering import GIVEN, ORACLE, filter_poses
from camloc.scene import build_scene, build_settings
from camloc.sparse_poses import pose_beam, sparse_poses

ProgressCallback = Callable[[int, int], None]

# The compiled loop's filters by their state's size (their states' difference, for the association spread).
FILTER_OF_SIZE = {6: make_filter("euler"), 3: make_filter("se2")}

# The progress callback is called this many times per run at most (between compiled blocks).
PROGRESS_STEPS = 200
# The beam hands settled poses to the filter's thread at least this often.
SEGMENT_POSES = 256


def run_compiled(dataset, config, on_progress: Optional[ProgressCallback] = None, *, initial_x, initial_P,
                 concurrent: bool = False, filter_ready: Optional[Callable[[], None]] = None, view_range=None,
                 null_cost_offset: float = 0.0, on_replay: Optional[Callable[["_Filter"], None]] = None):
    """Localize every pose of ``dataset``; returns the arrays ``camloc.localizer`` assembles into
    a RunResult: (states, covs, chosen landmark index per observation, Mahalanobis distance per
    observation, update pose indices, NIS, MAP costs, NIS dof, slipped pose indices, association
    spread per pose (zero without the beam)).
    ``concurrent``: with the beam, filter the settled poses in a second thread (same result).
    ``filter_ready``: with the beam, called once before the filter's first stretch (a first
    compile waits there for the process compiling the filter's kernels: ``camloc.warmup``).
    ``view_range``: ``observation_space.candidate_range`` of the run, when the caller has it;
    ``null_cost_offset``: ``observation_space.observation_noise``'s.
    ``on_replay``: with the beam, called with the filter's replay (``_Filter``: its ``chosen`` and
    ``filtered`` tell which poses' pairs are final) before the beam starts
    (``camloc.mapping_follower``)."""
    scene = build_scene(dataset, config, view_range, null_cost_offset)
    settings = build_settings(config, null_cost_offset)
    n = dataset.num_poses
    if config.association == "beam":
        replay = _Filter(scene, settings, GIVEN, initial_x, initial_P, ready=filter_ready)
        if on_replay is not None:
            on_replay(replay)
        progress = _Progress(n, on_progress, halves=2, most=SEGMENT_POSES if concurrent else None)
        if concurrent:
            progress.filtered = lambda: replay.filtered
        with _Replay(replay, concurrent) as segments:
            search_beam(scene, settings, initial_x, initial_P, progress, segments.settle)
            segments.finish(progress)
        return replay.outputs()
    run = _Filter(scene, settings, ORACLE, initial_x, initial_P)
    progress = _Progress(n, on_progress, halves=1)
    for first, last in progress.blocks():
        run.poses(first, last)
        progress.done(last)
    return run.outputs()


class CompiledRun(NamedTuple):
    """What ``run_compiled`` returns (``camloc.localizer`` assembles it into a RunResult)."""

    states: np.ndarray        # (N, d) the filter's states (d = 6: Euler; 3: planar)
    covs: np.ndarray          # (N, d, d) the filter's covariances
    chosen: np.ndarray        # (K,) landmark row of each observation, -1 for none
    distance: np.ndarray      # (K,) Mahalanobis distance of each pair, NaN for none
    update_pose: np.ndarray   # (U,) pose index of each update
    nis: np.ndarray           # (U,)
    map_cost: np.ndarray      # (U,)
    dof: np.ndarray           # (U,) NIS degrees of freedom
    slipped: np.ndarray       # indices of the poses explained as odometry slips
    spread: np.ndarray        # (N, d, d) the beam's association spread and its pairs' (zero without the beam)


class _Filter:
    """The filter's pass (``filter_poses``), stretch by stretch in pose order, and its outputs.
    With the beam (GIVEN), the pairs of each stretch are set (``set_pairs``) before it runs."""

    def __init__(self, scene, settings, method, initial_x, initial_P, ready: Optional[Callable[[], None]] = None):
        n, K, d = scene.pose_obs_start.size - 1, scene.z.shape[0], initial_x.size
        self.ready = ready    # called before the first stretch
        self.scene, self.settings, self.method = scene, settings, method
        self.x, self.P = initial_x.copy(), initial_P.copy()
        self.states, self.covs = np.zeros((n, d)), np.zeros((n, d, d))
        self.chosen, self.distance = np.full(K, -1, np.int64), np.full(K, np.nan)
        self.update_pose, self.nis, self.map_cost, self.dof = np.zeros(n, np.int64), np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
        self.counters = np.zeros(3, np.int64)
        # pose k's pairs are pair_obs/pair_landmark[pair_start[k]:pair_start[k + 1]]: the arrays
        # grow by copy, so a stretch handed to the thread keeps reading the arrays it was given
        self.pair_start, self.slipped = np.zeros(n + 1, np.int64), np.zeros(n, np.bool_)
        self.pair_obs, self.pair_landmark = np.zeros(max(64, 2 * K), np.int64), np.zeros(max(64, 2 * K), np.int64)
        self.spread = np.zeros((n, d, d))  # with the beam, how far its explanations of each pose spread (_backtrack)
        self.pair_spread = np.zeros((n, d, d))  # and what the chance that a replayed pair is clutter adds
        self.filtered = 0

    def set_pairs(self, first: int, pairs: list, slipped: np.ndarray, spread: Optional[np.ndarray] = None):
        """Pairs ((p, 2) of observation, landmark each), slip flags and association spreads of
        poses first, first + 1, ...; returns the pair arrays the stretch reads."""
        if spread is not None:
            self.spread[first:first + len(pairs)] = spread
        at = self.pair_start[first]
        sizes = np.array([p.shape[0] for p in pairs], dtype=np.int64)
        self.pair_start[first + 1:first + 1 + sizes.size] = at + np.cumsum(sizes)
        end = at + int(sizes.sum())
        if end > self.pair_obs.size:
            grown = max(end, 2 * self.pair_obs.size)
            self.pair_obs = np.concatenate([self.pair_obs, np.zeros(grown - self.pair_obs.size, np.int64)])
            self.pair_landmark = np.concatenate([self.pair_landmark, np.zeros(grown - self.pair_landmark.size, np.int64)])
        if pairs:
            joined = np.concatenate(pairs)
            self.pair_obs[at:end], self.pair_landmark[at:end] = joined[:, 0], joined[:, 1]
        self.slipped[first:first + sizes.size] = slipped
        return self.pair_obs, self.pair_landmark

    def poses(self, first: int, last: int, pair_obs=None, pair_landmark=None):
        """Filter poses first..last - 1, from the state after pose first - 1."""
        pair_obs = self.pair_obs if pair_obs is None else pair_obs
        pair_landmark = self.pair_landmark if pair_landmark is None else pair_landmark
        if self.ready is not None:
            ready, self.ready = self.ready, None
            ready()
        self.x, self.P = _at_pose(self.counters, filter_poses, self.scene, self.settings, self.method, first, last, self.x,
                                  self.P, self.pair_start, pair_obs, pair_landmark, self.slipped, self.states, self.covs,
                                  self.chosen, self.distance, self.update_pose, self.nis, self.map_cost, self.dof,
                                  self.pair_spread, self.counters)
        self.filtered = last

    def outputs(self):
        u = int(self.counters[0])
        return CompiledRun(self.states, self.covs, self.chosen, self.distance, self.update_pose[:u], self.nis[:u],
                           self.map_cost[:u], self.dof[:u], np.flatnonzero(self.slipped), self.spread + self.pair_spread)


class _Replay:
    """The filter's replay of the beam's settled poses: in a thread of its own (``concurrent``),
    stretch by stretch as the beam settles them, or in the caller's thread at ``finish``.

    A failure in the filter's thread surfaces at ``finish`` (after the beam's own, as when the two
    run one after the other); the stretches after it are skipped."""

    def __init__(self, replay: _Filter, concurrent: bool):
        self.replay, self.settled, self.pending = replay, 0, []
        self.executor = None
        if concurrent:
            from concurrent.futures import ThreadPoolExecutor

            self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="camloc-filter")
        self.failed = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=True)
        return False

    def settle(self, last: int, pairs: list, slipped: np.ndarray, spread: np.ndarray):
        """Poses settled..last - 1 are settled, with these pairs, slip flags and spreads."""
        first, self.settled = self.settled, last
        arrays = self.replay.set_pairs(first, pairs, slipped, spread)
        if self.executor is not None:
            self.pending.append(self.executor.submit(self._run, first, last, *arrays))

    def _run(self, first, last, pair_obs, pair_landmark):
        if self.failed:
            return
        try:
            self.replay.poses(first, last, pair_obs, pair_landmark)
        except BaseException:
            self.failed = True
            raise

    def finish(self, progress: "_Progress"):
        """Filter what is left (every pose when not concurrent), reporting progress."""
        if self.executor is None:
            for first, last in progress.blocks():
                self.replay.poses(first, last)
                progress.done(last)
            return
        for future in self.pending:
            future.result()
            progress.done(self.replay.filtered)


def search_beam(scene, settings, x0, P0, progress, settle):
    """Every pose's pairs as the beam decides them, handed to ``settle(last, pairs, slipped,
    spread)`` for poses up to last - 1 (pairs: a list of (p, 2) of (observation, landmark), the
    seed pair first at a slip; slipped (p,); spread (p, d, d), ``_backtrack``) as soon as the beam
    has settled them, and for the rest at the end."""
    n = scene.pose_obs_start.size - 1
    # a sparse pose keeps a wider beam (``sparse_poses.pose_beam``): room for the widest
    d = x0.size
    width = pose_beam(True, settings.beam_width, settings.beam_delta)[0]
    # the sensors' kinds are the camera table's fifth column
    sparse = sparse_poses(scene.camera_K[scene.obs_camera[scene.pose_obs], 4].astype(np.int64), scene.pose_obs_start, d)
    history = (np.zeros(n, np.int64), np.zeros((n, width), np.int64), np.zeros((n, width), np.bool_),
               np.zeros((n, width + 1), np.int64), np.zeros((max(4 * scene.z.shape[0], 64), 2), np.int64), np.zeros(1, np.int64),
               np.zeros((n, width, d)), np.zeros((n, width)))
    unexplained = np.zeros((n, 2), np.int64)
    counters = np.zeros(3, np.int64)
    beam = kb.new_generation(1, 1, d)
    beam[0][0], beam[1][0], beam[2][0] = x0, P0, 0.0
    size = 1
    settled = 0
    for first, last in progress.blocks():
        k = first
        while k < last:
            status, k, parents, n_parents, children, count = _at_pose(counters, kb.run_poses, scene, settings, sparse, k, last, beam, size,
                                                                     history, unexplained, counters)
            if status in (kb.GROW, kb.SLIP):
                obs = scene.pose_obs[scene.pose_obs_start[k]:scene.pose_obs_start[k + 1]]
                pose_width, pose_delta = pose_beam(bool(sparse[k]), settings.beam_width, settings.beam_delta)
                if status == kb.SLIP:
                    from camloc.seeds import explain_with_seeds

                    gen, kept = _at_pose(counters, explain_with_seeds, scene, settings, parents, n_parents, children, count, obs,
                                         unexplained[:counters[2]], pose_width, pose_delta)
                else:  # the pose was explained, but its record did not fit
                    gen, kept = children, kb.prune(scene, settings, children, count, pose_width, pose_delta)
                while not kb.commit(history, k, gen, kept):
                    history = history[:4] + (np.concatenate([history[4], np.zeros_like(history[4])]),) + history[5:]
                unexplained[counters[2]] = (gen[4][kept[0]], obs.size)
                counters[2] += 1
                beam, size = kb.carry(gen, kept), kept.size
                k += 1
                continue
            beam, size = parents, n_parents
        through = settled_through(history[0], settled, last)
        if through >= settled:
            settle(through + 1, *_backtrack(history, settled, through))
            settled = through + 1
        progress.done(last)
    if settled < n:
        settle(n, *_backtrack(history, settled, n - 1))


def settled_through(kept_count, first, stop):
    """The last pose of first..stop - 1 at which the beam kept one hypothesis (first - 1 if none):
    every hypothesis after it descends from that one, so its pairs and those of the poses before
    it no longer change."""
    single = np.flatnonzero(kept_count[first:stop] == 1)
    return first + int(single[-1]) if single.size else first - 1


def _backtrack(history, first, last):
    """The pairs, slip flags and association spreads (``camloc.beam.BeamSearch._spread_about``)
    of poses first..last along the ancestors of pose last's best hypothesis (poses before first
    are settled)."""
    count, parent, slipped_flag, pair_start, pairs, _, state, cost = history
    chosen = [None] * (last - first + 1)
    path = np.empty(last - first + 1, np.int64)      # the ancestor's row at each pose
    parents, starts = parent[first:last + 1].tolist(), pair_start[first:last + 1].tolist()   # Python's ints: no numpy scalars
    index = 0
    for k in range(last - first, -1, -1):
        path[k] = index
        chosen[k] = pairs[starts[k][index]:starts[k][index + 1]].copy()
        index = parents[k][index]
    slipped = slipped_flag[np.arange(first, last + 1), path]
    return chosen, slipped, _spreads_about(state[first:last + 1], cost[first:last + 1], count[first:last + 1], path)


def _spreads_about(state, cost, count, path):
    """``mixture_spread`` of each pose's kept hypotheses (state (K, W, d), cost (K, W), the first
    count (K,) of each) about row ``path`` (K,). The Euler state's are computed for the poses of
    one count at a time, as arrays: the same numbers to the bit as pose by pose (elementwise
    steps, and each pose's sums and products over the same count), where the loop of a few numpy
    calls per pose was 3.3% of the 20k pixel world's CPU (docs/performance.md, 2026-12-07)."""
    d = state.shape[2]
    spread = np.zeros((state.shape[0], d, d))
    if d != 6:                                        # the planar state's difference is a rotation: pose by pose
        model = FILTER_OF_SIZE[d]
        for k in np.flatnonzero(count > 1):
            differences = np.array([model.difference(state[k, h], state[k, path[k]]) for h in range(count[k])])
            spread[k] = mixture_spread(differences, cost[k, :count[k]])
        return spread
    for c in np.unique(count[count > 1]):
        ks = np.flatnonzero(count == c)
        differences = FILTER_OF_SIZE[d].differences(state[ks, :c], state[ks, path[ks]][:, None, :])
        spread[ks] = mixture_spread(differences, cost[ks, :c])
    return spread


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
    """Blocks of poses between progress reports (at most ``most`` poses each); with the beam, the
    search and the filter each count for half of the bar."""

    def __init__(self, n: int, callback: Optional[ProgressCallback], *, halves: int, most: Optional[int] = None):
        self.n, self.callback, self.halves, self.pass_ = n, callback, halves, 0
        self.stride = max(1, n // (PROGRESS_STEPS // halves)) if callback else max(n, 1)
        if most is not None:
            self.stride = min(self.stride, most)
        # the filter's count while the search goes on, where it runs in a thread of its own
        self.filtered: Callable[[], int] = lambda: 0

    def blocks(self):
        for first in range(0, self.n, self.stride):
            yield first, min(first + self.stride, self.n)
        self.pass_ += 1

    def done(self, last: int) -> None:
        """Poses up to ``last`` done in this pass (the search's, then the filter's)."""
        if self.callback is not None:
            done = self.pass_ * self.n + last + (self.filtered() if self.pass_ == 0 else 0)
            self.callback(min(self.n, done // self.halves), self.n)
