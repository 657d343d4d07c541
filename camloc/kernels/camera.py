"""The camera model of the Euler filter (model card: ``camloc.models``).

    p_robot  = R' (l - t)                 the landmark in the robot frame
    p_camera = R_c' (p_robot - t_c)       in the camera frame
    z = (fx p.x / p.z + cx, fy p.y / p.z + cy, third)

with ``third`` by the sensor's kind (``camloc.measurement``, the fifth column of its intrinsics):
p.z (depth), 1 / p.z (disparity) or the inert 0 of a pixel, whose Jacobian row is 0.

H = dz/dx through ``d p_robot / dt = -R'`` and ``d p_robot / d rpy = [p_robot]x E(rpy)``.

The same model serves a planar robot (its state (x, y, theta), ``camloc.planar``): a camera's
measurement from the lifted pose, its Jacobian by the right perturbation (dt, dtheta), and the
planar kinds (point2, marker, measured in the robot frame: ``planar.planar_observe_into``). H has
as many columns as the state has entries (``H.shape[2]``).
"""

from __future__ import annotations

import numpy as np

from camloc.kernels._jit import FIRST, inlined, jit
from camloc.kernels.planar import SE2_DIM, planar_frame_into, planar_observe_into
from camloc.measurement import DEPTH, DISPARITY, MARKER, POINT2
from camloc.kernels.rotation import euler_rate_into, euler_to_matrix, euler_to_matrix_into
from camloc.kernels.small import mm, mv


