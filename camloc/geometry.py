"""Pure SO(3)/SE(3) and Euler-angle geometry: the one place where rotations are built and read.

Conventions used everywhere in camloc
-------------------------------------
- Quaternions are ``quat_xyzw`` (scalar last), as in g2o and ``scipy.spatial.transform.Rotation``.
- Euler angles are ``rpy = (roll, pitch, yaw)`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``
  (intrinsic z-y'-x'', scipy's ``"ZYX"`` with the angles given as yaw, pitch, roll).
- A pose ``T_a_b`` (4, 4) maps points of frame b into frame a: ``p_a = R_a_b p_b + t_a_b``.
- Rotation perturbations are on the right (body frame): ``R(rpy + d) ~= R(rpy) Exp(E(rpy) d)``.

Every function accepts a single item or a leading batch dimension, and never does I/O.
"""

from __future__ import annotations

import math

import numpy as np


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix: ``hat(a) @ b == cross(a, b)``. (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    if v.shape == (3,):
        a, b, c = v.tolist()
        return np.array([[0.0, -c, b], [c, 0.0, -a], [-b, a, 0.0]])
    if v.shape == (1, 3):  # one point (a lone pair's camera model): the scalar form above
        return hat(v[0])[None]
    # gathered from (0, v, -v) in one take: the numpy beam builds one per camera model call, and
    # six strided assignments cost it half again as much (negation is exact: the same values)
    entries = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v, -v], axis=-1)
    return entries.take(_HAT_ENTRIES, axis=-1).reshape(v.shape[:-1] + (3, 3))


# hat(v)'s nine entries row by row, as positions in (0, v0, v1, v2, -v0, -v1, -v2)
_HAT_ENTRIES = np.array([0, 6, 2, 3, 0, 4, 5, 1, 0])


def normalized_quaternions(quat_xyzw: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) scaled to unit norm; none may be all zeros.

    Each is divided by its largest absolute component before its norm is taken: the squares of
    components beyond about 1e154 overflow (the norm is inf and the quotient all zeros), and those
    of components below about 1e-162 underflow.
    """
    quat_xyzw = np.asarray(quat_xyzw, dtype=float)
    scaled = quat_xyzw / np.max(np.abs(quat_xyzw), axis=-1, keepdims=True)
    return scaled / np.linalg.norm(scaled, axis=-1, keepdims=True)


def quat_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Quaternion(s) (..., 4) scalar last, scaled to unit norm first -> rotation matrices (..., 3, 3).

    Written out, as scipy's ``Rotation.from_quat(q).as_matrix()`` (the tests compare them): the
    import of scipy costs ``camloc run`` a fifth of its time on a small file."""
    q = np.asarray(quat_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = x * x - y * y - z * z + w * w, 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2.0 * (x * y + z * w), -x * x + y * y - z * z + w * w, 2.0 * (y * z - x * w)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), -x * x - y * y + z * z + w * w
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4), scalar last, with qw >= 0.

    Shepperd's method, as scipy's ``Rotation.from_matrix``: the quaternion is built from the
    largest of ``1 + trace`` and ``1 + 2 R_ii - trace`` (4 w^2 and 4 q_i^2), so that no component
    is found by dividing by a small one."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    trace = np.trace(flat, axis1=1, axis2=2)
    decision = np.column_stack([flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2], trace])
    choice = np.argmax(decision, axis=1)
    quat = np.empty((flat.shape[0], 4))
    by_trace = choice == 3
    Rt = flat[by_trace]
    quat[by_trace] = np.column_stack([Rt[:, 2, 1] - Rt[:, 1, 2], Rt[:, 0, 2] - Rt[:, 2, 0], Rt[:, 1, 0] - Rt[:, 0, 1], 1.0 + trace[by_trace]])
    for i in range(3):
        rows = np.flatnonzero(choice == i)
        j, k = (i + 1) % 3, (i + 2) % 3
        Ri = flat[rows]
        quat[rows, i] = 1.0 - trace[rows] + 2.0 * Ri[:, i, i]
        quat[rows, j] = Ri[:, j, i] + Ri[:, i, j]
        quat[rows, k] = Ri[:, k, i] + Ri[:, i, k]
        quat[rows, 3] = Ri[:, k, j] - Ri[:, j, k]
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    quat *= np.where(quat[:, 3:4] < 0.0, -1.0, 1.0)
    return quat.reshape(R.shape[:-2] + (4,))


