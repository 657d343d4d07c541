"""The localizer: an Euler-angle EKF over the odometry chain, corrected by camera observations whose
landmark is unknown and found by data association.

    result = localize(dataset, LocalizerConfig(association="best-friends"))

One pose at a time (``_Localizer.step``): predict with the odometry increment, associate the pose's
observations with the map, update with every accepted pair stacked, record.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import MISSING, asdict, dataclass, field, fields, is_dataclass, replace
from typing import Callable, ClassVar, Optional

import numpy as np

from camloc import association, associators, ekf, geometry, measurement, models, warmup
from camloc.associators import AssociationScene
from camloc.sensors import sensors_of
from camloc.measurement import observation_gates
from camloc.beam import BeamSearch, BeamSettings, BeamStatistics
from camloc.filters import FILTERS, SINGULARITY_WARNING_DEG, make_filter
from camloc.dataset import Dataset
from camloc.errors import ConfigError
from camloc.g2o import MAX_COORDINATE
from camloc.results import UNASSOCIATED, Associations, RunResult
from camloc.tails import chi2_quantile

ASSOCIATION_METHODS = ("beam", "jcbb", "best-friends", "oracle")
# What the oracle ignores (it takes the file's ids, gated): the re-check, the candidate view and
# the null cost, which belong to the methods that search for the pairs. They are accepted with it
# (a study compares each method with the oracle under the same options) and the run says so.
IGNORED_BY_ORACLE = ("null_cost", "recheck", "view")
# The largest beam: its history holds width hypotheses per pose.
MAX_BEAM_WIDTH = 1024
# The largest covariance factor of a slip's hypothesis: sigma x 100.
MAX_SLIP_INFLATION = 1e4
COSTS = ("nll", "mahalanobis", "euclidean")

ProgressCallback = Callable[[int, int], None]

# Bound on the initial rotation sigma: far beyond any meaningful angle, far from overflow.
MAX_SIGMA_DEG = 1e6


@dataclass(frozen=True)
class BeamOptions:
    """The beam's options (``association="beam"``, ``camloc.beam``; costs are 2 x negative
    log-likelihoods). Defaults: ``camloc.beam.BeamSettings``.

    Attributes
    ----------
    width : association hypotheses kept after each pose.
    delta : drop hypotheses this much costlier than the best.
    branch_delta : explore only an observation's options within this cost of its best.
    slip_inflation : covariance factor of the odometry-slip hypothesis (>= 1).
    slip_cost : extra cost of the odometry-slip hypothesis.
    """

    METHODS: ClassVar[tuple[str, ...]] = ("beam",)

    width: int = BeamSettings.beam_width
    delta: float = BeamSettings.beam_delta
    branch_delta: float = BeamSettings.branch_delta
    slip_inflation: float = BeamSettings.slip_inflation
    slip_cost: float = BeamSettings.slip_cost


@dataclass(frozen=True)
class BestFriendsOptions:
    """Best friends' options (``association="best-friends"``; cost and margin also pick the pairs
    that seed ``"jcbb"``).

    Attributes
    ----------
    cost : pair cost: "nll" (d^2 + ln det S), "mahalanobis" (d^2), "euclidean" (|z - z_hat| in
        measurement units).
    margin : lonely-best-friends margin, in cost units: a pair is rejected when a rival in its row
        or column is less than ``margin`` more expensive.
    sequential : accept pairs one at a time, most unambiguous first, conditioning the filter on
        each before looking at the rest (the final update is still one stacked update from the
        prior); False pairs all observations at once (the original method). Best friends only:
        jcbb takes its seed in one batch.
    """

    METHODS: ClassVar[tuple[str, ...]] = ("best-friends", "jcbb")

    cost: str = "nll"
    margin: float = 1.0
    sequential: bool = field(default=True, metadata={"methods": ("best-friends",)})


@dataclass(frozen=True)
class JcbbOptions:
    """Joint compatibility branch and bound's options (``association="jcbb"``, ``camloc.jcbb``).

    Attributes
    ----------
    max_nodes : bound on the joint compatibility tests per pose; past it the best set found is kept.
    """

    METHODS: ClassVar[tuple[str, ...]] = ("jcbb",)

    max_nodes: int = 2000


@dataclass(frozen=True)
class RecheckOptions:
    """The re-check after each update (every association but "oracle", which ignores it).

    Each accepted pair is judged again by the posterior of the pose's other pairs (its own left
    out, ``association.leave_one_out_costs``) and the pose updated again without the pairs that do
    not hold. A pair holds when leaving its observation unassigned or pairing it with another
    landmark costs more than ``margin``, and handing its landmark to another of the pose's
    observations costs more than ``steal_margin`` (two detections that fit one landmark about
    equally well: one of them is clutter, and which is not known).

    Attributes
    ----------
    enabled : run the re-check.
    margin, steal_margin : as above, in cost units (>= 0).
    """

    enabled: bool = True
    margin: float = 0.0
    steal_margin: float = 6.0


@dataclass(frozen=True)
class ViewOptions:
    """Which map landmarks are candidates for a camera's observations (every association but
    "oracle", which takes the file's ids).

    Attributes
    ----------
    min_depth, max_depth : candidate depth range in metres; None = from the data (0 and
        1.25 x the largest measured depth + 0.5 m).
    max_angle_deg : candidates within this angle of the optical axis; None = from the data (the
        widest observed ray + 10 deg, at most 89 deg).
    """

    min_depth: Optional[float] = None
    max_depth: Optional[float] = None
    max_angle_deg: Optional[float] = None


@dataclass(frozen=True)
class LocalizerConfig:
    """Every option of the localizer; ``summary.json`` records it (``dataclasses.asdict``) so a run
    can be repeated.

    The options every run may want are at the top; each method's own options are in its group,
    and an option of a method that is not selected must keep its default (``validate``).
    ``camloc.options`` names each option as the command line and config files do.

    Attributes
    ----------
    filter : "euler" (state x, y, z, roll, pitch, yaw; singular at pitch +-90 deg) or "se3" (an
        error-state filter on SE(3), no singularity), see ``camloc.filters``.
    association : "beam" (a beam of association hypotheses, see ``camloc.beam``), "jcbb" (joint
        compatibility branch and bound, seeded by best friends), "best-friends" (mutual best
        match + gates) or "oracle" (the file's landmark ids, gated like any pair: what perfect
        association gives). Only "oracle" reads the file's landmark ids.
    iterations : linearizations per update (1 = EKF, more = iterated EKF).
    gate : probability of the chi^2 gate on each pair's innovation, 3 degrees of freedom.
    null_cost : cost of leaving an observation unassigned, read by the beam and by the re-check
        (so by no single method: it is not in a method's group); None: per observation, from the
        data (``association.clutter_null_cost``: clutter uniform over the measured volume).
    initial_sigma_xyz, initial_sigma_deg : standard deviation of the start pose (metres, degrees).
    beam, best_friends, jcbb : each method's own options (``BeamOptions``, ``BestFriendsOptions``,
        ``JcbbOptions``).
    recheck : the re-check after each update (``RecheckOptions``).
    view : the candidate landmarks' depth range and field of view (``ViewOptions``).
    """

    filter: str = "euler"
    association: str = "beam"
    iterations: int = 3
    gate: float = 0.99
    null_cost: Optional[float] = None
    initial_sigma_xyz: float = 0.01
    initial_sigma_deg: float = 0.5
    beam: BeamOptions = field(default_factory=BeamOptions)
    best_friends: BestFriendsOptions = field(default_factory=BestFriendsOptions)
    jcbb: JcbbOptions = field(default_factory=JcbbOptions)
    recheck: RecheckOptions = field(default_factory=RecheckOptions)
    view: ViewOptions = field(default_factory=ViewOptions)

    def validate(self) -> None:
        """Raise ``OptionError`` naming the first option that is out of range, of a wrong kind, or
        set (to other than its default) for a method that is not selected."""
        for path, ok, reason in self._checks():
            if not ok:
                raise OptionError(path, reason)
        for path, methods in option_methods().items():
            if self.association not in methods and option_value(self, path) != option_value(_DEFAULT_CONFIG, path):
                raise OptionError(path, f"applies only with association {' or '.join(methods)}; the selected "
                                        f"association is {self.association}")

    def _checks(self) -> list[tuple[str, bool, str]]:
        """(option path, holds, what it must be) for every rule of a single option's range."""
        groups = [(f.name, isinstance(getattr(self, f.name), type(f.default_factory()))) for f in fields(self)
                  if f.default_factory is not MISSING]
        wrong = next((name for name, ok in groups if not ok), None)
        if wrong is not None:  # the checks below read the groups' fields
            kind = type(getattr(_DEFAULT_CONFIG, wrong)).__name__
            return [(wrong, False, f"must be a {kind}, got {getattr(self, wrong)!r}")]
        beam, best_friends, recheck, view = self.beam, self.best_friends, self.recheck, self.view
        return [
            ("filter", self.filter in FILTERS, f"must be one of {', '.join(FILTERS)}, got {self.filter!r}"),
            ("association", self.association in ASSOCIATION_METHODS,
             f"must be one of {', '.join(ASSOCIATION_METHODS)}, got {self.association!r}"),
            ("iterations", _is_integer(self.iterations) and 1 <= self.iterations <= 50, f"must be an integer in 1..50, got {self.iterations}"),
            ("gate", 0.0 < self.gate < 1.0, f"must be a probability in (0, 1), got {self.gate}"),
            ("null_cost", self.null_cost is None or _finite(self.null_cost) and self.null_cost > 0.0,
             f"must be a finite number > 0, got {self.null_cost}"),
            ("initial_sigma_xyz", 0.0 < self.initial_sigma_xyz <= MAX_COORDINATE,
             f"must be in (0, {MAX_COORDINATE:.0e}] m, got {self.initial_sigma_xyz}"),
            ("initial_sigma_deg", 0.0 < self.initial_sigma_deg <= MAX_SIGMA_DEG,
             f"must be in (0, {MAX_SIGMA_DEG:.0e}] deg, got {self.initial_sigma_deg}"),
            ("beam.width", _is_integer(beam.width) and 1 <= beam.width <= MAX_BEAM_WIDTH,
             f"must be an integer in 1..{MAX_BEAM_WIDTH}, got {beam.width}"),
            ("beam.delta", _finite(beam.delta) and beam.delta > 0.0, f"must be a finite number > 0, got {beam.delta}"),
            ("beam.branch_delta", _finite(beam.branch_delta) and beam.branch_delta > 0.0,
             f"must be a finite number > 0, got {beam.branch_delta}"),
            ("beam.slip_inflation", 1.0 <= beam.slip_inflation <= MAX_SLIP_INFLATION,
             f"must be in [1, {MAX_SLIP_INFLATION:g}], got {beam.slip_inflation}"),
            ("beam.slip_cost", _finite(beam.slip_cost) and beam.slip_cost >= 0.0, f"must be a finite number >= 0, got {beam.slip_cost}"),
            ("best_friends.cost", best_friends.cost in COSTS, f"must be one of {', '.join(COSTS)}, got {best_friends.cost!r}"),
            ("best_friends.margin", _finite(best_friends.margin) and best_friends.margin >= 0.0,
             f"must be a finite number >= 0, got {best_friends.margin}"),
            ("jcbb.max_nodes", _is_integer(self.jcbb.max_nodes) and self.jcbb.max_nodes >= 1,
             f"must be an integer >= 1, got {self.jcbb.max_nodes}"),
            ("recheck.margin", _finite(recheck.margin) and recheck.margin >= 0.0, f"must be a finite number >= 0, got {recheck.margin}"),
            ("recheck.steal_margin", _finite(recheck.steal_margin) and recheck.steal_margin >= 0.0,
             f"must be a finite number >= 0, got {recheck.steal_margin}"),
            ("view.min_depth", view.min_depth is None or 0.0 <= view.min_depth <= MAX_COORDINATE,
             f"must be in [0, {MAX_COORDINATE:.0e}] m, got {view.min_depth}"),
            ("view.max_depth", view.max_depth is None or (view.min_depth or 0.0) < view.max_depth <= MAX_COORDINATE,
             f"must be above the minimum depth ({view.min_depth or 0.0:g} m) and at most {MAX_COORDINATE:.0e} m, got {view.max_depth}"),
            ("view.max_angle_deg", view.max_angle_deg is None or 0.0 < view.max_angle_deg < 90.0,
             f"must be in (0, 90) deg, got {view.max_angle_deg}"),
        ]


