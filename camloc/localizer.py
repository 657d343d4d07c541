"""The localizer: an Euler-angle EKF over the odometry chain, corrected by camera observations whose
landmark is unknown and found by data association.

    result = localize(dataset, LocalizerConfig(association="best-friends"))

One pose at a time (``_Localizer.step``): predict with the odometry increment, associate the pose's
observations with the map, update with every accepted pair stacked, record.
"""

from __future__ import annotations

import os
import time
from contextlib import nullcontext
from dataclasses import replace
from typing import Callable, Optional

import numpy as np

from camloc import association, associators, ekf, geometry, lacking_spread, measurement, planar, recentre, tags, warmup
from camloc.tag_orientations import TagOrientations
from camloc.associators import AssociationScene, orientation_terms
from camloc.sensors import sensors_of
from camloc.stacked_update import StackedUpdate
from camloc.measurement import observation_gates
from camloc.observation_space import (candidate_distance, candidate_range, detection_range, landmark_rows, observation_noise, planar_range, reach_unmeasured,
                                      with_map_uncertainty)
from camloc.beam import BeamSearch
from camloc.beam_types import BeamSettings, BeamStatistics
from camloc.filters import make_filter, near_singularity_deg, rotation_pitch_deg
from camloc.dataset import Dataset, first_poses
from camloc.diagnostics import divergence_cause
from camloc.constants import RESTORE_LIMIT
from camloc.errors import ConfigError
from camloc.localizer_config import AUTO_FILTER, AUTO_MAP, LocalizerConfig
from camloc.mapping_follower import MappingFollower
from camloc.results import UNASSOCIATED, RunResult
from camloc.run_records import build_result, recorded_nis
from camloc.tails import chi2_quantile
from camloc.view_reach import MIN_RATE_RATIO, ReachStep, camera_reach

ProgressCallback = Callable[[int, int], None]


ENGINES = ("auto", "compiled", "numpy")

# Below this many poses the numpy localizer finishes first: the compiled loop pays about 0.6 s a
# process to start numba and load its kernels from the cache (the real file's 101 poses: 1.3 s
# wall with the compiled loop, 0.8 s with numpy), and the numpy beam costs 2-4 ms a pose more.
COMPILED_MIN_POSES = 300
# ... unless numpy would take this long over it (``warmup.numpy_seconds``): a pixel-only
# observation's ray gates many landmarks, and the numpy beam took 17.7 s over a 200-pose file of
# two pixel-only cameras that the compiled loop runs in under a second.
COMPILED_MIN_NUMPY_SECONDS = 2.0


def localize(
    dataset: Dataset,
    config: Optional[LocalizerConfig] = None,
    *,
    on_progress: Optional[ProgressCallback] = None,
    parallel: Optional[bool] = None,
    engine: str = "auto",
    on_compile: Optional[Callable[[], None]] = None,
    on_background_compile: Optional[Callable[[bool], None]] = None,
) -> RunResult:
    """Localize every pose of ``dataset`` against its landmark map.

    Parameters
    ----------
    dataset : the dataset; its ``obs_true_landmark`` is read only with ``association="oracle"``.
    config : options (defaults when None).
    on_progress : called as ``on_progress(poses_done, poses_total)`` about 200 times per run.
    parallel : with the beam, run the filter that replays its association while the beam goes on:
        the compiled loop in a second thread (``camloc.loop``), the numpy beam in a second process
        (``camloc.replay``); the result is the same either way. None: with two CPUs (and, for the
        numpy beam's process, at least ``PARALLEL_MIN_POSES`` poses). Where the compiled beam's
        kernels are not yet compiled, a parallel run compiles the filter's in a second process
        (``camloc.warmup.start_filter_compile``); False keeps the compile to this process too.
    engine : "compiled" (the loop over numba kernels, ``camloc.loop``: the Euler or the SE(2) filter with beam
        or oracle association), "numpy" (``_Localizer``, every filter and method; the compiled
        loop's reference, equal to it to rounding), or "auto": compiled where it can run and the
        dataset has at least ``COMPILED_MIN_POSES`` poses or numpy would take
        ``COMPILED_MIN_NUMPY_SECONDS`` over it (pixel-only observations). ``summary["timing"]["engine"]`` says
        which ran. The mapping pass (``config.map`` prior or none, or a map lacking landmarks)
        follows it: its steps compiled (``camloc.slam_compiled``, "compiled update") or in numpy,
        their reference (``_mapping_compiled``).
    on_compile : called once before the compiled loop starts when its kernels are not yet in
        numba's cache (the first run after an install compiles them: a minute or two).
    on_background_compile : given, a run that "auto" would give to the compiled loop while its
        kernels are not yet compiled, that numpy takes at most ``warmup.NUMPY_FIRST_RUN_SECONDS`` over,
        runs in numpy instead (the same result, sooner than the compile) and has the kernels
        compiled in a detached background process for the runs after it (``camloc.warmup``);
        called with whether this call started that process (False: an earlier one is running).
        ``summary["timing"]["background_compile"]`` says so. Where that process cannot run, the
        kernels compile in the foreground as without it. ``camloc run`` passes it.
    """
    config = resolved_config(config or LocalizerConfig(), dataset)
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, got {engine!r}")
    hooks = dict(parallel=parallel, engine=engine, on_compile=_once(on_compile), on_background_compile=_once(on_background_compile))
    offset = recentre.far_origin_offset(dataset)
    if offset is None:
        return _localize_in_reach(dataset, config, on_progress, hooks)
    # far from the origin, in a frame at the start: the mapping pass's Jacobians carry world positions
    result = _localize_in_reach(recentre.translated(dataset, offset), config, on_progress, hooks)
    return recentre.moved_back(result, dataset, offset)


def _localize_in_reach(dataset: Dataset, config: LocalizerConfig, on_progress, hooks: dict) -> RunResult:
    """``_localize_mapped`` with a pixel-only file's candidates held within the reach learned from
    its start (``_with_learned_reach``); where that run pairs a share of its observations below
    ``REACH_LOST_SHARE`` times the start's, run again with the reach guessed from the map and keep
    the run that pairs more (a warning says so)."""
    held, reach, reach_seconds, start_share, step = _with_learned_reach(dataset, config, hooks)
    result = _localize_mapped(dataset, held, on_progress, hooks)
    warnings = [_no_reach_warning(step, result)] if reach is None and reach_seconds > 0.0 else []
    if reach is not None and _paired_share(result) < REACH_LOST_SHARE * start_share:
        again = _localize_mapped(dataset, config, on_progress, hooks)
        reach_seconds += result.summary["timing"]["filter_seconds"]
        if _paired_share(again) > _paired_share(result):
            warnings.append(f"the run with the pixel cameras' reach learned from the first poses ({reach:.2f} m) paired "
                            f"{_paired_share(result):.0%} of its observations against {start_share:.0%} at the start: "
                            f"run again with the reach guessed from the map (candidates within "
                            f"{again.summary['candidate_range']['max_depth']:.2f} m), which paired {_paired_share(again):.0%}")
            result, reach = again, None
    result.summary["candidate_range"]["learned_reach"] = reach
    result.summary["candidate_range"]["reach_step"] = _step_summary(step)
    result.summary["warnings"] += warnings
    timing = result.summary["timing"]
    timing["reach_seconds"] = reach_seconds  # the runs over the start that learned it (or not kept), counted in filter_seconds
    timing["filter_seconds"] += reach_seconds
    timing["poses_per_second"] = dataset.num_poses / timing["filter_seconds"] if timing["filter_seconds"] > 0 else float("inf")
    return result


def _paired_share(run: RunResult) -> float:
    """The share of ``run``'s observations it paired with a landmark."""
    counts = run.summary["counts"]
    return counts["accepted"] / counts["observations"] if counts["observations"] else 0.0


