"""The mapping localizer's tags (``camloc.slam_run``): a tag's orientation in the state beside its
centre (``camloc.slam_tags``' model), as the localizer holds it (``camloc.tag_orientations``):

- **association**: a tag observation is judged as one measurement of centre and orientation
  together: its pair with a tag costs the joint innovation's ``d^2 + ln det S - ln det R`` (S of
  both halves, their correlation through the pose and the tag's own blocks included) and must
  pass the joint gate (``TAG_GATE_TAIL``); with a landmark without orientation, or left unexplained,
  its orientation costs clutter's (uniform over SO(3), ``rotation_clutter_cost``). Two tags near
  one another are told apart by their orientations;
- **update**: the pairs decided, each tag pair's orientation joins it, unless its orientation fails
  ``VETO_GATE`` at the prior (the pair is then dropped: the localizer's rule);
- **state**: a tag enters with its orientation (a first sighting: ``slam_tags.inverse_orientation``;
  a map's tag under a prior: ``map_sigma`` radians per axis, as a marker's heading), leaves and
  re-enters it with its centre.

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np

from camloc import geometry, measurement, slam, slam_tags
from camloc.dataset import LANDMARK_POINT3
from camloc.slam_association import column_products
from camloc.slam_landmarks import UNPAIRED
from camloc.tag_orientations import TAG_GATE_TAIL, VETO_GATE, rotation_clutter_cost
from camloc.tails import chi2_quantile


class TagStates:
    """A mix-in of ``slam_run.MappingLocalizer`` (its ``x``, ``P``, ``table``, ``state_landmark``,
    ``sensors``, ``obs_sensor``, ``dataset``, ``association_cov``, ``chosen``)."""

    def _init_tags(self, held: bool, null_cost: np.ndarray) -> np.ndarray:
        """The run's tags: ``rotation_of`` (K,) each tag position's orientation observation (-1:
        none), the map's tags' orientations in the table (held exactly, or to ``map_sigma`` radians
        under a prior); returns the association's null cost (K,) with a tag's orientation left
        unexplained too."""
        ds = self.dataset
        rotation = np.flatnonzero(ds.obs_kind == measurement.TAG_ROTATION)
        self.has_tags = bool(rotation.size)
        self.ray_turns: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # a tag's ray: its world orientation and spread
        self.rotation_of = np.full(ds.num_observations, -1, np.int64)
        self.rotation_of[ds.obs_partner[rotation]] = rotation
        if not self.has_tags:
            return null_cost
        if held:
            tag = np.flatnonzero(np.isfinite(ds.landmark_quat_xyzw[:, 0]))
            self.table.rotvec[tag] = geometry.so3_log(geometry.quat_to_matrix(ds.landmark_quat_xyzw[tag]))
            self.table.rot_cov[tag] = self.table.cov[tag]  # map_sigma^2 I: metres read as radians (a marker's heading's rule)
            self.table.kind[tag] = LANDMARK_POINT3  # seen by cameras as a point is (a planar map's tags too)
        self.rotation_clutter = np.zeros(ds.num_observations)
        self.rotation_clutter[ds.obs_partner[rotation]] = rotation_clutter_cost(self.association_cov[rotation])
        tail = min(1.0 - self.config.gate, TAG_GATE_TAIL)
        self.tag_position_gate = np.array([chi2_quantile(d, tail) if d else 0.0 for d in range(measurement.MAX_DIM + 1)])
        self.joint_gate = chi2_quantile(measurement.dof_of(ds.obs_kind) + 3, tail)
        return null_cost + self.rotation_clutter

    def _position_gates(self, obs: np.ndarray) -> np.ndarray:
        """The chi^2 gate (M,) of each observation's position alone: its dof's at the association's
        probability, a tag's at its joint gate's tail (``TAG_GATE_TAIL``: its orientation then
        judges the pair with it, ``_orientation_costs``; at 99% the position alone left out right
        pairs that then became a second landmark beside the first)."""
        gates = self.gate[self.obs_dof[obs]]
        if self.has_tags:
            tags = self.rotation_of[obs] >= 0
            gates = np.where(tags, self.tag_position_gate[self.obs_dof[obs]], gates)
        return gates

    def _is_tag(self, landmarks) -> np.ndarray:
        return np.isfinite(self.table.rotvec[landmarks, 0])

    # -- association ----------------------------------------------------------------------------

    def _orientation_prediction(self, r: int, landmark: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prediction (3,), Jacobian (3, dim) and extra covariance (3, 3) (a tag held outside
        the state with a covariance) of orientation observation r of tag ``landmark``."""
        row = int(self.table.rot_row[landmark])
        rotvec = self.x.L[row] if row >= 0 else self.table.rotvec[landmark]
        sensor = self.sensors[int(self.obs_sensor[r])]
        z_hat, H = slam_tags.observe_orientations(self.x, sensor, rotvec[None], np.array([2 + row if row >= 0 else -1]),
                                                  self.x.dim, self.dataset.obs_z[r][None])
        A = -H[0, :, 3:6]  # a world error e of the tag enters as the heading's with the sign turned
        extra = A @ self.table.rot_cov[landmark] @ A.T if row < 0 else np.zeros((3, 3))
        return z_hat[0], H[0], extra

    def _orientation_costs(self, obs: np.ndarray, landmarks: np.ndarray, cost: np.ndarray, z_hat: np.ndarray,
                           H: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """``landmark_costs``' costs (O, C) of observations ``obs`` (O,) against ``landmarks`` (C,)
        (their predictions z_hat (C, 3), Jacobians H (C, 3, dim), extra covariances (C, 3, 3)) with
        the tags' orientations: a tag's with a tag, the joint cost and gate; with another landmark,
        its orientation's clutter cost added."""
        if not self.has_tags:
            return cost
        cost = cost.copy()
        ds = self.dataset
        for i, o in enumerate(obs.tolist()):
            r = int(self.rotation_of[o])
            if r < 0:
                continue
            for j in np.flatnonzero(cost[i] < UNPAIRED).tolist():
                landmark = int(landmarks[j])
                if not self._is_tag(landmark):
                    cost[i, j] += self.rotation_clutter[o]
                    continue
                dof = int(self.obs_dof[o])
                z_rot, H_rot, extra_rot = self._orientation_prediction(r, landmark)
                y = np.concatenate([(ds.obs_z[o] - z_hat[j])[:dof], ds.obs_z[r] - z_rot])
                H6 = np.vstack([H[j][:dof], H_rot])
                R6 = np.zeros((dof + 3, dof + 3))
                R6[:dof, :dof] = (self.association_cov[o] + extra[j])[:dof, :dof]
                R6[dof:, dof:] = self.association_cov[r] + extra_rot
                S = column_products(H6[None], self.P)[0] + R6
                d2 = float(y @ np.linalg.solve(S, y))
                noise = np.linalg.slogdet(self.association_cov[o][:dof, :dof])[1] + np.linalg.slogdet(self.association_cov[r])[1]
                joint = d2 + np.linalg.slogdet(S)[1] - noise
                cost[i, j] = joint if np.isfinite(joint) and d2 <= self.joint_gate[o] else UNPAIRED
        return cost

    # -- update ---------------------------------------------------------------------------------

    def _with_orientations(self, pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """``pairs`` and, after them, the orientation observation of each pair of a tag's position
        with a tag, paired with that tag; a pair whose orientation fails ``VETO_GATE`` at the prior
        is dropped with it (a tag's position alone can pair with the wrong tag nearby)."""
        if not self.has_tags or not pairs:
            return pairs
        kept, riders = [], []
        for o, landmark in pairs:
            r = int(self.rotation_of[o])
            if r < 0 or not self._is_tag(landmark):
                kept.append((o, landmark))
                continue
            z_rot, H_rot, extra_rot = self._orientation_prediction(r, landmark)
            S = column_products(H_rot[None], self.P)[0] + self.association_cov[r] + extra_rot
            e = self.dataset.obs_z[r] - z_rot
            if float(e @ np.linalg.solve(S, e)) <= VETO_GATE:
                kept.append((o, landmark))
                riders.append((r, landmark))
        return kept + riders

    def _state_rows(self, obs: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """Each pair's row in the state (-1: held outside it): a tag's orientation's own row."""
        rows = self.table.state_row[landmarks]
        if self.has_tags:
            rotation = self.dataset.obs_kind[obs] == measurement.TAG_ROTATION
            rows = np.where(rotation, self.table.rot_row[landmarks], rows)
        return rows

    # -- the state ------------------------------------------------------------------------------

    def _enter_orientations(self, landmarks: list[int]) -> None:
        """The tags among ``landmarks`` (entering the state with their centres) enter with their
        orientations, from the table's world covariance (``slam_tags.prior_coefficients``)."""
        if not self.has_tags:
            return
        table = self.table
        tags = [lm for lm in landmarks if self._is_tag(lm) and table.rot_row[lm] < 0 and np.any(table.rot_cov[lm] != 0.0)]
        if not tags:
            return
        q = len(tags)
        B = np.broadcast_to(slam_tags.prior_coefficients(), (q, 3, slam.POSE_DIM))
        self.x, self.P = slam.augmented_many(self.x, self.P, table.rotvec[tags], B, table.rot_cov[tags], np.ones(q, bool))
        table.rot_row[tags] = len(self.state_landmark) + np.arange(q)
        self.state_landmark.extend(tags)

    def _add_orientation(self, o: int, landmark: int, observations: list[int]) -> None:
        """A new landmark from observation o is a tag where o has an orientation: it enters the
        state too (``slam_tags.inverse_orientation``), and its observations' orientations are its."""
        r = int(self.rotation_of[o])
        if r < 0:
            return
        sensor = self.sensors[int(self.obs_sensor[r])]
        rotvec, B, N = slam_tags.inverse_orientation(self.x, sensor, self.dataset.obs_z[r], self.dataset.obs_cov[r])
        self.x, self.P = slam.augmented_many(self.x, self.P, rotvec[None], B[None], N[None], np.ones(1, bool))
        self.table.rotvec[landmark] = rotvec
        self.table.rot_row[landmark] = len(self.state_landmark)
        self.state_landmark.append(landmark)
        riders = self.rotation_of[np.array(observations, np.int64)]
        self.chosen[riders[riders >= 0]] = landmark

    def _ray_fits(self, o: int):
        """Where pixel observation o is a tag's, whether a track's observations are of a tag o's
        orientation agrees with (``_turns_agree``), None otherwise: rays of two tags that meet
        by chance are not one track (measured: such a track made a tag 120-150 degrees off)."""
        if not self.has_tags or self.rotation_of[o] < 0:
            return None
        r = int(self.rotation_of[o])
        R_world = self.x.R @ self.sensors[int(self.obs_sensor[r])].T_robot_camera[:3, :3] @ geometry.so3_exp(self.dataset.obs_z[r])
        # its world orientation, and the spread of it: the measurement's and the robot's heading's
        self.ray_turns[o] = (R_world, R_world @ self.dataset.obs_cov[r] @ R_world.T + self.P[3:6, 3:6])
        return lambda observations: self._turns_agree(o, observations)

    def _turns_agree(self, o: int, observations: list) -> bool:
        """Whether every one of ``observations`` with a world orientation (``ray_turns``) is within
        ``VETO_GATE`` of o's."""
        R_o, C_o = self.ray_turns[o]
        for other in observations:
            if other in self.ray_turns:
                R_i, C_i = self.ray_turns[other]
                e = geometry.so3_log(R_o @ R_i.T)
                if float(e @ np.linalg.solve(C_o + C_i, e)) > VETO_GATE:
                    return False
        return True

    def _position_rows(self) -> np.ndarray:
        """(m,) bool: which of the state's landmark rows are positions (not a tag's orientation)."""
        return ~self.x.orientation if self.x.orientation is not None else np.ones(self.x.L.shape[0], bool)

    def _leave_orientations(self, landmarks: np.ndarray, rows: np.ndarray) -> None:
        """The state's orientation rows ``rows`` (of tags ``landmarks``) leave it: the table keeps
        their estimate and world covariance."""
        self.table.rotvec[landmarks] = self.x.L[rows]
        for landmark, row in zip(landmarks.tolist(), rows.tolist()):
            self.table.rot_cov[landmark] = slam_tags.orientation_world_cov(self.P, row)

    def _estimated_orientations(self) -> tuple[np.ndarray, np.ndarray]:
        """Every table landmark's orientation (rotation vector (n, 3), NaN: not a tag) and its world
        covariance (n, 3, 3), the state's estimate where it holds one."""
        rotvec, cov = self.table.rotvec.copy(), self.table.rot_cov.copy()
        for row, landmark in enumerate(self.state_landmark):
            if self.x.orientation is not None and self.x.orientation[row]:
                rotvec[landmark], cov[landmark] = self.x.L[row], slam_tags.orientation_world_cov(self.P, row)
        return rotvec, cov

