"""The poses a pixel track's first ray was cast from, kept in the mapping localizer's state until
the track becomes a landmark or is dropped (stochastic cloning: ``camloc.slam_rays``).

A clone is three rows of the state's landmarks (``slam_rays.clone_points``) that are no landmark:
in the table they are ``dead`` (never a candidate, never in the map) with id -1. One clone per
pose, shared by every track that starts there; it leaves the state (marginalized) once no track
starts at its pose within the last ``CLONE_WINDOW`` poses. A track waits that long for its second
view: one extended past that starts again from its latest ray (an oracle's track, never dropped,
that is not seen again simply loses its clone), so the clones in the state stay within the window;
they do not count against ``slam_landmarks.MAX_STATE_LANDMARKS``.

A track becomes a landmark from its first ray (the clone's) and the latest one only when the
linearization is good: the depth's standard deviation along the latest ray at most
``MAX_DEPTH_SPREAD`` of the range (the role of the linearity index of inverse depth: a
two-ray point at low parallax is far from Gaussian in depth, and its linearized covariance then
understates it). 0.6 is a compromise between that and mapping at all: at 0.2 the new landmarks'
NEES at entry was near its 3 dof on every world measured (medians 1.4-6.9), but on the
benchmark's worlds (odometry drifting decimetres a pose) few tracks ever got there
(docs/performance.md, 2026-12-05).

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from camloc import slam, slam_rays

CLONE_WINDOW = 40
MAX_DEPTH_SPREAD = 0.6


class RayAnchors:
    """A mix-in of ``slam_run.MappingLocalizer`` (its ``x``, ``P``, ``table``, ``state_landmark``,
    ``tracks``, ``oracle_tracks``, ``dataset``, ``sensors``): the clones of its rays' poses."""

    clones: dict

    def _clone_pose(self, k: int) -> None:
        """Pose k (the estimate now) joins the state as a clone, unless it has."""
        if k in self.clones:
            return
        B = np.zeros((slam_rays.CLONE_ROWS, 3, slam.POSE_DIM))
        B[:, :, 0:3] = np.eye(3)  # a point rigid with the robot: its translation error, exactly
        points = slam_rays.clone_points(self.x.R, self.x.t)
        self.x, self.P = slam.augmented_many(self.x, self.P, points, B, np.zeros((slam_rays.CLONE_ROWS, 3, 3)))
        table = self.table
        rows = np.array([table.append(-1) for _ in range(slam_rays.CLONE_ROWS)], np.int64)
        table.dead[rows] = True
        table.added[rows] = False
        table.state_row[rows] = len(self.state_landmark) + np.arange(slam_rays.CLONE_ROWS)
        table.last_seen[rows] = table.born[rows] = k
        self.state_landmark.extend(rows.tolist())
        self.clones[k] = rows

    def _anchored(self, k: int, track) -> None:
        """A track that grew at pose k: its first ray's pose cloned (a new track), or the track
        started again from its latest ray where its first waited past ``CLONE_WINDOW`` poses."""
        first = int(self.dataset.obs_pose_index[track.observations[0]])
        if k - first > CLONE_WINDOW:
            for name in ("observations", "origins", "directions", "sigma_angle"):
                setattr(track, name, getattr(track, name)[-1:])
            first = k
        if first == k:
            self._clone_pose(k)

    def _needed_clones(self, k: int) -> set:
        """The poses within ``CLONE_WINDOW`` of pose k a track (of rays) starts at (an oracle's
        track is never dropped: one that started before that no longer has its clone)."""
        first = [t.observations[0] for t in self.tracks.tracks]
        first += [t.observations[0] for t in self.oracle_tracks.values() if getattr(t, "origins", None)]
        poses = self.dataset.obs_pose_index[np.array(first, np.int64)]
        return set(poses[k - poses <= CLONE_WINDOW].tolist())

    def _unneeded_clones(self, k: int) -> np.ndarray:
        """The table rows of the clones no track needs any more (the caller drops them from the
        state; they leave the bookkeeping here). The others' ``last_seen`` is set to k, so that no
        retiring takes them."""
        needed = self._needed_clones(k)
        for j in needed & self.clones.keys():
            self.table.last_seen[self.clones[j]] = k
        rows = [self.clones.pop(j) for j in list(self.clones) if j not in needed]
        return np.concatenate(rows) if rows else np.zeros(0, np.int64)

    def _ray_landmark(self, k: int, o: int, track) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """The landmark of a track of rays from its first ray (from its pose's clone) and its
        latest, observation o at pose k: its point (3,), its error's coefficients C (3, 12) on the
        error's components ``columns`` (12,) (the robot's translation, the clone's points) and its
        noise (3, 3) (``slam.augmented_on``); None where the clone is missing, the rays fix no point
        in front of the cameras, or the depth is not yet known well (``MAX_DEPTH_SPREAD``)."""
        first = int(track.observations[0])
        j = int(self.dataset.obs_pose_index[first])
        if j == k or j not in self.clones:
            return None
        ds = self.dataset
        rows = self.table.state_row[self.clones[j]]
        columns = (slam.POSE_DIM + 3 * rows[:, None] + np.arange(3)).ravel()
        sensor, anchor_sensor = self.sensors[int(self.obs_sensor[o])], self.sensors[int(self.obs_sensor[first])]
        fix = slam_rays.two_ray_landmark(self.x.L[rows], anchor_sensor, ds.obs_z[first], ds.obs_cov[first][:2, :2],
                                         slam_rays.clone_points(self.x.R, self.x.t), sensor, ds.obs_z[o], ds.obs_cov[o][:2, :2])
        if fix is None:
            return None
        point, B_anchor, B_translation, N, _ = fix
        if float(slam.camera_points(self.x, sensor, point[None, :])[0, 2]) <= max(self.min_depth, 1e-3):
            return None
        touched = np.concatenate([np.arange(3), columns])  # the robot's translation, the clone's points
        C = np.hstack([B_translation, B_anchor])
        cov = C @ self.P[np.ix_(touched, touched)] @ C.T + N
        centre = self.x.t + self.x.R @ sensor.T_robot_camera[:3, 3]
        ray = point - centre
        distance = float(np.linalg.norm(ray))
        along = ray / distance
        if np.sqrt(max(float(along @ cov @ along), 0.0)) > MAX_DEPTH_SPREAD * distance:
            return None
        return point, C, touched, N