def _localize_mapped(dataset: Dataset, config: LocalizerConfig, on_progress, hooks: dict) -> RunResult:
    """``localize`` after its config is resolved: the map held exactly (with landmarks the map
    lacks added where the run finds it lacking) or, under ``prior`` and ``none``, the mapping
    localizer."""
    if config.map != "exact":  # landmarks in the state: the mapping localizer
        return _localize_mapping(dataset, config, on_progress, hooks)
    # in every mode, landmarks the map lacks are added: where the rejected observations agree on
    # places the map has no landmark at, the mapping localizer takes the run's pairs and adds them
    with _follower(dataset, config, hooks) as follower:
        result, _, places = _map_run(dataset, dataset, config, on_progress, hooks, follower)
        if places:
            result = _localize_mapping(dataset, config, on_progress, hooks, given_run=result, follower=follower)
    if places:
        added = result.summary["map"]["added"]
        # where the mapping pass placed none (a jump in the odometry, rays it cannot place), "0
        # landmark(s) added" read as a contradiction of the first half
        outcome = f"{added} landmark(s) added" if added else "the mapping pass added none of them"
        result.summary["warnings"].append(
            f"the map lacks landmarks: the rejected observations agreed on {places} place(s) it has none at; "
            f"{outcome} (map.csv of the run folder; docs/mapping.md)")
    return result


# A pixel-only file's reach (how far its cameras detect landmarks; no depth in the file says) is
# learned from the run over its first REACH_POSES poses (``view_reach.camera_reach``), and the
# candidates' depth and distance (``ViewOptions.max_depth``, ``max_distance``) held to it, REACH_MARGIN
# over it (the distance since 2026-12-05: docs/performance.md, "The precision possible on pixel-only
# worlds"). A far landmark on
# an observation's ray gates as well as the near one it sees; the reach guessed from the map's
# density (``observation_space.pixel_reach``) let 1-5% of pairs take such landmarks. A margin of
# 0.05 gave a little more precision but lost the robot on one world of 40 where 0.1 did not (a
# landmark near the reach, estimated beyond it, left out). Measured: docs/performance.md,
# 2026-12-04, "A pixel camera's reach, learned".
REACH_POSES = 300
REACH_MARGIN = 0.1
# A run held within the learned reach that pairs less than this share of what the start's run
# paired has lost the robot where the guess did not (a landmark near the reach, estimated beyond
# it, left out): it runs again with the guess (measured: performance.md, as above).
REACH_LOST_SHARE = 0.8


def _with_learned_reach(dataset: Dataset, config: LocalizerConfig,
                        hooks: dict) -> tuple[LocalizerConfig, Optional[float], float, float, Optional[ReachStep]]:
    """``config`` with its candidates' depth and distance held to the reach learned from the start of the run
    (``REACH_POSES``), that reach in metres, the seconds the start's run took, the share of its
    observations it paired and the sharpest step of its pairing rate (``view_reach.ReachStep``);
    ``config``, None, 0, 0 and None where the file measures range or has no map, the reach is
    given (``config.view.max_depth`` or ``max_distance``), the association is the oracle (no
    candidates); ``config`` and None for the reach where the start shows no step of at least
    ``view_reach.MIN_RATE_RATIO`` (the step, if any, still returned: the warning cites it)."""
    if (config.view.max_depth is not None or config.view.max_distance is not None or config.association == "oracle"
            or dataset.landmark_ids.size == 0 or not reach_unmeasured(dataset)):
        return config, None, 0.0, 0.0, None
    started = time.perf_counter()
    view = candidate_range(dataset, config)
    start = first_poses(dataset, REACH_POSES)
    run = _localize_exact(start, replace(config, map="exact"), None, **hooks)
    rows = landmark_rows(dataset.landmark_ids, _observation_landmarks(start, run))
    step = camera_reach(start, run.estimate_xyz, run.estimate_quat_xyzw, rows, view)
    seconds, share = time.perf_counter() - started, _paired_share(run)
    if step is None or step.ratio < MIN_RATE_RATIO:
        return config, None, seconds, share, step
    held = (1.0 + REACH_MARGIN) * step.reach
    # the reach is a distance from the camera: held as one, not only as a depth (which let
    # candidates at the cone's edge lie up to 1.7 times as far), also where the guess is the nearer depth
    return replace(config, view=replace(config.view, max_depth=min(view[1], held), max_distance=held)), step.reach, seconds, share, step


def _step_summary(step: Optional[ReachStep]) -> Optional[dict]:
    """The summary's record of the step the reach was (or was not) learned from."""
    if step is None:
        return None
    return {"reach": step.reach, "poses": step.poses, "near_rate": step.near_rate, "far_rate": step.far_rate,
            "near_low": step.near_low, "far_high": step.far_high, "ratio": step.ratio}


def _no_reach_warning(step: Optional[ReachStep], result: RunResult) -> str:
    """Why the candidates reach as far as the map's density guesses: the start showed no step."""
    sharpest = ("none" if step is None else
                f"near surely {step.ratio:.1f} times far at {step.reach:.2f} m over its first {step.poses} poses, against {MIN_RATE_RATIO:g}")
    return (f"the pixel cameras' reach was not learned: the run over the first poses showed no sure step in its pairing rate "
            f"(sharpest: {sharpest}); candidates within {result.summary['candidate_range']['max_depth']:.2f} m, guessed "
            f"from the map's density (--max-distance sets the reach)")


# Where the map lacks landmarks, the beam decides the map's pairs again with the null cost lowered
# by this much (the reasons and measures: ``camloc.lacking_spread``, where the mapping pass prices the
# same alternative).
LACKING_NULL_OFFSET = lacking_spread.LACKING_NULL_OFFSET  # defined beside the mapping pass's use of it


# Under a prior, a rejected observation within this many map sigmas of a mapped landmark (more than
# the screening's own radius) may be of that landmark, moved: not a landmark the map lacks.
PRIOR_REACH_SIGMAS = 3.0


# A run of at least LACKING_PREFIX_MIN_POSES poses screens its first LACKING_PREFIX_SHARE first:
# where the map lacks landmarks there, the whole run's beam judges with LACKING_NULL_OFFSET at
# once, one pass of the beam instead of two (the 20,000-pose world with a fifth withheld: the
# second beam pass had taken it from about 1,150 to 500 poses/s); a complete map pays the
# prefix, a fortieth of its beam. Shorter runs are screened after their run (the prefix would
# cost more than its share: the compiled loop's least is COMPILED_MIN_POSES), as is a map that
# lacks landmarks only later in a long run.
LACKING_PREFIX_MIN_POSES = 12000
LACKING_PREFIX_SHARE = 0.025


