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


def prediction(R_world_robot: np.ndarray, R_robot_camera: np.ndarray, R_world_tag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted orientations (M, 3, 3) of tags (M, 3, 3) in the camera frame, and H_R (M, 3, 3):
    ``R_pred(R Exp(dtheta)) = R_pred Exp(H_R dtheta)`` for the robot's right rotation perturbation."""
    R_pred = R_robot_camera.T @ R_world_robot.T @ R_world_tag
    H_R = -np.swapaxes(R_world_tag, -1, -2) @ R_world_robot
    return R_pred, H_R


def residual(R_meas: np.ndarray, R_pred: np.ndarray) -> np.ndarray:
    """e = Log(R_pred^-1 R_meas), (M, 3)."""
    return geometry.so3_log(np.swapaxes(R_pred, -1, -2) @ R_meas)


def aligned(z: np.ndarray, R_pred: np.ndarray, H_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The prediction (M, 3) and Jacobian (M, 3, n) of measurements z = Log(R_meas) (M, 3) in the
    filter's ``z - z_hat`` form: ``z_hat = z - e`` (so that the innovation is the residual e) and
    ``Jl^-1(e) H_R`` (H_R (M, 3, n): R_pred's right perturbation per state error)."""
    e = residual(geometry.so3_exp(z), R_pred)
    return z - e, geometry.so3_right_jacobian_inverse(-e) @ H_R


def position_pairs_only(run, dataset):
    """``run`` (a ``RunResult``) with the pairs of its tags' orientation observations left out
    (``measurement.TAG_ROTATION``): what the smoothers, which model a tag's position only, take."""
    import dataclasses

    from camloc.measurement import TAG_ROTATION
    from camloc.results import UNASSOCIATED

    rotation = np.asarray(dataset.obs_kind) == TAG_ROTATION
    if not np.any(rotation) or len(run.associations.landmark) != rotation.size:
        return run
    landmark = np.where(rotation, UNASSOCIATED, run.associations.landmark)
    return dataclasses.replace(run, associations=dataclasses.replace(run.associations, landmark=landmark))
