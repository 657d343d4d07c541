"""How far a pixel-only camera sees, learned from a run: where its detections stop.

A pixel measures no depth, so nothing in a pixel-only file says how far its cameras see, and the
candidates of an observation are every mapped landmark near its ray up to a reach guessed from the
map's density (``observation_space.pixel_reach``). Farther landmarks on the ray are wrong pairs
that gate as well as the right one; on simulated pixel worlds, knowing the true reach took the
default association's precision from 0.945-0.992 to 0.975-1.0 (docs/performance.md, 2026-12-04,
"A pixel camera's reach, learned").

A run over the first poses tells the reach: among the mapped landmarks in a camera's view cone at
each estimated pose, those near the camera are paired with an observation at a high rate and those
beyond its reach at a low one (the run's wrong pairs). ``camera_reach`` fits that step: the
distance that splits the landmarks into a near and a far group of constant pairing rates with the
greatest likelihood (a change point of Bernoulli rates), kept only where the near rate is well
above the far one.

A start run can lose the robot (on worlds with half the map withheld, most do within their first
hundred poses: docs/performance.md, 2026-12-06 seventeenth session); once lost, it pairs landmarks
at random distances and its pairs blunt the step the poses before showed. The ratio is read surely
(the near rate's lower bound over the far rate's upper one); where the whole run's step is not sure,
it is read from the prefix of the run where it is sharpest (``camera_reach``): of the run's first
``PREFIX_MIN_POSES``, ``PREFIX_MIN_POSES + PREFIX_STEP``, ... poses, the one whose near rate is
surely the most times its far rate. A run on track keeps its step as it grows; a lost one shows
none in any prefix (no reach learned, which the caller reports).

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from statistics import NormalDist

import numpy as np

from camloc import geometry, measurement, models
from camloc.dataset import Dataset, observations_by_pose

# The fitted step is trusted only where the near group's pairing rate is at least this many times
# the far group's, on at least MIN_PAIRED paired landmarks (a run that lost the robot pairs at
# random distances: no step).
# The ratio is read conservatively: the near rate's lower bound over the far rate's upper one, each
# at RATE_CONFIDENCE_TAIL (Wilson score intervals; no scipy: a small run does not import it): a far group of a few samples with none paired (the
# rim of the view cone beyond where a lost run's candidates stop) would otherwise read as infinite.
MIN_RATE_RATIO = 4.0
RATE_CONFIDENCE_TAIL = 0.025
MIN_PAIRED = 30
# The prefixes of the start run the step is read from: the first PREFIX_MIN_POSES poses (about
# 250-1,000 view samples on the simulated worlds), then every PREFIX_STEP more, and the whole run.
PREFIX_MIN_POSES = 50
PREFIX_STEP = 25


@dataclass(frozen=True)
class ReachStep:
    """A change point of the pairing rate: ``reach`` metres, the near and far groups' rates, the
    near rate's lower and the far rate's upper bound (``RATE_CONFIDENCE_TAIL``) and ``poses``,
    the prefix of the run it was read from."""

    reach: float
    near_rate: float
    far_rate: float
    near_low: float
    far_high: float
    poses: int

    @property
    def ratio(self) -> float:
        """How many times the far rate's upper bound the near rate's lower bound is: the step is
        trusted from ``MIN_RATE_RATIO``."""
        return self.near_low / self.far_high


def pairing_step(distance: np.ndarray, paired: np.ndarray) -> Optional[tuple[float, float, float]]:
    """The change point of the pairing rate along ``distance`` (M,): (reach, near rate, far rate),
    the reach halfway between the last near sample and the first far one, maximizing the
    Bernoulli log-likelihood of the two groups' constant rates; None where there are fewer than
    ``MIN_PAIRED`` paired samples or the near rate is not surely (``ReachStep.ratio``)
    ``MIN_RATE_RATIO`` times the far one."""
    step = _sharpest_split(distance, paired, 0)
    if step is None or step.ratio < MIN_RATE_RATIO:
        return None
    return step.reach, step.near_rate, step.far_rate


def _sharpest_split(distance: np.ndarray, paired: np.ndarray, poses: int) -> Optional[ReachStep]:
    """``pairing_step``'s change point as a ``ReachStep`` read from ``poses`` poses, whatever its
    ratio; None where there are fewer than ``MIN_PAIRED`` paired samples or no step down."""
    order = np.argsort(distance, kind="stable")
    d, y = distance[order], paired[order].astype(np.float64)
    n, total = d.size, float(y.sum())
    if total < MIN_PAIRED:
        return None
    near_n = np.arange(1, n, dtype=np.float64)  # a split after each sample but the last
    near_paired = np.cumsum(y)[:-1]
    far_n, far_paired = n - near_n, total - near_paired
    log_likelihood = _bernoulli_log_likelihood(near_paired, near_n) + _bernoulli_log_likelihood(far_paired, far_n)
    # a step down only, and only between distinct distances
    valid = (near_paired / near_n > far_paired / far_n) & (d[1:] > d[:-1])
    if not valid.any():
        return None
    split = int(np.argmax(np.where(valid, log_likelihood, -np.inf)))
    near_rate, far_rate = near_paired[split] / near_n[split], far_paired[split] / far_n[split]
    near_low = _wilson_bound(near_rate, near_n[split], -1.0)
    far_high = _wilson_bound(far_rate, far_n[split], 1.0)
    return ReachStep(float(0.5 * (d[split] + d[split + 1])), float(near_rate), float(far_rate), near_low, far_high, poses)


def _wilson_bound(rate: float, n: float, side: float) -> float:
    """The Wilson score interval's lower (``side`` -1) or upper (+1) bound of a Bernoulli rate
    observed as ``rate`` over ``n`` samples, each bound at ``RATE_CONFIDENCE_TAIL``."""
    z = NormalDist().inv_cdf(1.0 - RATE_CONFIDENCE_TAIL)
    centre = rate + z * z / (2.0 * n)
    spread = z * np.sqrt(rate * (1.0 - rate) / n + z * z / (4.0 * n * n))
    return float((centre + side * spread) / (1.0 + z * z / n))


def _bernoulli_log_likelihood(successes: np.ndarray, trials: np.ndarray) -> np.ndarray:
    """The maximized log-likelihood of ``successes`` in ``trials`` at the rate successes/trials."""
    rate = successes / trials
    with np.errstate(divide="ignore", invalid="ignore"):
        hit = np.where(successes > 0, successes * np.log(rate), 0.0)
        miss = np.where(trials > successes, (trials - successes) * np.log1p(-rate), 0.0)
    return hit + miss


def view_samples(dataset: Dataset, T_world_robot: np.ndarray, observation_landmark: np.ndarray,
                 view: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each pose and pixel camera, each mapped landmark in the camera's candidate view
    ``view`` = (min depth, max depth, max angle rad) at the estimated pose ``T_world_robot``
    (N, 4, 4): its distance from the camera (M,), whether an observation of that camera at that
    pose was paired with it (M,) and the pose's index (M,). ``observation_landmark`` (K,): each
    observation's map row, -1 for none."""
    from camloc.association import PointIndex

    min_depth, max_depth, max_angle = view
    index = PointIndex(dataset.landmark_xyz)
    radius = max_depth / max(np.cos(max_angle), 1e-6)  # the view cone lies within this of the camera
    order, bounds = observations_by_pose(dataset)
    rays = measurement.is_ray(dataset.obs_kind)
    distances, paired, poses = [], [], []
    for k in range(dataset.num_poses):
        at_pose = order[bounds[k]:bounds[k + 1]]
        at_pose = at_pose[rays[at_pose]]
        for camera_id in np.unique(dataset.obs_camera[at_pose]).tolist():
            T_world_camera = T_world_robot[k] @ dataset.cameras[camera_id].T_robot_camera
            near = index.within(T_world_camera[:3, 3], radius)
            _, p_camera = models.camera_points(T_world_camera, np.eye(4), dataset.landmark_xyz[near])
            distance = np.linalg.norm(p_camera, axis=1)
            depth = p_camera[:, 2]
            inside = (depth > min_depth) & (depth <= max_depth) & (depth >= np.cos(max_angle) * distance)
            rows = observation_landmark[at_pose[dataset.obs_camera[at_pose] == camera_id]]
            distances.append(distance[inside])
            paired.append(np.isin(near[inside], rows[rows >= 0]))
            poses.append(np.full(int(inside.sum()), k))
    if not distances:
        return np.zeros(0), np.zeros(0, bool), np.zeros(0, np.int64)
    return np.concatenate(distances), np.concatenate(paired), np.concatenate(poses)


