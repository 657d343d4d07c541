"""Data association between a pose's observations and the map's landmarks: pure functions of arrays.

Pipeline for one camera at one pose:
1. ``candidate_indices``: map landmarks in front of the camera within the depth range, found through
   a k-d tree of the map (cost independent of the map's size beyond the local density);
2. ``pair_statistics``: for every (observation, candidate) pair, the squared Mahalanobis distance of
   the innovation and the pair's negative log-likelihood ``d^2 + ln det S``;
3. ``best_friends``: keep a pair only when each is the other's cheapest, the pair passes the chi^2
   gate, and no rival comes within ``margin`` of it ("lonely best friends").

Why ``d^2 + ln det S`` and not ``d^2``: plain Mahalanobis distance favours the landmarks whose
prediction is most uncertain (far, large S) because their d^2 is small for everything; the log
determinant charges for that spread, making the cost a proper likelihood comparison.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def candidate_indices(
    tree: cKDTree,
    landmark_xyz: np.ndarray,
    T_world_camera: np.ndarray,
    *,
    min_depth: float,
    max_depth: float,
    max_angle_rad: float,
) -> np.ndarray:
    """Indices (m,) of landmarks that may be visible from a camera.

    Parameters
    ----------
    tree : k-d tree over ``landmark_xyz`` (L, 3), world frame.
    T_world_camera : (4, 4) the camera's pose.
    min_depth, max_depth : range of depth (camera z) in metres.
    max_angle_rad : largest angle between the optical axis and a visible landmark's direction.
    """
    centre = T_world_camera[:3, 3]
    radius = max_depth / max(np.cos(max_angle_rad), 1e-3)
    near = np.asarray(tree.query_ball_point(centre, radius), dtype=np.int64)
    if near.size == 0:
        return near
    p_camera = (landmark_xyz[near] - centre) @ T_world_camera[:3, :3]
    depth = p_camera[:, 2]
    off_axis = np.hypot(p_camera[:, 0], p_camera[:, 1])
    visible = (depth > min_depth) & (depth < max_depth) & (off_axis <= depth * np.tan(max_angle_rad))
    return near[visible]


def pair_statistics(
    z: np.ndarray, R_obs: np.ndarray, z_hat: np.ndarray, HPH: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Squared Mahalanobis distance and negative log-likelihood of every (observation, candidate).

    Parameters
    ----------
    z : (n, 3) measurements; R_obs : (n, 3, 3) their covariances.
    z_hat : (m, 3) predicted measurements; HPH : (m, 3, 3) ``H P H'`` of each prediction.

    Returns
    -------
    d2 : (n, m) ``y' S^-1 y`` with ``S = H P H' + R`` and ``y = z - z_hat``.
    nll : (n, m) ``d2 + ln det S``.
    """
    S = HPH[None, :, :, :] + R_obs[:, None, :, :]
    y = z[:, None, :] - z_hat[None, :, :]
    L = np.linalg.cholesky(S)
    w = np.linalg.solve(L, y[..., None])[..., 0]  # L w = y, so |w|^2 = y' S^-1 y
    d2 = np.einsum("...i,...i->...", w, w)
    log_det = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
    return d2, d2 + log_det


def best_friends(
    cost: np.ndarray, d2: np.ndarray, *, gate: float, margin: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual-best pairs that pass the gate and have no close rival.

    Parameters
    ----------
    cost : (n, m) pair costs (lower is better); d2 : (n, m) squared Mahalanobis distances.
    gate : accept only pairs with ``d2 <= gate`` (a chi^2 quantile).
    margin : reject a pair when a rival in its row or column costs less than ``cost + margin``.

    Returns
    -------
    obs_index, cand_index : (p,) int arrays of accepted pairs.
    gap : (p,) how much more the closest rival of each pair costs (inf when there is none): the
        pair's confidence.
    """
    n, m = cost.shape
    if n == 0 or m == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0)
    rows = np.arange(n)
    best_cand = np.argmin(cost, axis=1)
    best_obs = np.argmin(cost, axis=0)
    best_cost = cost[rows, best_cand]
    mutual = best_obs[best_cand] == rows
    gated = d2[rows, best_cand] <= gate
    gap = np.minimum(_runner_up(cost, axis=1), _runner_up(cost, axis=0)[best_cand]) - best_cost
    keep = mutual & gated & (gap >= margin)
    return rows[keep], best_cand[keep], gap[keep]


def _runner_up(cost: np.ndarray, *, axis: int) -> np.ndarray:
    """Second smallest value along an axis (inf when there is only one)."""
    if cost.shape[axis] < 2:
        return np.full(cost.shape[1 - axis], np.inf)
    return np.partition(cost, 1, axis=axis).take(1, axis=axis)


def clutter_null_cost(uvd: np.ndarray, cov: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Cost (K,) of explaining each observation as clutter rather than as a landmark.

    Clutter is taken as uniform over the box the camera's measurements span, of volume V, so in
    the units of a pair's cost ``d^2 + ln det S - ln det R`` (twice the negative log-likelihood,
    less ``ln det 2 pi R``) an unassigned observation costs ``2 ln V - ln det(2 pi R)``.

    Parameters
    ----------
    uvd : (K, 3) measurements; cov : (K, 3, 3) their covariances; camera : (K,) camera ids.
    """
    cost = np.zeros(uvd.shape[0])
    for camera_id in np.unique(camera):
        mine = camera == camera_id
        span = np.ptp(uvd[mine], axis=0)
        sigma = np.sqrt(np.median(np.diagonal(cov[mine], axis1=1, axis2=2), axis=0))
        log_volume = np.log(np.maximum(span, 6.0 * sigma)).sum()  # a few sigmas at least
        cost[mine] = 2.0 * log_volume - np.linalg.slogdet(2.0 * np.pi * cov[mine])[1]
    return cost
