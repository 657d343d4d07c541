"""Every option of the localizer (``LocalizerConfig`` and its groups), their ranges and which
association methods each belongs to: what a run is asked to do, apart from the code that does it,
so that the compiled loop, the warm-up compile, config files and the command line read it without
loading the numpy localizer.

    config = LocalizerConfig(association="best-friends", beam=BeamOptions(width=8))
    config.validate()
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import ClassVar, Optional

import numpy as np

from camloc.beam_types import BeamSettings
from camloc.constants import MAX_LINEARIZATIONS
from camloc.errors import ConfigError
from camloc.filters import FILTERS

# the filter a dataset's robot calls for: se2 for a planar one, euler otherwise (``localizer.resolved_config``)
AUTO_FILTER = "auto"
from camloc.g2o import MAX_COORDINATE

ASSOCIATION_METHODS = ("beam", "jcbb", "best-friends", "oracle")
# How the run holds the map (``camloc.slam_run``): "auto" is exact where the file has a map, none
# where it has none (``localizer.resolved_config``).
MAP_MODES = ("auto", "exact", "prior", "none")
AUTO_MAP = "auto"
MAX_MAP_SIGMA = 1e3
# What the oracle ignores (it takes the file's ids, gated): the re-check, the candidate view and
# the null cost, which belong to the methods that search for the pairs. They are accepted with it
# (a study compares each method with the oracle under the same options) and the run says so.
IGNORED_BY_ORACLE = ("null_cost", "recheck", "view")
# The largest beam: its history holds width hypotheses per pose (three times as many: a sparse
# pose's, ``camloc.sparse_poses``).
MAX_BEAM_WIDTH = 1024
# The largest covariance factor of a slip's hypothesis: sigma x 100.
MAX_SLIP_INFLATION = 1e4
COSTS = ("nll", "mahalanobis", "euclidean")

# Bound on the initial rotation sigma: far beyond any meaningful angle, far from overflow.
MAX_SIGMA_DEG = 1e6
# The re-check's margin for a pixel observation over its nearest rival landmark (a ray passes near
# several): pairs closer than this are left out. Measured on the 72 pixel-only worlds of
# benchmarks/pixel_worlds.py (docs/performance.md, 2026-12-05, "A ray's rival landmarks").
RAY_MARGIN = 3.0


@dataclass(frozen=True)
class BeamOptions:
    """The beam's options (``association="beam"``, ``camloc.beam``; costs are 2 x negative
    log-likelihoods). Defaults: ``camloc.beam.BeamSettings``.

    Attributes
    ----------
    width : association hypotheses kept after each pose.
    delta : drop hypotheses this much costlier than the best. At a pose of a few rays only
        (``camloc.sparse_poses``) the beam keeps ``SPARSE_WIDTH_FACTOR`` times the width and
        ``SPARSE_DELTA_EXTRA`` more delta.
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
    equally well: one of them is clutter, and which is not known). Where the candidates' distance
    is bounded (``ViewOptions.max_distance``: a pixel-only file's learned reach), a pixel
    observation's pair holds only when every other landmark near its ray costs more than
    ``ray_margin`` (a ray passes near several landmarks; ``association.rival_margins``), and a
    pair holds only when its landmark lies within that distance of the camera at the updated pose;
    there, the rays that failed only against leaving them unassigned are weighed together under the
    kept pairs' posterior and the cheapest subset taken back (``association.restored_pairs``).
    Unbounded (a file that measures range, the mapping localizer, the run that learns the reach),
    none of these: beyond the camera's reach, landmarks it cannot see crowd every ray.

    Attributes
    ----------
    enabled : run the re-check.
    margin, steal_margin, ray_margin : as above, in cost units (>= 0).
    """

    enabled: bool = True
    margin: float = 0.0
    steal_margin: float = 6.0
    ray_margin: float = RAY_MARGIN


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
    max_distance : candidates within this distance of the camera's centre, metres; None = no such
        bound (a pixel-only file's run sets it to the reach it learns, a distance, with
        ``max_depth``: ``localizer._with_learned_reach``).
    """

    min_depth: Optional[float] = None
    max_depth: Optional[float] = None
    max_angle_deg: Optional[float] = None
    max_distance: Optional[float] = None


@dataclass(frozen=True)
class LocalizerConfig:
    """Every option of the localizer; ``summary.json`` records it (``dataclasses.asdict``) so a run
    can be repeated.

    The options every run may want are at the top; each method's own options are in its group,
    and an option of a method that is not selected must keep its default (``validate``).
    ``camloc.options`` names each option as the command line and config files do.

    Attributes
    ----------
    filter : "euler" (state x, y, z, roll, pitch, yaw; singular at pitch +-90 deg), "se3" (an
        error-state filter on SE(3), no singularity), "se2" (an error-state filter on SE(2): a
        planar robot), see ``camloc.filters``; or "auto" (the default): se2 for a planar dataset,
        euler otherwise (``localizer.resolved_config``; the run's summary records which ran).
    association : "beam" (a beam of association hypotheses, see ``camloc.beam``), "jcbb" (joint
        compatibility branch and bound, seeded by best friends), "best-friends" (mutual best
        match + gates) or "oracle" (the file's landmark ids, gated like any pair: what perfect
        association gives). Only "oracle" reads the file's landmark ids.
    iterations : linearizations per update (1 = EKF, more = iterated EKF).
    gate : probability of the chi^2 gate on each pair's innovation, 3 degrees of freedom.
    null_cost : cost of leaving an observation unassigned, read by the beam and by the re-check
        (so by no single method: it is not in a method's group); None: per observation, from the
        data (``observation_space.clutter_null_cost``: clutter uniform over the measured volume).
    initial_sigma_xyz, initial_sigma_deg : standard deviation of the start pose (metres, degrees).
    beam, best_friends, jcbb : each method's own options (``BeamOptions``, ``BestFriendsOptions``,
        ``JcbbOptions``).
    recheck : the re-check after each update (``RecheckOptions``).
    view : the candidate landmarks' depth range and field of view (``ViewOptions``).
    map : how the map is held: "exact" (landmarks where the map says, the localizer of every
        filter and method), "prior" (mapped landmarks estimated too, pulled toward the map with
        ``map_sigma``), "none" (the map's positions unused); in "prior" and "none" the mapping
        localizer (``camloc.slam_run``: EKF-SLAM, landmarks the map lacks added) runs. "auto"
        (the default): exact where the file has a map, none where it has none.
    map_sigma : the map prior's standard deviation per axis, metres (``map = "prior"``).
    """

    filter: str = "auto"
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
    map: str = AUTO_MAP
    map_sigma: float = 0.1

    def initial_cov(self) -> np.ndarray:
        """(6, 6) the start pose's covariance: ``initial_sigma_xyz`` on the position (metres),
        ``initial_sigma_deg`` on the rotation (as radians), uncorrelated."""
        sigma = np.r_[np.full(3, self.initial_sigma_xyz), np.full(3, np.radians(self.initial_sigma_deg))]
        return np.diag(sigma**2)

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
            ("filter", self.filter in FILTERS or self.filter == AUTO_FILTER,
             f"must be one of {AUTO_FILTER}, {', '.join(FILTERS)}, got {self.filter!r}"),
            ("map", self.map in MAP_MODES, f"must be one of {', '.join(MAP_MODES)}, got {self.map!r}"),
            ("map_sigma", _finite(self.map_sigma) and 0.0 < self.map_sigma <= MAX_MAP_SIGMA,
             f"must be in (0, {MAX_MAP_SIGMA:g}] m, got {self.map_sigma}"),
            ("association", self.association in ASSOCIATION_METHODS,
             f"must be one of {', '.join(ASSOCIATION_METHODS)}, got {self.association!r}"),
            ("iterations", _is_integer(self.iterations) and 1 <= self.iterations <= MAX_LINEARIZATIONS,
             f"must be an integer in 1..{MAX_LINEARIZATIONS}, got {self.iterations}"),
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
            ("recheck.ray_margin", _finite(recheck.ray_margin) and recheck.ray_margin >= 0.0,
             f"must be a finite number >= 0, got {recheck.ray_margin}"),
            ("view.min_depth", view.min_depth is None or 0.0 <= view.min_depth <= MAX_COORDINATE,
             f"must be in [0, {MAX_COORDINATE:.0e}] m, got {view.min_depth}"),
            ("view.max_depth", view.max_depth is None or (view.min_depth or 0.0) < view.max_depth <= MAX_COORDINATE,
             f"must be above the minimum depth ({view.min_depth or 0.0:g} m) and at most {MAX_COORDINATE:.0e} m, got {view.max_depth}"),
            ("view.max_angle_deg", view.max_angle_deg is None or 0.0 < view.max_angle_deg < 90.0,
             f"must be in (0, 90) deg, got {view.max_angle_deg}"),
            ("view.max_distance", view.max_distance is None or (view.min_depth or 0.0) < view.max_distance <= MAX_COORDINATE,
             f"must be above the minimum depth ({view.min_depth or 0.0:g} m) and at most {MAX_COORDINATE:.0e} m, got {view.max_distance}"),
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
