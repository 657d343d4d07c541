"""A pixel-only camera's new landmark from two rays, one cast from a past pose kept in the state
(stochastic cloning): the point and its error's coefficients on the state.

Why a clone: a ray fixes no point, so a landmark seen only by pixels needs a second view with
parallax. Triangulating from past poses as if they were exact (the delayed triangulation before
this) placed the landmark to millimetres while the poses it was cast from had drifted by the
odometry's decimetres, with no correlation to them: overconfident, and the robot was then pulled
to it (docs/performance.md, "Pixel-only cameras mapped, moved and no map"). Here the pose a track's
first ray was cast from is **cloned** into the state when the ray is seen (correlated with the robot
exactly), and the landmark is the point nearest to that ray and the latest one, its error written
on the clone's and the current pose's errors with the rays' pixel noise: first-order consistent,
whatever the drift between the two views. (Inverse depth would also be consistent from the first
view, but as a 6-parameter landmark the filter's models and the smoother's would all carry it.)

The clone is three world points rigid with the robot at that pose: its position ``t`` and
``t + R e_x``, ``t + R e_y``. In the invariant error (``camloc.slam``) a point rigid with the
robot has the robot's translation error, exactly (``t + R a = Exp(xi_theta) (t^ + R^ a) + J
xi_t``), so cloning is the augmentation with ``B = [I, 0]`` and no noise, and afterwards the
points are world points like any landmark (the motion's noise moves them as it moves a landmark).
Three points hold the pose's six degrees of freedom with three redundant (their distances): the
covariance is singular there, exactly, and nothing measures those directions.

The two-ray point (``midpoint``: halfway along the common perpendicular) commutes with turning
and shifting the world, so its error is ``sum_i dm/dp_i xi_i`` over the points it is built from
(the rays' centres and a second point on each), with no xi_theta term: its Jacobians are the
Euclidean ones. Every Jacobian here is checked against finite differences in
tests/test_slam_rays.py.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from camloc import geometry

if TYPE_CHECKING:
    from camloc.sensors import CameraModel

CLONE_ROWS = 3  # the points of a clone: the robot's position and a metre along its x and y axes


def clone_points(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The clone of pose (R, t): (3, 3), the points t, t + R e_x, t + R e_y."""
    return np.stack([t, t + R[:, 0], t + R[:, 1]])


def clone_rotation(points: np.ndarray) -> np.ndarray:
    """The pose's rotation (3, 3) as the clone's points give it (exact for a clone as made; the
    estimate of one moved by updates is orthonormal to first order)."""
    e1, e2 = points[1] - points[0], points[2] - points[0]
    return np.column_stack([e1, e2, np.cross(e1, e2)])


def rigid_point(points: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point at ``a`` (3,) in the frame of a clone's points (3, 3) (``p0 + a_x e1 + a_y e2 +
    a_z e1 x e2``, e_i = p_i - p0) and its Jacobian (3, 9) on the points (p0, p1, p2)."""
    e1, e2 = points[1] - points[0], points[2] - points[0]
    v = points[0] + a[0] * e1 + a[1] * e2 + a[2] * np.cross(e1, e2)
    d_e1 = a[0] * np.eye(3) - a[2] * geometry.hat(e2)  # d (e1 x e2) / d e1 = -[e2]x
    d_e2 = a[1] * np.eye(3) + a[2] * geometry.hat(e1)
    return v, np.hstack([np.eye(3) - d_e1 - d_e2, d_e1, d_e2])


def pixel_direction(z: np.ndarray, sensor: "CameraModel") -> tuple[np.ndarray, np.ndarray]:
    """A pixel z (2+,)'s unit ray in the camera frame (3,) and its Jacobian on (u, v) (3, 2)."""
    fx, fy, cx, cy = sensor.intrinsics
    v = np.array([(z[0] - cx) / fx, (z[1] - cy) / fy, 1.0])
    norm = float(np.linalg.norm(v))
    d = v / norm
    return d, ((np.eye(3) - np.outer(d, d)) / norm)[:, :2] @ np.diag([1.0 / fx, 1.0 / fy])