def camera_reach(dataset: Dataset, estimate_xyz: np.ndarray, estimate_quat_xyzw: np.ndarray,
                 observation_landmark: np.ndarray, view: tuple[float, float, float]) -> Optional[ReachStep]:
    """The step of the run's pixel cameras' pairing rate (``view_samples``): the whole run's where
    it is sure (``ReachStep.ratio`` of ``MIN_RATE_RATIO``: the most samples, the nearest reach),
    otherwise the sharpest over its prefixes (``PREFIX_MIN_POSES``, every ``PREFIX_STEP`` more
    poses), or None where none shows a step down; the caller trusts it from ``MIN_RATE_RATIO``."""
    T = geometry.pose_from_quat(estimate_xyz, estimate_quat_xyzw)
    distance, paired, pose = view_samples(dataset, T, observation_landmark, view)
    sharpest = _sharpest_split(distance, paired, dataset.num_poses)
    if sharpest is not None and sharpest.ratio >= MIN_RATE_RATIO:
        return sharpest
    for poses in range(PREFIX_MIN_POSES, dataset.num_poses, PREFIX_STEP):
        within = pose < poses
        step = _sharpest_split(distance[within], paired[within], poses)
        if step is not None and (sharpest is None or step.ratio > sharpest.ratio):
            sharpest = step
    return sharpest