def _map_run(judged: Dataset, dataset: Dataset, config: LocalizerConfig, on_progress, hooks: dict,
             follower: Optional[MappingFollower] = None) -> tuple[RunResult, float, int]:
    """The localizer's run against the map held exactly, its association judging ``judged``
    (``dataset``, or under a prior the same with the map's uncertainty in the noise), with the
    null cost lowered by ``LACKING_NULL_OFFSET`` where the map lacks landmarks (the start of a
    long run screened first, ``_lacking_at_start``; otherwise the run screened, and the beam's run
    again). Returns the run, the offset it used and the places the map lacks a landmark at (0
    where it is not screened: a dataset the mapping localizer does not run, or the oracle's where
    the file's ids name no landmark the map lacks, ``_ids_lacking``). The oracle's run is screened
    too: where the map lacks landmarks, the true association maps them (the mapping localizer
    pairs by the file's ids), the reference the default association's mapping run is measured
    against; left unscreened, it ignored them, a reference no run with mapping reaches.
    ``follower``: the mapping pass to run beside the run whose pairs it takes: the run where the
    start found the map lacking (no second run of the beam follows), or the beam's second run."""
    offset = _lacking_at_start(judged, dataset, config, hooks)
    follow = follower.on_replay if follower is not None else None
    run = _localize_exact(judged, replace(config, map="exact"), on_progress, null_cost_offset=offset,
                          on_replay=follow if offset > 0.0 else None, map_uncertain=judged is not dataset, **hooks)
    screened = _mappable(dataset) and (config.association != "oracle" or _ids_lacking(dataset))
    places = _lacking_places(dataset, run, config) if screened else 0
    if places and offset == 0.0 and config.association == "beam":
        offset = LACKING_NULL_OFFSET
        run = _lacking_map_beam(judged, config, on_progress, hooks, run, on_replay=follow, map_uncertain=judged is not dataset)
    return run, offset, places


def _ids_lacking(dataset: Dataset) -> bool:
    """Whether the file's ids name a landmark the map lacks, observed at least twice: what the
    oracle's mapping pass adds (``slam_landmarks._oracle_new``; clutter's ids are seen once). A
    map whose landmark moved has none: the oracle pairs its observations by their ids, and the
    exact map's run stays the localizer's (nothing to add)."""
    ids, seen = np.unique(dataset.obs_true_landmark, return_counts=True)
    return bool(np.any((seen >= 2) & ~np.isin(ids, dataset.landmark_ids) & (ids >= 0)))


def _lacking_at_start(judged: Dataset, dataset: Dataset, config: LocalizerConfig, hooks: dict) -> float:
    """The null cost's offset for the run: ``LACKING_NULL_OFFSET`` where the beam's run over the
    start of a long run (judging ``judged``) finds ``dataset``'s map lacking, else 0."""
    if config.association != "beam" or not _mappable(dataset) or dataset.num_poses < LACKING_PREFIX_MIN_POSES:
        return 0.0
    # at least the compiled loop's least (numpy runs shorter ones, at ~2 ms a pose more)
    count = max(COMPILED_MIN_POSES, int(LACKING_PREFIX_SHARE * dataset.num_poses))
    prefix = first_poses(dataset, count)
    run = _localize_exact(prefix if judged is dataset else first_poses(judged, count), replace(config, map="exact"), None, **hooks)
    return LACKING_NULL_OFFSET if _lacking_places(prefix, run, config) else 0.0


def _once(callback: Optional[Callable]) -> Optional[Callable]:
    """``callback`` called at most once (a run's engines may start twice: the prefix screened
    first, ``_lacking_at_start``), None for None."""
    if callback is None:
        return None
    called = []

    def once(*args):
        if not called:
            called.append(True)
            callback(*args)
    return once


def _lacking_places(dataset: Dataset, run: RunResult, config: LocalizerConfig) -> int:
    """How many places the map lacks a landmark at, by ``run``'s rejected observations
    (``slam_landmarks.lacking_landmarks``)."""
    from camloc.slam_landmarks import lacking_landmarks

    T = geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw)
    reach = PRIOR_REACH_SIGMAS * config.map_sigma if config.map == "prior" else 0.0
    return lacking_landmarks(dataset, T, run.estimate_cov, _observation_landmarks(dataset, run) == UNASSOCIATED, reach)


def _lacking_map_beam(dataset: Dataset, config: LocalizerConfig, on_progress, hooks: dict, first: RunResult,
                     on_replay=None, map_uncertain: bool = False) -> RunResult:
    """The exact map's run again, its beam judging with ``LACKING_NULL_OFFSET`` (the map lacks
    landmarks: ``first``, the run that found so, is replaced; its time is counted)."""
    again = _localize_exact(dataset, replace(config, map="exact"), on_progress, null_cost_offset=LACKING_NULL_OFFSET,
                            on_replay=on_replay, map_uncertain=map_uncertain, **hooks)
    again.summary["timing"]["filter_seconds"] += first.summary["timing"]["filter_seconds"]
    return again


def _localize_exact(dataset: Dataset, config: LocalizerConfig, on_progress, *, parallel, engine, on_compile,
                    on_background_compile, null_cost_offset: float = 0.0, on_replay=None,
                    map_uncertain: bool = False) -> RunResult:
    """The localizer against the map held exactly (``localize``'s engines); ``null_cost_offset``
    lowers the cost of leaving an observation unexplained (``LACKING_NULL_OFFSET``); ``on_replay``:
    ``loop.run_compiled``'s, where the compiled loop runs the beam; ``map_uncertain``: the
    dataset's noise holds a map prior's uncertainty (``with_map_uncertainty``)."""
    # a tag's orientation is the numpy engine's only (camloc.tags)
    compilable = (config.filter in COMPILED_FILTERS and config.association in COMPILED_ASSOCIATIONS
                  and not np.any(dataset.obs_kind == measurement.TAG_ROTATION))
    if engine == "compiled" and not compilable:
        raise ConfigError(f"the compiled loop runs the {' and '.join(COMPILED_FILTERS)} filters with {' or '.join(COMPILED_ASSOCIATIONS)} "
                          f"association, without tag orientations; filter {config.filter!r} with association {config.association!r} "
                          "runs in numpy")
    numpy_slower = map_uncertain or null_cost_offset > 0.0
    use_compiled = engine == "compiled" or (engine == "auto" and compilable
                                            and (_compiled_pays(dataset) or (numpy_slower and _kernels_ready())))
    background = None  # the state of the background compile this run leaves the kernels to
    filter_compile = None  # the process compiling the filter's kernels while this one compiles the beam's
    warm = True
    if use_compiled:
        from camloc.kernels import cache_is_warm

        # a background compile caches its first kernels before its last: cold until it is done
        warm = cache_is_warm()
        if not warm or warmup.compiling():
            if engine == "auto" and on_background_compile is not None:
                background = _compile_in_background(dataset)
            if background is not None:
                on_background_compile(background == warmup.STARTED)
                use_compiled = False
            elif on_compile is not None:
                on_compile()
    concurrent = parallel if parallel is not None else _cpus() >= 2
    if use_compiled and not warm and config.association == "beam" and concurrent:
        # a first compile: the filter's kernels in a second process (parallel=False keeps to one core)
        filter_compile = warmup.start_filter_compile()
    if use_compiled:
        result = _localize_compiled(dataset, config, on_progress, concurrent,
                                    filter_ready=(lambda: warmup.wait_for(filter_compile)) if filter_compile else None,
                                    null_cost_offset=null_cost_offset, on_replay=on_replay)
    else:
        result = _localize_numpy(dataset, config, on_progress, parallel, null_cost_offset)
    result.summary["timing"]["background_compile"] = background is not None
    return result


# Under a prior, how many times the beam decides the map's pairs: each pass after the first judges
# them against the map the pass before estimated (a moved landmark nearer where it is), so that
# observations a moved landmark's map position left out are paired in the next pass (see
# docs/performance.md, 2026-12-03: moved landmarks' error on pixel-only worlds). A later pass
# is kept only where the filter found it as consistent (NIS per degree of freedom at most
# PASS_NIS_SLACK times the kept pass's): a pass judged against a map that a lost first pass bent
# can lose the robot for good (one pixel world: NIS per dof 1.2 -> 7.8, RMSE 0.36 -> 4.4 m).
PRIOR_PASSES = 2
PASS_NIS_SLACK = 1.2
# A pass after the first runs only where the first moved the map: more than MOVED_SHARE of the
# mapped landmarks it observed (and more than MOVED_LEAST of them) left their map positions by over
# MOVED_SIGMAS map sigmas. Measured after a first pass (docs/performance.md): maps that are right,
# 0-1 of 168-689 landmarks on 300-pose worlds of every kind (depth and pixel cameras) and 20 of
# 1,594 (1.3%) on a 2,000-pose world with a fifth withheld; a quarter moved 0.3 m, 13-22%.
MOVED_SIGMAS = 1.5
MOVED_SHARE = 0.03
MOVED_LEAST = 2


