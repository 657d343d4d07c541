"""The landmarks of a mapping run (``camloc.slam_run``): their table, and how landmarks the map
lacks are added.

- ``LandmarkTable``: every landmark of the run, the map's then the added ones, in the state or
  waiting outside it.
- ``LandmarkAdditions``: the mapping localizer's part that adds landmarks. An unassigned
  observation that no landmark in view fits within its gate is a candidate: one with range enters
  the state at once as a **tentative** landmark (the inverse observation: consistent in the
  invariant error), confirmed or dropped by its track score (below); a pixel gathers into a track
  of rays (``camloc.slam_tracks``) until their parallax fixes a depth (delayed initialization,
  from its first ray's pose kept in the state: ``camloc.slam_anchors``).
  Under the oracle, an id the map lacks becomes a landmark at its second observation.

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from camloc import measurement, slam
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3, Dataset, landmark_kind_of
from camloc.results import LandmarkMap
from camloc.slam_rays import CLONE_ROWS
from camloc.slam_tracks import Tracks, triangulate

# an assignment's cost outside the gate
UNPAIRED = 1e12

# A landmark entered from one observation is **tentative** until its score, the log-likelihood
# ratio of "a landmark" over "clutter" of what was seen of it (the track score of multi-target
# tracking: + (null cost - pair cost) / 2 for each pair, + ln(1 - DETECTION_PROBABILITY) each time
# it was surely in view and not seen), reaches CONFIRM_SCORE (odds 1000:1); it is dropped, with
# its pairs, below DROP_SCORE or when not seen again within TENTATIVE_GAP poses. Clutter, uniform
# over what the cameras see, is not seen again where it was: it is dropped.
CONFIRM_SCORE = float(np.log(1000.0))
DROP_SCORE = -2.0
DETECTION_PROBABILITY = 0.9
TENTATIVE_GAP = 10
# Without a map a tentative landmark unseen for TENTATIVE_GAP poses is not dropped at once: it
# stays in the state up to TENTATIVE_KEEP poses unseen, but is paired again only among a pose's
# set of pairs that vouch for it (``slam_association.joint_pairs``: a loop closure), never on its
# own cost (a lone sighting near a landmark seen once is as likely a neighbour not yet mapped).
# Why: the real file's kind of world sees most landmarks two or three times, often a loop apart,
# and dropping them after 10 poses lost those returns (the real file: 39 of its 218 returns start
# a new landmark for that, 20 more are kept out). Measured (docs/performance.md, 2026-12-05, "No
# map: a loop closure's returns judged together"): kept and paired alone, 100-pose grid worlds
# gained but mean NEES rose and 300-pose grid worlds lost 0.8 m; kept forever and paired jointly,
# the 300-pose grid and aerial worlds lost 0.4 m; kept 40 poses, the 100-pose grid worlds reached
# the true association's RMSE (1.166 -> 0.921 m, mean NEES 8.0 -> 6.6) and the 300-pose depth
# worlds gained 0.1-0.4 m (smooth3d and aerial 100-pose worlds within noise).
TENTATIVE_KEEP = 40


def kept_longer(map_mode: str, kinds: np.ndarray) -> np.ndarray:
    """(M,) bool: which tentative landmarks of ``kinds`` (M,) are kept up to TENTATIVE_KEEP poses
    unseen: a camera's points with no map. Not a planar robot's floor points or markers: on 300-pose
    planar worlds it cost 0.568 -> 0.684 m, and on loop worlds whose odometry claims a quarter of
    its noise 7 -> 31 landmarks added twice of about 250 (docs/performance.md, 2026-12-05)."""
    return (kinds == LANDMARK_POINT3) & (map_mode == "none")


def with_state_estimates(values: np.ndarray, rows: np.ndarray, landmarks: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The table's ``values`` (positions or tags' rotation vectors, (N, 3)) of ``landmarks`` (any
    shape of table indices), with the state's estimate ``L[rows]`` wherever the state holds one
    (the table's ``rows`` (N,) >= 0): an array of landmarks' shape + (3,)."""
    out, at = values[landmarks], rows[landmarks]
    held = at >= 0
    out[held] = L[at[held]]
    return out


# Poses a landmark may go unseen before it leaves the state, with a map (exact or prior: the map
# holds the robot, so what a landmark's correlation with it carries is small); with no map,
# landmarks stay in the state (their correlations are the whole estimate) up to MAX_STATE_LANDMARKS,
# the least recently seen leaving beyond that.
RETIRE_AFTER = 30
MAX_STATE_LANDMARKS = 600

# Without a map, an observation no pair took becomes a new landmark only where no landmark it
# could be of fits it within the chi^2 gate of this tail (wider than the association's 1%),
# wherever that landmark is predicted in front of the sensor: a landmark added twice stays twice
# for the rest of the run, where an observation left out is one measurement lost. (With a map:
# the association's gate, in view, as measured there.)
NEW_LANDMARK_TAIL = 1e-4


