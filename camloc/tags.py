"""A tag's orientation measured by a camera (an AprilTag's rotation from its homography), in the
error-state form of the micro Lie theory (Sola et al. 2018): pure functions of arrays. (The
numpy localizer's use of them: ``camloc.tag_orientations``.)

Model card
----------
Landmark    a tag: its centre l (world) and its orientation R_tag (world), ``VERTEX_TAG``.
Measurement R_meas, the tag's orientation in the camera frame, with noise as a right
            perturbation in the tag's frame: ``R_meas = R_pred(x_true) Exp(n)``, n ~ N(0, Q_tag).
            Its position is an ordinary camera measurement of l (``EDGE_PROJECT_TAG``'s u, v, depth).
Prediction  R_pred = R_c^T R^T R_tag (R the robot's orientation, R_c the camera's mount).
Residual    e = Log(R_pred^-1 R_meas) (3,), which is n at the truth.
Jacobian    for a right perturbation of the robot's rotation, R -> R Exp(dtheta):
              R_pred -> R_pred Exp(-R_tag^T R dtheta)                         (``prediction``: H_R)
              e -> Log(Exp(R_tag^T R dtheta) Exp(e)) = e + Jl^-1(e) R_tag^T R dtheta
            (Jl the left Jacobian of SO(3); ``Jl^-1(e) = Jr^-1(-e)``), so in the filter's
            ``z - z_hat`` form, with z = Log(R_meas) stored, the prediction that gives the exact
            residual is ``z_hat = z - e`` and its Jacobian ``Jl^-1(e) H_R`` (``aligned``). The
            translation does not enter. A state whose rotation error is not a right rotation
            vector (Euler angles, SE(2)'s heading) chains its own d(dtheta)/d(state).
Every Jacobian is checked against central finite differences in tests/test_tags.py.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry
from camloc.measurement import TAG_ROTATION


def prediction(R_world_robot: np.ndarray, R_robot_camera: np.ndarray, R_world_tag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted orientations (M, 3, 3) of tags (M, 3, 3) in the camera frame, and H_R (M, 3, 3):
    ``R_pred(R Exp(dtheta)) = R_pred Exp(H_R dtheta)`` for the robot's right rotation perturbation.
    The robot's rotation and the camera's mount: one (3, 3) each, or (M, 3, 3) a tag each."""
    R_pred = np.swapaxes(R_robot_camera, -1, -2) @ np.swapaxes(R_world_robot, -1, -2) @ R_world_tag
    H_R = -np.swapaxes(R_world_tag, -1, -2) @ R_world_robot
    return R_pred, H_R


def residual(R_meas: np.ndarray, R_pred: np.ndarray) -> np.ndarray:
    """e = Log(R_pred^-1 R_meas), (M, 3)."""
    return geometry.so3_log(np.swapaxes(R_pred, -1, -2) @ R_meas)


def smoother_residual(R_meas: np.ndarray, R_pred: np.ndarray, H_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smoother's factor of a tag's orientation: ``r = Log(R_meas^T R_pred)`` (M, 3) (the
    filter's residual e, negated: ``-n`` at the truth, of the same covariance) and its Jacobian
    (M, 3, 3) for the robot's right rotation perturbation: ``R_pred -> R_pred Exp(H_R dtheta)``
    gives ``Log(Exp(r) Exp(H_R dtheta)) = r + Jr^-1(r) H_R dtheta`` (Jr the right Jacobian)."""
    r = geometry.so3_log(np.swapaxes(R_meas, -1, -2) @ R_pred)
    return r, geometry.so3_right_jacobian_inverse(r) @ H_R


def aligned(z: np.ndarray, R_pred: np.ndarray, H_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The prediction (M, 3) and Jacobian (M, 3, n) of measurements z = Log(R_meas) (M, 3) in the
    filter's ``z - z_hat`` form: ``z_hat = z - e`` (so that the innovation is the residual e) and
    ``Jl^-1(e) H_R`` (H_R (M, 3, n): R_pred's right perturbation per state error)."""
    e = residual(geometry.so3_exp(z), R_pred)
    return z - e, geometry.so3_right_jacobian_inverse(-e) @ H_R


def association_rows(obs_kind: np.ndarray) -> np.ndarray:
    """The observations (R,) that are a row of ``associations.csv``, of a dataset's kinds (K,):
    every one but a tag's orientation, whose tag is its position's row (one row a tag)."""
    return np.flatnonzero(np.asarray(obs_kind) != TAG_ROTATION)


def observation_landmarks(landmark: np.ndarray, obs_kind: np.ndarray, obs_partner: np.ndarray, *, orientations: bool) -> np.ndarray:
    """Each observation's chosen landmark (K,) from the rows of ``associations.csv`` (R,: their
    ``landmark``, ``association_rows``): a tag's orientation gets its position's, or none
    (``UNASSOCIATED``) with ``orientations=False`` (a tag's position alone)."""
    from camloc.results import UNASSOCIATED

    out = np.full(np.shape(obs_kind), UNASSOCIATED, dtype=np.int64)
    out[association_rows(obs_kind)] = landmark
    if orientations:
        rotation = np.flatnonzero(np.asarray(obs_kind) == TAG_ROTATION)
        out[rotation] = out[obs_partner[rotation]]
    return out


def row_distances(mahalanobis: np.ndarray, obs_kind: np.ndarray, obs_partner: np.ndarray) -> np.ndarray:
    """The Mahalanobis distance (R,) of each row of ``associations.csv`` from each observation's
    (K,): a tag's, ``sqrt(d_position^2 + d_orientation^2)`` where its orientation joined the
    update (the two halves' innovations taken as independent), its position's otherwise."""
    d = np.array(mahalanobis, dtype=float)
    rotation = np.flatnonzero(np.asarray(obs_kind) == TAG_ROTATION)
    joined = rotation[np.isfinite(d[rotation])]
    d[obs_partner[joined]] = np.hypot(d[obs_partner[joined]], d[joined])
    return d[association_rows(obs_kind)]


def landmark_headings(heading: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Each landmark's heading in the plane (L,), radians: a marker's own (``heading``), a tag's
    yaw (the direction of its x axis, from its orientation ``quat_xyzw`` (L, 4)), NaN for the
    others (points: NaN in both)."""
    out = np.array(heading, dtype=float)
    tag = np.isfinite(quat_xyzw[:, 0]) & np.isnan(out)
    if np.any(tag):
        R = geometry.quat_to_matrix(quat_xyzw[tag])
        out[tag] = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return geometry.wrap_angle(out)  # a file's psi may be any angle