def euler_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (..., 3) in radians -> ``Rz(yaw) Ry(pitch) Rx(roll)`` (..., 3, 3).

    Written out rather than through scipy: the filter calls it for one state at a time, where
    scipy's per-call overhead dominates (tests compare it with scipy's ``"ZYX"``).
    """
    rpy = np.asarray(rpy, dtype=float)
    if rpy.shape == (3,):  # one state: scalar math, a tenth of the array version's overhead
        try:
            roll, pitch, yaw = rpy.tolist()
            sr, sp, sy = math.sin(roll), math.sin(pitch), math.sin(yaw)
            cr, cp, cy = math.cos(roll), math.cos(pitch), math.cos(yaw)
            return np.array([
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ])
        except ValueError:  # an infinite angle: NaN as numpy gives it, below
            pass
    sr, sp, sy = np.sin(rpy[..., 0]), np.sin(rpy[..., 1]), np.sin(rpy[..., 2])
    cr, cp, cy = np.cos(rpy[..., 0]), np.cos(rpy[..., 1]), np.cos(rpy[..., 2])
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> roll, pitch, yaw (..., 3), pitch in [-pi/2, pi/2].

    At pitch = +-pi/2 (gimbal lock) roll and yaw are not separable and the split between them is
    arbitrary; the Euler filter warns before it gets there.
    """
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        (r00, _, _), (r10, _, _), (r20, r21, r22) = R.tolist()
        sin_pitch = -r20
        if sin_pitch > 1.0:  # rounding; a NaN passes both tests and stays NaN
            sin_pitch = 1.0
        elif sin_pitch < -1.0:
            sin_pitch = -1.0
        return np.array([math.atan2(r21, r22), math.asin(sin_pitch), math.atan2(r10, r00)])
    rpy = np.empty(R.shape[:-2] + (3,))
    rpy[..., 0] = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    rpy[..., 1] = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    rpy[..., 2] = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return rpy


def quat_to_euler(quat_xyzw: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) -> roll, pitch, yaw (..., 3)."""
    return matrix_to_euler(quat_to_matrix(quat_xyzw))


def euler_to_quat(rpy: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (..., 3) -> quaternions (..., 4) with qw >= 0."""
    return matrix_to_quat(euler_to_matrix(rpy))


def euler_rate_matrix(rpy: np.ndarray) -> np.ndarray:
    """E(rpy) (..., 3, 3) such that the body-frame rotation for an Euler step d is ``E @ d``.

    ``R(rpy + d) = R(rpy) Exp(E(rpy) d) + O(|d|^2)``; E is singular at pitch = +-pi/2.
    """
    rpy = np.asarray(rpy, dtype=float)
    if rpy.shape == (3,):
        try:
            roll, pitch, _ = rpy.tolist()
            sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
            return np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])
        except ValueError:  # an infinite angle
            pass
    roll, pitch = rpy[..., 0], rpy[..., 1]
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    E = np.zeros(rpy.shape[:-1] + (3, 3))
    E[..., 0, 0] = 1.0
    E[..., 0, 2] = -sp
    E[..., 1, 1], E[..., 1, 2] = cr, sr * cp
    E[..., 2, 1], E[..., 2, 2] = -sr, cr * cp
    return E