class OptionError(ConfigError):
    """An option out of range: ``path`` is its place in ``LocalizerConfig`` (``"beam.width"``),
    ``reason`` what it must be. The message names the option by its path; ``camloc.config`` names
    it as the user wrote it (``--beam-width``, ``[beam] width``)."""

    def __init__(self, path: str, reason: str):
        self.path, self.reason = path, reason
        super().__init__(f"{path} {reason}")


def option_methods() -> dict[str, tuple[str, ...]]:
    """The options that belong to some association methods only: option path -> those methods.
    A group's methods are its ``METHODS``; a field's own ``methods`` metadata narrows them."""
    out = {}
    for group in fields(LocalizerConfig):
        options = getattr(_DEFAULT_CONFIG, group.name)
        if not is_dataclass(options):
            continue
        for f in fields(options):
            methods = f.metadata.get("methods", getattr(options, "METHODS", None))
            if methods is not None:
                out[f"{group.name}.{f.name}"] = methods
    return out


def option_value(config: LocalizerConfig, path: str):
    """The value of option ``path`` (``"iterations"``, ``"beam.width"``)."""
    value = config
    for name in path.split("."):
        value = getattr(value, name)
    return value


def ignored_options(config: LocalizerConfig) -> list[str]:
    """The options set (to other than their defaults) that the selected association ignores: with
    the oracle, those of ``IGNORED_BY_ORACLE``."""
    if config.association != "oracle":
        return []
    paths = []
    for name in IGNORED_BY_ORACLE:
        default = getattr(_DEFAULT_CONFIG, name)
        paths += [f"{name}.{f.name}" for f in fields(default)] if is_dataclass(default) else [name]
    return [path for path in paths if option_value(config, path) != option_value(_DEFAULT_CONFIG, path)]


