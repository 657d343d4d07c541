"""Simulated tags (``camloc simulate --tag-sigma-deg``): a 3-D world whose landmarks are tags
(AprilTags) with an orientation, each detection measuring the tag's orientation in the camera as
well as its position (``EDGE_PROJECT_TAG``). Pure: returns a ``Dataset``, does no I/O.

Model card
----------
Tags        every landmark of the world ``camloc.simulate`` makes, given an orientation uniform over
            SO(3) (a tag's visibility does not depend on it here: the camera model of
            ``camloc.simulate`` decides what is seen).
Orientation each depth or pixel detection of a map landmark (not clutter, not an outlier) gets its
            tag's orientation in the camera, ``R_meas = R_c^T R^T R_tag Exp(n)``, n ~ N(0, sigma^2 I)
            (``camloc.tags``), as the observation right after its position's (written as
            ``EDGE_PROJECT_TAG``, or ``EDGE_PROJECT_TAG_UV`` for a camera without depth).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from camloc import geometry, measurement, tags
from camloc.dataset import LANDMARK_TAG, Dataset
from camloc.g2o import observation_cov_from_info
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.simulate_map import edit_map, edits_map, without_map_edits


# the kinds of camera measurement a tag's record carries with its orientation (camloc.g2o): a
# disparity camera's detections of a tag keep their position alone
TAG_POSITION_KINDS = (measurement.DEPTH, measurement.PIXEL)


def simulate_tags(config: SimulationConfig, *, seed: int, sigma_rad: float) -> Dataset:
    """``camloc.simulate``'s world of ``config`` with every landmark a tag and every detection of
    one (outliers aside) also measuring its orientation with noise ``sigma_rad`` (radians, > 0).
    The map is edited (``camloc.simulate_map``) once the whole world of tags is made."""
    if not sigma_rad > 0.0:
        raise ValueError(f"a tag's orientation noise must be > 0 rad, got {sigma_rad}")
    if edits_map(config):
        return edit_map(simulate_tags(without_map_edits(config), seed=seed, sigma_rad=sigma_rad), config, seed=seed).dataset
    simulation = simulate_labelled(config, seed=seed)
    dataset = simulation.dataset
    rng = np.random.default_rng([seed, 37])
    tag_quat = Rotation.random(len(dataset.landmark_ids), random_state=rng).as_quat()
    # a depth camera's detection is an EDGE_PROJECT_TAG, a pixel-only camera's an EDGE_PROJECT_TAG_UV
    rows = np.flatnonzero(~simulation.is_clutter & ~simulation.is_outlier & np.isin(dataset.obs_kind, TAG_POSITION_KINDS))
    return _with_orientations(dataset, rows, _measured(dataset, rows, tag_quat, rng, sigma_rad), sigma_rad, tag_quat)


def planar_tags(dataset: Dataset, *, seed: int, sigma_rad: float) -> Dataset:
    """A planar robot's cameras seeing tags: a world of ``camloc.simulate_planar`` with cameras
    (``dataset``) with every camera landmark a tag (orientations drawn from ``seed``) and every
    camera detection of one measuring its orientation too (the planar simulator's cameras make no
    outliers; clutter has no tag)."""
    from camloc.dataset import LANDMARK_POINT3

    rng = np.random.default_rng([seed, 37])
    point = dataset.landmark_kind == LANDMARK_POINT3
    tag_quat = np.full((len(dataset.landmark_ids), 4), np.nan)
    tag_quat[point] = Rotation.random(int(np.count_nonzero(point)), random_state=rng).as_quat()
    mapped = np.isin(dataset.obs_true_landmark, dataset.landmark_ids[point])
    rows = np.flatnonzero(mapped & np.isin(dataset.obs_kind, TAG_POSITION_KINDS))
    kind = np.where(point, LANDMARK_TAG, dataset.landmark_kind)
    tagged = _with_orientations(dataset, rows, _measured(dataset, rows, tag_quat, rng, sigma_rad), sigma_rad, tag_quat)
    return dataclasses.replace(tagged, landmark_kind=kind, tag_counts={**dataset.tag_counts, "VERTEX_TAG": int(np.count_nonzero(point))})


def _measured(dataset: Dataset, rows: np.ndarray, tag_quat: np.ndarray, rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    """The measured orientations (R, 3) (rotation vectors) of the tags of observations ``rows``
    (R,) in their cameras at the true poses, with noise ``sigma_rad`` per axis."""
    T_truth = dataset.T_world_truth
    row_of = {int(i): n for n, i in enumerate(dataset.landmark_ids.tolist())}
    z = np.zeros((rows.size, 3))
    for n, o in enumerate(rows.tolist()):
        camera = dataset.cameras[int(dataset.obs_camera[o])]
        R_pred, _ = tags.prediction(T_truth[dataset.obs_pose_index[o], :3, :3], camera.T_robot_camera[:3, :3],
                                    geometry.quat_to_matrix(tag_quat[row_of[int(dataset.obs_true_landmark[o])]])[None])
        z[n] = geometry.so3_log(R_pred[0] @ geometry.so3_exp(rng.normal(scale=sigma_rad, size=3)))
    return z


def _with_orientations(dataset: Dataset, rows: np.ndarray, z: np.ndarray, sigma_rad: float, tag_quat: np.ndarray) -> Dataset:
    """``dataset`` with an orientation observation (z (R, 3)) after each of its observations ``rows``."""
    K = dataset.num_observations
    # the new order: every observation, and after each of rows its orientation (index K + n)
    after = np.full(K, -1, np.int64)
    after[rows] = K + np.arange(rows.size)
    order = np.concatenate([[o, after[o]] if after[o] >= 0 else [o] for o in range(K)]).astype(np.int64) if K else np.zeros(0, np.int64)
    info = np.broadcast_to(np.eye(3) / sigma_rad**2, (rows.size, 3, 3))

    def extended(old: np.ndarray, new: np.ndarray) -> np.ndarray:
        return np.concatenate([old, new])[order]

    kinds = extended(dataset.obs_kind, np.full(rows.size, measurement.TAG_ROTATION, np.int64))
    obs_info = extended(dataset.obs_info, info)
    return dataclasses.replace(
        dataset,
        source=dataset.source.replace("simulate(", f"simulate(tags with orientation sigma {np.degrees(sigma_rad):g} deg, ", 1),
        obs_pose_index=extended(dataset.obs_pose_index, dataset.obs_pose_index[rows]),
        obs_camera=extended(dataset.obs_camera, dataset.obs_camera[rows]),
        obs_z=extended(dataset.obs_z, z), obs_info=obs_info, obs_cov=observation_cov_from_info(obs_info),
        obs_true_landmark=extended(dataset.obs_true_landmark, dataset.obs_true_landmark[rows]), obs_kind=kinds,
        obs_partner=np.where(kinds == measurement.TAG_ROTATION, np.arange(order.size) - 1, -1),
        landmark_kind=np.full(len(dataset.landmark_ids), LANDMARK_TAG, np.int64), landmark_quat_xyzw=tag_quat,
        tag_counts={**dataset.tag_counts, "VERTEX_TAG": len(dataset.landmark_ids)},
    )


def without_orientations(dataset: Dataset) -> Dataset:
    """``dataset`` with its tags' orientation observations left out (positions alone), for comparison."""
    keep = np.flatnonzero(dataset.obs_kind != measurement.TAG_ROTATION)
    return dataclasses.replace(
        dataset, obs_pose_index=dataset.obs_pose_index[keep], obs_camera=dataset.obs_camera[keep], obs_z=dataset.obs_z[keep],
        obs_info=dataset.obs_info[keep], obs_cov=dataset.obs_cov[keep], obs_true_landmark=dataset.obs_true_landmark[keep],
        obs_kind=dataset.obs_kind[keep], obs_partner=np.full(keep.size, -1, np.int64),
    )


