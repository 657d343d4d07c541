"""The mapping localizer (``camloc run --map prior|none``): EKF-SLAM over a map that may be wrong,
incomplete or absent.

    result = localize_mapping(dataset, replace(config, map="prior", map_sigma=0.1))

One pose at a time (``MappingLocalizer.step``):

1. predict (``camloc.slam``: the invariant error, the pose block only);
2. associate the pose's observations, per camera, with the landmarks in view: mapped ones (held
   at the map under "exact", with the map's ``map_sigma`` under "prior"; unused under "none"),
   added ones, and "none of them" (clutter or a new landmark) at the observation's null cost:
   the assignment of least total cost (``landmark_costs``, the beam's units: Mahalanobis
   distance + ln det S - ln det R) within the chi^2 gate, solved exactly per camera;
3. a landmark paired for the first time, or again after it left the state, enters the state
   with its prior (the map's sigma, or the estimate it left with); one stacked iterated update;
   then landmarks added twice, displaced together from their originals, are fused with them
   (``camloc.slam_fusion``);
4. unassigned observations gather into tracks (``camloc.slam_tracks``): a confirmed track becomes
   an **added** landmark, from its latest observation (the inverse observation);
5. landmarks unseen for ``RETIRE_AFTER`` poses leave the state (marginalized) and wait in the
   table with the estimate and covariance they left with, so that the state stays small (the
   filter's cost does not grow with the map): a landmark seen again re-enters from there, its
   correlation with the pose at that time dropped (the one approximation of this design).

The oracle association pairs by the file's ids; an id the map lacks becomes a landmark at its
second observation (clutter's ids are seen once). Pure computation: no I/O, no printing.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, Optional

import numpy as np

from camloc import ekf, geometry, measurement, planar, slam, slam_tags
from camloc.association import mahalanobis_3x3
from camloc.diagnostics import divergence_cause
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, Dataset, observations_by_pose
from camloc.filters import make_filter
from camloc.lacking_spread import GivenPairsDoubt
from camloc.localizer_config import LocalizerConfig
from camloc.observation_space import candidate_range, observation_noise, planar_range
from camloc.results import UNASSOCIATED, RunResult
from camloc.run_records import build_result, recorded_nis
from camloc.sensors import sensors_of
from camloc.slam_anchors import RayAnchors
from camloc.slam_association import BEAM_RECENT, PoseAssociation
from camloc.slam_fusion import LandmarkFusion
from camloc.slam_landmarks import LandmarkAdditions, LandmarkTable, floor_sure_view, sure_view
from camloc.slam_tag_states import TagStates
from camloc.slam_tracks import Tracks
from camloc.tails import chi2_quantile

ProgressCallback = Callable[[int, int], None]

# Beyond this distance from the run's origin the mapping pass lost precision (measured: docs/performance.md,
# "A world far from the origin": its error changed in the fifth digit at 10^4 m, it failed from 10^5 m).
FAR_MAPPING_M = 1e4


class MappingLocalizer(PoseAssociation, LandmarkAdditions, RayAnchors, TagStates, GivenPairsDoubt, LandmarkFusion):
    """The mapping localizer's state over one run; ``step(k)`` processes pose k."""

    def __init__(self, dataset: Dataset, config: LocalizerConfig, given_pairs: Optional[np.ndarray] = None,
                 compiled: bool = True):
        from camloc.association import PointIndex

        self.dataset, self.config = dataset, config
        self.given_pairs = given_pairs  # (K,) the map landmark (row) each observation was paired with, -1 none
        self.beam_paired_at = np.full(dataset.landmark_ids.size, -BEAM_RECENT - 1, np.int64)  # the last pose it did so, per landmark
        self.beam_missed = np.zeros(dataset.landmark_ids.size, np.int64)  # poses it was surely in view and not paired
        self.sensors, self.obs_sensor = sensors_of(dataset)
        # the beam's pairs with an exact map that lacks landmarks: each may be of a landmark the
        # map lacks, and the covariance holds that chance (``camloc.lacking_spread``)
        self.doubt_given = given_pairs is not None and config.map == "exact"
        # None: the numpy update (a tag's orientation is the numpy update's only, as in the localizer)
        self.compiled = _compiled_update(self.sensors) if compiled and not np.any(dataset.obs_kind == measurement.TAG_ROTATION) else None
        self.obs_dof = measurement.dof_of(dataset.obs_kind)
        noise = observation_noise(dataset, config)
        self.association_cov, self.log_det_R, self.null_cost = noise.cov, noise.log_det, noise.null_cost
        self.min_depth, self.max_depth, self.max_angle = candidate_range(dataset, config)
        self.planar_range = planar_range(dataset)  # how far a planar robot's point sensor sees (0: none)
        self.reach = max(self.max_depth, self.planar_range) + 1.0  # the landmarks searched around the robot
        self.sure_view = sure_view(dataset)
        self.floor_view = floor_sure_view(dataset)  # a planar robot's point sensor's (None: no such sensor)
        self.gate = np.array([chi2_quantile(int(d), 1.0 - config.gate) for d in range(measurement.MAX_DIM + 1)])
        held = config.map != "none"
        ids = dataset.landmark_ids if held else np.zeros(0, np.int64)
        xyz = dataset.landmark_xyz if held else np.zeros((0, 3))
        sigma2 = config.map_sigma ** 2 if config.map == "prior" else 0.0
        self.table = LandmarkTable(ids, xyz, np.tile(sigma2 * np.eye(3), (ids.size, 1, 1)))
        if held and dataset.planar:
            self._planar_landmarks(dataset)
        self.null_cost = self._init_tags(held, self.null_cost)  # a tag's orientation in the table, its clutter cost
        self.mapped_index = PointIndex(xyz) if ids.size else None
        self.table.scan = self.compiled.live_within if self.compiled is not None else None
        self.state_landmark: list[int] = []  # table index of each landmark in the state
        self.tracks = Tracks(chi2_quantile(3, 1.0 - config.gate), self.min_depth, self.max_depth)
        self.oracle_tracks: dict[int, object] = {}
        self.clones: dict[int, np.ndarray] = {}  # pose -> the table rows of its clone (``RayAnchors``)
        self.oracle_landmark: dict[int, int] = {int(i): n for n, i in enumerate(ids.tolist())}
        all_ids = np.concatenate([dataset.landmark_ids, dataset.pose_ids, dataset.obs_true_landmark, [-1]])
        self.next_id = int(all_ids.max()) + 1
        order, bounds = observations_by_pose(dataset)
        self.obs_order, self.obs_bounds = order, bounds  # pose k's observations: order[bounds[k]:bounds[k + 1]]
        self.obs_of_pose = [order[bounds[k]:bounds[k + 1]] for k in range(dataset.num_poses)]
        if self.has_tags:  # what association sees of a pose: a tag's orientation rides with its position (``TagStates``)
            self.obs_of_pose = [obs[dataset.obs_kind[obs] != measurement.TAG_ROTATION] for obs in self.obs_of_pose]

        self.T_increments = dataset.T_odometry  # a property that converts every quaternion: once, not per pose
        T0 = dataset.T_world_start
        self.x = slam.SlamMean(T0[:3, :3].copy(), T0[:3, 3].copy(), np.zeros((0, 3)))
        self.P = (slam.planar_initial_cov if dataset.planar else slam.initial_cov)(self.x, config.initial_cov())
        self.T_odometry = T0
        n, K = dataset.num_poses, dataset.num_observations
        self.covs = np.zeros((n, 6, 6))  # the SE(3) filter's right perturbation (its states: the poses, at the end)
        self.poses, self.odometry_poses = np.zeros((n, 4, 4)), np.zeros((n, 4, 4))
        self.chosen = np.full(K, -1, np.int64)  # table index per observation
        self.mahalanobis = np.full(K, np.nan)
        self.update_pose_ids: list[int] = []
        self.nis: list[float] = []
        self.map_costs: list[float] = []
        self.nis_dof: list[int] = []
        # without a map a return to a landmark seen long ago is a wide prior and a bent measurement,
        # where Gauss-Newton's iterates can overshoot: the update is the cheapest iterate (``ekf.update``)
        self._monotone = config.map == "none"
        # landmarks added twice fused (``camloc.slam_fusion``); not under the oracle, whose ids are one landmark each
        self._init_fusion(config.association != "oracle")

    def _planar_landmarks(self, dataset: Dataset) -> None:
        """A planar map's kinds in the table: a point of the floor pinned at z = 0 (``slam``'s model
        card), its prior in the plane; a marker with its heading as its third coordinate, held to
        ``map_sigma`` radians under a prior."""
        table = self.table
        table.kind[:] = dataset.landmark_kind
        table.cov[table.kind == LANDMARK_POINT2, 2, 2] = 0.0
        markers = table.kind == LANDMARK_MARKER
        table.xyz[markers, 2] = dataset.landmark_heading[markers]
        table.has_markers = bool(markers.any())

    # -- one pose -------------------------------------------------------------------------------

    def step(self, k: int) -> None:
        try:
            self._step(k)
        except ekf.NUMERICAL_FAILURES as error:
            raise ekf.as_divergence(error).at_pose(int(self.dataset.pose_ids[k]),
                                                   self._far_cause() or divergence_cause(self.dataset)) from None

    def _far_cause(self) -> str:
        """Where the robot or a landmark has gone far from the run's origin (the start, or the world's
        origin within ``recentre.FAR_FROM_ORIGIN_M`` of it), that as the failure's likely cause: the
        invariant error's Jacobians carry world positions, and a path of 10^8 m in one odometry step
        broke the innovation covariance as a start at 10^5 m did before the recentring."""
        far = float(np.max(np.abs(np.vstack([self.x.t.reshape(1, 3), self.x.L.reshape(-1, 3)]))))
        if far <= FAR_MAPPING_M:
            return ""
        return (f"the robot or a landmark is {far:.3g} m from where the run's frame starts, where the mapping pass "
                "loses its precision: odometry that jumps that far usually causes this")

    def _step(self, k: int) -> None:
        ds = self.dataset
        if k > 0:
            predicted = self.compiled.predict(self.x, self.P, self.T_increments[k - 1], ds.odom_cov[k - 1]) if self.compiled else None
            if predicted is None:
                self.x, self.P = slam.predict(self.x, self.P, self.T_increments[k - 1], ds.odom_cov[k - 1])
            else:
                self.x, self.P = slam.SlamMean(predicted[0], predicted[1], self.x.L), predicted[2]
            self.T_odometry = self.T_odometry @ self.T_increments[k - 1]
        obs = self.obs_of_pose[k]
        if self.config.association == "oracle":
            pairs = self._oracle_pairs(k, obs)
        elif self.given_pairs is not None:  # the beam paired these with the map; the rest may be added landmarks
            given = self.given_pairs[obs]
            pairs = [(int(o), int(lm)) for o, lm in zip(obs[given >= 0].tolist(), given[given >= 0].tolist())]
            self.beam_paired_at[given[given >= 0]] = k
            if self.config.map != "exact":  # the misses decide which mapped landmarks are tried again: under a prior only
                self._count_beam_misses(k)
            # under a prior, what the beam left may be a mapped landmark that moved (the beam held
            # the map exactly): the map's landmarks the beam has not paired lately are candidates
            # again, with their prior (one it pairs is where the map says; what it left near one is
            # another landmark)
            pairs += self._associated(obs[given < 0], added_only=self.config.map == "exact", k=k)
        else:
            pairs = self._associated(obs, k=k)
        pairs = self._with_orientations(pairs)  # a tag pair's orientation joins it
        if pairs:
            self._update(k, pairs)
            if self.fusing:
                self._fuse_seen(k, {lm for _, lm in pairs})
        paired = {o for o, _ in pairs}
        self._count_misses({lm for _, lm in pairs})
        unassigned = [int(o) for o in obs.tolist() if int(o) not in paired]
        if self.config.association == "oracle":
            self._oracle_new(k, unassigned)
        else:
            self._tracked(k, unassigned)
        self._retire(k)
        self.covs[k] = self.compiled.pose_right_cov(self.x, self.P) if self.compiled else slam.pose_right_cov(self.x, self.P)
        self.poses[k], self.odometry_poses[k] = self.x.pose(), self.T_odometry

    def _enter(self, landmarks: list[int]) -> None:
        """Landmarks outside the state, held with a covariance, join it (one new covariance for all)."""
        xyz = self.table.xyz[landmarks]
        B = np.stack([slam.world_prior_coefficients(self.x, p) for p in xyz])
        self.x, self.P = slam.augmented_many(self.x, self.P, xyz, B, self.table.cov[landmarks])
        self.table.state_row[landmarks] = len(self.state_landmark) + np.arange(len(landmarks))
        self.state_landmark.extend(landmarks)
        self._enter_orientations(landmarks)

    def _update(self, k: int, pairs: list[tuple[int, int]]) -> None:
        obs, landmarks = np.array(pairs, np.int64).T
        # landmarks outside the state held with a covariance (not exactly) enter it
        positions = landmarks if not self.has_tags else landmarks[self.dataset.obs_kind[obs] != measurement.TAG_ROTATION]
        outside = positions[self.table.state_row[positions] < 0]
        entering = outside[np.any(self.table.cov[outside] != 0.0, axis=(1, 2))].tolist()
        if entering:
            self._enter(entering)
        rows = self._state_rows(obs, landmarks)
        ds = self.dataset
        done = None
        if self.compiled is not None:
            try:
                done = self.compiled(self.x.R, self.x.t, self.x.L, self.P, ds.obs_z[obs], ds.obs_cov[obs], ds.obs_info[obs],
                                     self.table.xyz[landmarks], rows, self.obs_sensor[obs], self.config.iterations,
                                     self._monotone)
            except np.linalg.LinAlgError:  # S not positive definite: the numpy update raises the run's error
                done = None
        if done is not None and done[0]:
            _, R, t, L, self.P, _, _, nis, map_cost, d2 = done
            self.x = slam.SlamMean(R, t, L)
        else:
            innovation, S, nis, map_cost = self._numpy_update(obs, landmarks, rows)
            d2, _ = mahalanobis_3x3(S, innovation.reshape(obs.size, 3))
        if self.doubt_given:
            self._doubt_given(obs, landmarks)
        self.chosen[obs], self.mahalanobis[obs] = landmarks, np.sqrt(d2)
        self.table.last_seen[landmarks] = k
        np.add.at(self.table.observations, positions, 1)
        self.update_pose_ids.append(int(ds.pose_ids[k]))
        self.nis.append(recorded_nis(nis, map_cost, self.config.iterations))
        self.map_costs.append(map_cost)
        self.nis_dof.append(int(self.obs_dof[obs].sum()))

    def _numpy_update(self, obs: np.ndarray, landmarks: np.ndarray, rows: np.ndarray):
        """The pose's iterated update in numpy (the compiled one's reference, ``camloc.slam_compiled``):
        (innovation (3 p,), S's diagonal blocks (p, 3, 3), NIS, MAP cost); sets x and P."""
        fixed_xyz = self.table.xyz[landmarks]
        if self.has_tags:  # a tag's orientation: its rotation vector where the state does not hold it
            rotation = self.dataset.obs_kind[obs] == measurement.TAG_ROTATION
            fixed_xyz[rotation] = self.table.rotvec[landmarks[rotation]]
        sensors = self.obs_sensor[obs]
        in_state = rows >= 0
        groups = [(self.sensors[s], sensors == s) for s in np.unique(sensors).tolist()]
        # H on the columns the pairs touch (the pose, the landmarks seen), never the whole state's
        columns, block = slam.state_columns(rows)

        ds = self.dataset
        kinds = ds.obs_kind[obs]

        def measure(x: slam.SlamMean):
            xyz = fixed_xyz.copy()
            xyz[in_state] = x.L[rows[in_state]]
            if len(groups) == 1:  # one camera: no gathering
                z_hat, H = slam.observe_columns(x, groups[0][0], xyz, block, columns.size)
            else:
                z_hat, H = np.zeros((obs.size, measurement.MAX_DIM)), np.zeros((obs.size, measurement.MAX_DIM, columns.size))
                for sensor, at in groups:
                    if sensor.kind == measurement.TAG_ROTATION:
                        z_hat[at], H[at] = slam_tags.observe_orientations(x, sensor, xyz[at], block[at], columns.size, ds.obs_z[obs[at]])
                    else:
                        z_hat[at], H[at] = slam.observe_columns(x, sensor, xyz[at], block[at], columns.size)
            return slam.wrapped_predictions(z_hat, ds.obs_z[obs], kinds).ravel(), H.reshape(-1, columns.size)

        result = ekf.update(self.x, self.P, ds.obs_z[obs].ravel(), ds.obs_cov[obs], measure, retract=slam.retract,
                            difference=slam.difference, iterations=self.config.iterations, map_cost=True,
                            R_inverse=ds.obs_info[obs], columns=columns, monotone=self._monotone)
        self.x, self.P = result.state, result.cov
        p = obs.size
        S = result.S if result.S.ndim == 3 else result.S.reshape(p, 3, p, 3)[np.arange(p), :, np.arange(p), :]
        return result.innovation, S, result.nis, result.map_cost

    # -- landmarks the map lacks ----------------------------------------------------------------

    def result(self, filter_seconds: float) -> RunResult:
        table = self.table
        unmapped = table.dead | table.tentative
        left_out = (self.chosen >= 0) & unmapped[np.maximum(self.chosen, 0)] if len(table) else np.zeros(self.chosen.size, bool)
        self.chosen[left_out], self.mahalanobis[left_out] = -1, np.nan  # pairs with what the map does not keep
        chosen_ids = np.where(self.chosen >= 0, self.table.ids[np.maximum(self.chosen, 0)] if len(self.table) else 0, UNASSOCIATED)
        if self.dataset.planar:  # a planar robot's run is recorded as the SE(2) filter's: (x, y, theta), 3 dof
            filter_model, states, covs = make_filter("se2"), planar.flatten(self.poses), planar.planar_block(self.covs)
        else:
            filter_model, states, covs = make_filter("se3"), np.concatenate(geometry.pose_to_quat(self.poses), axis=1), self.covs
        result = build_result(
            self.dataset, self.config, filter_model, states, covs,
            self.poses, self.odometry_poses,
            chosen_ids.astype(np.int64), self.mahalanobis, self.update_pose_ids, self.nis, self.map_costs, self.nis_dof,
            warnings=[], slip_pose_ids=[], candidate_range=(self.min_depth, self.max_depth, self.max_angle),
            timing={"filter_seconds": filter_seconds, "engine": "numpy" if self.compiled is None else "compiled update", "replay_process": False,
                    "replay_process_peak_mb": None, "replay_thread": False})
        landmark_map = self.estimated_map()
        result = replace(result, landmark_map=landmark_map)
        result.summary["map"] = {
            "mode": self.config.map, "sigma": self.config.map_sigma if self.config.map == "prior" else None,
            "mapped": int(self.table.num_mapped), "added": int(np.count_nonzero(landmark_map.added)),
            "mapped_observed": int(np.count_nonzero(self.table.observations[:self.table.num_mapped])),
            "estimator": "invariant EKF-SLAM", "beam_seconds": 0.0,
        }
        return result