def _finite(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)


def _is_integer(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and float(value).is_integer()


_DEFAULT_CONFIG = LocalizerConfig()


ENGINES = ("auto", "compiled", "numpy")

# Below this many poses the numpy localizer finishes first: the compiled loop pays about 0.6 s a
# process to start numba and load its kernels from the cache (the real file's 101 poses: 1.3 s
# wall with the compiled loop, 0.8 s with numpy), and the numpy beam costs 2-4 ms a pose more.
COMPILED_MIN_POSES = 300


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
    engine : "compiled" (the loop over numba kernels, ``camloc.loop``: the Euler filter with beam
        or oracle association), "numpy" (``_Localizer``, every filter and method; the compiled
        loop's reference, equal to it to rounding), or "auto": compiled where it can run and the
        dataset has at least ``COMPILED_MIN_POSES`` poses. ``summary["timing"]["engine"]`` says
        which ran.
    on_compile : called once before the compiled loop starts when its kernels are not yet in
        numba's cache (the first run after an install compiles them: a minute or two).
    on_background_compile : given, a run that "auto" would give to the compiled loop while its
        kernels are not yet compiled, of at most ``warmup.BACKGROUND_COMPILE_MAX_POSES`` poses,
        runs in numpy instead (the same result, sooner than the compile) and has the kernels
        compiled in a detached background process for the runs after it (``camloc.warmup``);
        called with whether this call started that process (False: an earlier one is running).
        ``summary["timing"]["background_compile"]`` says so. Where that process cannot run, the
        kernels compile in the foreground as without it. ``camloc run`` passes it.
    """
    config = config or LocalizerConfig()
    config.validate()
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, got {engine!r}")
    compilable = config.filter == "euler" and config.association in COMPILED_ASSOCIATIONS
    if engine == "compiled" and not compilable:
        raise ConfigError(f"the compiled loop runs the euler filter with {' or '.join(COMPILED_ASSOCIATIONS)} association; "
                          f"filter {config.filter!r} with association {config.association!r} runs in numpy")
    use_compiled = engine == "compiled" or (engine == "auto" and compilable and dataset.num_poses >= COMPILED_MIN_POSES)
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
                                    filter_ready=(lambda: warmup.wait_for(filter_compile)) if filter_compile else None)
    else:
        result = _localize_numpy(dataset, config, on_progress, parallel)
    result.summary["timing"]["background_compile"] = background is not None
    return result


def _compile_in_background(dataset: Dataset) -> Optional[str]:
    """``warmup.STARTED`` or ``warmup.RUNNING`` where this run goes to numpy while the kernels
    compile in the background; None where it compiles them first."""
    if dataset.num_poses > warmup.BACKGROUND_COMPILE_MAX_POSES:
        return None
    return warmup.start_background_compile()


def _localize_numpy(dataset: Dataset, config: LocalizerConfig, on_progress: Optional[ProgressCallback],
                    parallel: Optional[bool]) -> RunResult:
    localizer = _Localizer(dataset, config)
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


# The associations the compiled loop (``camloc.loop``) runs; the others run in numpy below.
COMPILED_ASSOCIATIONS = ("beam", "oracle")


def _localize_compiled(dataset: Dataset, config: LocalizerConfig, on_progress: Optional[ProgressCallback],
                       concurrent: bool, filter_ready: Optional[Callable[[], None]] = None) -> RunResult:
    from camloc.loop import PoseFailure, run_compiled
    from camloc.scene import candidate_range

    euler = make_filter("euler")
    x0 = euler.initial(dataset.T_world_start)
    sigma = np.r_[np.full(3, config.initial_sigma_xyz), np.full(3, np.radians(config.initial_sigma_deg))]
    started = time.perf_counter()
    view_range = candidate_range(dataset, config)
    try:
        states, covs, chosen, distance, update_k, nis, map_cost, dof, slipped = run_compiled(
            dataset, config, on_progress, initial_x=x0, initial_P=np.diag(sigma**2), concurrent=concurrent,
            filter_ready=filter_ready, view_range=view_range)
    except PoseFailure as failure:
        detail = str(failure) if str(failure).startswith("a covariance") else f"a covariance is no longer positive definite ({failure})"
        raise ekf.FilterDivergedError(detail).at_pose(int(dataset.pose_ids[failure.k])) from None
    seconds = time.perf_counter() - started
    odometry = np.empty((dataset.num_poses, 4, 4))
    T = dataset.T_world_start
    increments = dataset.T_odometry
    for k in range(dataset.num_poses):
        if k > 0:
            T = T @ increments[k - 1]
        odometry[k] = T
    warnings = []
    pitch = np.degrees(np.abs(states[:, 4]))
    near = np.flatnonzero(pitch > SINGULARITY_WARNING_DEG)
    if near.size:
        k = int(near[0])
        warnings.append(f"pose {int(dataset.pose_ids[k])}: pitch {np.degrees(states[k, 4]):.1f} deg is close to the Euler filter's "
                        "singularity at +-90 deg; its estimate may degrade from here (--filter se3 has no singularity)")
    landmark = np.where(chosen >= 0, dataset.landmark_ids[np.maximum(chosen, 0)] if dataset.landmark_ids.size else UNASSOCIATED, UNASSOCIATED)
    return build_result(
        dataset, config, euler, states, covs, geometry.pose_from_euler(states), odometry, landmark.astype(np.int64), distance,
        dataset.pose_ids[update_k], nis, map_cost, dof, warnings=warnings,
        slip_pose_ids=[int(i) for i in dataset.pose_ids[slipped]], candidate_range=view_range,
        timing={"filter_seconds": seconds, "engine": "compiled", "replay_process": False, "replay_process_peak_mb": None,
                "replay_thread": concurrent and config.association == "beam"},
    )

# Below this many poses a second process costs more to start (an interpreter and its imports,
# about half a second) than it saves.
PARALLEL_MIN_POSES = 500


def _parallel_worthwhile(num_poses: int) -> bool:
    return num_poses >= PARALLEL_MIN_POSES and _cpus() >= 2


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


class _Localizer:
    """The filter's state over one run; ``step(k)`` processes pose k."""

    def __init__(self, dataset: Dataset, config: LocalizerConfig):
        self.dataset = dataset
        self.config = config
        self.filter = make_filter(config.filter)
        # a sensor is a camera and the kind of its measurements (camloc.measurement)
        self.cameras, self.obs_sensor = sensors_of(dataset)
        self.single_camera = 0 if len(self.cameras) == 1 else None
        self.obs_dof = measurement.dof_of(dataset.obs_kind)
        self.map_index = association.PointIndex(dataset.landmark_xyz) if len(dataset.landmark_xyz) else None
        from camloc.scene import candidate_range, detection_range, landmark_rows, observation_noise

        self.true_landmark_row = landmark_rows(dataset.landmark_ids, dataset.obs_true_landmark)  # -1: not in the map
        self.min_depth, self.max_depth, self.max_angle = candidate_range(dataset, config)
        self.detect_range = detection_range(dataset, self.max_angle)  # the beam's miss term
        self.obs_gate = observation_gates(dataset.obs_kind, 1.0 - config.gate)  # each observation's, at its dof
        # what association judges each observation by (the update keeps the file's own noise), and
        # every observation as a camera-frame point (the beam's other coordinates, the update's restart)
        noise = observation_noise(dataset, config)
        self.association_cov, self.association_info, self.log_det_R = noise.cov, noise.info, noise.log_det
        self.point, self.point_cov, self.log_det_point_cov = noise.point, noise.point_cov, noise.log_det_point_cov
        self.null_cost = noise.null_cost
        self.nis_bounds: dict[int, float] = {}

        order = np.argsort(dataset.obs_pose_index, kind="stable")
        bounds = np.searchsorted(dataset.obs_pose_index[order], np.arange(dataset.num_poses + 1))
        self.obs_of_pose = [order[bounds[k] : bounds[k + 1]] for k in range(dataset.num_poses)]
        self.T_increments = dataset.T_odometry
        self.scene = AssociationScene(  # what the per-pose association methods read
            dataset=dataset, filter=self.filter, cameras=self.cameras, obs_sensor=self.obs_sensor, map_index=self.map_index,
            min_depth=self.min_depth, max_depth=self.max_depth, max_angle=self.max_angle, obs_gate=self.obs_gate,
            association_cov=self.association_cov,
            true_landmark_row=self.true_landmark_row, conditioned=self.conditioned,
        )
        self.associate = per_pose_associator(config)  # None for the beam (search_beam)

        n, k_obs = dataset.num_poses, dataset.num_observations
        self.states = np.zeros((n, self.filter.stored_size))
        self.poses = np.zeros((n, 4, 4))
        self.covs = np.zeros((n, 6, 6))
        self.odometry_poses = np.zeros((n, 4, 4))
        self.chosen_landmark = np.full(k_obs, UNASSOCIATED, dtype=np.int64)
        self.mahalanobis = np.full(k_obs, np.nan)
        self.update_pose_ids: list[int] = []
        self.nis: list[float] = []
        self.map_costs: list[float] = []
        self.nis_dof: list[int] = []
        self.warnings: list[str] = []
        self.warned_singularity = False

        sigma = np.r_[np.full(3, config.initial_sigma_xyz), np.full(3, np.radians(config.initial_sigma_deg))]
        self.x = self.filter.initial(dataset.T_world_start)
        self.P = np.diag(sigma**2)
        self.T_odometry = dataset.T_world_start
        self.beam_pairs: list[np.ndarray] | None = None
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
            slip_inflation=c.beam.slip_inflation, slip_cost=c.beam.slip_cost,
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
        slips = np.flatnonzero(self.beam_slipped)
        self.slip_pose_ids = [int(self.dataset.pose_ids[k]) for k in slips]

    def step(self, k: int) -> None:
        try:
            self._step(k)
        except ekf.NUMERICAL_FAILURES as error:
            raise ekf.as_divergence(error).at_pose(int(self.dataset.pose_ids[k])) from None

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
                keep = self._recheck(self.obs_of_pose[k], obs, landmarks, self.P, result.state)
                if not keep.all():
                    obs, landmarks = obs[keep], landmarks[keep]
                    if obs.size:
                        result = self.updated(self.x, self.P, obs, landmarks, map_cost=True)
        if obs.size:
            self._record_pairs(k, obs, landmarks, result)
            self.x, self.P = result.state, result.cov
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
        """Which of a pose's pairs keep at least ``recheck.margin`` over their nearest alternative
        (``association.assignment_margins``) when each observation is judged by the posterior of
        the other pairs (``association.leave_one_out_costs``): (p,) bool."""
        ds = self.dataset
        keep = np.ones(pair_obs.size, dtype=bool)
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
            pair_information[int(camera_id)] = (np.swapaxes(Hc, 1, 2) @ np.linalg.solve(R_paired, Hc)).sum(axis=0) if Hc.size else np.zeros((6, 6))
            groups.append((int(camera_id), mine, z_hat, H, chosen))
        prior_information = np.linalg.solve(P_prior, np.eye(6))
        for camera_id, mine, z_hat, H, chosen in groups:
            if z_hat.shape[0] == 0:
                continue
            information = prior_information + sum(v for c, v in pair_information.items() if c != camera_id)
            cost = association.leave_one_out_costs(ds.obs_z[mine], self.association_cov[mine], z_hat, H, chosen, information=information,
                                                   gate=float(self.obs_gate[mine[0]]))
            row, steal = association.assignment_margins(cost, self.null_cost[mine], chosen)
            for o, r, st in zip(mine.tolist(), row.tolist(), steal.tolist()):
                if o in position and not (r > self.config.recheck.margin and st > self.config.recheck.steal_margin):
                    keep[position[o]] = False
        return keep

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

    def updated(
        self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray, *, map_cost: bool = False,
        at_prior: tuple[np.ndarray, np.ndarray] | None = None, for_association: bool = False,
        start: Optional[np.ndarray] = None,
    ) -> ekf.UpdateResult:
        """The stacked (iterated) EKF update of (x, P) with the given pairs; ``at_prior``: their
        predictions (p, 3) and Jacobians (p, 3, n) at x, when the caller has them. With
        ``for_association``, the pairs weigh by the noise association judges them by
        (``association_cov``): the scratch filters that decide an association, not the estimate.
        ``start``: a state near the posterior, when the caller knows one; the iterations also run
        from it, and the posterior with the lower MAP cost is kept."""
        z = self.dataset.obs_z[obs].reshape(-1)
        if for_association:
            R, R_inverse = self.association_cov[obs], self.association_info[obs]
        else:  # the blocks of a block-diagonal covariance (ekf.update)
            R, R_inverse = self.dataset.obs_cov[obs], self.dataset.obs_info[obs]
        cameras = self.obs_sensor[obs]
        if self.single_camera is not None:  # nothing to group (np.unique costs more than the algebra)
            groups = [(self.cameras[self.single_camera], slice(None))]
        else:
            groups = [(self.cameras[int(c)], cameras == c) for c in np.unique(cameras)]
        landmark_xyz = self.dataset.landmark_xyz[landmarks]

        def measure(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if len(groups) == 1:
                camera = groups[0][0]
                z_hat, H = self.filter.observe(state, camera.T_robot_camera, camera.intrinsics, landmark_xyz, camera.kind)
                return z_hat.reshape(-1), H.reshape(-1, H.shape[-1])
            z_hat = np.empty((obs.size, 3))
            H = np.empty((obs.size, 3, 6))
            for camera, mask in groups:
                z_hat[mask], H[mask] = self.filter.observe(state, camera.T_robot_camera, camera.intrinsics, landmark_xyz[mask], camera.kind)
            return z_hat.reshape(-1), H.reshape(-1, 6)

        prior = measure(x) if at_prior is None else (at_prior[0].reshape(-1), at_prior[1].reshape(-1, at_prior[1].shape[-1]))
        options = dict(retract=self.filter.retract, difference=self.filter.difference, iterations=self.config.iterations,
                       at_prior=prior, R_inverse=R_inverse)
        result = ekf.update(x, P, z, R, measure, map_cost=map_cost, **options)
        if self.config.iterations < 2:
            return result
        starts = [] if start is None else [start]
        if result.nis > self._nis_bound(int(self.obs_dof[obs].sum())):
            # An innovation this unlikely under the prior's linearization: with a wide prior (after
            # a slip, or odometry much noisier than the landmarks' spacing) Gauss-Newton in (u, v,
            # depth) from the prior can stall far from the MAP estimate. Iterate also from one
            # update in camera-frame points, where the model is nearly linear in the position.
            starts.append(self._point_step(x, P, obs, groups, prior))
        if not starts:
            return result
        best, lowest = result, result.map_cost if map_cost else ekf.posterior_cost(result.state, x, P, z, R, measure, self.filter.difference, R_inverse)
        for state in starts:  # keep whichever posterior the MAP cost prefers
            alternative = ekf.update(x, P, z, R, measure, map_cost=True, start=state, **options)
            if alternative.map_cost < lowest:
                best, lowest = alternative, alternative.map_cost
        if best is result or map_cost:
            return best
        return replace(best, map_cost=float("nan"))

    def _point_step(self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, groups: list, prior: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """x after one EKF update with the pairs' measurements as camera-frame points (those
        ``measurement.judged_as_point``; the others, a pixel's ray, as they are)."""
        z_hat, H = prior[0].reshape(-1, 3), prior[1].reshape(obs.size, 3, -1)
        y = self.dataset.obs_z[obs] - z_hat
        Hp, R = H.copy(), self.association_cov[obs].copy()
        for camera, mask in groups:
            if not measurement.judged_as_point(camera.kind):
                continue
            mine = np.arange(obs.size)[mask]
            p_hat, J = models.back_project(z_hat[mine], camera.intrinsics, camera.kind)
            Hp[mine] = J @ H[mine]
            y[mine] = self.point[obs[mine]] - p_hat
            R[mine] = self.point_cov[obs[mine]]
        return self.filter.retract(x, ekf.correction(P, Hp.reshape(3 * obs.size, -1), R, y.reshape(-1)))

    def _nis_bound(self, dof: int) -> float:
        """The 99.9% quantile of chi^2 with dof degrees of freedom."""
        if dof not in self.nis_bounds:
            self.nis_bounds[dof] = float(chi2_quantile(dof, 0.001))
        return self.nis_bounds[dof]

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
            timing={"filter_seconds": filter_seconds, "engine": "numpy", "replay_process": self.replayed_in_parallel,
                    "replay_process_peak_mb": self.replay_peak_mb, "replay_thread": False},
        )


def build_result(dataset, config, filter_model, states, covs, poses, odometry_poses, chosen_landmark, mahalanobis,
                 update_pose_ids, nis, map_costs, nis_dof, *, warnings, slip_pose_ids, candidate_range, timing) -> RunResult:
    """The RunResult of a run's records: per pose the filter's stored state (N, S), covariance
    (N, 6, 6), pose and odometry pose (N, 4, 4); per observation the chosen landmark id
    (UNASSOCIATED for none) and Mahalanobis distance; per update its pose id, NIS, MAP cost, dof."""
    ds = dataset
    estimate_xyz, estimate_quat = geometry.pose_to_quat(poses)
    odometry_xyz, odometry_quat = geometry.pose_to_quat(odometry_poses)
    associations = Associations(
        pose_id=ds.pose_ids[ds.obs_pose_index], camera=ds.obs_camera.copy(), uvd=ds.obs_z.copy(),
        landmark=chosen_landmark, true_landmark=ds.obs_true_landmark.copy(), mahalanobis=mahalanobis,
    )
    accepted = int(np.count_nonzero(chosen_landmark != UNASSOCIATED))
    filter_seconds = timing["filter_seconds"]
    min_depth, max_depth, max_angle = candidate_range
    summary = {
        "dataset": ds.source,
        "config": asdict(config),
        "candidate_range": {"min_depth": min_depth, "max_depth": max_depth, "max_angle_deg": float(np.degrees(max_angle))},
        "counts": {
            "poses": ds.num_poses, "observations": ds.num_observations, "accepted": accepted,
            "rejected": ds.num_observations - accepted, "updates": len(nis), "landmarks": int(ds.landmark_ids.size),
        },
        "timing": {
            "filter_seconds": filter_seconds,
            "poses_per_second": ds.num_poses / filter_seconds if filter_seconds > 0 else float("inf"),
            **{key: value for key, value in timing.items() if key != "filter_seconds"},
        },
        "warnings": list(ds.warnings) + list(warnings),
    }
    ignored = ignored_options(config)
    if ignored:
        summary["warnings"].append(f"association oracle takes the file's landmark ids and ignores {', '.join(ignored)}")
    if slip_pose_ids:
        summary["warnings"].append(
            f"{len(slip_pose_ids)} pose(s) were explained as odometry slips (prior covariance widened "
            f"{config.beam.slip_inflation:g}x): " + ", ".join(str(i) for i in slip_pose_ids[:10]) + (" ..." if len(slip_pose_ids) > 10 else "")
        )
    guard = divergence_guard(np.asarray(update_pose_ids, dtype=np.int64), np.asarray(map_costs), np.asarray(nis_dof))
    summary["divergence_guard"] = guard
    summary["slip_poses"] = list(slip_pose_ids)
    if guard["runs"]:
        summary["warnings"].append(
            f"the filter may have diverged: its updates' chi-square statistic stayed above the {100 * GUARD_PROBABILITY:g}% bound for "
            f"{GUARD_RUN_LENGTH} or more consecutive updates at poses "
            + ", ".join(f"{a}-{b}" for a, b in guard["runs"][:5])
            + (" ..." if len(guard["runs"]) > 5 else "")
        )
    return RunResult(
        dataset=ds.source, pose_ids=ds.pose_ids.copy(), estimate_xyz=estimate_xyz, estimate_quat_xyzw=estimate_quat,
        estimate_cov=filter_model.pose_cov(states, covs), filter_state=states, filter_cov=covs,
        odometry_xyz=odometry_xyz, odometry_quat_xyzw=odometry_quat, truth_xyz=ds.truth_xyz, truth_quat_xyzw=ds.truth_quat_xyzw,
        map_landmark_ids=ds.landmark_ids, map_landmark_xyz=ds.landmark_xyz, associations=associations,
        update_pose_ids=np.asarray(update_pose_ids, dtype=np.int64), nis=np.asarray(nis, dtype=float),
        nis_dof=np.asarray(nis_dof, dtype=np.int64), summary=summary,
    )


def recorded_nis(nis_at_prior: float, map_cost: float, iterations: int) -> float:
    """The consistency statistic an update records: for an iterated update, the MAP cost at the
    posterior (chi^2 with 3p dof; at convergence the NIS at the last linearization), since the NIS
    at the prior's linearization carries the second-order error the iterations removed (two pixel
    cameras: NIS per dof 5.3 at the prior, 1.00 at the posterior, with the true association)."""
    if iterations > 1 and np.isfinite(map_cost):
        return float(map_cost)
    return float(nis_at_prior)


GUARD_PROBABILITY = 0.999
GUARD_RUN_LENGTH = 3


def divergence_guard(update_pose_ids: np.ndarray, statistic: np.ndarray, dof: np.ndarray) -> dict:
    """Updates whose accepted pairs are jointly inconsistent, and runs of them.

    ``statistic`` is each update's chi^2 statistic with ``dof`` degrees of freedom (3 per pair):
    the MAP cost at the posterior (``ekf.UpdateResult.map_cost``; NIS for a single linearization).
    An update is inconsistent when it is above the ``GUARD_PROBABILITY`` quantile;
    ``GUARD_RUN_LENGTH`` or more consecutive inconsistent updates (poses without observations do
    not break a run) are reported as a possible divergence, as (first pose id, last pose id) pairs.
    """
    if statistic.size == 0:
        return {"inconsistent_poses": [], "runs": []}
    bad = statistic > chi2_quantile(dof, 1.0 - GUARD_PROBABILITY)
    runs, start, length = [], None, 0
    for pose_id, is_bad in zip(update_pose_ids.tolist(), bad.tolist()):
        if is_bad:
            start, length = (pose_id if length == 0 else start), length + 1
            last = pose_id
        else:
            if length >= GUARD_RUN_LENGTH:
                runs.append([start, last])
            length = 0
    if length >= GUARD_RUN_LENGTH:
        runs.append([start, last])
    return {"inconsistent_poses": update_pose_ids[bad].tolist(), "runs": runs}