def euler_rate_matrix_inverse(rpy: np.ndarray) -> np.ndarray:
    """E(rpy)^-1 (3, 3) for one rpy (3,), in closed form: the Euler step of a body rotation w is
    ``E^-1 w``. det E = cos(pitch), so it is singular at pitch = +-pi/2 like E itself.
    """
    roll, pitch = float(rpy[0]), float(rpy[1])
    if not (math.isfinite(roll) and math.isfinite(pitch)):
        return np.full((3, 3), np.nan)
    sr, cr = math.sin(roll), math.cos(roll)
    tp, sec = math.tan(pitch), 1.0 / math.cos(pitch)
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr * sec, cr * sec]])


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) -> rotation matrices (..., 3, 3), by Rodrigues' formula
    ``I + sin(a)/a K + (1 - cos a)/a^2 K^2`` (Taylor series below 1e-4 rad)."""
    phi = np.asarray(rotvec, dtype=float)
    a = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = a < _SMALL_ANGLE
    safe = np.where(small, 1.0, a)
    c1 = np.where(small, 1.0 - a**2 / 6.0, np.sin(safe) / safe)
    c2 = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    K = hat(phi)
    return np.eye(3) + c1 * K + c2 * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), angle in [0, pi].

    ``a = arccos((tr R - 1)/2)``, ``phi = a / (2 sin a) vee(R - R^T)``; within 1e-3 rad of pi,
    where that division loses precision, the quaternion's route is taken instead
    (``2 atan2(|v|, w) v / |v|``).
    """
    R = np.asarray(R, dtype=float)
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    cos_a = np.clip(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    a = np.arccos(cos_a)
    small = a < _SMALL_ANGLE
    safe = np.where(small, 1.0, a)
    factor = np.where(small, 0.5 + a**2 / 12.0, safe / (2.0 * np.sin(safe)))
    phi = factor[..., None] * vee
    near_pi = a > np.pi - 1e-3
    if np.any(near_pi):
        quat = matrix_to_quat(R[near_pi].reshape(-1, 3, 3))
        v_norm = np.linalg.norm(quat[:, :3], axis=1, keepdims=True)
        phi[near_pi] = 2.0 * np.arctan2(v_norm, quat[:, 3:4]) * quat[:, :3] / v_norm
    return phi


# Below this angle the closed forms of the SO(3) Jacobians lose digits to cancellation; their
# Taylor series (two terms) are exact to double precision there.
_SMALL_ANGLE = 1e-4


def so3_right_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """Right Jacobian Jr (..., 3, 3) of SO(3) at rotation vector(s) (..., 3).

    ``Exp(phi + d) ~= Exp(phi) Exp(Jr(phi) d)``:
    ``Jr = I - (1 - cos a)/a^2 [phi]x + (a - sin a)/a^3 [phi]x^2`` with ``a = |phi|``.
    """
    phi = np.asarray(rotvec, dtype=float)
    a = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = a < _SMALL_ANGLE
    safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    K = hat(phi)
    return np.eye(3) - c1 * K + c2 * (K @ K)


def so3_right_jacobian_inverse(rotvec: np.ndarray) -> np.ndarray:
    """Inverse of the right Jacobian, (..., 3, 3), in closed form (angle below pi).

    ``Log(Exp(phi) Exp(d)) ~= phi + Jr^-1(phi) d``:
    ``Jr^-1 = I + [phi]x / 2 + (1/a^2 - (1 + cos a)/(2 a sin a)) [phi]x^2``.
    """
    phi = np.asarray(rotvec, dtype=float)
    a = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = a < _SMALL_ANGLE
    safe = np.where(small, 1.0, a)
    c2 = np.where(small, 1.0 / 12.0 + a**2 / 720.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    K = hat(phi)
    return np.eye(3) + 0.5 * K + c2 * (K @ K)


# One rotation vector at a time, in plain floats (the same formulas as the batched forms above).


def so3_exp_and_left_jacobian_one(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp(phi)`` and ``J_l(phi)`` (3, 3) of one rotation vector, in plain floats: the batched
    forms above cost some 20 numpy calls each, and the mapping filter takes these several times a pose.
    ``Exp = I + s K + c K^2``, ``J_l = I + c K + j K^2`` with K = [phi]x, ``K^2 = phi phi' - a^2 I``."""
    x, y, z = phi.tolist()
    a2 = x * x + y * y + z * z
    a = math.sqrt(a2)
    if a < _SMALL_ANGLE:
        s, c, j = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
    else:
        s, c, j = math.sin(a) / a, (1.0 - math.cos(a)) / a2, (a - math.sin(a)) / (a2 * a)
    xx, yy, zz, xy, xz, yz = x * x - a2, y * y - a2, z * z - a2, x * y, x * z, y * z  # K^2
    E = np.array([[1.0 + c * xx, -s * z + c * xy, s * y + c * xz],
                  [s * z + c * xy, 1.0 + c * yy, -s * x + c * yz],
                  [-s * y + c * xz, s * x + c * yz, 1.0 + c * zz]])
    J = np.array([[1.0 + j * xx, -c * z + j * xy, c * y + j * xz],
                  [c * z + j * xy, 1.0 + j * yy, -c * x + j * yz],
                  [-c * y + j * xz, c * x + j * yz, 1.0 + j * zz]])
    return E, J


def so3_log_one(R: np.ndarray) -> np.ndarray:
    """``Log(R)`` (3,) of one rotation, in plain floats away from pi (``so3_log`` there)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    cos_a = min(1.0, max(-1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
    a = math.acos(cos_a)
    if a > math.pi - 1e-3:
        return so3_log(R)
    factor = 0.5 + a * a / 12.0 if a < _SMALL_ANGLE else a / (2.0 * math.sin(a))
    return np.array([factor * (r21 - r12), factor * (r02 - r20), factor * (r10 - r01)])


def so3_left_jacobian_inverse_one(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi)^-1 = J_r(-phi)^-1 = I - K / 2 + c K^2`` in closed form, plain floats
    (``so3_right_jacobian_inverse``'s formula; angle below pi)."""
    x, y, z = phi.tolist()
    a2 = x * x + y * y + z * z
    a = math.sqrt(a2)
    c = 1.0 / 12.0 + a2 / 720.0 if a < _SMALL_ANGLE else 1.0 / a2 - (1.0 + math.cos(a)) / (2.0 * a * math.sin(a))
    xx, yy, zz, xy, xz, yz = x * x - a2, y * y - a2, z * z - a2, x * y, x * z, y * z  # K^2
    return np.array([[1.0 + c * xx, 0.5 * z + c * xy, -0.5 * y + c * xz],
                     [-0.5 * z + c * xy, 1.0 + c * yy, 0.5 * x + c * yz],
                     [0.5 * y + c * xz, -0.5 * x + c * yz, 1.0 + c * zz]])


def retract_right(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Pose(s) (..., 4, 4) moved by a right perturbation delta (..., 6) = (dt, dtheta).

    ``R -> R Exp(dtheta)``, ``t -> t + R dt``: ``T @ make_pose(so3_exp(dtheta), dt)``, the noise
    convention of ``camloc.models`` (SO(3) x R^3, not the SE(3) exponential).
    """
    T = np.asarray(T, dtype=float)
    delta = np.asarray(delta, dtype=float)
    R, t = T[..., :3, :3], T[..., :3, 3]
    return make_pose(R @ so3_exp(delta[..., 3:6]), t + np.einsum("...ij,...j->...i", R, delta[..., 0:3]))


def difference_right(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """The right perturbation (..., 6) = (dt, dtheta) that moves ``T_ref`` to ``T``: the inverse
    of ``retract_right``, ``retract_right(T_ref, difference_right(T, T_ref)) == T``."""
    R_ref_T = np.swapaxes(np.asarray(T_ref, dtype=float)[..., :3, :3], -1, -2)
    dt = np.einsum("...ij,...j->...i", R_ref_T, T[..., :3, 3] - T_ref[..., :3, 3])
    return np.concatenate([dt, so3_log(R_ref_T @ T[..., :3, :3])], axis=-1)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle (...,) in radians of rotation matrices (..., 3, 3)."""
    return np.linalg.norm(so3_log(R), axis=-1)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) and translation (..., 3) -> homogeneous pose (..., 4, 4)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_from_quat(t: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Translation (..., 3) and quaternion (..., 4) -> pose (..., 4, 4)."""
    return make_pose(quat_to_matrix(quat_xyzw), t)


def pose_to_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose (..., 4, 4) -> translation (..., 3) and quaternion (..., 4) with qw >= 0."""
    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3])


def pose_from_euler(state: np.ndarray) -> np.ndarray:
    """Euler state ``(x, y, z, roll, pitch, yaw)`` (..., 6) -> pose (..., 4, 4)."""
    state = np.asarray(state, dtype=float)
    return make_pose(euler_to_matrix(state[..., 3:6]), state[..., 0:3])


def pose_to_euler(T: np.ndarray) -> np.ndarray:
    """Pose (..., 4, 4) -> Euler state ``(x, y, z, roll, pitch, yaw)`` (..., 6)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], matrix_to_euler(T[..., :3, :3])], axis=-1)


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of pose(s) (..., 4, 4) without a general matrix inverse."""
    T = np.asarray(T, dtype=float)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(R_t, -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3]))