def with_twin_tags(dataset: Dataset, *, offset_m: float, turn_deg: float, seed: int) -> Dataset:
    """``dataset`` (a tag world) with a twin beside every tag: ``offset_m`` away in a random
    direction, its orientation the tag's turned by ``turn_deg`` about a random axis, and never seen
    (the observations name the originals). A world where a tag's position alone cannot tell it
    from its twin (an offset within the position's noise) and its orientation can."""
    rng = np.random.default_rng([seed, 3737])
    n = len(dataset.landmark_ids)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    axis = rng.normal(size=(n, 3))
    turn = np.radians(turn_deg) * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    twin_quat = geometry.matrix_to_quat(geometry.quat_to_matrix(dataset.landmark_quat_xyzw) @ geometry.so3_exp(turn))
    return dataclasses.replace(
        dataset,
        landmark_ids=np.concatenate([dataset.landmark_ids, dataset.landmark_ids.max() + 1 + np.arange(n)]),
        landmark_xyz=np.concatenate([dataset.landmark_xyz, dataset.landmark_xyz + offset_m * direction]),
        landmark_kind=np.concatenate([dataset.landmark_kind, dataset.landmark_kind]),
        landmark_heading=np.concatenate([dataset.landmark_heading, dataset.landmark_heading]),
        landmark_quat_xyzw=np.concatenate([dataset.landmark_quat_xyzw, twin_quat]),
        tag_counts={**dataset.tag_counts, "VERTEX_TAG": 2 * n},
    )
