"""Landmarks as variables of the smoother: which ones, their map prior and their first estimate.

``camloc.smoother`` estimates landmarks with the poses when the map is not trusted exactly
(``SmootherConfig.map``):

- ``exact`` (the default): mapped landmarks are held at the map; no landmark variable unless an
  observation is assigned to a landmark the map lacks.
- ``prior``: every observed mapped landmark is a variable with the factor
  ``r = (l - l_map) / sigma`` (3,), isotropic, ``sigma = SmootherConfig.map_sigma`` metres.
- ``none``: the map is not used at all, its ids aside: every observed landmark is a free variable,
  started from the observations, and the start pose alone fixes the gauge.

In every mode a landmark the map lacks but that observations are assigned to (an **added** one)
is a free variable, started where the caller says or, by default, from its observations:
``initial_positions`` back-projects its first observation with a range (depth or disparity)
through the camera and the pose, or triangulates the rays of its pixel-only observations (the
point nearest to all of them in the least-squares sense; one ray, or rays from one centre, leave
it undetermined: NaN).

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from camloc import geometry, measurement

MAP_MODES = ("exact", "prior", "none")
# Rays whose normal matrix sum(I - d d^T) has a smallest eigenvalue below this share of its
# largest do not fix a point (about 0.06 degrees of parallax): the landmark is left undetermined.
_MIN_RAY_SPREAD = 1e-6


@dataclass(frozen=True)
class LandmarkVariables:
    """L landmarks estimated with the poses.

    Attributes
    ----------
    ids : (L,) int64 landmark ids (the map's, or new ones for added landmarks).
    xyz : (L, 3) initial positions, world frame, metres; NaN: start from the observations.
    added : (L,) bool, True for a landmark the map lacks.
    prior_xyz : (L, 3) the map's position, pulling the estimate when ``prior_sigma`` is finite.
    prior_sigma : (L,) the prior's standard deviation per axis, metres; inf: no prior (free).
    kind : (L,) int64 each landmark's kind (``dataset.LANDMARK_POINT3``, ``LANDMARK_POINT2``,
        ``LANDMARK_MARKER``), read by the planar smoother; None: every one a 3-D point. A planar
        robot's landmarks are its coordinates: a floor point's third is its z (0, pinned), a
        marker's its heading (radians; its prior's sigma read as radians there).
    """

    ids: np.ndarray
    xyz: np.ndarray
    added: np.ndarray
    prior_xyz: np.ndarray
    prior_sigma: np.ndarray
    kind: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def select(self, keep: np.ndarray) -> "LandmarkVariables":
        """The landmarks where the boolean (L,) ``keep`` is True."""
        return LandmarkVariables(self.ids[keep], self.xyz[keep], self.added[keep], self.prior_xyz[keep],
                                 self.prior_sigma[keep], None if self.kind is None else self.kind[keep])

    def with_xyz(self, xyz: np.ndarray) -> "LandmarkVariables":
        return replace(self, xyz=np.asarray(xyz, dtype=float))

    @property
    def has_prior(self) -> np.ndarray:
        """(L,) bool: a map prior holds the landmark."""
        return np.isfinite(self.prior_sigma)


@dataclass(frozen=True)
class LandmarkEstimate:
    """The smoother's landmark variables at the solution.

    Attributes
    ----------
    ids : (L,) int64; xyz : (L, 3) positions, world frame, metres.
    cov : (L, 3, 3) marginal covariances, m^2 (the landmark blocks of the inverse information).
    added : (L,) bool, True for a landmark the map lacks.
    observations : (L,) int64 observation factors of each.
    """

    ids: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    added: np.ndarray
    observations: np.ndarray


def landmark_variables(
    ids: np.ndarray,
    map_ids: np.ndarray,
    map_xyz: np.ndarray,
    mode: str,
    sigma: float,
    added_xyz: dict[int, np.ndarray] | None = None,
) -> LandmarkVariables:
    """The variables for the landmark ids that observations are assigned to.

    Parameters
    ----------
    ids : (L,) distinct observed landmark ids that are variables (under ``exact``, only those the
        map lacks).
    map_ids, map_xyz : (K,), (K, 3) the map.
    mode : one of ``MAP_MODES``.
    sigma : the prior's standard deviation (``prior``), metres.
    added_xyz : initial positions of added landmarks by id (the others start from the observations).
    """
    ids = np.asarray(ids, dtype=np.int64)
    order = np.argsort(map_ids, kind="stable")
    at = np.clip(np.searchsorted(map_ids[order], ids), 0, max(len(order) - 1, 0))
    mapped = (map_ids[order][at] == ids) if len(order) else np.zeros(len(ids), dtype=bool)
    prior_xyz = np.full((len(ids), 3), np.nan)
    prior_xyz[mapped] = map_xyz[order][at[mapped]]
    xyz = np.full((len(ids), 3), np.nan)
    if mode == "prior":
        xyz[mapped] = prior_xyz[mapped]  # the map is the best guess a prior gives
    for k in np.flatnonzero(~mapped):
        if added_xyz is not None and int(ids[k]) in added_xyz:
            xyz[k] = added_xyz[int(ids[k])]
    prior_sigma = np.where(mapped & (mode == "prior"), sigma, np.inf)
    return LandmarkVariables(ids, xyz, ~mapped, prior_xyz, prior_sigma.astype(float))


def initial_positions(
    T_pose: np.ndarray,
    T_robot_camera: np.ndarray,
    intrinsics: np.ndarray,
    z: np.ndarray,
    kinds: np.ndarray,
    landmark: np.ndarray,
    count: int,
) -> np.ndarray:
    """First estimates (count, 3) of landmarks from their observations (M of them), world frame.

    Parameters
    ----------
    T_pose, T_robot_camera : (M, 4, 4) each observation's robot pose and camera mount.
    intrinsics : (M, 4) fx, fy, cx, cy.
    z : (M, 3) measurements (``camloc.measurement``'s layout); kinds (M,) their kinds.
    landmark : (M,) the landmark (0..count-1) each observation is assigned to.

    Returns
    -------
    (count, 3): the back-projection of each landmark's first observation with a range; for a
    landmark seen by pixels alone, the least-squares intersection of its rays; NaN where neither
    fixes a point (no observation, a single ray, parallel rays, or a point behind a camera). A
    planar robot's floor point or marker (kinds ``POINT2``, ``MARKER``, in the robot's frame: T_pose
    the lifted pose, the mount the identity) is its measured point on the floor, z = 0; a marker's
    third coordinate is its heading, the robot's plus the measured one.
    """
    xyz = np.full((count, 3), np.nan)
    R_world_camera = T_pose[:, :3, :3] @ T_robot_camera[:, :3, :3]
    centre = np.einsum("mij,mj->mi", T_pose[:, :3, :3], T_robot_camera[:, :3, 3]) + T_pose[:, :3, 3]
    ranged = np.zeros(len(landmark), dtype=bool)
    points = np.full((len(landmark), 3), np.nan)
    on_floor = measurement.is_planar(kinds)
    if np.any(on_floor):
        rows = np.flatnonzero(on_floor)
        in_robot = np.concatenate([z[rows, :2], np.zeros((rows.size, 1))], axis=1)
        points[rows] = np.einsum("mij,mj->mi", R_world_camera[rows], in_robot) + centre[rows]
        marker = rows[np.asarray(kinds)[rows] == measurement.MARKER]
        heading = np.arctan2(R_world_camera[marker, 1, 0], R_world_camera[marker, 0, 0]) + z[marker, 2]
        points[marker, 2] = geometry.wrap_angle(heading)
        ranged[rows] = True
    for kind in (measurement.DEPTH, measurement.DISPARITY):
        rows = np.flatnonzero(kinds == kind)
        if rows.size:
            p_camera, _ = measurement.back_project(z[rows], intrinsics[rows].T, kind)
            good = p_camera[:, 2] > measurement.MIN_POINT_DEPTH
            points[rows[good]] = np.einsum("mij,mj->mi", R_world_camera[rows[good]], p_camera[good]) + centre[rows[good]]
            ranged[rows[good]] = True
    first = np.flatnonzero(ranged)
    first = first[np.unique(landmark[first], return_index=True)[1]]  # each landmark's first ranged one
    xyz[landmark[first]] = points[first]
    rays = ~np.isin(landmark, landmark[first])
    if np.any(rays):
        xyz[np.unique(landmark[rays])] = np.nan
        triangulated = _triangulate(R_world_camera[rays], centre[rays], z[rays], intrinsics[rays], landmark[rays], count)
        missing = np.isnan(xyz[:, 0]) & ~np.isnan(triangulated[:, 0])
        xyz[missing] = triangulated[missing]
    return xyz


def _triangulate(R_world_camera, centre, z, intrinsics, landmark, count) -> np.ndarray:
    """The point nearest to each landmark's rays, ``argmin sum |(I - d d^T)(x - c)|^2``; NaN
    where the rays do not fix one or it lies behind a camera that saw it."""
    fx, fy, cx, cy = intrinsics.T
    d_camera = np.stack([(z[:, 0] - cx) / fx, (z[:, 1] - cy) / fy, np.ones(len(z))], axis=1)
    d = np.einsum("mij,mj->mi", R_world_camera, d_camera)
    d /= np.linalg.norm(d, axis=1)[:, None]
    P = np.eye(3) - d[:, :, None] * d[:, None, :]  # projector off each ray
    A = np.zeros((count, 3, 3))
    b = np.zeros((count, 3))
    np.add.at(A, landmark, P)
    np.add.at(b, landmark, np.einsum("mij,mj->mi", P, centre))
    out = np.full((count, 3), np.nan)
    eig = np.linalg.eigvalsh(A)
    fixed = eig[:, 0] > _MIN_RAY_SPREAD * np.maximum(eig[:, 2], 1e-300)
    out[fixed] = np.linalg.solve(A[fixed], b[fixed][:, :, None])[:, :, 0]
    ahead = np.einsum("mi,mi->m", out[landmark] - centre, d) > 0.0
    behind = np.unique(landmark[~ahead & fixed[landmark]])
    out[behind] = np.nan
    return out
