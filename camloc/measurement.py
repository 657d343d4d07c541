"""The camera measurement models, defined once: what each kind of observation measures of a
camera-frame point, its Jacobian, its inverse where one exists, and how its rows are laid out.

Kinds (``KINDS``; the g2o record that carries each in parentheses)
-------------------------------------------------------------------
depth      z = (u, v, depth)       3 rows   (``EDGE_PROJECT_DEPTH``)
pixel      z = (u, v)              2 rows   (``EDGE_PROJECT_UV``: a monocular camera, a ray)
disparity  z = (u, v, 1 / depth)   3 rows   (``EDGE_PROJECT_DISPARITY``, g2o's stereo form)

with ``u = fx x / z + cx`` and ``v = fy y / z + cy`` of the camera-frame point p = (x, y, z).

Planar kinds, measured in the robot frame of a planar robot (no camera: ``frame == "robot"``;
their model is ``camloc.planar``'s, the SE(2) filter's only)
--------------------------------------------------------------------------------------------
point2     z = (x, y)              2 rows   (``EDGE_SE2_XY``: a point landmark in the robot frame)
marker     z = (x, y, psi)         3 rows   (``EDGE_SE2_MARKER``: a marker's planar pose in the
                                             robot frame; psi an angle, residuals wrapped)

A tag's orientation (``frame == "tag"``; its model is ``camloc.tags``', the numpy engine's only)
------------------------------------------------------------------------------------------------
tag_rotation  z = Log(R_tag/c)     3 rows   (the orientation half of ``EDGE_PROJECT_TAG``, whose
                                             position half is a depth measurement: the two are
                                             consecutive observations, ``Dataset.obs_partner``)

One layout for every kind: ``MAX_DIM`` rows
-------------------------------------------
Every measurement is stored in ``MAX_DIM`` (3) rows. A kind of fewer rows (pixel: 2) fills the
rest with an **inert** component: measured 0, predicted 0, a zero Jacobian row and unit variance,
uncorrelated with the others. Such a row adds nothing to any quantity the filter or the
association computes: its residual is 0, so it adds 0 to a Mahalanobis distance and to an
update's gradient; its Jacobian row is 0, so it adds no information; the innovation covariance
S = H P H' + R is block-diagonal in it with the unit block of R, so ``ln det S - ln det R`` is
that of the real rows. What differs between kinds is then only their degrees of freedom
(``dof``), which set the chi^2 gates, the NIS bounds and a clutter density's dimension. The
compiled kernels (fixed 3x3 blocks) and the numpy engine run every kind with one algorithm.
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import Optional

import numpy as np

MAX_DIM = 3

DEPTH, PIXEL, DISPARITY = 0, 1, 2
POINT2, MARKER = 3, 4
TAG_ROTATION = 5

# the sensor id of the planar kinds' observations, which no camera makes (they are in the robot frame)
ROBOT_FRAME_SENSOR = -1


@dataclass(frozen=True)
class MeasurementKind:
    """One kind of camera measurement: its code, name, g2o tag, rows and their names."""

    code: int
    name: str
    tag: str
    components: tuple[str, ...]
    frame: str = "camera"  # "camera": a camera's measurement; "robot": a planar robot's, in its own frame; "tag": a tag's orientation

    @property
    def dof(self) -> int:
        return len(self.components)

    @property
    def measures_range(self) -> bool:
        """Whether a single camera measurement places the landmark as a point (not a ray); the
        planar kinds, which have no camera, say False."""
        return self.frame == "camera" and self.dof == MAX_DIM


KINDS: dict[int, MeasurementKind] = {
    DEPTH: MeasurementKind(DEPTH, "depth", "EDGE_PROJECT_DEPTH", ("u", "v", "depth")),
    PIXEL: MeasurementKind(PIXEL, "pixel", "EDGE_PROJECT_UV", ("u", "v")),
    DISPARITY: MeasurementKind(DISPARITY, "disparity", "EDGE_PROJECT_DISPARITY", ("u", "v", "inverse_depth")),
    POINT2: MeasurementKind(POINT2, "point2", "EDGE_SE2_XY", ("x", "y"), "robot"),
    MARKER: MeasurementKind(MARKER, "marker", "EDGE_SE2_MARKER", ("x", "y", "psi"), "robot"),
    TAG_ROTATION: MeasurementKind(TAG_ROTATION, "tag_rotation", "EDGE_PROJECT_TAG", ("rx", "ry", "rz"), "tag"),
}
CAMERA_KINDS = tuple(code for code, kind in KINDS.items() if kind.frame == "camera")
PLANAR_KINDS = tuple(code for code, kind in KINDS.items() if kind.frame == "robot")
# the row of a kind's measurement that is an angle (its residual is wrapped), -1 for none
ANGLE_ROW = np.array([2 if code == MARKER else -1 for code in sorted(KINDS)], dtype=np.int64)
KIND_BY_NAME = {kind.name: kind for kind in KINDS.values()}
KIND_BY_TAG = {kind.tag: kind for kind in KINDS.values()}

# the dof of each code, for array lookups: DOF[obs_kind]
DOF = np.array([KINDS[code].dof for code in sorted(KINDS)], dtype=np.int64)


def dof_of(kinds: np.ndarray) -> np.ndarray:
    """Degrees of freedom (K,) of measurements of the given kind codes (K,)."""
    return DOF[np.asarray(kinds, dtype=np.int64)]


_MEASURES_RANGE = np.array([KINDS[code].measures_range for code in sorted(KINDS)])


def measures_range(kinds: np.ndarray) -> np.ndarray:
    """(K,) bool: whether each camera measurement of the given kinds (K,) places its landmark as a
    point (False for a pixel and for the planar kinds, which have no camera)."""
    return _MEASURES_RANGE[np.asarray(kinds, dtype=np.int64)]


def is_ray(kinds: np.ndarray) -> np.ndarray:
    """(K,) bool: which of the kinds (K,) are a camera's ray (a pixel: no range)."""
    return np.asarray(kinds, dtype=np.int64) == PIXEL