@jit
def robot_frame(x):
    """What ``observe_into`` needs of the state x: the robot's rotation R (3, 3), rate matrix E
    (3, 3) (the body rotation of each rotation error, by column; a planar state's one: the z axis)
    and position t (3,)."""
    frame = (np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    robot_frame_into(x, frame)
    return frame


@jit
def robot_frame_into(x, frame):
    """``robot_frame`` written into frame, (R, E, t) arrays of its shapes: an iterated update
    predicts its pairs at every step, each time from a new state, into the same buffers."""
    if x.shape[0] == SE2_DIM:
        planar_frame_into(x, frame)
    else:
        euler_frame_into(x, frame)


@jit
def euler_frame_into(x, frame):
    """``robot_frame_into`` of the Euler state (6,): small enough for LLVM to inline into
    ``observe_pairs_into``, which picks it by the state's size (``robot_frame_into`` with the
    planar branch in it was called there, not inlined: the filter's predictions 79 of 325 perf
    samples slower than the filing's, docs/performance.md, 2026-12-07 (twenty-third session))."""
    R, E, t = frame
    euler_to_matrix_into(x[3], x[4], x[5], R)
    euler_rate_into(x[3], x[4], E)
    t[0], t[1], t[2] = x[0], x[1], x[2]


@inlined
def observe_into(R, E, t, R_rc, t_rc, intrinsics, landmarks, j, z_hat, H, i, d_position, dim):
    """Write a camera's prediction z_hat[i] (3,) of landmark landmarks[j] (x, y, z, ...) and its
    Jacobian H[i] (3, n) with respect to the state's error (robot rotation R, rate matrix E,
    position t: ``robot_frame``; n = 6, the Euler state, or 3, the planar one); d_position =
    -R_rc' R', the derivative of the camera-frame point by the world position. Scalar code on whole
    arrays and indices: this runs for every candidate of every hypothesis, where a temporary array
    or a row view (counting references) costs more than the arithmetic. A planar robot's own
    sensor (point2, marker) is ``planar.planar_observe_into``, which each caller's loop picks by
    the sensor's kind: that branch inside this step (or inside a step wrapping both) made the 3-D
    world's predictions 1.6x as slow (500 -> 800 ns for three pairs). The state's size ``dim`` (H's
    columns) is a constant at each call, each caller looping once per size: a branch on a size read
    when it runs, inside the caller's loop, left the arrays passed to this step counted once more
    per candidate (numba's reference-count pruning gives up on the two paths' ends)."""
    fx, fy, cx, cy, kind = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], intrinsics[4]
    d0, d1, d2 = landmarks[j, 0] - t[0], landmarks[j, 1] - t[1], landmarks[j, 2] - t[2]
    r0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2           # p_robot = R' (l - t)
    r1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    r2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    q0, q1, q2 = r0 - t_rc[0], r1 - t_rc[1], r2 - t_rc[2]
    px = R_rc[0, 0] * q0 + R_rc[1, 0] * q1 + R_rc[2, 0] * q2  # p_camera = R_c' (p_robot - t_c)
    py = R_rc[0, 1] * q0 + R_rc[1, 1] * q1 + R_rc[2, 1] * q2
    pz = R_rc[0, 2] * q0 + R_rc[1, 2] * q1 + R_rc[2, 2] * q2
    inverse_depth = 1.0 / pz
    z_hat[i, 0] = fx * px * inverse_depth + cx
    z_hat[i, 1] = fy * py * inverse_depth + cy
    # the third row: depth (d/dz 1), inverse depth (d/dz -1/z^2) or a pixel's inert 0
    if kind == DEPTH:
        z_hat[i, 2], third = pz, 1.0
    elif kind == DISPARITY:
        z_hat[i, 2], third = inverse_depth, -inverse_depth * inverse_depth
    else:
        z_hat[i, 2], third = 0.0, 0.0
    # d z / d p_camera = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2], [0, 0, third]]
    u_x, u_z = fx * inverse_depth, -fx * px * inverse_depth * inverse_depth
    v_y, v_z = fy * inverse_depth, -fy * py * inverse_depth * inverse_depth
    if dim == SE2_DIM:
        planar_camera_jacobian(R, R_rc, r0, r1, u_x, u_z, v_y, v_z, third, H, i, d_position)
    else:
        for c in range(3):
            # d p_robot / d rpy = [p_robot]x E, column c
            m0 = -r2 * E[1, c] + r1 * E[2, c]
            m1 = r2 * E[0, c] - r0 * E[2, c]
            m2 = -r1 * E[0, c] + r0 * E[1, c]
            rot0 = R_rc[0, 0] * m0 + R_rc[1, 0] * m1 + R_rc[2, 0] * m2   # d p_camera / d rpy = R_c' [p_robot]x E
            rot1 = R_rc[0, 1] * m0 + R_rc[1, 1] * m1 + R_rc[2, 1] * m2
            rot2 = R_rc[0, 2] * m0 + R_rc[1, 2] * m1 + R_rc[2, 2] * m2
            H[i, 0, c] = u_x * d_position[0, c] + u_z * d_position[2, c]
            H[i, 1, c] = v_y * d_position[1, c] + v_z * d_position[2, c]
            H[i, 2, c] = third * d_position[2, c]
            H[i, 0, 3 + c] = u_x * rot0 + u_z * rot2
            H[i, 1, 3 + c] = v_y * rot1 + v_z * rot2
            H[i, 2, 3 + c] = third * rot2


@inlined
def planar_camera_jacobian(R, R_rc, r0, r1, u_x, u_z, v_y, v_z, third, H, i, d_position):
    """H[i] (3, 3) of a camera's measurement by a planar robot's right perturbation (dt, dtheta),
    from the robot-frame point (r0, r1, .), the projection's derivatives (``observe_into``) and
    d_position = -R_rc' R' (by the world position): dt moves the robot by R dt in the world (R's
    third row is zero there), dtheta turns it about z, moving the robot-frame point by (r1, -r0, 0)."""
    for c in range(2):
        a0, a1 = R[0, c], R[1, c]
        g0 = d_position[0, 0] * a0 + d_position[0, 1] * a1
        g1 = d_position[1, 0] * a0 + d_position[1, 1] * a1
        g2 = d_position[2, 0] * a0 + d_position[2, 1] * a1
        H[i, 0, c] = u_x * g0 + u_z * g2
        H[i, 1, c] = v_y * g1 + v_z * g2
        H[i, 2, c] = third * g2
    rot0 = R_rc[0, 0] * r1 - R_rc[1, 0] * r0                       # R_c' (r1, -r0, 0)
    rot1 = R_rc[0, 1] * r1 - R_rc[1, 1] * r0
    rot2 = R_rc[0, 2] * r1 - R_rc[1, 2] * r0
    H[i, 0, 2] = u_x * rot0 + u_z * rot2
    H[i, 1, 2] = v_y * rot1 + v_z * rot2
    H[i, 2, 2] = third * rot2


