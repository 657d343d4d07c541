"""A tag's orientation in the mapping localizer's state (``camloc.slam``): pure functions of arrays.

Model card
----------
State      a tag in the state is two rows of ``SlamMean.L``: its centre (a landmark like any
           other) and its orientation R_tag (world), stored as its rotation vector, with the row
           marked in ``SlamMean.orientation``.
Error      on the **left**, riding on the robot's heading error like the positions do:
              R_tag = Exp(xi_theta) Exp(xi_o) R^_tag.
           Why this form: a turn of the whole world by phi is then xi = (0, phi, 0, .., 0) for
           the pose, every landmark and every tag alike, whatever the estimate, so the
           unobservable directions with no map stay out of the linearization (the invariant
           EKF's property, ``camloc.slam``), and the orientation's measurement has no heading
           term: R^T R_tag = R^^T Exp(-xi_theta) Exp(xi_theta) Exp(xi_o) R^_tag, exactly.
Motion     the robot's noise moves xi_theta by R w_theta; R_tag does not move, so
           xi_o -= R w_theta (``slam.noise_coefficients``); F = I still.
Measure    R_pred = R_c^T R^T R_tag (``camloc.tags``) = R^_pred Exp(R^_tag^T xi_o) for a tag in the
           state (H_R = R^_tag^T on xi_o, nothing on the pose), R^_pred Exp(-R_tag^T xi_theta)
           for a tag held fixed; the innovation is ``tags.aligned``'s e = Log(R_pred^-1 R_meas).
Inverse    a first sighting R_tag = R R_c R_meas, R_meas = R_meas,true Exp(n):
           xi_o = -R^_tag n exactly: **no pose term** (B = 0), noise R^_tag Q_tag R^_tag^T.
Prior      a map's tag R_tag = Exp(e) R_map with e ~ N(0, sigma^2 I) (world, independent of the
           pose): xi_o = e - xi_theta to first order (B = [0, -I]).
World      the world error of an estimated orientation, e = Log(R_tag R^_tag^T) = xi_theta + xi_o
           to first order (``orientation_world_cov``).
Every Jacobian is checked against finite differences of ``slam.retract`` in tests/test_slam.py.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from camloc import geometry, tags
from camloc.ekf import symmetrize

if TYPE_CHECKING:
    from camloc.sensors import CameraModel

# (the estimate ``x`` below is ``camloc.slam.SlamMean``: not imported, slam imports this module)

POSE_DIM = 6  # xi_t, xi_theta (``camloc.slam``'s)


def turned(rotvec: np.ndarray, delta: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Orientations (q, 3) (rotation vectors, world) moved by their errors delta (q, 3) and the
    heading's E = Exp(xi_theta) (3, 3): ``Log(E Exp(delta) Exp(rotvec))``."""
    return geometry.so3_log(E @ geometry.so3_exp(delta) @ geometry.so3_exp(rotvec))


def turn_between(a: np.ndarray, b: np.ndarray, E: np.ndarray) -> np.ndarray:
    """The errors (q, 3) with ``turned(b, delta, E) == a``: ``Log(E^T R_a R_b^T)``."""
    return geometry.so3_log(E.T @ geometry.so3_exp(a) @ np.swapaxes(geometry.so3_exp(b), -1, -2))


def observe_orientations(x, sensor: "CameraModel", rotvec: np.ndarray, block: np.ndarray, width: int,
                         z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predictions (M, 3) of orientation measurements z (M, 3) (``Log(R_meas)``) of tags whose
    orientations are ``rotvec`` (M, 3), in the filter's ``z - z_hat`` form (``tags.aligned``), and
    their Jacobians (M, 3, width) on ``width`` columns of the error in blocks of three: the tag's
    orientation block ``block`` (M,) (>= 2), or -1 for a tag held fixed (the pose's heading, block 1)."""
    R_tag = geometry.so3_exp(rotvec)
    R_pred, _ = tags.prediction(x.R, sensor.T_robot_camera[:3, :3], R_tag)
    M = rotvec.shape[0]
    H_R = np.zeros((M, 3, width))
    blocks = H_R.reshape(M, 3, width // 3, 3)
    R_tag_T = np.swapaxes(R_tag, -1, -2)
    fixed = block < 0
    blocks[fixed, :, 1, :] = -R_tag_T[fixed]
    mine = np.flatnonzero(~fixed)
    blocks[mine, :, block[mine], :] = R_tag_T[mine]
    return tags.aligned(z, R_pred, H_R)


def inverse_orientation(x, sensor: "CameraModel", z: np.ndarray, R_z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A new tag's orientation from one measurement z (3,) (``Log(R_meas)``) of noise R_z (3, 3):
    its rotation vector (3,) (world), the coefficients B (3, POSE_DIM) of its error on the pose's
    (zero: ``xi_o = -R_tag n``) and the noise's covariance (3, 3)."""
    R_tag = x.R @ sensor.T_robot_camera[:3, :3] @ geometry.so3_exp(z)
    return geometry.so3_log(R_tag), np.zeros((3, POSE_DIM)), symmetrize(R_tag @ R_z @ R_tag.T)


def prior_coefficients() -> np.ndarray:
    """B (3, POSE_DIM) of a tag's orientation whose world error e is independent of the pose:
    ``xi_o = e - xi_theta``."""
    B = np.zeros((3, POSE_DIM))
    B[:, 3:6] = -np.eye(3)
    return B


def orientation_world_cov(P: np.ndarray, row: int) -> np.ndarray:
    """The world covariance (3, 3) of the orientation in the state's row ``row``: e = xi_theta + xi_o."""
    c = POSE_DIM + 3 * row
    rows = np.array([3, 4, 5, c, c + 1, c + 2])
    A = np.hstack([np.eye(3), np.eye(3)])
    return symmetrize(A @ P[np.ix_(rows, rows)] @ A.T)


def angle_between(rotvec_a: np.ndarray, quat_b_xyzw: np.ndarray) -> np.ndarray:
    """The angles (M,) (radians) between orientations (M, 3) (rotation vectors) and (M, 4) (quaternions)."""
    R_b = geometry.quat_to_matrix(quat_b_xyzw)
    return np.linalg.norm(geometry.so3_log(np.swapaxes(geometry.so3_exp(rotvec_a), -1, -2) @ R_b), axis=-1)

