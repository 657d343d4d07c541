"""The numpy beam's shared types (``camloc.beam``): its settings, what it reads of the run
(``BeamContext``), a hypothesis and a partial explanation, and what a search counts
(``BeamStatistics``). Its pieces (``camloc.pair_options``, ``camloc.beam_expansion``,
``camloc.beam_seeded`` and ``camloc.beam``'s ``BeamSearch``) all import them from here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, NamedTuple, Optional, Protocol

import numpy as np

from camloc import association, ekf
from camloc.constants import MERGE_SIGMA, MISS_COST, PARTIAL_BUDGET, SEED_EXPLANATIONS, SLIP_CANDIDATES, SLIP_SEEDS, STATE_GATE

if TYPE_CHECKING:
    from camloc.associators import CameraModel
    from camloc.dataset import Dataset
    from camloc.filters import EulerFilter, SE3Filter
    from camloc.tag_orientations import TagOrientations


@dataclass(frozen=True)
class BeamSettings:
    """Parameters of the beam (costs are 2 x negative log-likelihoods).

    beam_width : hypotheses kept after each pose.
    beam_delta : drop hypotheses this much costlier than the best. Both are the run's: at a pose of
        a few rays only the beam keeps more, and further (``camloc.sparse_poses.pose_beam``).
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
        past each one's own best (``PoseExpansion.explain_all``).
    state_gate : a seeded explanation whose state is further than this from its prior (its
        squared Mahalanobis distance, 6 dof) is dropped (``SeededSearch.within_prior``); inf keeps
        every one.
    miss_cost : what an explanation pays for a landmark surely on a pixel observation's ray, within
        the range where a camera surely detects what it sees (``observation_space.detection_range``), that it
        leaves unclaimed; one less sure is charged by its chance of being on the ray
        (``PoseExpansion.missed``, ``camloc.miss_term``); 0: no such term.
    null_offset : how much the run's null cost was lowered (``localizer.LACKING_NULL_OFFSET``: a
        map that lacks landmarks). Whether leaving an observation unassigned is explored (within
        ``branch_delta`` of its best option) is judged at the null cost before the lowering, so the
        lower price decides between the explanations the default would grow without growing more
        of them (judged at the lowered cost, the beam grew 14x the children and ran 4x as long;
        ``docs/performance.md``, 2026-12-04).
    """

    beam_width: int = 16
    beam_delta: float = 14.0
    branch_delta: float = 8.0
    merge_sigma: float = MERGE_SIGMA
    slip_inflation: float = 25.0
    slip_cost: float = 10.0
    slip_candidates: int = SLIP_CANDIDATES
    slip_seeds: int = SLIP_SEEDS
    seed_explanations: int = SEED_EXPLANATIONS
    partial_budget: int = PARTIAL_BUDGET
    state_gate: float = STATE_GATE
    miss_cost: float = MISS_COST
    null_offset: float = 0.0


class PartialPruning(NamedTuple):
    """One pruning of a pose's partial explanations (``PoseExpansion.prune_partials``): ``grown``
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
    children_created : children paired with a landmark (``PoseExpansion.branches``), whose state
        is computed only when first read.
    children_settled : of those, the ones whose state was computed.
    """

    slip_search_poses: list[int] = field(default_factory=list)
    seeded_search_poses: list[int] = field(default_factory=list)
    partial_prunings: list[PartialPruning] = field(default_factory=list)
    children_created: int = 0
    children_settled: int = 0


class Hypothesis:
    """A filter (x, P), the assignments at this pose that produced it and their cost.

    A child grown by one more pair (``PoseExpansion.branches``) has its cost at once, from the
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
class Partial:
    """A hypothesis that has explained some of a pose's observations (``PoseExpansion.explain_all``)."""

    h: Hypothesis
    order: tuple                      # observations (positions in the pose's obs) still to explain, in order
    options: list                     # PairOptions of every observation under base_x
    base_x: np.ndarray                # the state the options were computed under
    least: dict                       # position -> the least its explanation costs under base_x
    rest: float                       # sum of least over order
    root: int                         # which parent it grew from
    # the pose's prior its chain of pairs is checked against (``camloc.beam_chain``), None where not wide
    chain_root: Optional[Hypothesis] = None


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
    log_det_R: np.ndarray                # (K,) its ln det     (``observation_space.noise_floored``)
    point: np.ndarray                    # (K, 3) each observation as a point in its camera's frame,
    point_cov: np.ndarray                # (K, 3, 3) its covariance
    log_det_point_cov: np.ndarray        # (K,) and that covariance's ln det
    tag_orientations: TagOrientations    # the tags' orientations (``camloc.tag_orientations``; False without)
    detect_range: tuple[float, float]    # distances from a camera within which it surely detects a landmark
                                         # it sees (``observation_space.detection_range``; (0, 0): no pixel observations)

    def visible(self, x: np.ndarray, camera_id: int, P: Optional[np.ndarray] = None) -> np.ndarray:
        """The landmarks camera ``camera_id`` may see from x; with P, from within three standard
        deviations of x."""

    def observe(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (m, 3) of the landmarks by camera ``camera_id`` from x, and their Jacobians."""

    def in_front_of(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> np.ndarray:
        """Which of the landmarks (m,) lie in front of camera ``camera_id`` at x, (m,) bool."""

    def updated(
        self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray, *,
        at_prior: tuple[np.ndarray, np.ndarray] | None = None, for_association: bool = False,
    ) -> ekf.UpdateResult:
        """The filter's stacked, iterated update of (x, P) with the given pairs."""
