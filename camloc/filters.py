"""The two state parametrizations the localizer can filter in, behind one small interface.

- ``EulerFilter`` (``--filter euler``, the default): the state is the 6-vector (x, y, z, roll,
  pitch, yaw) and the update is additive; singular at pitch +-90 deg.
- ``SE2Filter`` (``--filter se2``, the default for planar files): an error-state EKF on SE(2), the
  state (x, y, theta), the error its right perturbation (``camloc.planar``); 3 degrees of freedom.
- ``SE3Filter`` (``--filter se3``): an error-state EKF on SE(3). The state is the pose matrix T; the
  covariance is over the right perturbation delta = (dt, dtheta) with T_true = T Exp(delta) in the
  sense of ``geometry.retract_right``; the update is applied through that retraction. No
  singularity.

Both give the filter the same things: the initial state, prediction with its Jacobians, the
measurement model with its Jacobian, retraction and difference (for the iterated update), the pose,
and the pose covariance in camloc's common parametrization (``geometry.pose_error_vector``) so that
NEES is comparable across filters.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry, models, planar, tags
from camloc.measurement import DEPTH, PLANAR_KINDS, TAG_ROTATION

SINGULARITY_WARNING_DEG = 80.0


def rotation_pitch_deg(pitch: np.ndarray) -> np.ndarray:
    """The pitch, degrees in [-90, 90], of the rotation an Euler state's pitch (radians) gives: an
    update can carry the state's angle past +-90 deg (the same rotation as 180 deg minus it, roll and
    yaw turned half a turn), where its own value no longer says how near the singularity it is
    (the audit of 2026-12-06: a state's -218.9 deg, a rotation pitched 38.9 deg, was warned of)."""
    return np.degrees(np.arcsin(np.clip(np.sin(pitch), -1.0, 1.0)))


def near_singularity_deg(pitch: np.ndarray) -> np.ndarray:
    """Whether each Euler state pitch (radians) puts the rotation within ``90 -
    SINGULARITY_WARNING_DEG`` degrees of the singularity at +-90 deg."""
    return np.abs(rotation_pitch_deg(pitch)) > SINGULARITY_WARNING_DEG


class EulerFilter:
    """State (x, y, z, roll, pitch, yaw), ``R = Rz(yaw) Ry(pitch) Rx(roll)``; additive updates."""

    name = "euler"
    stored_size = 6
    dim = 6

    def initial(self, T_world_robot: np.ndarray) -> np.ndarray:
        return geometry.pose_to_euler(T_world_robot)

    def predict(self, x: np.ndarray, T_increment: np.ndarray):
        return models.motion(x, T_increment)

    def observe(self, x, T_robot_camera, intrinsics, landmark_xyz, kind=DEPTH, heading=None, tag_quat=None):
        if kind == TAG_ROTATION:  # a body rotation E d: the rotation error's Jacobian chains E
            return _tag_rotation(geometry.euler_to_matrix(x[3:6]), T_robot_camera, tag_quat,
                                 geometry.euler_rate_matrix(x[3:6]), translation_columns=3)
        return models.observe(x, T_robot_camera, intrinsics, landmark_xyz, kind)

    def observe_rig(self, x, mounts, intrinsics, landmark_xyz, sizes, kind):
        """``observe`` of several cameras of one kind (not a tag's orientation) in one batch
        (``models.observe_rig``)."""
        return models.observe_rig(x, mounts, intrinsics, landmark_xyz, sizes, kind)

    def retract(self, x: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """``x + delta`` with roll and yaw wrapped into [-pi, pi)."""
        out = x + delta
        _, _, _, roll, _, yaw = out.tolist()
        out[3], out[5] = geometry.wrap_angle_float(roll), geometry.wrap_angle_float(yaw)
        return out

    def difference(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``a - b`` with the angle differences wrapped."""
        d = a - b
        _, _, _, roll, pitch, yaw = d.tolist()
        d[3], d[4], d[5] = geometry.wrap_angle_float(roll), geometry.wrap_angle_float(pitch), geometry.wrap_angle_float(yaw)
        return d

    def differences(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``difference`` of states a (..., 6) and b (..., 6) broadcast against each other (a (6,)
        from each row of b (m, 6), or rows of a from one row of b): the same numbers to the bit as
        one at a time (numpy's float remainder is Python's, ``geometry.wrap_angle_float``)."""
        d = a - b
        d[..., 3:] = geometry.wrap_angle(d[..., 3:])
        return d

    def pose(self, x: np.ndarray) -> np.ndarray:
        return geometry.pose_from_euler(x)

    def stored(self, x: np.ndarray) -> np.ndarray:
        return x

    def pose_cov(self, stored_states: np.ndarray, covs: np.ndarray) -> np.ndarray:
        """Covariances (N, 6, 6) of Euler states -> of the pose error ``geometry.pose_error_vector``.

        An Euler error d moves the rotation by ``R Exp(E d) = Exp(R E d) R``: the world-frame
        rotation vector is ``R E d``, so ``J = blockdiag(I, R E)`` and ``cov_pose = J P J'``.
        """
        J = np.zeros_like(covs)
        J[:, 0:3, 0:3] = np.eye(3)
        rpy = stored_states[:, 3:6]
        J[:, 3:6, 3:6] = geometry.euler_to_matrix(rpy) @ geometry.euler_rate_matrix(rpy)
        return _symmetric(J @ covs @ np.swapaxes(J, 1, 2))

    def near_singularity(self, x: np.ndarray) -> float | None:
        """The rotation's pitch in degrees (``rotation_pitch_deg``) when it is close to +-90 deg, else None."""
        return float(rotation_pitch_deg(x[4])) if near_singularity_deg(x[4]) else None


class SE3Filter:
    """State the pose T (4, 4); error the right perturbation (dt, dtheta) of ``retract_right``."""

    name = "se3"
    stored_size = 7  # x, y, z, qx, qy, qz, qw
    dim = 6

    def initial(self, T_world_robot: np.ndarray) -> np.ndarray:
        return np.array(T_world_robot, dtype=float)

    def predict(self, x: np.ndarray, T_increment: np.ndarray):
        return models.motion_se3(x, T_increment)

    def observe(self, x, T_robot_camera, intrinsics, landmark_xyz, kind=DEPTH, heading=None, tag_quat=None):
        if kind == TAG_ROTATION:
            return _tag_rotation(x[:3, :3], T_robot_camera, tag_quat, np.eye(3), translation_columns=3)
        return models.observe_se3(x, T_robot_camera, intrinsics, landmark_xyz, kind)

    def observe_rig(self, x, mounts, intrinsics, landmark_xyz, sizes, kind):
        """``observe`` of several cameras of one kind (not a tag's orientation) in one batch
        (``models.observe_rig_se3``)."""
        return models.observe_rig_se3(x, mounts, intrinsics, landmark_xyz, sizes, kind)

    def retract(self, x: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return geometry.retract_right(x, delta)

    def difference(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return geometry.difference_right(a, b)

    def pose(self, x: np.ndarray) -> np.ndarray:
        return x

    def stored(self, x: np.ndarray) -> np.ndarray:
        t, q = geometry.pose_to_quat(x)
        return np.concatenate([t, q])

    def pose_cov(self, stored_states: np.ndarray, covs: np.ndarray) -> np.ndarray:
        """A right perturbation (dt, dtheta) is the world-frame error (R dt, R dtheta):
        ``J = blockdiag(R, R)``."""
        R = geometry.quat_to_matrix(stored_states[:, 3:7])
        J = np.zeros_like(covs)
        J[:, 0:3, 0:3] = R
        J[:, 3:6, 3:6] = R
        return _symmetric(J @ covs @ np.swapaxes(J, 1, 2))

    def near_singularity(self, x: np.ndarray) -> float | None:
        return None


class SE2Filter:
    """State the planar pose (x, y, theta); error its right perturbation (dt (2), dtheta)
    (``camloc.planar``). Observes the planar kinds (point2, marker) and 3-D cameras on the robot."""

    name = "se2"
    stored_size = 3  # x, y, theta
    dim = 3

    def initial(self, T_world_robot: np.ndarray) -> np.ndarray:
        return planar.flatten(np.asarray(T_world_robot, dtype=float))

    def predict(self, x: np.ndarray, T_increment: np.ndarray):
        return planar.motion(x, T_increment)

    def observe(self, x, T_robot_camera, intrinsics, landmark_xyz, kind=DEPTH, heading=None, tag_quat=None):
        """Predictions (M, 3) and Jacobians (M, 3, 3); ``heading`` (M,): a marker's, in the world;
        ``tag_quat`` (M, 4): a tag's orientation."""
        if kind == TAG_ROTATION:  # a turn about z
            return _tag_rotation(planar.lift(x)[:3, :3], T_robot_camera, tag_quat, np.array([[0.0], [0.0], [1.0]]),
                                 translation_columns=2)
        if kind in PLANAR_KINDS:
            return planar.observe_planar(x, landmark_xyz[:, :2], heading, kind)
        return planar.observe_camera(x, T_robot_camera, intrinsics, landmark_xyz, kind)

    def retract(self, x: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return planar.retract(x, delta)

    def difference(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return planar.difference(a, b)

    def pose(self, x: np.ndarray) -> np.ndarray:
        return planar.lift(x)

    def stored(self, x: np.ndarray) -> np.ndarray:
        return np.array(x, dtype=float)

    def pose_cov(self, stored_states: np.ndarray, covs: np.ndarray) -> np.ndarray:
        """Covariances (N, 3, 3) of the right perturbation -> (N, 6, 6) of the pose error
        ``geometry.pose_error_vector``, zero in z, roll and pitch (the robot stays in the plane;
        NEES of a planar run is taken on the (x, y, yaw) block, ``planar.planar_block``): the world
        error is (R(theta) dt, dtheta), ``J = blockdiag(R(theta), 1)``."""
        J = np.zeros_like(covs)
        J[:, :2, :2] = planar.rotation(stored_states[:, 2])
        J[:, 2, 2] = 1.0
        return planar.lifted_cov(_symmetric(J @ covs @ np.swapaxes(J, 1, 2)))

    def near_singularity(self, x: np.ndarray) -> float | None:
        return None


FILTERS = {"euler": EulerFilter, "se3": SE3Filter, "se2": SE2Filter}


def make_filter(name: str):
    return FILTERS[name]()


def _tag_rotation(R_world_robot: np.ndarray, T_robot_camera: np.ndarray, tag_quat: np.ndarray, rotation_of_state: np.ndarray,
                  *, translation_columns: int) -> tuple[np.ndarray, np.ndarray]:
    """A tag's orientation in the camera (``camloc.tags``): z_hat = Log(R_pred) (M, 3) and H (M, 3, n),
    R_pred's right perturbation per state error: zeros for the translation, ``H_R`` times
    ``rotation_of_state`` (d dtheta / d state's rotation part) for the rotation. The filter's update
    aligns both with the measurement (``tags.aligned``)."""
    R_pred, H_R = tags.prediction(R_world_robot, T_robot_camera[:3, :3], geometry.quat_to_matrix(tag_quat))
    H = np.zeros((R_pred.shape[0], 3, translation_columns + rotation_of_state.shape[1]))
    H[:, :, translation_columns:] = H_R @ rotation_of_state
    return geometry.so3_log(R_pred), H


def _symmetric(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))
