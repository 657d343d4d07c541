"""The numpy localizer's per-pose association methods, behind one signature:

    associate(scene, x, P, obs) -> (obs_indices (p,), landmark_indices (p,))

``scene`` (``AssociationScene``) is what the methods read of the run and never change: the
dataset's arrays, the cameras, the map's ``association.PointIndex``, each observation's noise as association judges
it, the gate and the candidate range. ``(x, P)`` is the filter's prediction at the pose; ``obs``
(m,) are the pose's observations (indices into the dataset's, at least one; the map has at least
one landmark). The result is the accepted pairs: observation indices and the map rows of their
landmarks (int64), which the filter then takes in one stacked update. A method's options are set
once per run, as the fields of its object (``BestFriends(cost="nll", margin=1.0, sequential=True)``).

- ``oracle``: the file's landmark ids, gated like any pair.
- ``BestFriends``: mutual best matches with a margin, one pair at a time or all at once.
- ``Jcbb``: joint compatibility branch and bound (``camloc.jcbb``), seeded by best friends.

The beam (``camloc.beam.BeamSearch``) yields the same pairs per pose but is not one of these: it
searches the whole run at once (a pose's pairs are final only once the poses after it have
confirmed them), and the localizer looks up each pose's pairs from its result.

The arithmetic is ``camloc.association``'s and ``camloc.jcbb``'s (pure functions of arrays); this
module gathers their inputs from the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np

from camloc import association, measurement, planar, tag_orientations
from camloc.constants import MAX_HALF_ANGLE_DEG, WIDENED_VIEW_SIGMAS
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3, LANDMARK_TAG
from camloc.jcbb import jcbb
from camloc.sensors import CameraModel

if TYPE_CHECKING:
    from camloc.dataset import Dataset
    from camloc.filters import EulerFilter, SE3Filter

Pairs = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True, eq=False)
class AssociationScene:
    """What the per-pose association methods read of a run, built once by the localizer.

    Attributes
    ----------
    dataset : the dataset (its observations ``obs_z`` and map ``landmark_xyz``).
    filter : the state's parametrization (``camloc.filters``): its measurement model and pose.
    cameras : sensor index -> ``CameraModel`` (``sensors_of``).
    obs_sensor : (K,) each observation's sensor.
    map_index : ``association.PointIndex`` over ``dataset.landmark_xyz``; None for an empty map.
    min_depth, max_depth : candidate landmarks' depth range, metres.
    max_distance : candidates within this distance of the camera, metres (inf: no bound).
    max_angle : candidates within this angle of the optical axis, radians.
    obs_gate : (K,) the chi^2 quantile a pair's d^2 must not exceed, at each observation's dof.
    association_cov : (K, 3, 3) each observation's covariance as association judges it
        (``observation_space.noise_floored``; the filter's update keeps the file's own).
    true_landmark_row : (K,) the map row of each observation's landmark by the file's ids, -1 where
        it has none; read by ``oracle`` only.
    conditioned : ``conditioned(x, P, obs, landmarks) -> (x, P)``: the state conditioned on the
        given pairs, weighed by ``association_cov`` (the localizer's stacked, iterated update),
        for a method that judges the rest of a pose's observations after some pairs.
    planar_range : how far a planar robot's own sensor (``measurement.PLANAR_KINDS``) sees,
        metres (``observation_space.planar_range``).
    tag_orientations : the tags' orientations, which a tag's pair is judged by with its position
        (``camloc.tag_orientations``); None or False: none.
    """

    dataset: Dataset
    filter: EulerFilter | SE3Filter
    cameras: dict[int, CameraModel]
    obs_sensor: np.ndarray
    map_index: Optional[association.PointIndex]
    min_depth: float
    max_depth: float
    max_angle: float
    obs_gate: np.ndarray
    association_cov: np.ndarray
    true_landmark_row: np.ndarray
    conditioned: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    planar_range: float = 0.0
    max_distance: float = np.inf
    tag_orientations: Optional[tag_orientations.TagOrientations] = None

    def within_reach(self, x: np.ndarray, pair_obs: np.ndarray, pair_landmarks: np.ndarray) -> np.ndarray:
        """Which pairs' landmarks lie within ``max_distance`` (a pixel-only file's learned reach) of
        their camera at x (a planar sensor's: every one): (p,) bool. The beam takes candidates from
        anywhere the prior may put the camera; from the posterior, a landmark beyond the camera's
        reach is one it cannot have seen (on pixel-only worlds nearly every such pair is wrong:
        docs/performance.md, 2026-12-05). The kernels' twin is ``kernels.filtering.within_reach``."""
        within = np.ones(pair_obs.size, dtype=bool)
        if not np.isfinite(self.max_distance):
            return within
        for n in np.flatnonzero(~measurement.is_planar(self.dataset.obs_kind[pair_obs])):
            centre = (self.filter.pose(x) @ self.cameras[int(self.obs_sensor[pair_obs[n]])].T_robot_camera)[:3, 3]
            within[n] = np.linalg.norm(self.dataset.landmark_xyz[pair_landmarks[n]] - centre) <= self.max_distance
        return within

    def in_front(self, x: np.ndarray, pair_obs: np.ndarray, pair_landmarks: np.ndarray) -> np.ndarray:
        """Which pairs' landmarks lie in front of their camera at x (``in_front_of``): (p,) bool.
        The kernels' twin is ``kernels.filtering.in_front``."""
        front = np.ones(pair_obs.size, dtype=bool)
        sensors = self.obs_sensor[pair_obs]
        for camera_id in np.unique(sensors):
            mine = sensors == camera_id
            front[mine] = self.in_front_of(x, int(camera_id), pair_landmarks[mine])
        return front

    def in_front_of(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> np.ndarray:
        """Which of the landmarks (m,) lie in front of camera ``camera_id`` at x (depth > 0; a
        planar sensor's: every one): (m,) bool. Behind the camera a projection's Jacobian grows as
        1/depth^2, and so does the S of a pair's gate, which then passes a prediction nowhere near
        its observation (the audit of 2026-12-06): such a pair is no option at x, for the oracle
        (``in_front``) or the beam (``pair_options.PairGating``), though the beam takes it as a
        candidate (its view is widened for where the camera may be) and judges it again at every
        state. The kernels' twin is ``kernels.camera.in_front_of``."""
        camera = self.cameras[int(camera_id)]
        return measurement.in_front(self.filter.pose(x) @ camera.T_robot_camera, camera.kind, self.dataset.landmark_xyz[landmarks])

    def ray_rival_margins(self, obs: np.ndarray, cost: np.ndarray, chosen: np.ndarray) -> np.ndarray:
        """``association.rival_margins`` of observations ``obs`` (cost (n, m), chosen (n,)) where they
        are rays (pixels) and ``max_distance`` is bounded, inf elsewhere: a ray passes near several
        landmarks, and which of them it is must be clear too; beyond the camera's reach, landmarks
        it cannot see would crowd every ray (in the run that learns the reach)."""
        rays = measurement.is_ray(self.dataset.obs_kind[obs]) & np.isfinite(self.max_distance)
        if not rays.any():
            return np.full(obs.size, np.inf)
        return np.where(rays, association.rival_margins(cost, chosen), np.inf)

    def visible(self, x: np.ndarray, camera_id: int, P: Optional[np.ndarray] = None) -> np.ndarray:
        """Indices of the landmarks in camera ``camera_id``'s depth range and field of view from
        state x, found through the map's index. With P, the view is widened by three
        standard deviations of the position (in metres) and of the orientation (in angle), for a
        prior too wide for the data's own margins."""
        camera = self.cameras[int(camera_id)]
        if self.filter.dim == 3:  # a planar robot (camloc.planar): its own sensor sees around it
            return self._visible_planar(x, camera, P)
        margin, max_angle = 0.0, self.max_angle
        if P is not None:
            margin = WIDENED_VIEW_SIGMAS * float(np.sqrt(np.linalg.eigvalsh(P[:3, :3])[-1]))
            widened = max_angle + WIDENED_VIEW_SIGMAS * float(np.sqrt(np.linalg.eigvalsh(P[3:6, 3:6])[-1]))
            max_angle = max(max_angle, min(widened, np.radians(MAX_HALF_ANGLE_DEG)))  # never narrower than the plain view
        return association.candidate_indices(
            self.map_index, self.dataset.landmark_xyz, self.filter.pose(x) @ camera.T_robot_camera,
            min_depth=self.min_depth, max_depth=self.max_depth, max_angle_rad=max_angle, margin=margin,
            max_distance=self.max_distance,
        )

    def _visible_planar(self, x: np.ndarray, camera: CameraModel, P: Optional[np.ndarray]) -> np.ndarray:
        """``visible`` for a planar state (x, y, theta): a planar sensor's landmarks of its kind
        within ``planar_range`` of the robot (with P, widened by three standard deviations of the
        position); a camera's 3-D points in its view from the lifted pose (the heading's
        standard deviation widening the view's angle)."""
        kinds = self.dataset.landmark_kind
        margin = 0.0 if P is None else WIDENED_VIEW_SIGMAS * float(np.sqrt(np.linalg.eigvalsh(P[:2, :2])[-1]))
        if camera.kind in measurement.PLANAR_KINDS:
            wanted = LANDMARK_MARKER if camera.kind == measurement.MARKER else LANDMARK_POINT2
            near = self.map_index.within(np.array([x[0], x[1], 0.0]), self.planar_range + margin)
            return near[kinds[near] == wanted]
        max_angle = self.max_angle
        if P is not None:
            widened = max_angle + WIDENED_VIEW_SIGMAS * float(np.sqrt(P[2, 2]))
            max_angle = max(max_angle, min(widened, np.radians(MAX_HALF_ANGLE_DEG)))
        near = association.candidate_indices(
            self.map_index, self.dataset.landmark_xyz, self.filter.pose(x) @ camera.T_robot_camera,
            min_depth=self.min_depth, max_depth=self.max_depth, max_angle_rad=max_angle, margin=margin,
            max_distance=self.max_distance,
        )
        return near[np.isin(kinds[near], (LANDMARK_POINT3, LANDMARK_TAG))]  # a camera sees points and tags

    def observe(self, x: np.ndarray, camera_id: int, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted measurements (m, 3) of the given landmark indices by camera ``camera_id`` from
        state x, and their Jacobians (m, 3, n)."""
        camera = self.cameras[int(camera_id)]
        return self.filter.observe(x, camera.T_robot_camera, camera.intrinsics, self.dataset.landmark_xyz[landmarks], camera.kind,
                                   heading=self.dataset.landmark_heading[landmarks], tag_quat=self.dataset.landmark_quat_xyzw[landmarks])

    def predictions(self, x: np.ndarray, P: np.ndarray, camera_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The landmarks camera ``camera_id`` may see from state x (``visible``): (candidates (m,),
        z_hat (m, 3), H (m, 3, n), HPH (m, 3, 3))."""
        candidates = self.visible(x, camera_id)
        z_hat, H = self.observe(x, camera_id, candidates)
        HPH = H @ P @ H.swapaxes(1, 2)
        return candidates, z_hat, H, HPH


Associator = Callable[[AssociationScene, np.ndarray, np.ndarray, np.ndarray], Pairs]


def oracle(scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray) -> Pairs:
    """The file's landmark ids, kept where the id is in the map, x puts the landmark in front of
    its camera (``AssociationScene.in_front``) and the pair passes the gate (a gross outlier
    keeps its true id but is no evidence any filter should take)."""
    index = scene.true_landmark_row[obs]
    obs, index = obs[index >= 0], index[index >= 0]
    front = scene.in_front(x, obs, index)
    obs, index = obs[front], index[front]
    keep = np.zeros(obs.size, dtype=bool)
    for camera_id in np.unique(scene.obs_sensor[obs]):
        mine = scene.obs_sensor[obs] == camera_id
        z_hat, H = scene.observe(x, camera_id, index[mine])
        S = H @ P @ H.swapaxes(1, 2) + scene.association_cov[obs[mine]]
        y = planar.wrap_residuals(scene.dataset.obs_z[obs[mine]] - z_hat, scene.dataset.obs_kind[obs[mine]])
        d2, _ = association.mahalanobis_3x3(S, y)
        keep[mine] = d2 <= scene.obs_gate[obs[mine]]
    return obs[keep], index[keep]


@dataclass(frozen=True)
class BestFriends:
    """Best friends (``association.best_friends``): an observation and a landmark pair when each
    is the other's cheapest, the pair passes the gate and no rival comes within ``margin``.

    Attributes
    ----------
    cost : "nll" (d^2 + ln det S), "mahalanobis" (d^2) or "euclidean" (|z - z_hat|).
    margin : a pair is refused when a rival in its row or column costs less than this more.
    sequential : accept the pair with the widest margin, condition the state on it
        (``AssociationScene.conditioned``) and look again at the rest; False pairs all the
        observations at once.
    """

    cost: str
    margin: float
    sequential: bool

    def __call__(self, scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray) -> Pairs:
        if not self.sequential:
            rows, landmarks, _ = best_friends_pairs(scene, x, P, obs, taken=np.zeros(0, np.int64), cost=self.cost, margin=self.margin)
            return obs[rows], landmarks
        return self._one_at_a_time(scene, x, P, obs)

    def _one_at_a_time(self, scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray) -> Pairs:
        """Accept the most unambiguous pair, condition a scratch copy of the filter on it, and look
        again at the rest. Each accepted pair shrinks the uncertainty that made the others
        ambiguous, so a pose's pairs support each other."""
        remaining = obs
        chosen_obs: list[int] = []
        chosen_landmarks: list[int] = []
        while remaining.size:
            rows, landmarks, gap = best_friends_pairs(scene, x, P, remaining, taken=np.asarray(chosen_landmarks, np.int64),
                                                      cost=self.cost, margin=self.margin)
            if rows.size == 0:
                break
            best = int(np.argmax(gap))
            chosen_obs.append(int(remaining[rows[best]]))
            chosen_landmarks.append(int(landmarks[best]))
            remaining = np.delete(remaining, rows[best])
            if remaining.size:
                x, P = scene.conditioned(x, P, np.asarray(chosen_obs[-1:]), np.asarray(chosen_landmarks[-1:]))
        return np.asarray(chosen_obs, np.int64), np.asarray(chosen_landmarks, np.int64)


def best_friends_pairs(
    scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray, *, taken: np.ndarray, cost: str, margin: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best-friends pairs at (x, P) over all cameras, each camera's observations against its own
    candidates less the landmarks ``taken``: (rows into obs, landmark indices, gaps: each pair's
    margin over its closest rival)."""
    ds = scene.dataset
    rows_all, landmarks_all, gaps_all = [], [], []
    for camera_id in np.unique(scene.obs_sensor[obs]):
        rows_c = np.flatnonzero(scene.obs_sensor[obs] == camera_id)
        candidates, z_hat, H, HPH = scene.predictions(x, P, camera_id)
        free = ~np.isin(candidates, taken)
        candidates, z_hat, H, HPH = candidates[free], z_hat[free], H[free], HPH[free]
        if candidates.size == 0:
            continue
        z = ds.obs_z[obs[rows_c]]
        kinds = ds.obs_kind[obs[rows_c]]
        d2, nll = association.pair_statistics(z, scene.association_cov[obs[rows_c]], z_hat, HPH, kinds)
        more_d2, more_cost, gate = orientation_terms(scene, x, P, obs[rows_c], candidates, z_hat, H)
        d2, nll = d2 + more_d2, nll + more_cost
        pair_cost = {"nll": nll, "mahalanobis": d2}.get(cost)
        if pair_cost is None:
            pair_cost = np.linalg.norm(planar.wrap_residuals(z[:, None, :] - z_hat[None, :, :], kinds[:, None]), axis=-1)
        r, c, gap = association.best_friends(pair_cost, d2, gate=gate, margin=margin)
        rows_all.append(rows_c[r])
        landmarks_all.append(candidates[c])
        gaps_all.append(gap)
    if not rows_all:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(rows_all), np.concatenate(landmarks_all), np.concatenate(gaps_all)


def orientation_terms(
    scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray, candidates: np.ndarray, z_hat: np.ndarray, H: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What tags' orientations add to every pair of observations obs (n,) and candidates (m,)
    (predictions z_hat (m, 3), H (m, 3, s)): d^2 (n, m), cost (n, m) and each pair's gate (n, m)
    (``tag_orientations.TagOrientations.pair_terms``; zeros and ``obs_gate`` without tags)."""
    gate = np.broadcast_to(scene.obs_gate[obs][:, None], (obs.size, candidates.size))
    if not scene.tag_orientations:
        return np.zeros(gate.shape), np.zeros(gate.shape), gate
    i, j = (part.ravel() for part in np.indices(gate.shape))
    y = planar.wrap_residuals(scene.dataset.obs_z[obs[i]] - z_hat[j], scene.dataset.obs_kind[obs[i]])
    terms = scene.tag_orientations.pair_terms(x, P, obs[i], candidates[j], y, H[j], scene.association_cov[obs[i]], scene.observe,
                                              scene.obs_sensor, gate.ravel())
    return tuple(term.reshape(gate.shape) for term in terms)


@dataclass(eq=False)
class Jcbb:
    """Joint compatibility branch and bound (``camloc.jcbb``) over every camera of the pose at
    once (the pairs share the pose's error), seeded by best friends' pairs taken all at once.

    Attributes
    ----------
    probability : of the joint chi^2 test.
    max_nodes : bound on the joint tests per pose; past it the best set found is kept.
    seed_cost, seed_margin : best friends' cost and margin, which pick the seed.
    poses_cut_short : poses where ``max_nodes`` ended the search before it was exhaustive, counted
        over the run for its warning: the one thing a call changes.
    """

    probability: float
    max_nodes: int
    seed_cost: str
    seed_margin: float
    poses_cut_short: int = field(default=0, init=False)

    def __call__(self, scene: AssociationScene, x: np.ndarray, P: np.ndarray, obs: np.ndarray) -> Pairs:
        ds = scene.dataset
        cands, z_hats, Hs, blocks = [], [], [], []
        for camera_id in np.unique(scene.obs_sensor[obs]):
            c = scene.visible(x, camera_id)
            z_hat, H = scene.observe(x, camera_id, c)
            cands.append(c), z_hats.append(z_hat), Hs.append(H), blocks.append((scene.obs_sensor[obs] == camera_id, c.size))
        candidates = np.concatenate(cands)
        if candidates.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        z_hat, H = np.concatenate(z_hats), np.concatenate(Hs)
        y_all = planar.wrap_residuals(ds.obs_z[obs][:, None, :] - z_hat[None, :, :], ds.obs_kind[obs][:, None])
        HPH = H @ P @ H.swapaxes(1, 2)
        d2, _ = association.pair_statistics(ds.obs_z[obs], scene.association_cov[obs], z_hat, HPH, ds.obs_kind[obs])
        same_camera = np.zeros(d2.shape, dtype=bool)
        start = 0
        for mine, size in blocks:
            same_camera[mine, start : start + size] = True
            start += size
        more_d2, _, gate = orientation_terms(scene, x, P, obs, candidates, z_hat, H)
        compatible = (d2 + more_d2 <= gate) & same_camera
        orientations = orientation_rows(scene, x, obs, candidates, compatible)
        rows, landmarks, _ = best_friends_pairs(scene, x, P, obs, taken=np.zeros(0, np.int64), cost=self.seed_cost, margin=self.seed_margin)
        # a landmark is a column per sensor that may see it (a camera of depth and pixel records
        # is two sensors): the seed's pair takes its observation's sensor's column
        seed = [(int(r), int(np.flatnonzero((candidates == l) & same_camera[r])[0])) for r, l in zip(rows, landmarks)]
        result = jcbb(y_all, H, P, scene.association_cov[obs], compatible, dof=measurement.dof_of(ds.obs_kind[obs]),
                      probability=self.probability, max_nodes=self.max_nodes, seed=seed, orientations=orientations,
                      landmark_of=candidates)
        if not result.exhaustive:
            self.poses_cut_short += 1
        paired = result.assignment >= 0
        return obs[paired], candidates[result.assignment[paired]]


def orientation_rows(scene: AssociationScene, x: np.ndarray, obs: np.ndarray, candidates: np.ndarray, compatible: np.ndarray) -> dict:
    """The orientation rows of the compatible pairs (i, j) of observations obs (n,) and candidates
    (m,) that are a tag's position with a tag: {(i, j): (e (3,), H_rot (3, s), R_rot (3, 3))}
    (``tag_orientations.TagOrientations.orientation_rows``), for ``jcbb``'s joint test."""
    if not scene.tag_orientations or not tag_orientations.ORIENTATION_IN_ASSOCIATION:
        return {}
    i, j = np.nonzero(compatible)
    both, e, H_rot, R_rot = scene.tag_orientations.orientation_rows(x, obs[i], candidates[j], scene.observe, scene.obs_sensor)
    return {(int(i[b]), int(j[b])): (e[n], H_rot[n], R_rot[n]) for n, b in enumerate(both)}