# The mapping pass runs beside the beam's run (a second process) only on runs of at least this
# many poses: its process costs about 1.5 s to start (an interpreter, camloc, the dataset, the
# kernels from the cache), more than the overlap saves on shorter runs (docs/performance.md,
# 2026-12-04, "The mapping pass beside the beam": 5,000 poses 3.9 -> 5.2 s, 20,000 poses 19.4-22.0
# -> 14.5-17.3 s).
FOLLOW_MIN_POSES = 12000


def _follower(dataset: Dataset, config: LocalizerConfig, hooks: dict) -> MappingFollower:
    """A mapping pass that may run beside the beam's run (``camloc.mapping_follower``): it follows
    a run only where the compiled loop runs the beam over at least ``FOLLOW_MIN_POSES`` poses,
    with two CPUs or more, one of them free (``_cpu_free``), and ``parallel`` not False; otherwise
    it never starts and the pass runs after."""
    # (not tags: a tag's orientation is the numpy mapping pass's only, and the follower runs the compiled one)
    able = (config.association == "beam" and hooks["parallel"] is not False and _cpus() >= 2 and _mappable(dataset)
            and not np.any(dataset.obs_kind == measurement.TAG_ROTATION)
            and dataset.num_poses >= FOLLOW_MIN_POSES and _cpu_free())
    return MappingFollower(dataset, config, lambda: _mapping_compiled(dataset, hooks), enabled=able)


def _localize_mapping(dataset, config, on_progress, hooks: dict, given_run: Optional[RunResult] = None,
                      follower: Optional[MappingFollower] = None) -> RunResult:
    """The mapping localizer (``camloc.slam_run``): ``config.map`` prior or none, or exact where
    the map lacks landmarks (``given_run``: the exact map's run). With the beam and a map, the beam
    first decides which observations are the map's, over the whole run and on the map as given
    (robust where one pose's evidence is not), and the mapping localizer takes those pairs and
    decides the rest among added landmarks, new ones and clutter. Under a prior, that is done up to
    ``PRIOR_PASSES`` times, the beam judging against the map the pass before estimated; every
    pass's estimate holds the map as given as its prior (only the pairs change)."""
    from camloc.slam_run import localize_mapping

    beamed = given_run is None and config.association == "beam" and config.map != "none" and dataset.landmark_ids.size
    passes = PRIOR_PASSES if beamed and config.map == "prior" else 1
    stages = 2 * passes if beamed else 1
    judged_map, seconds, kept, offset = dataset, 0.0, None, 0.0
    compiled = _mapping_compiled(dataset, hooks)
    for n in range(passes):
        given, warnings, beam_run = None, [], given_run
        # each pass's mapping may run beside its beam's run (``camloc.mapping_follower``)
        with _follower(dataset, config, hooks) if beamed else nullcontext(follower) as following:
            if beamed:
                # under a prior, the beam judges each pair with the map's uncertainty in its noise (a moved
                # landmark would fail every gate of an exact map); only its pairs are taken
                judged = with_map_uncertainty(judged_map, config.map_sigma) if config.map == "prior" else judged_map
                if n == 0:  # where the map lacks landmarks, as under exact
                    beam_run, offset, _ = _map_run(judged, dataset, config, _stage(on_progress, 0, stages), hooks, following)
                else:
                    beam_run = _localize_exact(judged, replace(config, map="exact"), _stage(on_progress, 2 * n, stages),
                                               null_cost_offset=offset, on_replay=following.on_replay,
                                               map_uncertain=config.map == "prior", **hooks)
            if beam_run is not None:
                given = landmark_rows(dataset.landmark_ids, _observation_landmarks(dataset, beam_run))
                seconds += beam_run.summary["timing"]["filter_seconds"]
                warnings = [w for w in beam_run.summary["warnings"] if w not in dataset.warnings]
            stage = _stage(on_progress, 2 * n + 1, stages) if beamed else on_progress
            result = following.result(given, stage) if following is not None and given is not None else None
            if result is None:
                result = localize_mapping(dataset, config, stage, given, compiled=compiled)
                if following is not None and following.failure:
                    warnings.append(f"the mapping pass's second process {following.failure}; it ran after the beam's run instead")
        seconds += result.summary["timing"]["filter_seconds"]
        if kept is None or _nis_per_dof(result) <= PASS_NIS_SLACK * _nis_per_dof(kept[0]):
            kept = result, warnings
        estimated = result.landmark_map
        rows = landmark_rows(estimated.ids, dataset.landmark_ids)
        if n + 1 == passes or not _map_moved(dataset, estimated, rows, config.map_sigma):
            break  # the last pass; or the next would judge against the map as given: the same pairs, twice the time
        judged_map = replace(dataset, landmark_xyz=_judged_positions(dataset, estimated, rows, config))
    result, warnings = kept
    timing = result.summary["timing"]
    timing["background_compile"] = False
    # the beam's passes over the map and the mapping passes not kept: all but the kept mapping pass
    result.summary["map"]["beam_seconds"] = seconds - timing["filter_seconds"]
    timing["filter_seconds"] = seconds
    timing["poses_per_second"] = dataset.num_poses / seconds if seconds > 0 else float("inf")
    result.summary["warnings"] += warnings
    return result


def _mapping_compiled(dataset: Dataset, hooks: dict) -> bool:
    """Whether the mapping pass runs its compiled steps (``camloc.slam_compiled``), as the
    localizer decides for its loop: not on a short run (``COMPILED_MIN_POSES``), and, where
    ``camloc run`` asks for a background compile, not while their cache is cold (numpy, which
    gives the same result, runs then, and a detached process compiles them: ~25 s of CPU)."""
    engine = hooks["engine"]
    if engine == "numpy" or (engine == "auto" and dataset.num_poses < COMPILED_MIN_POSES):
        return False
    if engine == "compiled" or hooks["on_background_compile"] is None:
        return True
    from camloc.slam_compiled import cache_folder, cache_is_warm

    if cache_is_warm():
        return True
    state = warmup.start_background_compile(cache_folder(), mapping=True)
    if state is None:  # it cannot run in the background: in the foreground
        return True
    hooks["on_background_compile"](state == warmup.STARTED)
    return False


def _map_moved(dataset: Dataset, estimated, rows: np.ndarray, sigma: float) -> bool:
    """Whether a mapping pass moved the map (``MOVED_SIGMAS``, ``MOVED_SHARE``, ``MOVED_LEAST``):
    ``estimated`` its map, ``rows`` each mapped landmark's row in it (-1: not kept)."""
    kept = rows >= 0
    observed = kept.copy()
    observed[kept] = estimated.observations[rows[kept]] > 0
    shift = np.linalg.norm(estimated.xyz[rows[observed]] - dataset.landmark_xyz[observed], axis=1)
    moved = int(np.count_nonzero(shift > MOVED_SIGMAS * sigma))
    return moved > max(MOVED_LEAST, MOVED_SHARE * int(np.count_nonzero(observed)))


