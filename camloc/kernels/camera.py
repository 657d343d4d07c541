"""The camera model of the Euler filter (model card: ``camloc.models``).

    p_robot  = R' (l - t)                 the landmark in the robot frame
    p_camera = R_c' (p_robot - t_c)       in the camera frame
    z = (fx p.x / p.z + cx, fy p.y / p.z + cy, p.z)

H = dz/dx through ``d p_robot / dt = -R'`` and ``d p_robot / d rpy = [p_robot]x E(rpy)``.
"""

from __future__ import annotations

import numpy as np

from camloc.kernels._jit import jit
from camloc.kernels.rotation import euler_rate, euler_to_matrix, hat
from camloc.kernels.small import mm, mtm, mtv


@jit
def observe_into(R, E, t, R_rc, t_rc, intrinsics, landmark, z_hat, H, d_position):
    """Write the prediction z_hat (3,) of one landmark (3,) and its Jacobian H (3, 6) with respect
    to the Euler state (rotation R, Euler rate matrix E, position t); d_position = -R_rc' R', the
    derivative of the camera-frame point by the position."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    p_robot = mtv(R, landmark - t)
    p = mtv(R_rc, p_robot - t_rc)
    d_rotation = mtm(R_rc, mm(hat(p_robot), E))        # d p_camera / d rpy
    inverse_depth = 1.0 / p[2]
    z_hat[0] = fx * p[0] * inverse_depth + cx
    z_hat[1] = fy * p[1] * inverse_depth + cy
    z_hat[2] = p[2]
    # d z / d p_camera = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2], [0, 0, 1]]
    u_x, u_z = fx * inverse_depth, -fx * p[0] * inverse_depth * inverse_depth
    v_y, v_z = fy * inverse_depth, -fy * p[1] * inverse_depth * inverse_depth
    for c in range(3):
        H[0, c] = u_x * d_position[0, c] + u_z * d_position[2, c]
        H[1, c] = v_y * d_position[1, c] + v_z * d_position[2, c]
        H[2, c] = d_position[2, c]
        H[0, 3 + c] = u_x * d_rotation[0, c] + u_z * d_rotation[2, c]
        H[1, 3 + c] = v_y * d_rotation[1, c] + v_z * d_rotation[2, c]
        H[2, 3 + c] = d_rotation[2, c]


@jit
def observe(x, R_rc, t_rc, intrinsics, landmark_xyz):
    """Predicted measurements z_hat (m, 3) of landmarks (m, 3) from the Euler state x through
    the camera mounted at (R_rc, t_rc) with intrinsics (fx, fy, cx, cy), and H (m, 3, 6)."""
    R = euler_to_matrix(x[3], x[4], x[5])
    E = euler_rate(x[3], x[4])
    t = x[0:3].copy()
    d_position = -mm(R_rc.T, R.T)
    m = landmark_xyz.shape[0]
    z_hat = np.empty((m, 3))
    H = np.empty((m, 3, 6))
    for j in range(m):
        observe_into(R, E, t, R_rc, t_rc, intrinsics, landmark_xyz[j], z_hat[j], H[j], d_position)
    return z_hat, H


@jit
def observe_pairs(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
    """``observe`` for pairs whose cameras differ: landmark (p, 3) seen by camera pair_camera (p,)
    (rows of camera_R (C, 3, 3), camera_t (C, 3), camera_K (C, 4))."""
    R = euler_to_matrix(x[3], x[4], x[5])
    E = euler_rate(x[3], x[4])
    t = x[0:3].copy()
    p = landmark_xyz.shape[0]
    z_hat = np.empty((p, 3))
    H = np.empty((p, 3, 6))
    for i in range(p):
        c = pair_camera[i]
        observe_into(R, E, t, camera_R[c], camera_t[c], camera_K[c], landmark_xyz[i], z_hat[i], H[i], -mm(camera_R[c].T, R.T))
    return z_hat, H


@jit
def back_project(z, intrinsics):
    """A measurement (3,) of u, v, depth as a camera-frame point p (3,), and d p / d z (3, 3)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    x_over_z, y_over_z, depth = (z[0] - cx) / fx, (z[1] - cy) / fy, z[2]
    p = np.empty(3)
    p[0], p[1], p[2] = x_over_z * depth, y_over_z * depth, depth
    J = np.zeros((3, 3))
    J[0, 0], J[0, 2] = depth / fx, x_over_z
    J[1, 1], J[1, 2] = depth / fy, y_over_z
    J[2, 2] = 1.0
    return p, J


@jit
def camera_pose(x, R_rc, t_rc):
    """T_world_camera as (R_wc (3, 3), c (3,)) of the Euler state x and the camera mount."""
    R = euler_to_matrix(x[3], x[4], x[5])
    return R @ R_rc, x[0:3] + R @ t_rc