def _compiled_update(sensors: dict):
    """The compiled update of these sensors (``camloc.slam_compiled``: numba, imported here so that
    the numpy update loads none), or None where it does not model one of them."""
    from camloc.constants import CONVERGED
    from camloc.slam_compiled import CompiledUpdate

    update = CompiledUpdate(sensors, geometry._SMALL_ANGLE, CONVERGED)  # the numpy update's thresholds
    return update if update.usable else None


def localize_mapping(dataset: Dataset, config: LocalizerConfig, on_progress: Optional[ProgressCallback] = None,
                     given_pairs: Optional[np.ndarray] = None, compiled: bool = True) -> RunResult:
    """Localize and map every pose of ``dataset`` (``config.map`` "prior" or "none"); the
    RunResult carries the estimated map (``landmark_map``). ``given_pairs`` (K,): the map landmark
    (row) each observation is paired with, -1 for none, where another association (the beam, over
    the whole run) decided the map's pairs; the rest are decided here among added landmarks, new
    ones and clutter. ``compiled``: each pose's update compiled (``camloc.slam_compiled``), else in numpy."""
    started = time.perf_counter()
    localizer = MappingLocalizer(dataset, config, given_pairs, compiled)
    n = dataset.num_poses
    stride = max(1, n // 200)
    for k in range(n):
        localizer.step(k)
        if on_progress is not None and (k % stride == 0 or k == n - 1):
            on_progress(k + 1, n)
    return localizer.result(time.perf_counter() - started)