def _judged_positions(dataset: Dataset, estimated, rows: np.ndarray, config: LocalizerConfig) -> np.ndarray:
    """(L, 3) where the next pass's beam judges the map's landmarks: each at the estimate the pass
    made of it (its map position where the pass did not keep it), and a mapped landmark at the
    landmark the pass added in its place (``slam_landmarks.moved_in_place_of_added``:
    a moved landmark added twice), so that the next pass pairs those observations with it."""
    from camloc.slam_landmarks import NEW_LANDMARK_TAIL, moved_in_place_of_added

    xyz = np.where((rows >= 0)[:, None], estimated.xyz[rows], dataset.landmark_xyz)
    # the gate by which an observation is a landmark already known rather than a new one (wider
    # than the association's: a landmark added twice stays twice)
    added = moved_in_place_of_added(dataset.landmark_xyz, estimated, rows, config.map_sigma, chi2_quantile(3, NEW_LANDMARK_TAIL))
    xyz[added >= 0] = estimated.xyz[added[added >= 0]]
    return xyz


def _nis_per_dof(result: RunResult) -> float:
    """A run's normalized innovation squared per degree of freedom over its updates (1 where
    consistent; 0 without updates)."""
    dof = float(np.sum(result.nis_dof))
    return float(np.sum(result.nis)) / dof if dof > 0 else 0.0


