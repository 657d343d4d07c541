"""Motion and camera models of the Euler-angle EKF, with their analytic Jacobians.

Model card
----------
State      x = (x, y, z, roll, pitch, yaw): the robot pose in the world frame, metres and radians,
           ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (see ``camloc.geometry``).
Control    u = dT = (dt, dR): the odometry increment, the next pose in the frame of the current one.
Motion     T_{k+1} = T_k dT Exp(w), with w = (w_t, w_theta) ~ N(0, Q) the increment's noise as a
           right perturbation (translation, rotation vector); Q comes from the edge's information in
           g2o's parametrization (``camloc.g2o.odometry_cov_from_info``).
Measure    z of a landmark l through camera (R_c, t_c) on the robot:
              p_robot  = R^T (l - t)
              p_camera = R_c^T (p_robot - t_c)
              z = h_kind(p_camera) + n,  n ~ N(0, R_obs)
           with h_kind the measurement kind's (``camloc.measurement``: (u, v, depth), (u, v) or
           (u, v, 1/depth), in one padded 3-row layout).
Jacobians  F = dx'/dx and G = dx'/dw of the motion, H = dz/dx of the measurement, derived through
           the body-frame perturbation ``R(rpy + d) = R Exp(E(rpy) d)`` (``geometry.euler_rate_matrix``).
           Every one is checked against central finite differences in tests/test_models.py.
Singularity  E(rpy) is singular at pitch = +-90 deg; the Euler filter is not usable there.

SE(3) error-state variant (``motion_se3``, ``observe_se3``)
-----------------------------------------------------------
State      the pose T = (R, t) itself; the filter's 6-dimensional error is a right perturbation
           delta = (dt, dtheta): T_true = retract_right(T, delta), i.e. R_true = R Exp(dtheta),
           t_true = t + R dt (``geometry.retract_right``). No singularity anywhere.
Motion     T' = T dT Exp(w) as above; the error propagates as
              dtheta' = dR^T dtheta + w_theta,  dt' = dR^T (dt - [dt_inc]x dtheta) + w_t,
           so F = [[dR^T, -dR^T [dt_inc]x], [0, dR^T]] and G = I.
Measure    the same camera model; d p_robot / d dt = -I, d p_robot / d dtheta = [p_robot]x.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry, measurement
from camloc.measurement import DEPTH


def motion(state: np.ndarray, T_increment: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compose an Euler state with an odometry increment.

    Parameters
    ----------
    state : (6,) x, y, z, roll, pitch, yaw of T_world_robot.
    T_increment : (4, 4) T_k_k+1, the next pose in the frame of the current one.

    Returns
    -------
    next_state : (6,) the state of T_world_robot @ T_increment.
    F : (6, 6) d next_state / d state.
    G : (6, 6) d next_state / d w, w = (translation, rotation vector) right perturbation of the
        increment.
    """
    R = geometry.euler_to_matrix(state[3:6])
    dR, dt = T_increment[:3, :3], T_increment[:3, 3]
    R_next = R @ dR
    rpy_next = geometry.matrix_to_euler(R_next)
    next_state = np.concatenate([state[0:3] + R @ dt, rpy_next])

    E = geometry.euler_rate_matrix(state[3:6])
    E_next_inverse = geometry.euler_rate_matrix_inverse(rpy_next)
    F = np.eye(6)
    # t' = t + R dt; perturbing R on the right by E d moves t' by -R [dt]x E d.
    F[0:3, 3:6] = -R @ geometry.hat(dt) @ E
    # R' = R Exp(E d) dR = R' Exp(dR^T E d); the new Euler step solves E' d' = dR^T E d.
    F[3:6, 3:6] = E_next_inverse @ (dR.T @ E)

    G = np.zeros((6, 6))
    G[0:3, 0:3] = R_next  # t' = t + R dT_t + R dR w_t
    G[3:6, 3:6] = E_next_inverse  # R' Exp(w_theta): E' d' = w_theta
    return next_state, F, G


