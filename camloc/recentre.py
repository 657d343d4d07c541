"""Localizing far from the world's origin: a dataset whose start pose is more than
``FAR_FROM_ORIGIN_M`` from it (a map in UTM metres, 10^5-10^6) is localized in a frame whose origin
is at its start position, and the result is moved back.

Why: the mapping localizer's invariant error puts each landmark's world position in its Jacobians
(``hat(l)``), where terms that cancel in exact arithmetic leave a rounding of about ``|l|^2 eps``.
Measured on a 60-pose world translated by (D, 2D, 0) (2026-12-05, branch fuzz-audit): at D = 10^4 m
the mapping pass's position error changed in its fifth digit, at 10^5 m (``--map exact`` with a map
lacking landmarks) and 5 x 10^6 m (``--map none``) its innovation covariance stopped being positive
definite and the run failed. A translation changes nothing else a run reads: odometry, observations
and their information are relative. Near the origin nothing is moved, so a run there is unchanged
to the bit.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from camloc.dataset import Dataset
from camloc.results import RunResult

FAR_FROM_ORIGIN_M = 1000.0


def far_origin_offset(dataset: Dataset) -> np.ndarray | None:
    """The translation (3,) to take off ``dataset``'s world coordinates: its start position rounded
    to the metre (z kept for a planar robot, whose poses and landmarks lie at z = 0), or None when
    the start is within ``FAR_FROM_ORIGIN_M`` of the origin on every axis."""
    start = np.asarray(dataset.start_xyz, dtype=float)
    if np.max(np.abs(start)) <= FAR_FROM_ORIGIN_M:
        return None
    offset = np.round(start)
    if dataset.planar:
        offset[2] = 0.0
    return offset


def translated(dataset: Dataset, offset: np.ndarray) -> Dataset:
    """``dataset`` in the frame whose origin is at ``offset`` (3,) of its world frame."""
    truth = None if dataset.truth_xyz is None else dataset.truth_xyz - offset
    return replace(dataset, landmark_xyz=dataset.landmark_xyz - offset, start_xyz=dataset.start_xyz - offset, truth_xyz=truth)


def moved_back(result: RunResult, dataset: Dataset, offset: np.ndarray) -> RunResult:
    """A run of ``translated(dataset, offset)`` in ``dataset``'s own world frame: the estimated and
    odometry positions and the filter's stored position (x, y, z; a planar state's x, y) plus
    ``offset``, the given map and the truth the dataset's own arrays."""
    state = np.array(result.filter_state, dtype=float, copy=True)
    # every stored state starts with the position (camloc.filters): (x, y, theta) of the SE(2) filter
    columns = 2 if state.shape[1] == 3 else 3
    state[:, :columns] += offset[:columns]
    landmark_map = result.landmark_map
    if landmark_map is not None:
        landmark_map = replace(landmark_map, xyz=landmark_map.xyz + offset)
    return replace(result, estimate_xyz=result.estimate_xyz + offset, odometry_xyz=result.odometry_xyz + offset,
                   filter_state=state, truth_xyz=dataset.truth_xyz, map_landmark_xyz=dataset.landmark_xyz,
                   landmark_map=landmark_map,
                   smoothed_xyz=None if result.smoothed_xyz is None else result.smoothed_xyz + offset)
