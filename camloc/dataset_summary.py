"""What a dataset holds, in numbers: the content of ``camloc info``. Pure: no I/O, no printing.

``summarize_dataset`` returns plain Python types (dicts, lists, ints, floats, None) with stable
snake_case keys, so the CLI can print it as JSON as is and render it as tables.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from camloc import geometry, measurement
from camloc.dataset import Dataset
from camloc.g2o import KNOWN_TAGS


def summarize_dataset(dataset: Dataset) -> dict[str, Any]:
    """Counts, cameras, trajectory, noise levels and observation coverage of a dataset.

    Returns
    -------
    A dict with keys:

    - ``dataset``: the dataset's source (its path), the key every command's JSON uses for it.
    - ``counts``: poses, odometry_edges, landmarks, observations, cameras.
    - ``tag_counts``: records per tag as in the file; ``unknown_tags``: the ones camloc skipped.
    - ``cameras``: per camera id, ``translation_m`` (3) and ``rotation_rpy_deg`` (3) of the mount
      in the robot frame (roll, pitch, yaw as in ``camloc.geometry``), and fx, fy, cx, cy.
    - ``trajectory``: ``source`` ("ground_truth", or "odometry" composed from the start pose),
      ``length_m`` (sum of step lengths), ``extent_min_m``, ``extent_max_m``, ``size_m`` (3 each,
      world frame bounding box of the positions).
    - ``odometry_noise``: ``sigma_translation_m`` and ``sigma_rotation_deg`` (x, y, z), the median
      over edges of the standard deviations in ``odom_cov`` (rotation-vector parametrization);
      None without edges.
    - ``observation_noise``: ``sigma_u``, ``sigma_v``, ``sigma_depth``, medians over observations
      of the standard deviations in ``obs_cov`` (depth: over depth observations); None without.
    - ``observation_kinds``: observations of each measurement kind (``camloc.measurement``):
      ``depth``, ``pixel``, ``disparity``, ``point2``, ``marker``.
    - ``robot``: ``planar`` (``VERTEX_SE2`` / ``EDGE_SE2``) or ``3d``.
    - ``observations_per_pose``: ``min``, ``median``, ``max``, ``poses_without``.
    - ``landmarks_never_observed``: ``count`` and ``ids`` of map landmarks no observation's true
      id names.
    - ``unmapped_observations``: ``count`` of observations whose true id is not in the map
      (clutter) and the distinct ``ids``.
    - ``warnings``: the reader's warnings.
    """
    return {
        "dataset": dataset.source,
        "counts": {
            "poses": dataset.num_poses,
            "odometry_edges": int(dataset.odom_translation.shape[0]),
            "landmarks": int(dataset.landmark_ids.shape[0]),
            "observations": dataset.num_observations,
            "cameras": len(dataset.cameras),
        },
        "tag_counts": dict(dataset.tag_counts),
        "unknown_tags": [tag for tag in dataset.tag_counts if tag not in KNOWN_TAGS],
        "cameras": [_camera_summary(camera) for camera in dataset.cameras.values()],
        "trajectory": _trajectory_summary(dataset),
        "odometry_noise": _odometry_noise(dataset.odom_cov),
        "observation_noise": _observation_noise(dataset.obs_cov, dataset.obs_kind),
        "observation_kinds": {kind.name: int(np.count_nonzero(dataset.obs_kind == kind.code))
                              for kind in measurement.KINDS.values()},
        "robot": "planar" if dataset.planar else "3d",
        "observations_per_pose": _observations_per_pose(dataset),
        "landmarks_never_observed": _ids_summary(np.setdiff1d(dataset.landmark_ids, dataset.obs_true_landmark)),
        "unmapped_observations": _unmapped_observations(dataset),
        "warnings": list(dataset.warnings),
    }


def odometry_positions(dataset: Dataset) -> np.ndarray:
    """(N, 3) world positions from the start pose and the odometry increments alone."""
    T = dataset.T_world_start
    T_increments = dataset.T_odometry
    positions = np.empty((dataset.num_poses, 3))
    positions[0] = T[:3, 3]
    for k, T_k_next in enumerate(T_increments, start=1):
        T = T @ T_k_next  # T_world_{k} = T_world_{k-1} T_{k-1}_{k}
        positions[k] = T[:3, 3]
    return positions


def _camera_summary(camera) -> dict[str, Any]:
    return {
        "id": camera.id,
        "translation_m": camera.translation.tolist(),
        "rotation_rpy_deg": np.degrees(geometry.quat_to_euler(camera.quat_xyzw)).tolist(),
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
    }


def _trajectory_summary(dataset: Dataset) -> dict[str, Any]:
    if dataset.truth_xyz is not None:
        source, positions = "ground_truth", dataset.truth_xyz
    else:
        source, positions = "odometry", odometry_positions(dataset)
    low, high = positions.min(axis=0), positions.max(axis=0)
    return {
        "source": source,
        "length_m": float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()),
        "extent_min_m": low.tolist(),
        "extent_max_m": high.tolist(),
        "size_m": (high - low).tolist(),
    }


def _median_sigmas(cov: np.ndarray) -> np.ndarray | None:
    """Median over the leading axis of the per-component standard deviations, or None if empty."""
    if cov.shape[0] == 0:
        return None
    return np.median(np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)), axis=0)


def _odometry_noise(odom_cov: np.ndarray) -> dict[str, Any]:
    sigmas = _median_sigmas(odom_cov)
    if sigmas is None:
        return {"sigma_translation_m": None, "sigma_rotation_deg": None}
    return {"sigma_translation_m": sigmas[:3].tolist(), "sigma_rotation_deg": np.degrees(sigmas[3:]).tolist()}


def _observation_noise(obs_cov: np.ndarray, kinds: np.ndarray) -> dict[str, Any]:
    """Median sigmas of u, v (every observation) and of depth (depth observations only: a pixel's
    third row is inert, a disparity's is an inverse depth)."""
    sigmas = _median_sigmas(obs_cov)
    values = [None, None, None] if sigmas is None else sigmas.tolist()
    depth = _median_sigmas(obs_cov[kinds == measurement.DEPTH])
    values[2] = None if depth is None else float(depth[2])
    return dict(zip(("sigma_u", "sigma_v", "sigma_depth"), values))


def _observations_per_pose(dataset: Dataset) -> dict[str, Any]:
    per_pose = np.bincount(dataset.obs_pose_index, minlength=dataset.num_poses)
    return {
        "min": int(per_pose.min()),
        "median": float(np.median(per_pose)),
        "max": int(per_pose.max()),
        "poses_without": int(np.count_nonzero(per_pose == 0)),
    }


def _ids_summary(ids: np.ndarray) -> dict[str, Any]:
    return {"count": int(ids.size), "ids": ids.tolist()}


def _unmapped_observations(dataset: Dataset) -> dict[str, Any]:
    unmapped = ~np.isin(dataset.obs_true_landmark, dataset.landmark_ids)
    return {"count": int(np.count_nonzero(unmapped)), "ids": np.unique(dataset.obs_true_landmark[unmapped]).tolist()}
