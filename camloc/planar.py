"""Planar (SE(2)) robot models with their analytic Jacobians: pure functions of arrays.

Model card
----------
State      x = (x, y, theta): the robot pose in the world plane, metres and radians; theta is kept in
           [-pi, pi) (``wrap``). Lifted to 3-D with z = 0 and a rotation about z by theta
           (``lift``), which is how a planar dataset's poses are stored (``camloc.dataset``).
Error      the right perturbation delta = (dt (2), dtheta): t_true = t + R(theta) dt,
           theta_true = theta + dtheta, the planar case of ``geometry.retract_right``
           (``retract``, ``difference``).
Control    u = the odometry increment (dx, dy, dtheta): the next pose in the frame of the current
           one (``EDGE_SE2``), stored lifted as a (4, 4) ``T_k_k+1`` like a 3-D increment.
Motion     t' = t + R(theta) dt_inc, theta' = theta + dtheta_inc, with the increment's noise a right
           perturbation w = (w_t, w_theta) as in 3-D; the error propagates as
              dt' = R(dtheta_inc)^T (dt + J dt_inc dtheta) + w_t,  dtheta' = dtheta + w_theta
           (J the rotation by +90 deg), so F = [[R_inc^T, R_inc^T J dt_inc], [0, 1]] and G selects
           (x, y, yaw) of the lifted 6-D noise (translation, rotation vector).
Measure    of a landmark l (world plane) in the robot frame, p = R(theta)^T (l - t):
              point2  z = p                                   H = [-I, -J p]
              marker  z = (p, wrap(psi_l - theta))             H = [[-I, -J p], [0, 0, -1]]
           (the textbook marker model: x_r = (x_l - x) cos theta + (y_l - y) sin theta,
           y_r = -(x_l - x) sin theta + (y_l - y) cos theta, psi_r = psi_l - theta); a camera on
           the planar robot is the 3-D camera model at the lifted pose, its Jacobian the columns
           (x, y, yaw) of the SE(3) right-perturbation Jacobian (``camera``).
Noise      the file's information of (x, y) or (x, y, psi); an angle residual is wrapped
           (``wrap_residuals``).
Every Jacobian is checked against central finite differences in tests/test_planar.py.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry, models
from camloc.measurement import ANGLE_ROW, MARKER, MAX_DIM, POINT2

# d R(theta) / d theta = R(theta) J
J = np.array([[0.0, -1.0], [1.0, 0.0]])
# the rows of the lifted 6-D error (translation, rotation vector) a planar error is
PLANAR_AXES = (0, 1, 5)
# the planar state's size (x, y, theta)
STATE_SIZE = 3


def wrap(angle):
    """Angles wrapped into [-pi, pi) (``geometry.wrap_angle``, the one helper)."""
    return geometry.wrap_angle(angle)


def rotation(theta) -> np.ndarray:
    """(..., 2, 2) the rotation by theta."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def lift(x: np.ndarray) -> np.ndarray:
    """Planar poses (..., 3) (x, y, theta) -> (..., 4, 4) ``T_world_robot`` with z = 0."""
    x = np.asarray(x, dtype=float)
    T = np.zeros(x.shape[:-1] + (4, 4))
    T[..., :2, :2] = rotation(x[..., 2])
    T[..., 2, 2] = T[..., 3, 3] = 1.0
    T[..., :2, 3] = x[..., :2]
    return T


def flatten(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) poses -> their planar part (..., 3) (x, y, yaw), yaw the heading of the x axis."""
    return np.concatenate([T[..., :2, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])[..., None]], axis=-1)


def quat_of_heading(theta) -> np.ndarray:
    """(..., 4) unit quaternions ``qx qy qz qw`` of rotations by theta about z."""
    theta = np.asarray(theta, dtype=float)
    return np.stack([np.zeros_like(theta), np.zeros_like(theta), np.sin(theta / 2), np.cos(theta / 2)], -1)


def retract(x: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """x (+) delta: ``t + R(theta) dt``, ``wrap(theta + dtheta)``."""
    out = np.empty(3)
    out[:2] = x[:2] + rotation(x[2]) @ delta[:2]
    out[2] = wrap(x[2] + delta[2])
    return out


def difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (-) b, the delta with ``retract(b, delta) = a``."""
    out = np.empty(3)
    out[:2] = rotation(b[2]).T @ (a[:2] - b[:2])
    out[2] = wrap(a[2] - b[2])
    return out