class LandmarkTable:
    """Every landmark of the run: the map's (in file order) then the added ones; where each is
    (its row in the state, -1 outside), its position and world covariance while outside the state
    (a zero covariance: held exactly), when it was last seen and how many observations it took.

    Its columns (``ids``, ``xyz``, ``cov``, ``added``, ``state_row``, ``last_seen``, ``born``,
    ``observations``, ``tentative``, ``score``, ``dead``) are views of arrays with room to grow:
    a run adds a tentative landmark for most unexplained observations (16,000 on a 20,000-pose
    world), and growing every column by one each time copied the whole table."""

    # name, dtype, shape of a row, the value a new row starts with
    _COLUMNS = (("ids", np.int64, (), 0), ("xyz", float, (3,), 0.0), ("cov", float, (3, 3), 0.0),
                ("added", bool, (), True), ("state_row", np.int64, (), -1), ("last_seen", np.int64, (), -1),
                ("born", np.int64, (), -1),  # the first pose of its observations (added ones)
                ("observations", np.int64, (), 0),
                ("tentative", bool, (), False),  # added from one observation, not yet confirmed by its score
                ("score", float, (), 0.0),       # a tentative landmark's log-likelihood ratio over clutter
                ("dead", bool, (), False),       # a tentative landmark dropped (clutter): out of the map
                ("kind", np.int64, (), LANDMARK_POINT3),  # a camera's point, a floor point (point2) or a marker (``Dataset.landmark_kind``)
                # a tag's orientation (``camloc.slam_tags``): its rotation vector (world; NaN: not a
                # tag), world covariance while outside the state, and its row in the state (-1: outside)
                ("rotvec", float, (3,), np.nan), ("rot_cov", float, (3, 3), 0.0), ("rot_row", np.int64, (), -1))

    ids: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    added: np.ndarray
    state_row: np.ndarray
    last_seen: np.ndarray
    born: np.ndarray
    observations: np.ndarray
    tentative: np.ndarray
    score: np.ndarray
    dead: np.ndarray
    kind: np.ndarray
    rotvec: np.ndarray
    rot_cov: np.ndarray
    rot_row: np.ndarray

    def __init__(self, ids: np.ndarray, xyz: np.ndarray, cov: np.ndarray):
        n = ids.size
        self.size = self.num_mapped = n
        self._columns = {name: np.full((max(2 * n, 64),) + shape, fill, dtype) for name, dtype, shape, fill in self._COLUMNS}
        self._views()
        self.ids[:], self.xyz[:], self.cov[:] = ids, xyz.reshape(n, 3), cov.reshape(n, 3, 3)
        self.added[:] = False
        self._live = None  # the added landmarks not dropped (``in_range``), rebuilt when that changes
        self.has_markers = False  # whether a landmark is a marker (its third coordinate a heading)
        self.scan = None  # the compiled scan of ``in_range`` (``slam_compiled.live_within``), where the run has it

    def _views(self) -> None:
        """Each column as an attribute, a view of its first ``size`` rows: set again when the size
        changes (a run reads them a million times: a view made at each read cost 0.6 s of 20,000 poses)."""
        for name, column in self._columns.items():
            self.__dict__[name] = column[:self.size]

    def __len__(self) -> int:
        return self.size

    def append(self, landmark_id: int) -> int:
        """A new (added) landmark, in the state: its index."""
        if self.size == self._columns["ids"].shape[0]:
            self._columns = {name: np.concatenate([c, np.full_like(c, fill)]) for (name, c), (_, _, _, fill)
                             in zip(self._columns.items(), self._COLUMNS)}
        self.size += 1
        self._views()
        self.ids[-1] = landmark_id
        self._live = None
        return self.size - 1

    def drop(self, landmarks: np.ndarray) -> None:
        """Tentative landmarks found to be clutter leave the map."""
        self.dead[landmarks] = True
        self._live = None

    def in_range(self, centre: np.ndarray, radius: float, mapped_index) -> np.ndarray:
        """Indices of the landmarks within ``radius`` of ``centre`` (the map's through its index)."""
        mapped = mapped_index.within(centre, radius) if mapped_index is not None else np.zeros(0, np.int64)
        if self._live is None:
            self._live = self.num_mapped + np.flatnonzero(~self.dead[self.num_mapped:])
        if self.scan is not None:  # compiled (camloc.slam_compiled.live_within): no gathered copy of the added ones
            added = self.scan(self._columns["xyz"], self._live, centre, radius)
        else:
            offset = self.xyz[self._live] - centre
            if self.has_markers:  # a marker's third coordinate is its heading: on the floor
                offset[self.kind[self._live] == LANDMARK_MARKER, 2] = 0.0
            added = self._live[np.einsum("ij,ij->i", offset, offset) <= radius * radius]
        return np.concatenate([mapped, added]).astype(np.int64)


