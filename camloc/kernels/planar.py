"""The planar robot's pieces of the compiled filter (model card: ``camloc.planar``, whose numpy
functions are these kernels' twins in the tests): the state (x, y, theta), its error the right
perturbation (dt (2), dtheta), 3 degrees of freedom.

Only what differs from the 6-DOF Euler model is here: motion with its Jacobians, retraction and
difference, the robot's frame as the camera model reads it, and the planar kinds' measurement
(point2, marker). The algorithm around them (beam, update, re-check, filter loop) is written once
for both models, its dimension the state's (``x.shape[0]``); the model's kernel is picked by the
state's size (``SE2_DIM``: ``camloc.kernels.state``, ``motion.predict``, ``camera.robot_frame_into``).
"""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import inlined, jit
from camloc.kernels.rotation import wrap_angle
from camloc.measurement import MARKER

# the planar state's size (x, y, theta): how a kernel tells a planar state from an Euler one (6)
SE2_DIM = 3
# of its error, the position's entries (dt); the heading's (dtheta) follows them
SE2_POSITION_DIM = 2


@jit
def planar_motion(x, T_increment):
    """(x' (3,), F (3, 3), G (3, 6)) of the planar state x composed with the lifted increment
    T_increment (4, 4): ``t' = t + R(theta) u_t``, ``theta' = wrap(theta + u_theta)``;
    F = [[R_inc', R_inc' J u_t], [0, 1]] (J the rotation by +90 deg) and G selects (x, y, yaw) of
    the lifted 6-D increment noise (translation, rotation vector)."""
    u0, u1 = T_increment[0, 3], T_increment[1, 3]
    u_theta = math.atan2(T_increment[1, 0], T_increment[0, 0])
    c, s = math.cos(x[2]), math.sin(x[2])
    x_next = np.empty(3)
    x_next[0] = x[0] + (c * u0 - s * u1)
    x_next[1] = x[1] + (s * u0 + c * u1)
    x_next[2] = wrap_angle(x[2] + u_theta)
    ci, si = math.cos(u_theta), math.sin(u_theta)
    F = np.zeros((3, 3))
    F[0, 0], F[0, 1], F[1, 0], F[1, 1] = ci, si, -si, ci       # R_inc'
    F[0, 2] = ci * -u1 + si * u0                               # R_inc' (J u_t), J u_t = (-u1, u0)
    F[1, 2] = -si * -u1 + ci * u0
    F[2, 2] = 1.0
    G = np.zeros((3, 6))
    G[0, 0] = G[1, 1] = G[2, 5] = 1.0
    return x_next, F, G


@jit
def planar_retract_into(x, delta, out):
    """x (+) delta into out (3,): ``t + R(theta) dt``, ``wrap(theta + dtheta)``."""
    c, s = math.cos(x[2]), math.sin(x[2])
    out[0] = x[0] + (c * delta[0] - s * delta[1])
    out[1] = x[1] + (s * delta[0] + c * delta[1])
    out[2] = wrap_angle(x[2] + delta[2])


@jit
def planar_difference_into(a, b, d):
    """a (-) b into d (3,): the delta with ``retract(b, delta) = a``, ``R(theta_b)' (t_a - t_b)``."""
    c, s = math.cos(b[2]), math.sin(b[2])
    e0, e1 = a[0] - b[0], a[1] - b[1]
    d[0] = c * e0 + s * e1
    d[1] = -s * e0 + c * e1
    d[2] = wrap_angle(a[2] - b[2])


@jit
def planar_frame_into(x, frame):
    """The robot's frame as the camera model reads it (``camera.robot_frame``): R (3, 3) the
    rotation by theta about z, E (3, 3) whose first column is the body rotation of dtheta (the z
    axis; the rest zero), t (3,) the position lifted to z = 0."""
    R, E, t = frame
    c, s = math.cos(x[2]), math.sin(x[2])
    for a in range(3):
        for b in range(3):
            R[a, b] = 0.0
            E[a, b] = 0.0
    R[0, 0], R[0, 1], R[1, 0], R[1, 1], R[2, 2] = c, -s, s, c, 1.0
    E[2, 0] = 1.0
    t[0], t[1], t[2] = x[0], x[1], 0.0


@inlined
def planar_observe_into(R, t, landmarks, j, kind, z_hat, H, i):
    """A planar kind's prediction z_hat[i] (3,) of landmark j (landmarks[j]: x, y on the floor,
    z, and a marker's heading in a fourth column, ``SceneArrays.landmark_xyz``) from the planar robot at (R, t), and its Jacobian H[i] (3, 3)
    by the right perturbation: point2 z = p = R' (l - t), H = [-I, -J p] (its third row inert);
    marker the same and psi = wrap(psi_l - theta), its row (0, 0, -1)."""
    d0, d1 = landmarks[j, 0] - t[0], landmarks[j, 1] - t[1]
    p0 = R[0, 0] * d0 + R[1, 0] * d1
    p1 = R[0, 1] * d0 + R[1, 1] * d1
    z_hat[i, 0], z_hat[i, 1] = p0, p1
    H[i, 0, 0], H[i, 0, 1], H[i, 0, 2] = -1.0, 0.0, p1          # -J p = (p1, -p0)
    H[i, 1, 0], H[i, 1, 1], H[i, 1, 2] = 0.0, -1.0, -p0
    H[i, 2, 0] = H[i, 2, 1] = 0.0
    if kind == MARKER:
        z_hat[i, 2] = wrap_angle(landmarks[j, 3] - math.atan2(R[1, 0], R[0, 0]))
        H[i, 2, 2] = -1.0
    else:
        z_hat[i, 2], H[i, 2, 2] = 0.0, 0.0


@inlined
def wrapped_residual(kind, a, r):
    """Row a of a residual z - z_hat of a measurement of ``kind``: a marker's psi (its angle row,
    ``measurement.ANGLE_ROW``) wrapped into [-pi, pi), as ``camloc.planar.wrap_residuals``; every
    other row as it is."""
    return wrap_angle(r) if a == 2 and kind == MARKER else r


@inlined
def onto_measured_branch(z, obs_camera, camera_K, obs, z_hat):
    """z_hat (p, 3), the predictions of observations obs (p,) (measured z, by sensors obs_camera:
    rows of camera_K, the scene's), with each marker's psi moved onto its measurement's branch
    (``z - wrap(z - z_hat)``): every residual z - z_hat taken of them is then wrapped, as the
    numpy engine's (``StackedUpdate.measurement_function``). Inlined, and passed three of the
    scene's arrays, not the scene: its loop is a cycle across which numba does not prune the
    references counted to what an inlined step is passed (34 for the scene, at every update)."""
    for i in range(obs.size):
        o = obs[i]
        if camera_K[obs_camera[o], 4] == MARKER:
            z_hat[i, 2] = z[o, 2] - wrap_angle(z[o, 2] - z_hat[i, 2])