def compose(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The pose x (3,) moved by the increment u (3,) expressed in x's frame."""
    return np.concatenate([x[:2] + rotation(x[2]) @ u[:2], [wrap(x[2] + u[2])]])


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The increment (3,) from pose a to pose b, in a's frame: ``compose(a, between(a, b)) = b``."""
    return np.concatenate([rotation(a[2]).T @ (b[:2] - a[:2]), [wrap(b[2] - a[2])]])


def motion(x: np.ndarray, T_increment: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compose a planar state (3,) with a lifted increment (4, 4); F (3, 3) = d delta' / d delta and
    G (3, 6) = d delta' / d w for the lifted 6-D increment noise w (model card)."""
    u = flatten(T_increment)
    R_inc_T = rotation(u[2]).T
    F = np.eye(3)
    F[:2, :2] = R_inc_T
    F[:2, 2] = R_inc_T @ (J @ u[:2])
    G = np.zeros((3, 6))
    G[0, 0] = G[1, 1] = G[2, 5] = 1.0
    return compose(x, u), F, G


def robot_points(x: np.ndarray, landmark_xy: np.ndarray) -> np.ndarray:
    """Landmarks (M, 2) of the world plane in the frame of the robot at x: ``R^T (l - t)``."""
    return (landmark_xy - x[:2]) @ rotation(x[2])


def observe_planar(x: np.ndarray, landmark_xy: np.ndarray, heading: np.ndarray | None, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """Predicted point2 or marker measurements (M, MAX_DIM) of landmarks (M, 2) (markers: with
    their headings (M,)) from x, in ``camloc.measurement``'s padded layout, and their Jacobians
    (M, MAX_DIM, 3) with respect to the right perturbation of x. A point2's third row is inert."""
    p = robot_points(x, landmark_xy)
    m = p.shape[0]
    z_hat = np.zeros((m, MAX_DIM))
    z_hat[:, :2] = p
    H = np.zeros((m, MAX_DIM, 3))
    H[:, 0, 0] = H[:, 1, 1] = -1.0
    H[:, :2, 2] = -(p @ J.T)  # -J p: a turn of the robot by dtheta moves p by -J p dtheta
    if kind == MARKER:
        z_hat[:, 2] = wrap(np.asarray(heading) - x[2])
        H[:, 2, 2] = -1.0
    elif kind != POINT2:
        raise ValueError(f"kind {kind} is not a planar kind")
    return z_hat, H


def observe_camera(x: np.ndarray, T_robot_camera: np.ndarray, intrinsics, landmark_xyz: np.ndarray, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """A 3-D camera on the planar robot: the camera model at the lifted pose, and its Jacobian
    (M, MAX_DIM, 3) with respect to the planar right perturbation (the SE(3) one's x, y, yaw
    columns: a planar error is the SE(3) right perturbation with dz = droll = dpitch = 0)."""
    z_hat, H = models.observe_se3(lift(x), T_robot_camera, intrinsics, landmark_xyz, kind)
    return z_hat, H[:, :, PLANAR_AXES]


def lifted_cov(cov: np.ndarray) -> np.ndarray:
    """Planar covariances (..., 3, 3) of (x, y, theta) -> (..., 6, 6) of the lifted (translation,
    rotation vector), zero in z, roll and pitch (a planar robot does not leave the plane)."""
    out = np.zeros(cov.shape[:-2] + (6, 6))
    axes = np.array(PLANAR_AXES)
    out[..., axes[:, None], axes[None, :]] = cov
    return out


def planar_block(cov: np.ndarray) -> np.ndarray:
    """The inverse of ``lifted_cov``: the (x, y, yaw) block (..., 3, 3) of (..., 6, 6)."""
    axes = np.array(PLANAR_AXES)
    return cov[..., axes[:, None], axes[None, :]]


def has_angles(kinds) -> bool:
    """Whether any measurement of ``kinds`` has an angle row (``measurement.ANGLE_ROW``: a marker's
    psi) for ``wrap_residuals`` to wrap; a camera's has none, and its callers skip the wrapping."""
    return bool(np.any(ANGLE_ROW[np.asarray(kinds, dtype=np.int64)] >= 0))


def wrap_residuals(y: np.ndarray, kinds) -> np.ndarray:
    """Residuals ``z - z_hat`` (..., MAX_DIM) of measurements of ``kinds`` (a code, or codes that
    broadcast against y's leading axes) with their angle rows (``measurement.ANGLE_ROW``: a
    marker's psi) wrapped into [-pi, pi); y itself where no kind has an angle (the camera kinds:
    unchanged, bit for bit). Here rather than in ``camloc.measurement``, whose values the compiled
    kernels take in (and which may not reach ``camloc.geometry``)."""
    kinds = np.asarray(kinds, dtype=np.int64)
    angle = ANGLE_ROW[kinds] == 2
    if not np.any(angle):
        return y
    y = np.array(y, dtype=float, copy=True)
    y[..., 2] = np.where(np.broadcast_to(angle, y.shape[:-1]), wrap(y[..., 2]), y[..., 2])
    return y