def relative_se3(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """``T_a_b = T_w_a^-1 T_w_b``: the pose of b in the frame of a."""
    return se3_inverse(T_w_a) @ T_w_b


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply pose (4, 4) to points (..., 3) expressed in frame b; returns points in frame a."""
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


_TWO_PI = 2.0 * math.pi


def wrap_angle_float(angle: float) -> float:
    """``wrap_angle`` of one Python float, to the bit: numpy's float remainder and Python's both
    take the C ``fmod`` and add the divisor where the signs differ (a zero keeps the divisor's
    sign). A filter's few angles per update, where numpy's four calls on an array of two or three
    cost the numpy engine 2% of a run."""
    return (angle + math.pi) % _TWO_PI - math.pi


def pose_error_vector(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Error (..., 6) of an estimate against the truth: ``(t_true - t_est, Log(R_true R_est^T))``.

    The rotation part is a world-frame (left) rotation vector; this is the parametrization in which
    camloc stores pose covariances (``cov_pose``) so that NEES is filter-agnostic.
    """
    dt = T_true[..., :3, 3] - T_est[..., :3, 3]
    dR = T_true[..., :3, :3] @ np.swapaxes(T_est[..., :3, :3], -1, -2)
    return np.concatenate([dt, so3_log(dR)], axis=-1)
