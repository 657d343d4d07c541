"""The sensors of a dataset: a camera on the robot and the kind of measurement its observations
are (``camloc.measurement``). A camera whose file gives observations of two kinds (some with depth,
some without) is two sensors; both engines group a pose's observations by sensor."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from camloc import measurement

if TYPE_CHECKING:
    from camloc.dataset import Dataset


@dataclass(frozen=True)
class CameraModel:
    """A sensor as the filter's measurement model takes it: a camera (``T_robot_camera`` (4, 4),
    ``intrinsics`` (fx, fy, cx, cy)) and the kind of measurement its observations are
    (``camloc.measurement``). A camera whose file gives observations of two kinds is two sensors."""

    T_robot_camera: np.ndarray
    intrinsics: tuple[float, float, float, float]
    kind: int = measurement.DEPTH
    camera_id: int = 0

    @property
    def dof(self) -> int:
        return measurement.KINDS[self.kind].dof


def sensors_of(dataset: "Dataset") -> tuple[dict[int, CameraModel], np.ndarray]:
    """The dataset's sensors, (camera, measurement kind) pairs, indexed 0.. in the order of
    (camera id, kind), and each observation's sensor (K,) int64. Every camera is a sensor (of
    depth, when it made no observation) so that the table is never empty."""
    kinds = len(measurement.KINDS)
    code = np.asarray(dataset.obs_camera, np.int64) * kinds + np.asarray(dataset.obs_kind, np.int64)
    observed, obs_sensor = np.unique(code, return_inverse=True)  # sorted by (camera id, kind)
    keys = [(int(c) // kinds, int(c) % kinds) for c in observed]  # floor division: the robot frame's -1 too
    seen = {c for c, _ in keys}
    unobserved = [(int(c), measurement.DEPTH) for c in sorted(dataset.cameras) if int(c) not in seen]
    ordered = sorted(keys + unobserved)
    sensors = {}
    for index, (camera_id, kind) in enumerate(ordered):
        if camera_id == measurement.ROBOT_FRAME_SENSOR:  # a planar robot's own sensor: in the robot frame
            sensors[index] = CameraModel(np.eye(4), (1.0, 1.0, 0.0, 0.0), kind, camera_id)
            continue
        camera = dataset.cameras[camera_id]
        sensors[index] = CameraModel(camera.T_robot_camera, (camera.fx, camera.fy, camera.cx, camera.cy), kind, camera_id)
    # rows of the observed sensors among all of them (the unobserved cameras interleave by id)
    row_of = np.array([ordered.index(key) for key in keys], dtype=np.int64)
    obs_sensor = row_of[obs_sensor].astype(np.int64) if code.size else np.zeros(0, np.int64)
    return sensors, obs_sensor


def intrinsics_by_row(cameras: list[CameraModel], sizes: list[int]) -> tuple:
    """fx, fy, cx, cy as (M,) arrays, a camera per row: the first ``sizes[0]`` rows
    ``cameras[0]``'s, the next ``sizes[1]`` the second's, ... (the rows of a batch of several
    cameras, ``models.observe_rig``); the four scalars where the cameras share them (a rig of one
    model: each row's arithmetic is the same, without the arrays)."""
    first = cameras[0].intrinsics
    if all(c.intrinsics == first for c in cameras):
        return first
    return tuple(np.repeat(np.array([c.intrinsics for c in cameras], dtype=float), sizes, axis=0).T)


def observed_as_rig(filter, kind: int) -> bool:
    """Whether ``filter`` observes several cameras of measurement ``kind`` in one batch
    (``observe_rig``; a planar filter does not): a camera's kind, not a tag's orientation."""
    return hasattr(filter, "observe_rig") and kind in measurement.CAMERA_KINDS and kind != measurement.TAG_ROTATION
