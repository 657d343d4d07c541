"""Reading and writing g2o camera-localization files (see FORMAT.md), and the one place where a
file's information matrices become covariances.
"""

from __future__ import annotations

import numpy as np

# g2o's EDGE_SE3:QUAT error is (translation, vector part of the error quaternion). A small rotation
# vector theta has quaternion vector part theta/2, so d(rotvec)/d(qvec) = 2 on the rotation block.
_QVEC_TO_ROTVEC = np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


def odometry_cov_from_info(info: np.ndarray) -> np.ndarray:
    """Covariance (..., 6, 6) of (translation, rotation vector) from g2o information (..., 6, 6).

    ``cov = J info^-1 J^T`` with ``J = diag(1, 1, 1, 2, 2, 2)``: the rotation block is 4x, the
    cross blocks 2x the inverse of the file's information.
    """
    cov_g2o = np.linalg.inv(info)
    cov = _QVEC_TO_ROTVEC @ cov_g2o @ _QVEC_TO_ROTVEC
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def odometry_info_from_cov(cov: np.ndarray) -> np.ndarray:
    """Inverse of ``odometry_cov_from_info``: g2o information (..., 6, 6) for a covariance of
    (translation, rotation vector)."""
    cov_g2o = np.linalg.inv(_QVEC_TO_ROTVEC) @ cov @ np.linalg.inv(_QVEC_TO_ROTVEC)
    info = np.linalg.inv(cov_g2o)
    return 0.5 * (info + np.swapaxes(info, -1, -2))


def observation_cov_from_info(info: np.ndarray) -> np.ndarray:
    """Covariance (..., 3, 3) of (u, v, depth) from the file's information (..., 3, 3)."""
    cov = np.linalg.inv(info)
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))
