"""What a localization run produces (``RunResult``), and saving/loading it as a run folder.

A run folder holds:
- ``estimate.tum``, ``odometry.tum``, ``groundtruth.tum`` (when there is ground truth): TUM lines
  ``timestamp x y z qx qy qz qw`` with the pose id as timestamp;
- ``associations.csv``: ``pose,camera,u,v,depth,landmark,true_landmark,mahalanobis``, one row per
  observation, ``landmark`` and ``mahalanobis`` empty when the observation was rejected;
- ``states.npz``: per-pose filter state and covariance, pose covariance, NIS per update;
- ``summary.json``: dataset, configuration, counts, timings and headline metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UNASSOCIATED = -1


@dataclass(frozen=True)
class Associations:
    """One row per observation of the dataset, in the dataset's order (K rows).

    Attributes
    ----------
    pose_id : (K,) int64 id of the observing pose.
    camera : (K,) int64 camera id.
    uvd : (K, 3) measured u, v, depth.
    landmark : (K,) int64 landmark chosen by the localizer, ``UNASSOCIATED`` (-1) when rejected.
    true_landmark : (K,) int64 the file's landmark id (for scoring only).
    mahalanobis : (K,) Mahalanobis distance of the accepted innovation, NaN when rejected.
    """

    pose_id: np.ndarray
    camera: np.ndarray
    uvd: np.ndarray
    landmark: np.ndarray
    true_landmark: np.ndarray
    mahalanobis: np.ndarray


@dataclass(frozen=True)
class RunResult:
    """A localization run over N poses.

    Attributes
    ----------
    dataset : the dataset's source (path).
    pose_ids : (N,) int64.
    estimate_xyz, estimate_quat_xyzw : (N, 3), (N, 4) the filter's poses, world frame.
    estimate_cov : (N, 6, 6) covariance of the pose error ``(t_true - t_est, Log(R_true R_est^T))``
        (world-frame position and rotation vector, see ``geometry.pose_error_vector``), whatever
        the filter's own parametrization, so that NEES is comparable across filters.
    filter_state, filter_cov : (N, S), (N, S, S) the filter's own state and covariance (for the
        Euler filter: x, y, z, roll, pitch, yaw).
    odometry_xyz, odometry_quat_xyzw : (N, 3), (N, 4) odometry alone from the same start.
    truth_xyz, truth_quat_xyzw : (N, 3), (N, 4) ground truth, or None.
    map_landmark_ids, map_landmark_xyz : (L,), (L, 3) the known map the run localized against.
    associations : one row per observation.
    update_pose_ids : (U,) int64 the pose of each filter update (one per pose with accepted pairs).
    nis : (U,) normalized innovation squared of each update; nis_dof : (U,) its degrees of freedom.
    summary : JSON-serializable dict (dataset, configuration, counts, timings, metrics, warnings).
    """

    dataset: str
    pose_ids: np.ndarray
    estimate_xyz: np.ndarray
    estimate_quat_xyzw: np.ndarray
    estimate_cov: np.ndarray
    filter_state: np.ndarray
    filter_cov: np.ndarray
    odometry_xyz: np.ndarray
    odometry_quat_xyzw: np.ndarray
    truth_xyz: np.ndarray | None
    truth_quat_xyzw: np.ndarray | None
    map_landmark_ids: np.ndarray
    map_landmark_xyz: np.ndarray
    associations: Associations
    update_pose_ids: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    summary: dict = field(default_factory=dict)