def is_planar(kinds: np.ndarray) -> np.ndarray:
    """(K,) bool: which of the kinds (K,) are measured in a planar robot's frame (no camera)."""
    return np.isin(np.asarray(kinds, dtype=np.int64), PLANAR_KINDS)


def in_front(T_world_camera: np.ndarray, kind: int, landmark_xyz: np.ndarray) -> np.ndarray:
    """(m,) bool: which landmarks (m, 3+) lie in front of a sensor of ``kind`` at T_world_camera
    (its camera-frame depth positive); a planar robot's own sensor sees all around it. The one
    numpy statement of the rule (``associators.AssociationScene.in_front_of``, the filter's MAP
    cost: ``stacked_update.PairMeasurement.feasible``); the kernels' is ``kernels.camera.in_front_of``."""
    if kind in PLANAR_KINDS:
        return np.ones(landmark_xyz.shape[0], dtype=bool)
    return (landmark_xyz[:, :3] - T_world_camera[:3, 3]) @ T_world_camera[:3, 2] > 0.0


def judged_as_point(kinds: np.ndarray) -> np.ndarray:
    """(K,) bool: which measurements association may also judge as the camera-frame point they
    back-project to (where a wide prior's linearization holds better), and the update may restart
    from: those of depth sensors. A pixel is a ray; a disparity's point is left out too (its
    inverse depth is nearly linear in the position's error already at range, and the compiled
    point arithmetic assumes a unit depth row)."""
    return np.asarray(kinds) == DEPTH


def observation_gates(kinds: np.ndarray, probability: float) -> np.ndarray:
    """(K,) the chi^2 gate of each observation of the given kinds (K,): the quantile that a
    right pair's d^2 exceeds with ``probability``, at the kind's degrees of freedom."""
    from camloc.tails import chi2_quantile

    by_dof = {dof: float(chi2_quantile(dof, probability)) for dof in set(DOF.tolist())}
    return np.array([by_dof[dof] for dof in DOF.tolist()])[np.asarray(kinds, dtype=np.int64)]


def project(p_camera: np.ndarray, intrinsics, kind) -> np.ndarray:
    """Camera-frame points (M, 3), in front of the camera, -> measurements (M, MAX_DIM) of
    ``kind`` (a code, or (M,) codes) in the padded layout. ``intrinsics``: fx, fy, cx, cy
    (scalars or (M,) arrays)."""
    fx, fy, cx, cy = intrinsics
    z = p_camera[:, 2]
    out = np.zeros((p_camera.shape[0], MAX_DIM))
    out[:, 0] = fx * p_camera[:, 0] / z + cx
    out[:, 1] = fy * p_camera[:, 1] / z + cy
    if isinstance(kind, (int, np.integer)):  # one camera's kind: no broadcast (the mapping filter's hot path)
        if kind == DEPTH:
            out[:, 2] = z
        elif kind == DISPARITY:
            out[:, 2] = 1.0 / z
        return out
    kind = np.broadcast_to(np.asarray(kind), z.shape)
    out[:, 2] = np.where(kind == DEPTH, z, np.where(kind == DISPARITY, 1.0 / z, 0.0))
    return out


def projection_jacobian(p_camera: np.ndarray, intrinsics, kind) -> np.ndarray:
    """d z / d p_camera, (M, MAX_DIM, 3), of ``project`` (the inert row of a pixel is 0)."""
    fx, fy = intrinsics[0], intrinsics[1]
    x, y, z = p_camera[:, 0], p_camera[:, 1], p_camera[:, 2]
    J = np.zeros((p_camera.shape[0], MAX_DIM, 3))
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * x / z**2
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * y / z**2
    if isinstance(kind, (int, np.integer)):  # one camera's kind: no broadcast
        if kind == DEPTH:
            J[:, 2, 2] = 1.0
        elif kind == DISPARITY:
            J[:, 2, 2] = -1.0 / z**2
        return J
    kind = np.broadcast_to(np.asarray(kind), z.shape)
    J[:, 2, 2] = np.where(kind == DEPTH, 1.0, np.where(kind == DISPARITY, -1.0 / z**2, 0.0))
    return J