@jit
def predict_candidates(R, E, t, R_rc, t_rc, K, landmarks, pool, z_hat, H, at, d_position):
    """Predictions z_hat and Jacobians H (rows at..) of landmarks pool (g,) by one sensor (mount
    R_rc, t_rc, intrinsics K) from the robot at (R, E, t) (``camera.robot_frame``). The sensor's
    kind and the state's size pick the loop, not each step of one loop: a branch inside the loop
    left the arrays each step is passed counted once more per candidate (numba's reference-count
    pruning gives up on it): 3.3 times ``condition_into``'s reference counts of before the planar kernels.
    Compiled once for its callers (``beam.options_for``, ``beam.condition_into``, ``observe``), not
    inlined into each: its three loops of the inlined ``observe_into`` were compiled at each (a
    first compile about 4 s of CPU shorter; the call counts its arrays once a pool, not once a
    candidate: the warm 20k worlds no slower, ``docs/performance.md``)."""
    if K[4] == POINT2 or K[4] == MARKER:         # a planar robot's own sensor (``observe_into``)
        for q in range(pool.size):
            planar_observe_into(R, t, landmarks, pool[q], K[4], z_hat, H, at + q)
    elif H.shape[2] == SE2_DIM:
        for q in range(pool.size):
            observe_into(R, E, t, R_rc, t_rc, K, landmarks, pool[q], z_hat, H, at + q, d_position, SE2_DIM)
    else:
        for q in range(pool.size):
            observe_into(R, E, t, R_rc, t_rc, K, landmarks, pool[q], z_hat, H, at + q, d_position, 6)


@jit
def observe(x, R_rc, t_rc, intrinsics, landmark_xyz):
    """Predicted measurements z_hat (m, 3) of landmarks (m, 3 or 4: ``observe_into``) from the
    state x (n,) through the sensor mounted at (R_rc, t_rc) with intrinsics (fx, fy, cx, cy,
    kind), and H (m, 3, n): ``predict_candidates`` of them all."""
    R, E, t = robot_frame(x)
    d_position = np.empty((3, 3))
    camera_position_jacobian(R, R_rc, d_position)
    m = landmark_xyz.shape[0]
    z_hat = np.empty((m, 3))
    H = np.empty((m, 3, x.shape[0]))
    predict_candidates(R, E, t, R_rc, t_rc, intrinsics, landmark_xyz, np.arange(m), z_hat, H, FIRST, d_position)
    return z_hat, H