def places_points(kinds: np.ndarray) -> np.ndarray:
    """(K,) bool: whether one measurement of each of ``kinds`` (K,) places its landmark: a camera's
    with range (depth, disparity) or a planar robot's own (point2, on the floor; a marker, with its
    heading); a pixel is a ray."""
    kinds = np.asarray(kinds, dtype=np.int64)
    return measurement.measures_range(kinds) | np.isin(kinds, measurement.PLANAR_KINDS)


def places_point(kind: int) -> bool:
    """``places_points`` of one kind."""
    return bool(places_points(np.array([kind]))[0])


class LandmarkAdditions:
    """The mapping localizer's additions (a mix-in of ``slam_run.MappingLocalizer``, whose state
    it reads and extends: ``x``, ``P``, ``table``, ``state_landmark``, ``tracks``, ``chosen``)."""

    def _oracle_pairs(self, k: int, obs: np.ndarray) -> list[tuple[int, int]]:
        """The pose's pairs by the file's ids (mapped, or added under the oracle), gated."""
        pairs = []
        for o in obs.tolist():
            landmark = self.oracle_landmark.get(int(self.dataset.obs_true_landmark[o]))
            if landmark is None:
                continue
            cost = self.landmark_costs(int(self.obs_sensor[o]), np.array([o]), np.array([landmark]))
            if cost is not None and cost[1][0, 0] < UNPAIRED:  # gated like any pair
                pairs.append((o, landmark))
        return pairs

    def estimated_map(self) -> LandmarkMap:
        """The map at the end of the run: every landmark of the table (the state's estimates for
        those in it)."""
        table = self.table
        xyz, cov = table.xyz.copy(), table.cov.copy()
        positions = self._position_rows()
        for row, landmark in enumerate(self.state_landmark):
            if positions[row]:
                xyz[landmark], cov[landmark] = self.x.L[row], slam.landmark_world_cov(self.x, self.P, row)
        markers = table.kind == LANDMARK_MARKER  # on the floor (its heading, the third coordinate, is not written)
        xyz[markers, 2] = 0.0
        cov[markers, 2, :] = cov[markers, :, 2] = 0.0
        keep = ~table.dead & ~table.tentative
        landmark_map = LandmarkMap(ids=table.ids[keep], xyz=xyz[keep], cov=cov[keep], added=table.added[keep],
                                   observations=table.observations[keep])
        if not self.has_tags:
            return landmark_map
        rotvec, rot_cov = self._estimated_orientations()
        return replace(landmark_map, orientation=rotvec[keep], orientation_cov=rot_cov[keep])

    def _retire(self, k: int) -> None:
        """Landmarks unseen for ``RETIRE_AFTER`` poses leave the state, keeping their estimate."""
        if not self.state_landmark:
            return
        clones = self._unneeded_clones(k) if self.clones else None  # (held ones: last_seen k, never retired)
        landmarks = np.array(self.state_landmark, np.int64)
        if self.config.map == "none":
            drop = np.zeros(landmarks.size, bool)
            limit = MAX_STATE_LANDMARKS + CLONE_ROWS * len(self.clones) + (clones.size if clones is not None else 0)  # landmarks only
            if landmarks.size > limit:
                drop[np.argsort(self.table.last_seen[landmarks], kind="stable")[:landmarks.size - limit]] = True
        else:
            drop = self.table.last_seen[landmarks] < k - RETIRE_AFTER
        # a tentative landmark is confirmed, or dropped with its pairs (clutter, or too rarely seen to map)
        table = self.table
        table.tentative[landmarks[table.score[landmarks] >= CONFIRM_SCORE]] = False
        unconfirmed = table.tentative[landmarks]
        keep = np.where(kept_longer(self.config.map, table.kind[landmarks]), TENTATIVE_KEEP, TENTATIVE_GAP)
        gone = unconfirmed & ((table.last_seen[landmarks] < k - keep) | (table.score[landmarks] < DROP_SCORE))
        if np.any(gone):
            table.drop(landmarks[gone])
            # their pairs: among the observations from the first of theirs to this pose's (not the whole run's)
            since = self.obs_order[self.obs_bounds[int(table.born[landmarks[gone]].min())]:self.obs_bounds[k + 1]]
            # (a comparison with the few dropped, not np.isin: its set-up cost more than this search)
            self.chosen[since[(self.chosen[since][:, None] == landmarks[gone][None, :]).any(axis=1)]] = -1
            drop |= gone
        if clones is not None and clones.size:
            drop |= np.isin(landmarks, clones)
        if not np.any(drop):
            return
        if self.x.orientation is not None:  # a tag's orientation rows leave with its centre's
            self._retire_tags(landmarks, drop)
            return
        rows = np.flatnonzero(drop)
        self.table.xyz[landmarks[rows]] = self.x.L[rows]
        if self.compiled is not None:
            self.table.cov[landmarks[rows]] = self.compiled.world_covs(self.x, self.P, rows)
        else:
            for row in rows.tolist():
                self.table.cov[int(landmarks[row])] = slam.landmark_world_cov(self.x, self.P, row)
        self.x, self.P = slam.without_landmarks(self.x, self.P, drop)
        self._rows_left(landmarks, drop)

    def _rows_left(self, landmarks: np.ndarray, drop: np.ndarray, position: np.ndarray | None = None) -> None:
        """The table's state rows after the state's rows ``drop`` (m,) of ``landmarks`` (m,, the
        state's, in row order) left it (``slam.without_landmarks``): theirs -1, the rest renumbered.
        ``position`` (m,) bool: which rows were positions, the others tags' orientations (None: all)."""
        if position is None:
            position = np.ones(landmarks.size, bool)
        self.table.state_row[landmarks[drop & position]] = -1
        self.table.rot_row[landmarks[drop & ~position]] = -1
        self.state_landmark = landmarks[~drop].tolist()
        kept_position = position[~drop]
        self.table.state_row[landmarks[~drop][kept_position]] = np.flatnonzero(kept_position)
        self.table.rot_row[landmarks[~drop][~kept_position]] = np.flatnonzero(~kept_position)

    def _retire_tags(self, landmarks: np.ndarray, drop: np.ndarray) -> None:
        """``_retire``'s leaving of the rows ``drop`` (m,) of a state that holds tags' orientations
        (numpy: the compiled steps do not run tags): positions and orientations each to their columns."""
        position = self._position_rows()
        for row in np.flatnonzero(drop & position).tolist():
            self.table.xyz[int(landmarks[row])] = self.x.L[row]
            self.table.cov[int(landmarks[row])] = slam.landmark_world_cov(self.x, self.P, row)
        turned = np.flatnonzero(drop & ~position)
        self._leave_orientations(landmarks[turned], turned)
        self.x, self.P = slam.without_landmarks(self.x, self.P, drop)
        self._rows_left(landmarks, drop, position)

    # -- the run's records ------------------------------------------------------------------------

    def _tracked(self, k: int, unassigned: list[int]) -> None:
        """Unassigned observations join tracks; a confirmed track becomes a landmark. One that a
        landmark of the map or the state would explain within its gate is not a new landmark (the
        association left it out for its cost or its partners): it stays unassigned, so that no
        landmark is added twice."""
        self.tracks.expire(k)
        unassigned = self._unexplained(unassigned)
        for o in unassigned:
            kind = int(self.dataset.obs_kind[o])
            if places_point(kind):
                # a point enters the state at once, tentative (``_retire`` drops it unless seen again):
                # the filter then judges its next observations with the correlations it holds
                self._add_landmark(k, o, SingleObservation(o), tentative=True)
                continue
            origin, direction, sigma = self._ray(o)
            track = self.tracks.add_ray(k, o, origin, direction, sigma, self._ray_fits(o))
            self._anchored(k, track)
            if self.tracks.confirmed(track) and self._add_landmark(k, o, track):
                self.tracks.remove(track)

    def _count_misses(self, seen: set) -> None:
        """A tentative landmark in the state that was surely in view (``sure_view``) and not
        seen at this pose: its score takes the miss."""
        table = self.table
        if not self.state_landmark or (self.sure_view is None and self.floor_view is None):
            return
        landmarks = np.array(self.state_landmark, np.int64)
        unseen = np.array([landmark not in seen for landmark in self.state_landmark])
        rows = np.flatnonzero(table.tentative[landmarks] & unseen & self._position_rows())
        if rows.size == 0:
            return
        in_view = self._in_sure_view(landmarks[rows], self.x.L[rows])
        table.score[landmarks[rows[in_view]]] += np.log(1.0 - DETECTION_PROBABILITY)

    def _in_sure_view(self, landmarks: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(M,) bool: which of the table's ``landmarks`` (M,), at ``xyz`` (M, 3), a sensor of their
        kind surely sees from the estimate: a camera (``sure_view``), or a planar robot's point
        sensor a point of the floor (``floor_sure_view``)."""
        floor = self.table.kind[landmarks] == LANDMARK_POINT2
        cameras = self.table.kind[landmarks] == LANDMARK_POINT3
        in_view = np.zeros(landmarks.size, bool)  # a marker: never surely (its detection depends on its heading)
        if self.sure_view is not None and cameras.any():
            if self.compiled is not None:
                in_view[cameras] = self.compiled.surely_in_view(self.x, xyz[cameras], self.sure_view)
            else:
                in_view[cameras] = surely_in_view(self.x, self.sensors, xyz[cameras], self.sure_view)
        if self.floor_view is not None and floor.any():
            in_view[floor] = floor_in_view(self.x, xyz[floor], self.floor_view)
        return in_view

    def _unexplained(self, obs: list[int]) -> list[int]:
        """The observations of ``obs`` that no landmark in view fits within its chi^2 gate."""
        if not obs or not len(self.table):
            return obs
        obs_array = np.array(obs, np.int64)
        self._sync_positions()
        nearby = self.table.in_range(self.x.t, self.reach, self.mapped_index)
        fits = np.zeros(obs_array.size, bool)
        for sensor_id in np.unique(self.obs_sensor[obs_array]).tolist():
            at = self.obs_sensor[obs_array] == sensor_id
            gated = self.landmark_costs(sensor_id, obs_array[at], nearby, tail=NEW_LANDMARK_TAIL if self.config.map == "none" else None)
            if gated is not None:  # (a tag's: with its orientation, so a tag beside another is a new one)
                fits[at] = np.any(self._orientation_costs(obs_array[at], *gated) < UNPAIRED, axis=1)
        return obs_array[~fits].tolist()

    def _oracle_new(self, k: int, unassigned: list[int]) -> None:
        """With the oracle, an id the map lacks becomes a landmark once seen twice (rays: with
        parallax enough); clutter's ids are seen once."""
        for o in unassigned:
            true_id = int(self.dataset.obs_true_landmark[o])
            if true_id in self.oracle_landmark:
                continue  # a known landmark out of the gate: left unassigned
            kind = int(self.dataset.obs_kind[o])
            track = self.oracle_tracks.get(true_id)
            if track is None:
                track = self.oracle_tracks[true_id] = OracleTrack(self.tracks)
            if places_point(kind):
                track.observations.append(o)
                ready = len(track.observations) >= 2
            else:
                origin, direction, sigma = self._ray(o)
                ready = track.add_ray(k, o, origin, direction, sigma)
                self._anchored(k, track)
                ready = ready and len(track.observations) >= 2
            if ready and self._add_landmark(k, o, track.as_track()):
                self.oracle_landmark[true_id] = len(self.table) - 1
                del self.oracle_tracks[true_id]

    def _inverse(self, o: int):
        sensor = self.sensors[int(self.obs_sensor[o])]
        return slam.inverse_observation(self.x, sensor, self.dataset.obs_z[o], self.dataset.obs_cov[o])

    def _ray(self, o: int) -> tuple[np.ndarray, np.ndarray, float]:
        """Observation o's ray: the camera's centre, its unit direction (world) and its angular
        standard deviation (radians)."""
        sensor = self.sensors[int(self.obs_sensor[o])]
        fx, fy, cx, cy = sensor.intrinsics
        z = self.dataset.obs_z[o]
        Rc, tc = sensor.T_robot_camera[:3, :3], sensor.T_robot_camera[:3, 3]
        d = self.x.R @ Rc @ np.array([(z[0] - cx) / fx, (z[1] - cy) / fy, 1.0])
        cov = self.dataset.obs_cov[o]
        sigma = float(np.sqrt(max(cov[0, 0] / fx**2, cov[1, 1] / fy**2)))
        return self.x.t + self.x.R @ tc, d / np.linalg.norm(d), sigma

    def _add_landmark(self, k: int, o: int, track, tentative: bool = False) -> bool:
        """A new landmark from observation o (the track's latest), in the state; False where a
        ray's track fixes no depth in front of the camera yet (``RayAnchors._ray_landmark``)."""
        sensor = self.sensors[int(self.obs_sensor[o])]
        z, R_z = self.dataset.obs_z[o].copy(), self.dataset.obs_cov[o].copy()
        if not places_point(sensor.kind):  # from its first ray's clone and this one (``slam_anchors``)
            fix = self._ray_landmark(k, o, track)
            if fix is None:
                return False
            self.x, self.P = slam.augmented_on(self.x, self.P, *fix)
        elif self.compiled is not None:
            xyz, self.P = self.compiled.augmented(self.x, self.P, sensor, z, R_z)
            self.x = slam.SlamMean(self.x.R, self.x.t, np.vstack([self.x.L, xyz]))
        else:
            xyz, B, N = slam.inverse_observation(self.x, sensor, z, R_z)
            self.x, self.P = slam.augmented(self.x, self.P, xyz, B, N)
        landmark = self.table.append(self.next_id)
        self.next_id += 1
        self.table.state_row[landmark] = len(self.state_landmark)
        self.state_landmark.append(landmark)
        self.table.last_seen[landmark] = k
        self.table.observations[landmark] = len(track.observations)
        self.table.born[landmark] = int(self.dataset.obs_pose_index[np.array(track.observations, np.int64)].min())
        self.table.tentative[landmark] = tentative
        self.table.kind[landmark] = landmark_kind_of(sensor.kind)
        self.table.has_markers |= sensor.kind == measurement.MARKER
        self.chosen[np.array(track.observations, np.int64)] = landmark
        if self.has_tags:
            self._add_orientation(o, landmark, track.observations)
        return True


# The share of the observations' distances and angles "surely in view" takes: inside what most
# observations span, so that a landmark predicted there and not seen was missed, not out of view.
_SURE_QUANTILES = (0.1, 0.9)


def surely_in_view(x: slam.SlamMean, sensors: dict, xyz: np.ndarray, view: tuple[float, float, float]) -> np.ndarray:
    """(M,) bool: which world points (M, 3) some camera of ``sensors`` surely sees from x
    (within ``view``: ``sure_view``'s distances and angle)."""
    near, far, angle = view
    in_view = np.zeros(xyz.shape[0], bool)
    for sensor in sensors.values():
        if sensor.camera_id < 0:  # a planar robot's own sensor
            continue
        p = slam.camera_points(x, sensor, xyz)
        distance = np.linalg.norm(p, axis=1)
        in_view |= (distance >= near) & (distance <= far) & (p[:, 2] >= np.cos(angle) * distance)
    return in_view


def sure_view(dataset: Dataset) -> Optional[tuple[float, float, float]]:
    """(nearest, farthest distance, widest angle) from the camera within which a landmark is surely
    seen: the 10th and 90th percentiles of the observations' distances, the 90th of their angles
    to the optical axis. None where no observation measures range."""
    ranged = np.flatnonzero(measurement.measures_range(dataset.obs_kind))
    if ranged.size < 10:
        return None
    from camloc.observation_space import observation_intrinsics

    intrinsics = observation_intrinsics(dataset)[ranged]
    points = np.zeros((ranged.size, 3))
    for kind in np.unique(dataset.obs_kind[ranged]).tolist():
        at = dataset.obs_kind[ranged] == kind
        points[at] = measurement.back_project(dataset.obs_z[ranged[at]], intrinsics[at].T, int(kind))[0]
    distance = np.linalg.norm(points, axis=1)
    angle = np.arccos(np.clip(points[:, 2] / np.maximum(distance, 1e-12), -1.0, 1.0))
    near, far = np.quantile(distance, _SURE_QUANTILES)
    return float(near), float(far), float(np.quantile(angle, _SURE_QUANTILES[1]))


def floor_sure_view(dataset: Dataset) -> Optional[tuple[float, float, float]]:
    """``sure_view`` of a planar robot's point sensor (point2): the 10th and 90th percentiles of its
    observations' distances from the robot, the 90th of their bearings from its x axis. None
    with fewer than 10 such observations."""
    mine = np.flatnonzero(dataset.obs_kind == measurement.POINT2)
    if mine.size < 10:
        return None
    z = dataset.obs_z[mine]
    near, far = np.quantile(np.hypot(z[:, 0], z[:, 1]), _SURE_QUANTILES)
    return float(near), float(far), float(np.quantile(np.abs(np.arctan2(z[:, 1], z[:, 0])), _SURE_QUANTILES[1]))


def floor_in_view(x: slam.SlamMean, xyz: np.ndarray, view: tuple[float, float, float]) -> np.ndarray:
    """(M,) bool: which points of the floor (M, 3) the planar robot's point sensor surely sees
    from x (within ``floor_sure_view``'s distances and bearing)."""
    near, far, angle = view
    p = (xyz - x.t) @ x.R  # in the robot frame
    distance = np.hypot(p[:, 0], p[:, 1])
    return (distance >= near) & (distance <= far) & (np.abs(np.arctan2(p[:, 1], p[:, 0])) <= angle)


class SingleObservation:
    """One observation as a track (a landmark entered from it alone)."""

    def __init__(self, o: int):
        self.observations = [o]


class OracleTrack:
    """The observations of one id the map lacks, under the oracle (rays: until they fix a depth)."""

    def __init__(self, tracks: Tracks):
        self.tracks = tracks
        self.observations: list[int] = []
        self.origins: list = []
        self.directions: list = []
        self.sigma_angle: list = []

    def add_ray(self, k, o, origin, direction, sigma) -> bool:
        self.observations.append(o)
        self.origins.append(origin)
        self.directions.append(direction)
        self.sigma_angle.append(sigma)
        return len(self.observations) >= 2 and triangulate(np.array(self.origins), np.array(self.directions),
                                                           np.array(self.sigma_angle)) is not None

    def as_track(self):
        return self


# The screening of an exact map's run (``lacking_landmarks``): rejected observations whose points
# agree, from at least SCREEN_POSES different poses, within SCREEN_SIGMAS of their spread.
SCREEN_POSES = 3
SCREEN_SIGMAS = 3.0


def lacking_landmarks(dataset: Dataset, T_world_robot: np.ndarray, pose_cov: np.ndarray, rejected: np.ndarray,
                      map_reach: float = 0.0) -> int:
    """How many places away from every mapped landmark the run's rejected observations
    (``rejected`` (K,) bool) point at from ``SCREEN_POSES`` or more poses, more of them than the
    rejected points around the place put there by chance (``_beyond_chance``): landmarks the map
    lacks (clutter, uniform over what the cameras see, agrees with itself three times only where
    it is dense). Each observation with range becomes a world
    point through its pose's estimate (N, 4, 4); they agree within ``SCREEN_SIGMAS`` of the spread
    of the pose's position and the measurement (``pose_cov`` (N, 6, 6) in the world), and away
    from every mapped landmark by that and ``map_reach`` more (how far a mapped landmark may be from
    its map position: under a prior, a moved landmark's rejected observations are not a landmark
    the map lacks). Rays (pixels) are not screened; a planar robot's points are (on the floor)."""
    from camloc.association import PointIndex  # a scan below a few thousand points: no scipy for a small run
    from camloc.sensors import sensors_of

    obs = np.flatnonzero(rejected & places_points(dataset.obs_kind))
    if obs.size < SCREEN_POSES:
        return 0
    sensors, obs_sensor = sensors_of(dataset)
    points, spread = np.zeros((obs.size, 3)), np.zeros(obs.size)
    for sensor_id in np.unique(obs_sensor[obs]).tolist():
        at = obs_sensor[obs] == sensor_id
        mine = obs[at]
        sensor = sensors[sensor_id]
        # a marker's position, as a floor point's (its heading is not screened)
        p_camera, G = slam.back_project(dataset.obs_z[mine], replace(sensor, kind=measurement.POINT2) if sensor.kind == measurement.MARKER else sensor)
        T = T_world_robot[dataset.obs_pose_index[mine]] @ sensor.T_robot_camera
        points[at] = np.einsum("nij,nj->ni", T[:, :3, :3], p_camera) + T[:, :3, 3]
        noise = np.einsum("nij,njk,nlk->nil", G, dataset.obs_cov[mine], G)
        position = pose_cov[dataset.obs_pose_index[mine], :3, :3]
        spread[at] = np.sqrt(np.trace(noise, axis1=1, axis2=2) + np.trace(position, axis1=1, axis2=2))
    radius = SCREEN_SIGMAS * float(np.median(spread))
    # an observation from a pose the run was unsure of (a slip, a stretch without pairs) is not
    # placed well enough to say what the map lacks: several of them agree on where the estimate
    # went wrong, not on a landmark
    sure = spread <= 2.0 * float(np.median(spread))
    obs, points = obs[sure], points[sure]
    if dataset.landmark_ids.size:  # a rejected observation near a mapped landmark is one the run missed, not one the map lacks
        landmarks = PointIndex(dataset.landmark_xyz)
        lone = np.array([landmarks.within(p, radius + map_reach).size == 0 for p in points], dtype=bool)
        obs, points = obs[lone], points[lone]
        if obs.size < SCREEN_POSES:
            return 0
    index = PointIndex(points)
    pose = dataset.obs_pose_index[obs]
    floor = np.isin(dataset.obs_kind[obs], measurement.PLANAR_KINDS)
    chance = PLACE_CHANCE / obs.size  # each point's share of the run's
    places = 0
    claimed = np.zeros(obs.size, bool)
    for i in range(obs.size):
        neighbours = index.within(points[i], radius) if not claimed[i] else ()
        if claimed[i] or len(neighbours) < SCREEN_POSES:
            continue
        if (np.unique(pose[neighbours]).size >= SCREEN_POSES
                and _beyond_chance(index, points[i], radius, len(neighbours), chance, 2 if floor[i] else 3)):
            places += 1
            claimed[neighbours] = True
    return places


def moved_in_place_of_added(map_xyz: np.ndarray, estimated: LandmarkMap, rows: np.ndarray, sigma: float,
                            gate: float) -> np.ndarray:
    """(L,) for each mapped landmark (at ``map_xyz`` (L, 3) in the map as given), the row in
    ``estimated`` (a mapping pass's map under a prior) of the landmark the pass added in its
    place, -1 for none. ``rows`` (L,): each mapped landmark's row in ``estimated``; ``sigma``: the
    map's, metres; ``gate``: the chi^2 value (3 dof) within which an added landmark's estimate
    fits a mapped landmark's prior (``sigma^2 I`` about its map position, with the added
    landmark's own covariance).

    Why: a landmark moved by a few sigma whose observations failed its gate (or whose map position
    lay outside the cameras' candidate view while it was in view) is added as a new landmark beside
    its own map entry: the same landmark twice, the mapped one left where it is not. An added
    landmark that fits a mapped landmark's prior and was seen more often than that landmark
    (never, mostly: a landmark in view is seen, so one at its map position would have been paired
    there) stands in for it, moved. Each added landmark stands for at most one mapped landmark,
    the best-fitting; an added landmark seen once is not enough to say so."""
    from scipy.spatial import cKDTree

    taken = np.full(map_xyz.shape[0], -1, np.int64)
    mapped = np.flatnonzero(rows >= 0)
    added = np.flatnonzero(estimated.added & (estimated.observations >= 2))
    if mapped.size == 0 or added.size == 0:
        return taken
    S = sigma**2 * np.eye(3) + estimated.cov[added]  # (A, 3, 3)
    # d' S^-1 d <= gate only within |d| <= sqrt(gate * largest eigenvalue of S): a ball query, not
    # every (added, mapped) pair (20,000-landmark maps)
    reach = np.sqrt(gate * np.linalg.eigvalsh(S)[:, -1])
    tree = cKDTree(map_xyz[mapped])
    seen = estimated.observations[rows[mapped]]
    for a in np.argsort(-estimated.observations[added], kind="stable").tolist():  # the best-seen added landmark first
        near = np.sort(np.asarray(tree.query_ball_point(estimated.xyz[added[a]], reach[a]), dtype=np.int64))
        near = near[(taken[mapped[near]] < 0) & (seen[near] < estimated.observations[added[a]])]
        if near.size == 0:
            continue
        d = map_xyz[mapped[near]] - estimated.xyz[added[a]]  # (K, 3)
        d2 = np.einsum("ki,ki->k", d, np.linalg.solve(S[a], d.T).T)
        if d2.min() <= gate:
            taken[mapped[near[int(np.argmin(d2))]]] = added[a]
    return taken
    d = estimated.xyz[added][:, None, :] - map_xyz[mapped][None, :, :]  # (A, M, 3)
    S = sigma**2 * np.eye(3) + estimated.cov[added]  # (A, 3, 3)
    d2 = np.einsum("ami,aij,amj->am", d, np.linalg.inv(S), d)
    seen = estimated.observations[rows[mapped]]
    for a in np.argsort(-estimated.observations[added], kind="stable").tolist():  # the best-seen added landmark first
        fits = np.where((d2[a] <= gate) & (taken[mapped] < 0) & (seen < estimated.observations[added[a]]), d2[a], np.inf)
        if np.isfinite(fits.min()):
            taken[mapped[int(np.argmin(fits))]] = added[a]
    return taken


# Clutter agrees with itself by chance where it is dense: a planar robot's rejected floor points
# (point2) lie in a plane, where it does far more often than a camera's in space (complete 1,000-pose
# maps with 10% clutter: 5-9 places of three chance clutter points each, and the run then went
# through the mapping pass), and a camera's do too at 30-50% clutter (complete 1,000-pose maps: 6-54
# places, 1-3 clutter landmarks added, and the beam's run again with the lowered null cost: aerial
# 0.153 -> 0.536 m). A place counts only where as many points within the radius are unlikely among
# the points around it (within DENSITY_REACH radii, spread evenly over the plane or the space), the
# chance that any of the run's rejected points makes one below PLACE_CHANCE (each point's share of
# it). Measured: on the floor, no place on complete 300- and 1,000-pose maps with 10% or 30% clutter
# (4 radii around left one of five chance points near the start of a 30% world), 12-124 on 300-pose
# worlds with half withheld; in space (2026-12-05, docs/performance.md), none on complete 1,000-pose
# maps with 30-50% clutter, 24-43 on 300-pose worlds with half withheld and 26-35 on 1,000-pose
# worlds with 10-20% withheld and 10-30% clutter, each run's result unchanged.
DENSITY_REACH = 8.0
PLACE_CHANCE = 0.01


def _beyond_chance(index, point: np.ndarray, radius: float, count: int, chance: float, dim: int) -> bool:
    """Whether ``count`` rejected points within ``radius`` of ``point`` (itself among them) are
    more than the points around it put there with probability ``chance``: each of the others
    within ``DENSITY_REACH`` radii falls within the radius with probability ``1 / DENSITY_REACH^dim``
    where they are spread evenly over ``dim`` dimensions (2: the floor, 3: space;
    ``tails.binomial_tail``)."""
    from camloc.tails import binomial_tail

    around = index.within(point, DENSITY_REACH * radius).size - 1
    return binomial_tail(count - 2, around, 1.0 / DENSITY_REACH**dim) < chance