def project_one(p_camera: np.ndarray, intrinsics, kind: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """``project`` and ``projection_jacobian`` of one point (3,) by a camera of scalar
    intrinsics and one kind, (1, MAX_DIM) and (1, MAX_DIM, 3), computed in Python floats: each
    entry the same IEEE operations in the same order as the array forms' (``z**2`` of an array
    is ``z * z``), so the same bits, at a fifth of their cost (a lone pair's update is the
    numpy beam's most frequent). None at a depth whose square is 0, where the array forms give inf."""
    x, y, z = p_camera.tolist()
    z2 = z * z
    if z2 == 0.0:  # Python's division by zero raises
        return None
    fx, fy, cx, cy = intrinsics
    third, d_third = (z, 1.0) if kind == DEPTH else (1.0 / z, -1.0 / z2) if kind == DISPARITY else (0.0, 0.0)
    return (np.array([[fx * x / z + cx, fy * y / z + cy, third]]),
            np.array([[[fx / z, 0.0, -fx * x / z2], [0.0, fy / z, -fy * y / z2], [0.0, 0.0, d_third]]]))


# Back-projection needs a positive depth; a measurement at or behind the camera keeps a tiny one,
# which makes it fit no landmark in front of the camera.
MIN_POINT_DEPTH = 1e-6


def depth_of(z: np.ndarray, kind: int) -> np.ndarray:
    """The depth (M,) measurements (M, MAX_DIM) of a kind that measures range give."""
    if kind == DEPTH:
        return z[:, 2].copy()
    if kind == DISPARITY:  # a non-positive inverse depth is behind the camera: depth -1
        return np.divide(1.0, z[:, 2], out=np.full(z.shape[0], -1.0), where=z[:, 2] > 0.0)
    raise ValueError(f"a {KINDS[kind].name} measurement gives no depth")


def back_project(z: np.ndarray, intrinsics, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """Measurements (M, MAX_DIM) of a kind that measures range -> camera-frame points (M, 3), the
    inverse of ``project``, and its Jacobian d p_camera / d z, (M, 3, MAX_DIM). The intrinsics
    fx, fy, cx, cy may each be an (M,) array: a camera per measurement. A pixel gives a ray, not
    a point: ValueError."""
    fx, fy, cx, cy = intrinsics
    x_over_z = (z[:, 0] - cx) / fx
    y_over_z = (z[:, 1] - cy) / fy
    depth = depth_of(z, kind)
    # written into its columns (np.stack costs the numpy beam more than the products)
    p_camera = np.empty((z.shape[0], 3))
    np.multiply(x_over_z, depth, out=p_camera[:, 0])
    np.multiply(y_over_z, depth, out=p_camera[:, 1])
    p_camera[:, 2] = depth
    J = np.zeros((z.shape[0], 3, MAX_DIM))
    J[:, 0, 0] = depth / fx
    J[:, 1, 1] = depth / fy
    # d depth / d z3: 1 for depth (its products with 1 are exact: left out), -depth^2 for inverse depth
    if kind == DEPTH:
        J[:, 0, 2], J[:, 1, 2], J[:, 2, 2] = x_over_z, y_over_z, 1.0
        return p_camera, J
    d_depth = -depth * depth
    J[:, 0, 2] = x_over_z * d_depth
    J[:, 1, 2] = y_over_z * d_depth
    J[:, 2, 2] = d_depth
    return p_camera, J


def padded_information(upper: np.ndarray, kind: int) -> np.ndarray:
    """(K, MAX_DIM, MAX_DIM) information of measurements of ``kind`` from the upper triangles
    (K, dof (dof + 1) / 2) of their dof x dof information, row by row as g2o writes them; the
    inert rows get unit information."""
    dof = KINDS[kind].dof
    rows, cols = np.triu_indices(dof)
    info = np.zeros((upper.shape[0], MAX_DIM, MAX_DIM))
    info[:, rows, cols] = upper
    info[:, cols, rows] = upper
    for a in range(dof, MAX_DIM):
        info[:, a, a] = 1.0
    return info


def upper_triangle(info: np.ndarray, kind: int) -> np.ndarray:
    """The inverse of ``padded_information``: (K, dof (dof + 1) / 2) upper triangles."""
    dof = KINDS[kind].dof
    return info[(slice(None), *np.triu_indices(dof))]


def inert_rows(kinds: np.ndarray) -> np.ndarray:
    """(K, MAX_DIM) bool: which rows of each measurement are the inert padding."""
    return np.arange(MAX_DIM)[None, :] >= dof_of(kinds)[:, None]