@jit
def observe_pairs(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
    """``observe`` for pairs whose cameras differ: landmark (p, 3) seen by camera pair_camera (p,)
    (rows of camera_R (C, 3, 3), camera_t (C, 3), camera_K (C, 4))."""
    p = landmark_xyz.shape[0]
    z_hat, H = np.empty((p, 3)), np.empty((p, 3, x.shape[0]))
    observe_pairs_into(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, z_hat, H,
                       np.empty((camera_R.shape[0], 3, 3)), robot_frame(x))
    return z_hat, H


@jit
def observe_pairs_into(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, z_hat, H, d_position, frame):
    """``observe_pairs`` written into z_hat (p, 3) and H (p, 3, n), with d_position (C, 3, 3) and
    frame (``robot_frame_into``'s) as scratch: an iterated update predicts its pairs at every
    step into the same buffers."""
    if x.shape[0] != SE2_DIM:                            # each frame step alone, inlined by LLVM (``euler_frame_into``)
        euler_frame_into(x, frame)
    else:
        planar_frame_into(x, frame)
    R, E, t = frame
    for c in range(camera_R.shape[0]):
        camera_position_jacobian(R, camera_R[c], d_position[c])
    if x.shape[0] != SE2_DIM:                            # the Euler robot: cameras only (``localizer.resolved_config``)
        for i in range(landmark_xyz.shape[0]):
            c = pair_camera[i]
            observe_into(R, E, t, camera_R[c], camera_t[c], camera_K[c], landmark_xyz, i, z_hat, H, i, d_position[c], 6)
        return
    for i in range(landmark_xyz.shape[0]):
        c = pair_camera[i]
        kind = camera_K[c, 4]
        if kind == POINT2 or kind == MARKER:             # a planar robot's own sensor
            planar_observe_into(R, t, landmark_xyz, i, kind, z_hat, H, i)
        else:
            observe_into(R, E, t, camera_R[c], camera_t[c], camera_K[c], landmark_xyz, i, z_hat, H, i, d_position[c], SE2_DIM)


@jit
def camera_position_jacobian(R, R_rc, d_position):
    """d_position (3, 3) = -R_rc' R', the derivative of the camera-frame point by the robot's
    position (rotation R) for a camera mounted with rotation R_rc."""
    for a in range(3):
        for b in range(3):
            s = 0.0
            for q in range(3):
                s += R_rc[q, a] * R[b, q]
            d_position[a, b] = -s


@jit
def cameras_of(obs_camera, obs, n_cameras):
    """The cameras (ascending) that made the observations obs: np.unique of their cameras, by a
    table of the few cameras rather than a sort (whose code every caller would link)."""
    seen = np.zeros(n_cameras, np.bool_)
    for o in obs:
        seen[obs_camera[o]] = True
    out = np.empty(seen.sum(), np.int64)
    count = 0
    for c in range(n_cameras):
        if seen[c]:
            out[count] = c
            count += 1
    return out


@jit
def back_project(z, intrinsics):
    """A measurement (3,) of a sensor that measures range (intrinsics (fx, fy, cx, cy, kind):
    depth or disparity) as a camera-frame point p (3,), and d p / d z (3, 3)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    x_over_z, y_over_z = (z[0] - cx) / fx, (z[1] - cy) / fy
    if intrinsics[4] == DISPARITY:
        depth = 1.0 / z[2]
        d_depth = -depth * depth  # d depth / d (1 / depth)
    else:
        depth, d_depth = z[2], 1.0
    p = np.empty(3)
    p[0], p[1], p[2] = x_over_z * depth, y_over_z * depth, depth
    J = np.zeros((3, 3))
    J[0, 0], J[0, 2] = depth / fx, x_over_z * d_depth
    J[1, 1], J[1, 2] = depth / fy, y_over_z * d_depth
    J[2, 2] = d_depth
    return p, J


@jit
def in_front_of(R, t, R_rc, t_rc, kind, landmarks, j):
    """Whether landmark landmarks[j] (x, y, z, ...) lies in front of the sensor mounted at (R_rc,
    t_rc) with measurement ``kind`` on the robot at (R, t) (``robot_frame``): its camera-frame
    depth is positive; a planar robot's own sensor (point2, marker) sees all around it. The one
    test of the kernels' association (the oracle's ``filtering.in_front``, the beam's
    ``beam.options_for`` and ``beam.condition_into``); its numpy twin is
    ``associators.AssociationScene.in_front_of``, which says why."""
    if kind == POINT2 or kind == MARKER:
        return True
    d0, d1, d2 = landmarks[j, 0] - t[0], landmarks[j, 1] - t[1], landmarks[j, 2] - t[2]
    depth = 0.0
    for a in range(3):                                  # R_c[:, 2]' (R' (l - t) - t_c)
        depth += R_rc[a, 2] * (R[0, a] * d0 + R[1, a] * d1 + R[2, a] * d2 - t_rc[a])
    return depth > 0.0


@jit
def camera_pose(x, R_rc, t_rc):
    """T_world_camera as (R_wc (3, 3), c (3,)) of the state x and the camera mount (a planar
    robot's own sensor, point2 or marker, is mounted at the robot: R_rc = I, t_rc = 0)."""
    if x.shape[0] == SE2_DIM:
        R, _, t = robot_frame(x)
        return mm(R, R_rc), t + mv(R, t_rc)
    R = euler_to_matrix(x[3], x[4], x[5])
    return mm(R, R_rc), x[0:3] + mv(R, t_rc)