def camera_points(
    T_world_robot: np.ndarray, T_robot_camera: np.ndarray, landmark_xyz: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks (M, 3) in the robot frame and in the camera frame, both (M, 3)."""
    return points_by_camera(T_world_robot[:3, :3], T_world_robot[:3, 3], (T_robot_camera,), landmark_xyz,
                            (landmark_xyz.shape[0],))


def project_points(p_camera: np.ndarray, intrinsics: tuple[float, float, float, float], kind: int = DEPTH) -> np.ndarray:
    """Camera-frame points (M, 3) -> measurements (M, 3) of ``kind`` (``camloc.measurement``):
    u, v and depth, inverse depth or the inert 0. Depth must be non-zero."""
    return measurement.project(p_camera, intrinsics, kind)


def back_project(uvd: np.ndarray, intrinsics: tuple[float, float, float, float], kind: int = DEPTH) -> tuple[np.ndarray, np.ndarray]:
    """Measurements (M, 3) of a kind that measures range -> camera-frame points (M, 3), the
    inverse of ``project_points``, and its Jacobian d p_camera / d z, (M, 3, 3). The intrinsics
    fx, fy, cx, cy may each be an (M,) array: a camera per measurement."""
    return measurement.back_project(uvd, intrinsics, kind)


MIN_POINT_DEPTH = measurement.MIN_POINT_DEPTH


def measured_points(
    uvd: np.ndarray, cov: np.ndarray, intrinsics: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Depth measurements (M, 3) with covariances (M, 3, 3) as camera-frame points (M, 3) with
    covariances (M, 3, 3), to first order in the measurement noise. In these coordinates a
    landmark's prediction is linear in the robot's position, so a wide prior's linearization
    holds where that of (u, v, depth) does not. (Only depth measurements are judged as points:
    ``measurement.judged_as_point``.)"""
    uvd = np.column_stack([uvd[:, :2], np.maximum(uvd[:, 2], MIN_POINT_DEPTH)])
    points, J = back_project(uvd, intrinsics)
    return points, J @ cov @ J.swapaxes(1, 2)


def observe(
    state: np.ndarray,
    T_robot_camera: np.ndarray,
    intrinsics: tuple[float, float, float, float],
    landmark_xyz: np.ndarray,
    kind: int = DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measurements of landmarks and their Jacobians with respect to the state.

    Parameters
    ----------
    state : (6,) Euler state of T_world_robot.
    T_robot_camera : (4, 4) camera mount.
    intrinsics : fx, fy, cx, cy.
    landmark_xyz : (M, 3) landmarks in the world frame, in front of the camera.
    kind : the measurement's kind (``camloc.measurement``): depth, pixel or disparity.

    Returns
    -------
    z_hat : (M, 3) predicted measurements, in ``camloc.measurement``'s padded layout.
    H : (M, 3, 6) d z_hat / d state.
    """
    return observe_rig(state, (T_robot_camera,), intrinsics, landmark_xyz, (landmark_xyz.shape[0],), kind)


def observe_rig(
    state: np.ndarray, mounts, intrinsics, landmark_xyz: np.ndarray, sizes, kind: int = DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """``observe`` of landmarks seen by several cameras of one kind on the robot, in one batch:
    the first ``sizes[0]`` rows of landmark_xyz by camera ``mounts[0]``, the next ``sizes[1]``
    by ``mounts[1]``, ...; ``intrinsics`` fx, fy, cx, cy are (M,) arrays, a camera per row (or
    scalars: cameras that share them). Each row's arithmetic is the one ``observe`` of its camera alone does."""
    R = geometry.euler_to_matrix(state[3:6])
    p_robot, p_camera = points_by_camera(R, state[0:3], mounts, landmark_xyz, sizes)
    E = geometry.euler_rate_matrix(state[3:6])
    # p_robot = R^T (l - t): d/dt = -R^T; a body rotation E d moves it by [p_robot]x E d.
    dprobot_dstate = np.empty((landmark_xyz.shape[0], 3, 6))
    dprobot_dstate[:, :, 0:3] = -R.T
    dprobot_dstate[:, :, 3:6] = geometry.hat(p_robot) @ E
    return projected(p_camera, dprobot_dstate, mounts, intrinsics, sizes, kind)


def points_by_camera(R: np.ndarray, t: np.ndarray, mounts, landmark_xyz: np.ndarray, sizes) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks (M, 3) in the frame of the robot at (R, t), and each in the frame of its camera
    (``sizes`` consecutive rows per camera of ``mounts``). Camera by camera: a product of one
    row takes another path in BLAS than the same row among several (its last bits differ)."""
    if len(mounts) == 1:
        p_robot = (landmark_xyz - t) @ R          # rows of R^T (l - t)
        return p_robot, (p_robot - mounts[0][:3, 3]) @ mounts[0][:3, :3]
    p_robot, p_camera = np.empty_like(landmark_xyz), np.empty_like(landmark_xyz)
    start = 0
    for mount, size in zip(mounts, sizes):
        part = slice(start, start + size)
        p_robot[part] = (landmark_xyz[part] - t) @ R
        p_camera[part] = (p_robot[part] - mount[:3, 3]) @ mount[:3, :3]
        start += size
    return p_robot, p_camera


def projected(p_camera: np.ndarray, dprobot: np.ndarray, mounts, intrinsics, sizes, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (M, 3) of cameras ``mounts`` (``sizes`` consecutive rows each), with
    the Jacobians (M, 3, n) of their robot-frame points -> measurements (M, 3) and Jacobians
    (M, 3, n)."""
    if len(mounts) == 1:
        dpcam = mounts[0][:3, :3].T @ dprobot
    else:
        dpcam, start = np.empty_like(dprobot), 0
        for mount, size in zip(mounts, sizes):
            dpcam[start : start + size] = mount[:3, :3].T @ dprobot[start : start + size]
            start += size
    # one point of one camera (a lone pair's update): in Python floats, the same bits
    one = measurement.project_one(p_camera[0], intrinsics, kind) if p_camera.shape[0] == 1 and isinstance(intrinsics[0], float) else None
    z_hat, J = one if one is not None else (measurement.project(p_camera, intrinsics, kind),
                                            measurement.projection_jacobian(p_camera, intrinsics, kind))
    return z_hat, J @ dpcam


def projection_jacobian(p_camera: np.ndarray, intrinsics: tuple[float, float, float, float], kind: int = DEPTH) -> np.ndarray:
    """d z / d p_camera, (M, 3, 3), of ``project_points``."""
    return measurement.projection_jacobian(p_camera, intrinsics, kind)


def motion_se3(T: np.ndarray, T_increment: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compose a pose with an odometry increment, with the error-state Jacobians.

    Parameters
    ----------
    T : (4, 4) T_world_robot.
    T_increment : (4, 4) T_k_k+1.

    Returns
    -------
    T_next : (4, 4) T @ T_increment.
    F : (6, 6) d delta' / d delta for right perturbations (dt, dtheta) of T and of T_next.
    G : (6, 6) d delta' / d w, w = (translation, rotation vector) right perturbation of the
        increment: the identity, the increment's noise being itself a right perturbation.
    """
    dR_T = T_increment[:3, :3].T
    F = np.zeros((6, 6))
    F[0:3, 0:3] = dR_T
    F[0:3, 3:6] = -dR_T @ geometry.hat(T_increment[:3, 3])
    F[3:6, 3:6] = dR_T
    return T @ T_increment, F, np.eye(6)


def observe_se3(
    T_world_robot: np.ndarray,
    T_robot_camera: np.ndarray,
    intrinsics: tuple[float, float, float, float],
    landmark_xyz: np.ndarray,
    kind: int = DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measurements (M, 3) of ``kind`` and their Jacobians (M, 3, 6) with respect to
    the right perturbation (dt, dtheta) of T_world_robot."""
    return observe_rig_se3(T_world_robot, (T_robot_camera,), intrinsics, landmark_xyz, (landmark_xyz.shape[0],), kind)


def observe_rig_se3(
    T_world_robot: np.ndarray, mounts, intrinsics, landmark_xyz: np.ndarray, sizes, kind: int = DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """``observe_se3`` of several cameras of one kind in one batch, rows laid out as in
    ``observe_rig``."""
    p_robot, p_camera = points_by_camera(T_world_robot[:3, :3], T_world_robot[:3, 3], mounts, landmark_xyz, sizes)
    dprobot = np.empty((landmark_xyz.shape[0], 3, 6))
    dprobot[:, :, 0:3] = -np.eye(3)
    dprobot[:, :, 3:6] = geometry.hat(p_robot)
    return projected(p_camera, dprobot, mounts, intrinsics, sizes, kind)