def _stage(on_progress, stage: int, stages: int):
    """``on_progress`` for one of ``stages`` equal parts of a run (the ``stage``-th, from 0)."""
    if on_progress is None or stages == 1:
        return on_progress
    return lambda done, total, report=on_progress: report((stage * total + done) // stages, total)


def _mappable(dataset: Dataset) -> bool:
    """Whether the mapping localizer runs the dataset: point landmarks, of a 3-D robot's cameras or
    a planar robot's cameras and point sensor, a planar robot's markers, and tags with their
    orientations (``camloc.slam_tags``)."""
    return unmappable_reason(dataset) is None


def unmappable_reason(dataset: Dataset) -> Optional[str]:
    """Why the mapping localizer (EKF-SLAM: landmarks the map lacks added) cannot run ``dataset``,
    as the end of a sentence, or None where it can: every dataset camloc reads is mapped now (the
    reason stays for the kinds a later reader may add)."""
    return None


def _observation_landmarks(dataset: Dataset, run: RunResult) -> np.ndarray:
    """The landmark id (K,) ``run`` paired each observation of ``dataset`` with (``UNASSOCIATED``:
    none), from its rows (one a tag, its position's: a tag's orientation gets none here)."""
    if not np.any(dataset.obs_kind == measurement.TAG_ROTATION):
        return run.associations.landmark
    return tags.observation_landmarks(run.associations.landmark, dataset.obs_kind, dataset.obs_partner, orientations=False)


def resolved_config(config: LocalizerConfig, dataset: Dataset) -> LocalizerConfig:
    """``config`` validated, its filter "auto" made the one the dataset's robot calls for (se2 for
    a planar robot, euler otherwise); ConfigError where the filter cannot run the dataset: the
    planar kinds of observation (point2, marker) are the SE(2) filter's only, and se2 needs a
    planar robot."""
    config.validate()
    if config.filter == AUTO_FILTER:
        config = replace(config, filter="se2" if dataset.planar else "euler")
    mappable = _mappable(dataset)
    if config.map == AUTO_MAP:
        config = replace(config, map="none" if mappable and dataset.landmark_ids.size == 0 else "exact")
    if config.map != "exact" and not mappable:
        raise ConfigError(f"map {config.map!r} (mapping) cannot run this dataset: {unmappable_reason(dataset)}: "
                          "use --map exact")
    planar_kinds = [measurement.KINDS[int(k)].tag for k in np.unique(dataset.obs_kind) if int(k) in measurement.PLANAR_KINDS]
    if planar_kinds and config.filter != "se2":
        raise ConfigError(f"filter {config.filter!r} cannot use {', '.join(planar_kinds)} observations (a planar robot's, "
                          "in its own frame): use --filter se2, the default for planar files")
    if config.filter == "se2" and not dataset.planar:
        raise ConfigError("filter 'se2' localizes a planar robot (VERTEX_SE2 / EDGE_SE2 poses); this dataset's robot is 3-D: "
                          "use euler or se3")
    return config


def initial_cov(config: LocalizerConfig, filter_model) -> np.ndarray:
    """The start pose's covariance in the filter's error: ``config.initial_cov()`` (6, 6), or its
    (x, y, yaw) block for a planar filter (3 dof)."""
    P = config.initial_cov()
    return P if filter_model.dim == 6 else planar.planar_block(P)


def _compiled_pays(dataset: Dataset) -> bool:
    """Whether "auto" gives ``dataset`` to the compiled loop: at least ``COMPILED_MIN_POSES``
    poses, or a file numpy would take ``COMPILED_MIN_NUMPY_SECONDS`` over."""
    if dataset.num_poses >= COMPILED_MIN_POSES:
        return True
    pixel = int(np.count_nonzero(measurement.is_ray(dataset.obs_kind)))
    return warmup.numpy_seconds(dataset.num_observations, pixel) >= COMPILED_MIN_NUMPY_SECONDS


def _kernels_ready() -> bool:
    """Whether the compiled loop's kernels are compiled and cached (no compile going on): a beam's
    pass that numpy is far slower over than ``warmup.numpy_seconds`` counts (with the null cost
    lowered where the map lacks landmarks, or judging with a map prior's uncertainty: wider gates,
    more hypotheses; 100-250-pose worlds with a quarter of the map moved, 7-45x its estimate,
    docs/performance.md) runs compiled on a short file too, where no compile is needed for it."""
    from camloc.kernels import cache_is_warm

    return cache_is_warm() and not warmup.compiling()


def _compile_in_background(dataset: Dataset) -> Optional[str]:
    """``warmup.STARTED`` or ``warmup.RUNNING`` where this run goes to numpy while the kernels
    compile in the background; None where it compiles them first."""
    pixel = int(np.count_nonzero(measurement.is_ray(dataset.obs_kind)))
    if warmup.numpy_seconds(dataset.num_observations, pixel) > warmup.NUMPY_FIRST_RUN_SECONDS:
        return None
    return warmup.start_background_compile()


def _localize_numpy(dataset: Dataset, config: LocalizerConfig, on_progress: Optional[ProgressCallback],
                    parallel: Optional[bool], null_cost_offset: float = 0.0) -> RunResult:
    localizer = _Localizer(dataset, config, null_cost_offset)
    started = time.perf_counter()
    n = dataset.num_poses
    stride = max(1, n // 200)
    beam_progress = lambda k: on_progress(k + 1, n) if on_progress and k % stride == 0 else None  # noqa: E731
    if config.association == "beam" and (parallel if parallel is not None else _parallel_worthwhile(n)):
        from camloc.replay import search_and_replay

        search_and_replay(localizer, beam_progress)
        if on_progress is not None:
            on_progress(n, n)
        return localizer.result(time.perf_counter() - started)
    if config.association == "beam":
        # The beam decides the association (most of the work), then the filter replays it.
        localizer.search_beam(beam_progress)
    for k in range(n):
        localizer.step(k)
        if on_progress is not None and ((k % stride == 0 and config.association != "beam") or k == n - 1):
            on_progress(k + 1, n)
    return localizer.result(time.perf_counter() - started)


# The filters and associations the compiled loop (``camloc.loop``) runs; the others run in numpy below.
COMPILED_FILTERS = ("euler", "se2")
COMPILED_ASSOCIATIONS = ("beam", "oracle")


def _localize_compiled(dataset: Dataset, config: LocalizerConfig, on_progress: Optional[ProgressCallback],
                       concurrent: bool, filter_ready: Optional[Callable[[], None]] = None,
                       null_cost_offset: float = 0.0, on_replay=None) -> RunResult:
    from camloc.loop import PoseFailure, run_compiled

    model = make_filter(config.filter)
    x0 = model.initial(dataset.T_world_start)
    started = time.perf_counter()
    view_range = candidate_range(dataset, config)
    try:
        states, covs, chosen, distance, update_k, nis, map_cost, dof, slipped, spread = run_compiled(
            dataset, config, on_progress, initial_x=x0, initial_P=initial_cov(config, model), concurrent=concurrent,
            filter_ready=filter_ready, view_range=view_range, null_cost_offset=null_cost_offset, on_replay=on_replay)
    except PoseFailure as failure:
        detail = str(failure) if str(failure).startswith("a covariance") else f"a covariance is no longer positive definite ({failure})"
        raise ekf.FilterDivergedError(detail).at_pose(int(dataset.pose_ids[failure.k]), divergence_cause(dataset)) from None
    seconds = time.perf_counter() - started
    odometry = np.empty((dataset.num_poses, 4, 4))
    T = dataset.T_world_start
    increments = dataset.T_odometry
    for k in range(dataset.num_poses):
        if k > 0:
            T = T @ increments[k - 1]
        odometry[k] = T
    warnings = []
    near = np.flatnonzero(near_singularity_deg(states[:, 4])) if model.name == "euler" else np.zeros(0, int)
    if near.size:
        k = int(near[0])
        warnings.append(f"pose {int(dataset.pose_ids[k])}: pitch {float(rotation_pitch_deg(states[k, 4])):.1f} deg is close to the Euler filter's "
                        "singularity at +-90 deg; its estimate may degrade from here (--filter se3 has no singularity)")
    landmark = np.where(chosen >= 0, dataset.landmark_ids[np.maximum(chosen, 0)] if dataset.landmark_ids.size else UNASSOCIATED, UNASSOCIATED)
    return build_result(
        dataset, config, model, states, covs, model.pose(states), odometry, landmark.astype(np.int64), distance,
        dataset.pose_ids[update_k], nis, map_cost, dof, warnings=warnings,
        slip_pose_ids=[int(i) for i in dataset.pose_ids[slipped]], candidate_range=view_range,
        association_spread=spread if config.association == "beam" else None,
        timing={"filter_seconds": seconds, "engine": "compiled", "replay_process": False, "replay_process_peak_mb": None,
                "replay_thread": concurrent and config.association == "beam"},
    )

# Below this many poses a second process costs more to start (an interpreter and its imports,
# about half a second) than it saves.
PARALLEL_MIN_POSES = 500


def _parallel_worthwhile(num_poses: int) -> bool:
    return num_poses >= PARALLEL_MIN_POSES and _cpus() >= 2


def _cpu_free() -> bool:
    """Whether a CPU is free beside the one this run keeps busy: the 1-minute load average at
    most the CPUs less one half (it counts this process's own busy thread, about 1 over runs back
    to back); True where the system does not say. A second process on a machine whose CPUs other
    work already takes slows the run (the 20,000-pose world with a fifth withheld, load 2 on 2
    CPUs: 19-24 s -> 22-24 s)."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # not on this system
        return True
    return load <= _cpus() - 0.5


def _cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


# The per-pose association methods (``camloc.associators``) by name, each with its options from the config.
PER_POSE_ASSOCIATORS: dict[str, Callable[[LocalizerConfig], associators.Associator]] = {
    "oracle": lambda config: associators.oracle,
    "best-friends": lambda config: associators.BestFriends(
        cost=config.best_friends.cost, margin=config.best_friends.margin, sequential=config.best_friends.sequential),
    "jcbb": lambda config: associators.Jcbb(
        probability=config.gate, max_nodes=config.jcbb.max_nodes, seed_cost=config.best_friends.cost,
        seed_margin=config.best_friends.margin),
}


def per_pose_associator(config: LocalizerConfig) -> Optional[associators.Associator]:
    """The per-pose method ``config.association`` names (``PER_POSE_ASSOCIATORS``); None for the
    beam, which decides the pairs of the whole run at once (``_Localizer.search_beam``)."""
    if config.association == "beam":
        return None
    return PER_POSE_ASSOCIATORS[config.association](config)


def _holds(recheck, row: float, steal: float, rival: float) -> bool:
    """Whether a re-checked pair holds (``RecheckOptions``): more than ``margin`` over its nearest
    alternative (another landmark or none; ``association.assignment_margins``' row), more than
    ``steal_margin`` over another observation taking its landmark, and, a ray's, more than
    ``ray_margin`` over its nearest rival landmark (``AssociationScene.ray_rival_margins``; inf
    where not judged so)."""
    return row > recheck.margin and steal > recheck.steal_margin and not rival <= recheck.ray_margin


def _against_null(recheck, row: float, steal: float, rival: float) -> bool:
    """Whether a pair that does not hold (``_holds``) failed only against leaving its observation
    unassigned: its own cost beyond the gate (row -inf: no other test means anything), or row
    within ``margin`` while the other tests pass."""
    return not row > recheck.margin and (not np.isfinite(row) or (steal > recheck.steal_margin and not rival <= recheck.ray_margin))


def _rechecked(localizer: "_Localizer", k: int, obs: np.ndarray, landmarks: np.ndarray, result: ekf.UpdateResult):
    """Pose k's pairs (obs, landmarks) after the re-check and their update (result: the update
    with all of them): ``_Localizer._recheck``'s drops, then the rays it dropped against leaving
    them unassigned alone restored where their joint cost under the kept pairs' posterior says so
    (``association.restored_pairs``). The compiled twin is ``kernels.filtering.rechecked``."""
    x, P = localizer.x, localizer.P
    keep, doubtful = localizer._recheck(localizer.obs_of_pose[k], obs, landmarks, P, result.state)
    if keep.all():
        return obs, landmarks, result
    x_kept, P_kept = x, P
    if keep.any():
        result = localizer.updated(x, P, obs[keep], landmarks[keep], map_cost=True)
        x_kept, P_kept = result.state, result.cov
    weighed = np.flatnonzero(doubtful)
    if weighed.size == 0 or weighed.size > RESTORE_LIMIT:
        return obs[keep], landmarks[keep], result
    stacked = localizer.stacked
    z_hat, H = stacked.measurement_function(obs[weighed], landmarks[weighed])[1](x_kept)
    o = obs[weighed]
    restore = association.restored_pairs(localizer.dataset.obs_z[o] - z_hat.reshape(-1, 3), H.reshape(o.size, 3, -1), P_kept,
                                         stacked.association_cov[o], stacked.null_cost[o])
    if not restore.any():
        return obs[keep], landmarks[keep], result
    keep[weighed[restore]] = True
    return obs[keep], landmarks[keep], localizer.updated(x, P, obs[keep], landmarks[keep], map_cost=True)


class _Localizer:
    """The filter's state over one run; ``step(k)`` processes pose k."""

    def __init__(self, dataset: Dataset, config: LocalizerConfig, null_cost_offset: float = 0.0):
        config = resolved_config(config, dataset)
        self.dataset, self.config = dataset, config
        self.null_cost_offset = null_cost_offset  # the replay process builds its own from these
        self.filter = make_filter(config.filter)
        # a sensor is a camera and the kind of its measurements (camloc.measurement)
        self.cameras, self.obs_sensor = sensors_of(dataset)
        self.obs_dof = measurement.dof_of(dataset.obs_kind)
        self.map_index = association.PointIndex(dataset.landmark_xyz) if len(dataset.landmark_xyz) else None

        self.true_landmark_row = landmark_rows(dataset.landmark_ids, dataset.obs_true_landmark)  # -1: not in the map
        self.min_depth, self.max_depth, self.max_angle = candidate_range(dataset, config)
        self.detect_range = detection_range(dataset, self.max_angle)  # the beam's miss term
        self.obs_gate = observation_gates(dataset.obs_kind, 1.0 - config.gate)  # each observation's, at its dof
        # what association judges each observation by (the update keeps the file's own noise), and
        # every observation as a camera-frame point (the beam's other coordinates, the update's restart)
        noise = observation_noise(dataset, config, null_cost_offset)
        self.association_cov, self.log_det_R = noise.cov, noise.log_det
        self.point, self.point_cov, self.log_det_point_cov = noise.point, noise.point_cov, noise.log_det_point_cov
        self.tag_orientations = TagOrientations(dataset, noise.cov, config.gate)
        self.null_cost = self.tag_orientations.null_cost(noise.null_cost)  # the association's (a tag's orientation too)
        self.stacked = StackedUpdate(dataset, self.filter, config.iterations, self.cameras, self.obs_sensor, noise, self.obs_dof)

        # what association sees of each pose: a tag's orientation rides with its position (``TagOrientations``)
        associated = np.flatnonzero(dataset.obs_kind != measurement.TAG_ROTATION)
        order = associated[np.argsort(dataset.obs_pose_index[associated], kind="stable")]
        bounds = np.searchsorted(dataset.obs_pose_index[order], np.arange(dataset.num_poses + 1))
        self.obs_of_pose = [order[bounds[k] : bounds[k + 1]] for k in range(dataset.num_poses)]
        self.T_increments = dataset.T_odometry
        self.scene = AssociationScene(  # what the per-pose association methods read
            dataset=dataset, filter=self.filter, cameras=self.cameras, obs_sensor=self.obs_sensor, map_index=self.map_index,
            min_depth=self.min_depth, max_depth=self.max_depth, max_angle=self.max_angle, obs_gate=self.obs_gate,
            max_distance=candidate_distance(config), association_cov=self.association_cov, tag_orientations=self.tag_orientations,
            true_landmark_row=self.true_landmark_row, conditioned=self.conditioned, planar_range=planar_range(dataset),
        )
        self.associate = per_pose_associator(config)  # None for the beam (search_beam)
        self.in_front_of = self.scene.in_front_of  # the beam's (``BeamContext.in_front_of``)

        n, k_obs = dataset.num_poses, dataset.num_observations
        self.states = np.zeros((n, self.filter.stored_size))
        self.poses = np.zeros((n, 4, 4))
        self.covs = np.zeros((n, self.filter.dim, self.filter.dim))
        self.odometry_poses = np.zeros((n, 4, 4))
        self.chosen_landmark = np.full(k_obs, UNASSOCIATED, dtype=np.int64)
        self.mahalanobis = np.full(k_obs, np.nan)
        self.update_pose_ids: list[int] = []
        self.nis: list[float] = []
        self.map_costs: list[float] = []
        self.nis_dof: list[int] = []
        self.warnings: list[str] = []
        self.warned_singularity = False

        self.x = self.filter.initial(dataset.T_world_start)
        self.P = initial_cov(config, self.filter)
        self.T_odometry = dataset.T_world_start
        self.beam_pairs: list[np.ndarray] | None = None
        self.association_spread: Optional[np.ndarray] = None  # (N, 6, 6) with the beam (search_beam)
        self.pair_spread = np.zeros((n, self.filter.dim, self.filter.dim))  # with the beam: its pairs' chance of being clutter
        self.beam_slipped: np.ndarray | None = None
        self.beam_statistics: Optional[BeamStatistics] = None  # what the beam did (search_beam)
        self.slip_pose_ids: list[int] = []
        self.replayed_in_parallel = False  # the replay ran in a second process (camloc.replay)
        self.replay_peak_mb: Optional[float] = None  # that process's peak memory, where known

    def beam_settings(self) -> BeamSettings:
        """The beam's settings of this run: the config's, and ``BeamSettings``' defaults for the
        rest."""
        c = self.config
        return BeamSettings(
            beam_width=c.beam.width, beam_delta=c.beam.delta, branch_delta=c.beam.branch_delta,
            slip_inflation=c.beam.slip_inflation, slip_cost=c.beam.slip_cost, null_offset=self.null_cost_offset,
        )

    def search_beam(
        self, on_pose: Optional[Callable[[int], None]] = None,
        on_decided: Optional[Callable[[int, list[np.ndarray], np.ndarray], None]] = None,
        *, settings: Optional[BeamSettings] = None,
    ) -> None:
        """Decide every pose's association with the beam (``camloc.beam``) before filtering;
        ``on_decided`` receives the decided poses as the beam goes (``BeamSearch.run``).
        ``settings``: the beam's, when not ``beam_settings()`` (for a setting the config does not
        hold, such as ``state_gate``). The search's statistics are kept in ``beam_statistics``."""
        search = BeamSearch(self, settings if settings is not None else self.beam_settings())
        self.beam_statistics = search.statistics
        self.beam_pairs, self.beam_slipped = search.run(self.x, self.P, on_pose=on_pose, on_decided=on_decided)
        self.association_spread = search.association_spread
        slips = np.flatnonzero(self.beam_slipped)
        self.slip_pose_ids = [int(self.dataset.pose_ids[k]) for k in slips]

    def step(self, k: int) -> None:
        try:
            self._step(k)
        except ekf.NUMERICAL_FAILURES as error:
            raise ekf.as_divergence(error).at_pose(int(self.dataset.pose_ids[k]), divergence_cause(self.dataset)) from None

    def _step(self, k: int) -> None:
        if k > 0:
            self._predict(k - 1)                       # x <- x (+) odometry increment
        obs, landmarks = self._associate(k, self.obs_of_pose[k])  # which observation is which landmark
        slipped = self.beam_slipped is not None and bool(self.beam_slipped[k])
        start = None
        if slipped:
            self.P = self.P * self.config.beam.slip_inflation  # as the beam did when it chose these pairs
            if obs.size:
                # the beam explained the pose from its seed pair, listed first (or, where no seed
                # held, from the pair it took first): one right pair pins the pose, where
                # Gauss-Newton from the slip's wide prior can settle metres away
                seed_obs, seed_landmark = self.beam_pairs[k][:1, 0], self.beam_pairs[k][:1, 1]
                start = self.updated(self.x, self.P, seed_obs, seed_landmark).state
        if obs.size:
            result = self.updated(self.x, self.P, obs, landmarks, map_cost=True, start=start)  # one stacked (iterated) update
            # A lone pair left out leaves the prior its association was already judged by; after a
            # slip, the widened prior leaves each pair's partners too little to confirm it by (a
            # few pairs pin the pose only together), and dropping them would leave the filter
            # metres wide where the beam's hypothesis went on from the slip's explanation.
            if self.config.recheck.enabled and self.config.association != "oracle" and obs.size >= 2 and not slipped:
                obs, landmarks, result = _rechecked(self, k, obs, landmarks, result)
            if self.tag_orientations and obs.size:
                # the pairs final, the orientations of their tags join them (camloc.tags): after
                # the re-check, which judges the pairs association chose, by their positions
                with_rotations = self.tag_orientations.joined(obs, landmarks, self.x, self.P, self.observe, self.obs_sensor,
                                                              self.association_cov)
                if with_rotations[0].size != obs.size or not np.array_equal(with_rotations[0], obs):
                    obs, landmarks = with_rotations
                    if obs.size:
                        result = self.updated(self.x, self.P, obs, landmarks, map_cost=True, start=result.state)
        if obs.size:
            self._record_pairs(k, obs, landmarks, result)
            self.x, self.P = result.state, result.cov
            self.pair_spread[k] = self.stacked.pair_spread(self.x, self.P, obs, landmarks) if self.beam_pairs is not None else 0.0
        self._warn_near_singularity(k)                 # by the estimate, as the compiled loop's warning
        self.states[k], self.covs[k] = self.filter.stored(self.x), self.P
        self.poses[k] = self.filter.pose(self.x)
        self.odometry_poses[k] = self.T_odometry

    def _predict(self, edge: int) -> None:
        T_increment = self.T_increments[edge]
        self.x, F, G = self.filter.predict(self.x, T_increment)
        self.P = ekf.predict(self.P, F, G, self.dataset.odom_cov[edge])  # P = F P F' + G Q G'
        self.T_odometry = self.T_odometry @ T_increment

    def _associate(self, k: int, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Accepted pairs of pose k: observation indices and landmark indices, both (p,)."""
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        if obs.size == 0 or self.map_index is None:
            return none
        if self.beam_pairs is not None:
            # the beam decided every pose's pairs over the whole run first (search_beam, or the
            # replay process handing them over as they are decided)
            pairs = self.beam_pairs[k]
            order = np.argsort(pairs[:, 0], kind="stable")
            return pairs[order, 0], pairs[order, 1]
        if self.associate is None:
            raise RuntimeError("the beam decides the pairs of the whole run first: call search_beam before step")
        return self.associate(self.scene, self.x, self.P, obs)

    def _recheck(self, obs: np.ndarray, pair_obs: np.ndarray, pair_landmarks: np.ndarray, P_prior: np.ndarray, x_post: np.ndarray) -> np.ndarray:
        """Which of a pose's pairs hold (``_holds``), each judged by the posterior of the others
        (``association.leave_one_out_costs``), and lie within the camera's reach and in front of it at x_post: (p,)
        bool; and which dropped rays (reach bounded) failed only ``_against_null`` (for ``_rechecked``)."""
        ds = self.dataset
        keep, doubtful = np.ones(pair_obs.size, dtype=bool), np.zeros(pair_obs.size, dtype=bool)
        position = {int(o): n for n, o in enumerate(pair_obs.tolist())}
        chosen_landmark = dict(zip(pair_obs.tolist(), pair_landmarks.tolist()))
        groups = []
        pair_information = {}
        for camera_id in np.unique(self.obs_sensor[obs]):
            mine = obs[self.obs_sensor[obs] == camera_id]
            candidates = self.visible(x_post, camera_id)
            z_hat, H = self.observe(x_post, camera_id, candidates)
            column_of = {int(c): j for j, c in enumerate(candidates.tolist())}
            chosen = np.array([column_of.get(chosen_landmark.get(int(o), -2), -1) for o in mine], dtype=np.int64)
            Hc = H[chosen[chosen >= 0]]
            R_paired = self.association_cov[mine[chosen >= 0]]
            dim = self.filter.dim
            pair_information[int(camera_id)] = (Hc.swapaxes(1, 2) @ ekf.solve(R_paired, Hc)).sum(axis=0) if Hc.size else np.zeros((dim, dim))
            groups.append((int(camera_id), mine, candidates, z_hat, H, chosen))
        prior_information = ekf.solve(P_prior, ekf.identity(self.filter.dim))
        for camera_id, mine, candidates, z_hat, H, chosen in groups:
            if z_hat.shape[0] == 0:
                continue
            information = prior_information + sum(v for c, v in pair_information.items() if c != camera_id)
            cost = association.leave_one_out_costs(ds.obs_z[mine], self.association_cov[mine], z_hat, H, chosen, information=information,
                                                   gate=float(self.obs_gate[mine[0]]), kinds=ds.obs_kind[mine])
            cost = cost + orientation_terms(self.scene, x_post, P_prior, mine, candidates, z_hat, H)[1]  # a tag's orientation
            row, steal, rival = *association.assignment_margins(cost, self.null_cost[mine], chosen), self.scene.ray_rival_margins(mine, cost, chosen)
            rays = measurement.is_ray(ds.obs_kind[mine]) & np.isfinite(self.scene.max_distance)
            for o, r, st, rv, ray in zip(mine.tolist(), row.tolist(), steal.tolist(), rival.tolist(), rays.tolist()):
                if o in position and not _holds(self.config.recheck, r, st, rv):
                    keep[position[o]] = False
                    doubtful[position[o]] = ray and _against_null(self.config.recheck, r, st, rv)
        within = self.scene.within_reach(x_post, pair_obs, pair_landmarks) & self.scene.in_front(x_post, pair_obs, pair_landmarks)
        return keep & within, doubtful & within

    def visible(self, x: np.ndarray, camera_id: int, P: Optional[np.ndarray] = None) -> np.ndarray:
        """``AssociationScene.visible``: the landmarks camera ``camera_id`` may see from x (with P,
        from anywhere within three standard deviations of it)."""
        return self.scene.visible(x, camera_id, P)

    def observe(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``AssociationScene.observe``: predictions (m, 3) of the landmarks by camera ``camera_id``
        from x, and their Jacobians (m, 3, n)."""
        return self.scene.observe(x, camera_id, landmarks)

    def conditioned(self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x, P) after the update with the given pairs, weighed as association judges them: the
        scratch filter of a method that conditions on some pairs before judging the rest."""
        result = self.updated(x, P, obs, landmarks, for_association=True)
        return result.state, result.cov

    def updated(self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray, **options) -> ekf.UpdateResult:
        """The stacked (iterated) EKF update of (x, P) with the given pairs (``StackedUpdate.updated``,
        whose keywords it takes)."""
        return self.stacked.updated(x, P, obs, landmarks, **options)

    def _record_pairs(self, k: int, obs: np.ndarray, landmarks: np.ndarray, result: ekf.UpdateResult) -> None:
        p = obs.size
        S_blocks = result.S if result.S.ndim == 3 else result.S.reshape(p, 3, p, 3)[np.arange(p), :, np.arange(p), :]  # each pair's own 3x3
        d2, _ = association.mahalanobis_3x3(S_blocks, result.innovation.reshape(p, 3))
        self.chosen_landmark[obs] = self.dataset.landmark_ids[landmarks]
        self.mahalanobis[obs] = np.sqrt(d2)
        self.update_pose_ids.append(int(self.dataset.pose_ids[k]))
        self.nis.append(recorded_nis(result.nis, result.map_cost, self.config.iterations))
        self.map_costs.append(result.map_cost)
        self.nis_dof.append(int(self.obs_dof[obs].sum()))

    def _warn_near_singularity(self, k: int) -> None:
        pitch = self.filter.near_singularity(self.x)
        if pitch is not None and not self.warned_singularity:
            self.warned_singularity = True
            self.warnings.append(
                f"pose {int(self.dataset.pose_ids[k])}: pitch {pitch:.1f} deg is close to the Euler filter's "
                "singularity at +-90 deg; its estimate may degrade from here (--filter se3 has no singularity)"
            )

    def result(self, filter_seconds: float) -> RunResult:
        cut_short = self.associate.poses_cut_short if isinstance(self.associate, associators.Jcbb) else 0
        return build_result(
            self.dataset, self.config, self.filter, self.states, self.covs, self.poses, self.odometry_poses,
            self.chosen_landmark, self.mahalanobis, self.update_pose_ids, self.nis, self.map_costs, self.nis_dof,
            warnings=self.warnings + ([f"JCBB hit its bound of {self.config.jcbb.max_nodes} joint tests at {cut_short} pose(s) "
                                        "and kept the best set found"] if cut_short else []),
            slip_pose_ids=self.slip_pose_ids, candidate_range=(self.min_depth, self.max_depth, self.max_angle),
            association_spread=None if self.association_spread is None else self.association_spread + self.pair_spread,
            timing={"filter_seconds": filter_seconds, "engine": "numpy", "replay_process": self.replayed_in_parallel,
                    "replay_process_peak_mb": self.replay_peak_mb, "replay_thread": False},
        )