def midpoint(c1: np.ndarray, q1: np.ndarray, c2: np.ndarray, q2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The point halfway along the common perpendicular of the lines (c1, q1) and (c2, q2), its
    Jacobian (3, 12) on (c1, q1, c2, q2), and the distances along each line from its first point
    to the nearest point, in units of |q - c| (2,). Differentiated through the normal equations
    (A'A) s = A' w of A = [d1, -d2], w = c2 - c1: (A'A) ds = dA' r + A' (dw - dA s), r = w - A s."""
    d1, d2, w = q1 - c1, q2 - c2, c2 - c1
    A = np.column_stack([d1, -d2])
    AtA = A.T @ A
    s = np.linalg.solve(AtA, A.T @ w)
    r = w - A @ s
    point = 0.5 * (c1 + s[0] * d1 + c2 + s[1] * d2)
    dc1, dq1, dc2, dq2 = np.eye(12).reshape(12, 4, 3).transpose(1, 0, 2)  # each (12, 3): one input moved per row
    dd1, dd2 = dq1 - dc1, dq2 - dc2
    dA_s = s[0] * dd1 - s[1] * dd2  # dA s, per row
    rhs = np.stack([dd1 @ r, -(dd2 @ r)]) + A.T @ (dc2 - dc1 - dA_s).T  # (2, 12)
    ds = np.linalg.solve(AtA, rhs)
    F = 0.5 * (dc1 + np.outer(ds[0], d1) + s[0] * dd1 + dc2 + np.outer(ds[1], d2) + s[1] * dd2).T
    return point, F, s


def ray_points(points: np.ndarray, sensor: "CameraModel", z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ray of pixel z of ``sensor`` seen from a clone (its points (3, 3)): its centre and a
    point a metre along it, stacked (6,), their Jacobian on the clone's points (6, 9), and on the
    pixel (6, 2)."""
    Rc, tc = sensor.T_robot_camera[:3, :3], sensor.T_robot_camera[:3, 3]
    direction, d_direction = pixel_direction(z, sensor)
    centre, J_centre = rigid_point(points, tc)
    ahead, J_ahead = rigid_point(points, tc + Rc @ direction)
    pixel = np.zeros((6, 2))
    pixel[3:] = clone_rotation(points) @ Rc @ d_direction
    return np.concatenate([centre, ahead]), np.vstack([J_centre, J_ahead]), pixel


def two_ray_landmark(anchor: np.ndarray, anchor_sensor: "CameraModel", z1: np.ndarray, R1: np.ndarray,
                     current: np.ndarray, sensor: "CameraModel", z2: np.ndarray, R2: np.ndarray):
    """A landmark from pixel z1 (noise R1 (2, 2)) seen from the clone ``anchor`` (3, 3) and
    pixel z2 (noise R2) seen from the robot now, whose clone ``current`` (3, 3) is: the point
    (3,), its error's coefficients on the anchor's points' errors (3, 9) and on the robot's
    translation error (3, 3) (every point rigid with the robot now has that error), the pixels'
    noise covariance (3, 3), and the distances along each ray from its camera (2,); None where the
    rays are parallel or the point is not in front of both."""
    ray1, J1, W1 = ray_points(anchor, anchor_sensor, z1)
    ray2, J2, W2 = ray_points(current, sensor, z2)
    try:
        point, F, along = midpoint(ray1[:3], ray1[3:], ray2[:3], ray2[3:])
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(point)) or np.any(along <= 0.0):
        return None
    F1, F2 = F[:, :6], F[:, 6:]
    B_anchor = F1 @ J1
    B_translation = F2 @ J2 @ np.tile(np.eye(3), (3, 1))  # each of the current clone's points: xi_t
    N = F1 @ W1 @ R1 @ W1.T @ F1.T + F2 @ W2 @ R2 @ W2.T @ F2.T
    return point, B_anchor, B_translation, 0.5 * (N + N.T), along
