"""EKF-SLAM in the invariant error form: the robot pose and the landmarks it maps, one Gaussian.

Model card
----------
State      the robot pose (R, t) and m landmarks l_1..l_m, world frame (an element of SE_{m+1}(3)).
Error      xi = (xi_t, xi_theta, xi_l1, .., xi_lm) (3 + 3 + 3 m), **left** of the estimate:
              R = Exp(xi_theta) R^,  t = Exp(xi_theta) t^ + J(xi_theta) xi_t,
              l_i = Exp(xi_theta) l^_i + J(xi_theta) xi_li
           (J the left Jacobian of SO(3); ``retract``). This is the right-invariant error of the
           invariant EKF (Barrau & Bonnabel): the error of the whole map and the robot moves
           together under a change of world frame, which is what keeps the filter consistent
           where the textbook error (robot heading and landmark positions apart) grows
           overconfident: the unobservable directions (world position and heading with no map)
           stay unobservable in the linearization.
Motion     T' = T dT Exp(w), w = (w_t, w_theta) ~ N(0, Q), the odometry's right perturbation.
           In this error **F = I** (the error does not depend on the estimate: the source of the
           consistency) and the noise enters through the adjoint of the new estimate:
           xi' = xi + G w, G = (R^, [t^]x R^ on xi_t; R^ on xi_theta; [l^_i]x R^ on each xi_li),
           so a prediction costs O(m^2) (``G Q G'``), no more than an update.
Measure    p_robot = R' (l - t) of a landmark in the state: d p_robot / d xi = R^' (-I on xi_t,
           0 on xi_theta, +I on xi_l), exactly to first order. Of a landmark held fixed (an
           exact map's): d p_robot / d xi = R^' (-I on xi_t, [l]x on xi_theta). Then the camera
           (``camloc.measurement``): p_camera = R_c' (p_robot - t_c), z = h_kind(p_camera).
Inverse    a new landmark from a measurement with range: l = t + R (t_c + R_c g(z)) with g the
           back-projection; its error is xi_l = xi_t + R^ R_c G dz: the robot's translation error
           plus the measurement's noise, no heading term (``inverse_observation``).
Planar     a planar robot (``Dataset.planar``) runs this model lifted: its pose a rotation about z
           at z = 0, its odometry noise Q and start covariance zero in z, roll and pitch
           (``planar_initial_cov``). G Q G' then spans only xi_t's x, y, xi_theta's z and the
           landmarks' x, y (``[l]x R e_z = (l_y, -l_x, 0)``), so P is zero in the other pose rows
           and every correction P H' w keeps the robot in the plane, exactly (tests/test_slam.py).
           A point of the floor (``EDGE_SE2_XY``, kind point2) is a landmark with z = 0 measured in
           the robot frame, z = the first two rows of R' (l - t) (``project``: the third row
           inert); its inverse observation puts no noise in z, so its z is pinned at 0 with zero
           variance: not information claimed, a point of the floor has no height, and no
           measurement's Jacobian reaches it (the third row of R' (l - t) is never measured).
           A marker (``EDGE_SE2_MARKER``) is a landmark whose third coordinate is its heading psi
           (its position on the floor), its error there psi's own (psi_true = psi^ + e: no turn of
           the world moves it, so G has no row for it); z = (R' (l - t) in x and y, psi - theta):
           d z_psi / d (e, xi_theta_z) = (1, -1), and in its inverse observation B puts xi_theta_z
           into e.
Tags       a tag in the state is two rows of L: its centre and its orientation's rotation vector
           (``SlamMean.orientation`` marks the latter), with the left error
           R_tag = Exp(xi_theta) Exp(xi_o) R^_tag: ``camloc.slam_tags``' model card (its
           measurement, inverse observation, prior and world covariance). Here: ``retract``,
           ``difference``, ``noise_coefficients`` (xi_o -= R w_theta) and the rows' bookkeeping.

Pure: no I/O, no printing. Every Jacobian is checked against finite differences of ``retract``
in tests/test_slam.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typing import TYPE_CHECKING, Optional

from camloc import ekf, geometry, measurement, planar, slam_tags

if TYPE_CHECKING:
    from camloc.sensors import CameraModel  # a camera: T_robot_camera, intrinsics, kind

POSE_DIM = 6  # xi_t, xi_theta


@dataclass
class SlamMean:
    """The estimate's mean: the robot pose (R (3, 3), t (3,)) and the landmarks in the state L (m, 3).
    ``orientation`` (m,) bool marks the rows of L that are a tag's orientation (the rotation vector
    of R_tag, world; ``camloc.slam_tags``), None where no row is (every row a position)."""

    R: np.ndarray
    t: np.ndarray
    L: np.ndarray
    orientation: Optional[np.ndarray] = None

    def orientation_rows(self) -> np.ndarray:
        """The rows (q,) of L that are a tag's orientation."""
        return np.zeros(0, np.int64) if self.orientation is None else np.flatnonzero(self.orientation)

    @property
    def dim(self) -> int:
        return POSE_DIM + 3 * self.L.shape[0]

    def pose(self) -> np.ndarray:
        return geometry.make_pose(self.R, self.t)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3), ``J_l(phi) = J_r(-phi)``."""
    return geometry.so3_right_jacobian(-np.asarray(phi, dtype=float))


def retract(x: SlamMean, delta: np.ndarray) -> SlamMean:
    """``exp(delta) x``: the estimate moved by an error delta (dim,) (the group's exponential)."""
    E, J = geometry.so3_exp_and_left_jacobian_one(delta[3:6])
    L = x.L @ E.T + delta[6:].reshape(-1, 3) @ J.T if x.L.size else x.L.copy()
    rows = x.orientation_rows()
    if rows.size:  # a tag's orientation: R_tag = Exp(xi_theta) Exp(xi_o) R^_tag (slam_tags)
        L[rows] = slam_tags.turned(x.L[rows], delta[6:].reshape(-1, 3)[rows], E)
    return SlamMean(E @ x.R, E @ x.t + J @ delta[0:3], L, x.orientation)


def difference(a: SlamMean, b: SlamMean) -> np.ndarray:
    """The error delta with ``retract(b, delta) == a`` (the group's logarithm of a b^-1)."""
    phi = geometry.so3_log_one(a.R @ b.R.T)
    E, _ = geometry.so3_exp_and_left_jacobian_one(phi)
    J_inverse = geometry.so3_left_jacobian_inverse_one(phi)
    dt = J_inverse @ (a.t - E @ b.t)
    dl = (a.L - b.L @ E.T) @ J_inverse.T if a.L.size else np.zeros((0, 3))
    rows = b.orientation_rows()
    if rows.size:
        dl[rows] = slam_tags.turn_between(a.L[rows], b.L[rows], E)
    return np.concatenate([dt, phi, dl.ravel()])


def predict(x: SlamMean, P: np.ndarray, T_increment: np.ndarray, Q: np.ndarray) -> tuple[SlamMean, np.ndarray]:
    """The estimate after an odometry increment T_k_k+1 (4, 4) with noise Q (6, 6) on its right
    perturbation (translation, rotation vector): F = I, ``P + G Q G'`` with G the adjoint of the
    new estimate (``noise_coefficients``)."""
    R_next = x.R @ T_increment[:3, :3]
    t_next = x.t + x.R @ T_increment[:3, 3]
    x_next = SlamMean(R_next, t_next, x.L, x.orientation)
    G = noise_coefficients(x_next)
    try:  # G Q G' as W W' (W = G chol(Q)): BLAS's symmetric product, exactly symmetric, so P's sum is too
        W = G @ np.linalg.cholesky(Q)
        return x_next, P + W @ W.T
    except np.linalg.LinAlgError:
        pass
    support = np.flatnonzero(np.any(Q != 0.0, axis=0))  # a planar robot's: zero in z, roll and pitch
    try:
        W = G[:, support] @ np.linalg.cholesky(Q[np.ix_(support, support)])
        return x_next, P + W @ W.T
    except np.linalg.LinAlgError:  # a Q not positive definite (a degenerate file's)
        return x_next, ekf.symmetrize(P + G @ Q @ G.T)


def noise_coefficients(x: SlamMean) -> np.ndarray:
    """G (dim, 6): how the increment's right perturbation w = (w_t, w_theta) moves the error: the
    body-frame noise seen in the world, ``xi_theta += R w_theta``, ``xi_t += R w_t + [t]x R w_theta``,
    and every landmark's ``xi_l += [l]x R w_theta`` (a turn of the robot about itself is, in this
    error, a turn of the world about its origin and a shift back; the adjoint of SE_{m+1}(3)); a
    tag's orientation ``xi_o -= R w_theta`` (``slam_tags``: it rides on xi_theta, which moved)."""
    G = np.zeros((x.dim, POSE_DIM))
    RW = x.R
    G[0:3, 0:3] = RW
    G[0:3, 3:6] = geometry.hat(x.t) @ RW
    G[3:6, 3:6] = RW
    if x.L.size:
        G[POSE_DIM:, 3:6] = (geometry.hat(x.L) @ RW).reshape(-1, 3)
    rows = x.orientation_rows()
    if rows.size:
        G[(POSE_DIM + 3 * rows[:, None] + np.arange(3)).ravel(), 3:6] = np.tile(-RW, (rows.size, 1))
    return G


def planar_initial_cov(x: SlamMean, world_cov: np.ndarray) -> np.ndarray:
    """``initial_cov`` of a planar robot: ``world_cov`` (6, 6) kept on (x, y, yaw) only, zero in
    z, roll and pitch (``planar.planar_block``, ``planar.lifted_cov``)."""
    return initial_cov(x, planar.lifted_cov(planar.planar_block(world_cov)))


# A planar robot's own measurements, d z / d p_robot: a point2's x and y rows (the third inert); a
# marker's x, y and its heading, stored as the landmark's third coordinate (less the robot's: ``observe_columns``)
_ROBOT_FRAME_JACOBIAN = {measurement.POINT2: np.diag([1.0, 1.0, 0.0]), measurement.MARKER: np.eye(3)}


def project(p_camera: np.ndarray, sensor: "CameraModel") -> tuple[np.ndarray, np.ndarray]:
    """Points in the sensor's frame (M, 3) -> its measurements (M, MAX_DIM) and their Jacobians
    d z / d p (M, MAX_DIM, 3): a camera's (``measurement.project``), or a planar robot's own
    (point2: the point's x and y in the robot frame, the third row inert; marker: x, y and the
    third coordinate, its heading, which ``observe_columns`` turns into the robot frame)."""
    if sensor.kind in _ROBOT_FRAME_JACOBIAN:
        Jh = _ROBOT_FRAME_JACOBIAN[sensor.kind]
        return p_camera @ Jh.T, np.broadcast_to(Jh, (p_camera.shape[0], 3, 3))
    return (measurement.project(p_camera, sensor.intrinsics, sensor.kind),
            measurement.projection_jacobian(p_camera, sensor.intrinsics, sensor.kind))


def back_project(z: np.ndarray, sensor: "CameraModel") -> tuple[np.ndarray, np.ndarray]:
    """``project``'s inverse for a measurement with range (M, MAX_DIM) -> points in the sensor's
    frame (M, 3) and d p / d z (M, 3, MAX_DIM): a camera's (``measurement.back_project``), a
    point2's on the floor (z = 0, no noise in it), a marker's with its heading in the robot frame
    as the third coordinate."""
    if sensor.kind in _ROBOT_FRAME_JACOBIAN:
        Jh = _ROBOT_FRAME_JACOBIAN[sensor.kind]
        return z @ Jh.T, np.broadcast_to(Jh, (z.shape[0], 3, measurement.MAX_DIM)).copy()
    return measurement.back_project(z, sensor.intrinsics, sensor.kind)


def heading(x: SlamMean) -> float:
    """The heading of a planar robot's pose (its x axis's angle in the world plane)."""
    return float(np.arctan2(x.R[1, 0], x.R[0, 0]))


def wrapped_predictions(z_hat: np.ndarray, z: np.ndarray, kinds) -> np.ndarray:
    """Predictions (..., MAX_DIM) with a marker's heading row moved by whole turns so that
    ``z - z_hat`` is wrapped into [-pi, pi) (``planar.wrap_residuals``); ``z_hat`` itself, bit for
    bit, where no kind has an angle."""
    if not np.any(np.asarray(kinds) == measurement.MARKER):
        return z_hat
    return z - planar.wrap_residuals(z - z_hat, kinds)


def camera_points(x: SlamMean, sensor: "CameraModel", xyz: np.ndarray) -> np.ndarray:
    """World points (M, 3) in the camera frame (M, 3)."""
    Rc, tc = sensor.T_robot_camera[:3, :3], sensor.T_robot_camera[:3, 3]
    return ((xyz - x.t) @ x.R - tc) @ Rc


def observe(x: SlamMean, sensor: "CameraModel", xyz: np.ndarray, state_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predictions (M, MAX_DIM) of points xyz (M, 3) and their Jacobians (M, MAX_DIM, dim) with
    respect to the error: a point with ``state_row`` i >= 0 is the state's landmark i (its xyz
    must be ``x.L[i]``), -1 a point held fixed."""
    return observe_columns(x, sensor, xyz, np.where(state_row >= 0, 2 + state_row, -1), x.dim)


def observe_columns(x: SlamMean, sensor: "CameraModel", xyz: np.ndarray, block: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``observe`` with the Jacobian on ``width`` columns of the error only, in blocks of three:
    the pose's translation (block 0) and rotation (1), then a landmark of the state wherever
    ``block`` (M,) puts it (>= 2; -1: the point is held fixed). An update whose pairs touch a few
    landmarks of a large state works on those columns (``state_columns``)."""
    p_camera = camera_points(x, sensor, xyz)
    z_hat, Jh = project(p_camera, sensor)  # (M, MAX_DIM), (M, 3, 3)
    A = Jh @ (sensor.T_robot_camera[:3, :3].T @ x.R.T)  # d z / d p_world-like: Jh Rc' R'
    M = xyz.shape[0]
    H = np.zeros((M, measurement.MAX_DIM, width))
    blocks = H.reshape(M, measurement.MAX_DIM, width // 3, 3)
    blocks[:, :, 0, :] = -A
    fixed = block < 0
    if fixed.all():
        blocks[:, :, 1, :] = A @ geometry.hat(xyz)
    else:
        blocks[fixed, :, 1, :] = A[fixed] @ geometry.hat(xyz[fixed])
        mine = np.flatnonzero(~fixed)  # each its own landmark's block, in one assignment
        blocks[mine, :, block[mine], :] = A[mine]
    if sensor.kind == measurement.MARKER:  # psi - theta: the robot's heading error enters with -1
        z_hat[:, 2] -= heading(x)
        H[:, 2, 5] -= 1.0
    return z_hat, H


def state_columns(state_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error's columns (k,) that observations of landmarks ``state_row`` (M,) (-1: held fixed)
    touch, the pose's and each landmark's once, and each observation's block among them
    (``observe_columns``)."""
    in_state = np.unique(state_row[state_row >= 0])
    columns = np.concatenate([np.arange(POSE_DIM), (POSE_DIM + 3 * in_state[:, None] + np.arange(3)).ravel()])
    return columns, np.where(state_row >= 0, 2 + np.searchsorted(in_state, state_row), -1)


def inverse_observation(x: SlamMean, sensor: "CameraModel", z: np.ndarray, R_z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A new landmark from one measurement with range z (MAX_DIM,) of noise R_z (MAX_DIM,
    MAX_DIM): its position (3,), the coefficients B (3, POSE_DIM) of its error on the pose's
    (xi_l = B xi_pose + noise: [I, 0]) and the noise's covariance N (3, 3)."""
    p_camera, G = back_project(z[None, :], sensor)
    Rc, tc = sensor.T_robot_camera[:3, :3], sensor.T_robot_camera[:3, 3]
    xyz = x.t + x.R @ (tc + Rc @ p_camera[0])
    W = x.R @ Rc @ G[0]  # d l / d z
    B = np.zeros((3, POSE_DIM))
    B[:, 0:3] = np.eye(3)
    if sensor.kind == measurement.MARKER:  # its heading in the world: the robot's plus the measured one
        xyz[2] += heading(x)
        B[2, 5] = 1.0
    return xyz, B, ekf.symmetrize(W @ R_z @ W.T)


def augmented(x: SlamMean, P: np.ndarray, xyz: np.ndarray, B: np.ndarray, N: np.ndarray) -> tuple[SlamMean, np.ndarray]:
    """The state with one more landmark at xyz (3,) whose error is ``B xi + n`` (B (3, dim) on the
    current error, n ~ N(0, N) independent of it): the new rows are ``B P`` and ``B P B' + N``."""
    return augmented_many(x, P, xyz[None, :], B[None, :, :], N[None, :, :])


def augmented_many(x: SlamMean, P: np.ndarray, xyz: np.ndarray, B: np.ndarray, N: np.ndarray,
                   orientation: Optional[np.ndarray] = None) -> tuple[SlamMean, np.ndarray]:
    """The state with q more landmarks at xyz (q, 3), landmark i's error ``B_i xi + n_i`` (B (q, 3,
    w) on the current error's first w components, the n_i ~ N(0, N_i) independent of it and of one
    another): one new covariance for all of them, the same as adding them one at a time (the
    later ones' B is zero on the earlier ones). A B on the pose alone (w = POSE_DIM, as the
    inverse observation's and a map prior's are) costs O(n), not O(n^2), a row. ``orientation``
    (q,) bool: which new rows are a tag's orientation (None: none)."""
    n, q, w = P.shape[0], xyz.shape[0], B.shape[2]
    B = B.reshape(3 * q, w)
    BP = B @ P[:w, :]  # (3q, n): B is zero beyond its w columns
    P_new = np.empty((n + 3 * q, n + 3 * q))
    P_new[:n, :n] = P
    P_new[n:, :n] = BP
    P_new[:n, n:] = BP.T
    block = BP[:, :w] @ B.T
    for i in range(q):
        block[3 * i:3 * i + 3, 3 * i:3 * i + 3] += N[i]
    P_new[n:, n:] = ekf.symmetrize(block)
    return SlamMean(x.R, x.t, np.vstack([x.L, xyz]), _joined_mask(x, q, orientation)), P_new


def augmented_on(x: SlamMean, P: np.ndarray, xyz: np.ndarray, C: np.ndarray, columns: np.ndarray,
                 N: np.ndarray) -> tuple[SlamMean, np.ndarray]:
    """``augmented`` of one landmark at xyz (3,) whose error is ``C xi[columns] + n`` (C (3, c) on
    the error's components ``columns`` (c,) anywhere in the state, n ~ N(0, N)): the new rows
    ``C P[columns]`` cost O(c n), not the O(n^2) of a B as wide as the state."""
    n = P.shape[0]
    CP = C @ P[columns, :]
    P_new = np.empty((n + 3, n + 3))
    P_new[:n, :n] = P
    P_new[n:, :n] = CP
    P_new[:n, n:] = CP.T
    P_new[n:, n:] = ekf.symmetrize(CP[:, columns] @ C.T + N)
    return SlamMean(x.R, x.t, np.vstack([x.L, xyz]), _joined_mask(x, 1, None)), P_new


def _joined_mask(x: SlamMean, q: int, orientation: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """The orientation mask of x's rows and q new ones (``orientation``, None: positions)."""
    if x.orientation is None and orientation is None:
        return None
    old = x.orientation if x.orientation is not None else np.zeros(x.L.shape[0], bool)
    return np.concatenate([old, orientation if orientation is not None else np.zeros(q, bool)])


def world_prior_coefficients(x: SlamMean, xyz: np.ndarray) -> np.ndarray:
    """B (3, POSE_DIM) of a landmark at xyz whose world error dl is independent of the pose:
    ``xi_l = dl + [l]x xi_theta`` (the invariant error carries the heading's lever arm)."""
    B = np.zeros((3, POSE_DIM))
    B[:, 3:6] = geometry.hat(xyz)
    return B


def without_landmarks(x: SlamMean, P: np.ndarray, drop: np.ndarray) -> tuple[SlamMean, np.ndarray]:
    """The state without the landmarks whose rows ``drop`` (bool (m,)) marks: marginalized out,
    which for a Gaussian in covariance form is deleting their rows and columns."""
    keep_rows = np.flatnonzero(np.concatenate([np.ones(POSE_DIM, bool), np.repeat(~drop, 3)]))
    kept = x.orientation[~drop] if x.orientation is not None else None
    return SlamMean(x.R, x.t, x.L[~drop], kept), P.take(keep_rows, axis=0).take(keep_rows, axis=1)  # (take: faster than np.ix_)


def landmark_world_cov(x: SlamMean, P: np.ndarray, i: int) -> np.ndarray:
    """The world-frame covariance (3, 3) of landmark i's position: ``dl = xi_l - [l]x xi_theta``
    (from the six rows it reads: O(1) in the state's size)."""
    c = POSE_DIM + 3 * i
    rows = np.array([3, 4, 5, c, c + 1, c + 2])
    A = np.hstack([-geometry.hat(x.L[i]), np.eye(3)])
    return ekf.symmetrize(A @ P[np.ix_(rows, rows)] @ A.T)


def pose_right_cov(x: SlamMean, P: np.ndarray) -> np.ndarray:
    """The pose block as the covariance (6, 6) of the SE(3) filter's right perturbation (dt,
    dtheta) (``geometry.retract_right``): ``dtheta = R' xi_theta``, ``dt = R' (xi_t - [t]x xi_theta)``."""
    J = np.zeros((POSE_DIM, POSE_DIM))
    J[0:3, 0:3] = x.R.T
    J[0:3, 3:6] = -x.R.T @ geometry.hat(x.t)
    J[3:6, 3:6] = x.R.T
    return ekf.symmetrize(J @ P[:POSE_DIM, :POSE_DIM] @ J.T)


def initial_cov(x: SlamMean, world_cov: np.ndarray) -> np.ndarray:
    """The start pose's error covariance from its world-frame one (translation, rotation vector;
    ``geometry.pose_error_vector``'s order): ``xi_t = dt + [t]x xi_theta``."""
    A = np.eye(POSE_DIM)
    A[0:3, 3:6] = geometry.hat(x.t)
    return ekf.symmetrize(A @ world_cov @ A.T)


def landmark_world_cov_of(x: SlamMean, P: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The world covariance (3, 3) of a point whose error is ``C`` (3, POSE_DIM) times the pose's."""
    return ekf.symmetrize(C @ P[:POSE_DIM, :POSE_DIM] @ C.T)
