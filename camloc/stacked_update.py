"""The numpy localizer's stacked, iterated EKF update of (x, P) with a pose's pairs
(``StackedUpdate.updated``), as its filter and its beam's hypotheses compute it: every pair's
camera model, the file's noise or the noise association judges pairs by, and a restart from one
update in camera-frame points where the innovation is too unlikely for Gauss-Newton from the
prior's linearization."""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from camloc import ekf, geometry, measurement, models, planar, tags
from camloc.dataset import Dataset
from camloc.observation_space import ObservationNoise
from camloc.sensors import intrinsics_by_row, observed_as_rig
from camloc.tails import chi2_quantile


class PairMeasurement:
    """A pose's pairs' measurement function (``ekf.MeasurementFunction``: state -> (z_hat, H)) and
    whether a state is feasible for them: every landmark in front of the camera that saw it
    (``measurement.in_front``), without which the MAP cost is infinite (``ekf.posterior_cost``)."""

    __slots__ = ("measure", "feasible")

    def __init__(self, measure, feasible):
        self.measure, self.feasible = measure, feasible

    def __call__(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.measure(state)


class StackedUpdate:
    """The update of ``dataset``'s pairs under ``filter`` (``camloc.filters``) with ``iterations``
    linearizations; ``cameras`` and ``obs_sensor`` by sensor (``sensors.sensors_of``), ``noise``
    how association judges each observation (``observation_space.observation_noise``),
    ``obs_dof`` (K,) each observation's degrees of freedom."""

    def __init__(self, dataset: Dataset, filter, iterations: int, cameras: dict, obs_sensor: np.ndarray, noise: ObservationNoise,
                 obs_dof: np.ndarray):
        self.dataset = dataset
        self.filter = filter
        self.iterations = iterations
        self.cameras, self.obs_sensor = cameras, obs_sensor
        self.single_camera = 0 if len(cameras) == 1 else None
        self.sensor_ids = np.unique(obs_sensor).tolist()  # ascending, as np.unique of a pose's sensors orders them
        # whether any measurement has an angle to wrap, or is a tag's orientation (a camera's is neither)
        self.angled = planar.has_angles(dataset.obs_kind)
        self.tagged = bool(np.any(dataset.obs_kind == measurement.TAG_ROTATION))
        self.association_cov, self.association_info = noise.cov, noise.info
        self.association_log_det, self.null_cost = noise.log_det, noise.null_cost
        self.point, self.point_cov = noise.point, noise.point_cov
        self.obs_dof = obs_dof
        self.nis_bounds: dict[int, float] = {}

    def updated(
        self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray, *, map_cost: bool = False,
        at_prior: tuple[np.ndarray, np.ndarray] | None = None, for_association: bool = False,
        start: Optional[np.ndarray] = None, step_sigma: float = 0.0,
    ) -> ekf.UpdateResult:
        """The stacked (iterated) EKF update of (x, P) with the given pairs; ``at_prior``: their
        predictions (p, 3) and Jacobians (p, 3, n) at x, when the caller has them. With
        ``for_association``, the pairs weigh by the noise association judges them by
        (``association_cov``): the scratch filters that decide an association, not the estimate.
        ``start``: a state near the posterior, when the caller knows one; the iterations also run
        from it, and the posterior with the lower MAP cost is kept. A posterior whose MAP cost is
        beyond the 99.9% chi^2 bound of its degrees of freedom is sought again from the prior (``damped``)
        where ``map_cost`` is asked for (the estimate's update; the beam's scratch updates as before).
        ``step_sigma``: ``ekf.update``'s (the beam's update of one ray: ``constants.RAY_STEP_SIGMA``)."""
        z = self.dataset.obs_z[obs].reshape(-1)
        if for_association:
            R, R_inverse = self.association_cov[obs], self.association_info[obs]
        else:  # the blocks of a block-diagonal covariance (ekf.update)
            R, R_inverse = self.dataset.obs_cov[obs], self.dataset.obs_info[obs]
        # the estimate's update only rules out states behind a camera: the beam's scratch updates
        # and chain check read the plain cost (docs/filter.md, "Behind the camera")
        groups, measure = self.measurement_function(obs, landmarks, in_front=map_cost and not for_association)
        prior = measure(x) if at_prior is None else (at_prior[0].reshape(-1), at_prior[1].reshape(-1, at_prior[1].shape[-1]))
        options = dict(retract=self.filter.retract, difference=self.filter.difference, iterations=self.iterations,
                       at_prior=prior, R_inverse=R_inverse, step_sigma=step_sigma)
        result = ekf.update(x, P, z, R, measure, map_cost=map_cost, **options)
        if self.iterations < 2:
            return result
        starts = [] if start is None else [start]
        bound = self.nis_bound(int(self.obs_dof[obs].sum()))
        if result.nis > bound:
            # An innovation this unlikely under the prior's linearization: with a wide prior (after
            # a slip, or odometry much noisier than the landmarks' spacing) Gauss-Newton in (u, v,
            # depth) from the prior can stall far from the MAP estimate. Iterate also from one
            # update in camera-frame points, where the model is nearly linear in the position.
            starts.append(self.point_step(x, P, obs, groups, prior))
        if not starts and not (map_cost and result.map_cost > bound):
            return result
        best, lowest = result, result.map_cost if map_cost else ekf.posterior_cost(result.state, x, P, z, R, measure, self.filter.difference, R_inverse)
        for state in starts:  # keep whichever posterior the MAP cost prefers
            alternative = ekf.update(x, P, z, R, measure, map_cost=True, start=state, **options)
            if alternative.map_cost < lowest:
                best, lowest = alternative, alternative.map_cost
        if map_cost and lowest > bound:  # the estimate disagrees with its pairs and prior: not the MAP, or no MAP agrees
            best, lowest = self.damped(best, lowest, x, P, z, R, measure, options)
        if best is result or map_cost:
            return best
        return replace(best, map_cost=float("nan"))

    def damped(self, best: ekf.UpdateResult, lowest: float, x, P, z, R, measure, options: dict):
        """``best`` (of MAP cost ``lowest``, beyond its chi^2 bound) or the posterior at the MAP
        estimate the damped Gauss-Newton (``ekf.damped_gauss_newton``) finds from the prior,
        whichever costs less; returns it and its cost. Gauss-Newton from a prior as wide as the
        landmarks' depth (odometry 2-3x noisier than the default, pixel Jacobians growing as
        1/depth^2) needs 4-10 linearizations, or runs off; stopped at ``iterations`` it leaves the
        pose off by the prior's spread with the millimetre covariance of its pairs (NEES 1e4-1e9).
        A MAP cost beyond the bound at the MAP estimate is the pairs' own inconsistency: kept,
        and recorded. The compiled twin is the end of ``kernels.update.updated``."""
        state = ekf.damped_gauss_newton(x, P, z, R, measure, retract=options["retract"], difference=options["difference"],
                                        R_inverse=options["R_inverse"])
        again = ekf.update(x, P, z, R, measure, map_cost=True, start=state, **options)
        if again.map_cost < lowest:
            return again, again.map_cost
        return best, lowest

    def measurement_function(self, obs: np.ndarray, landmarks: np.ndarray, in_front: bool = False):
        """(groups, measure): the pairs' sensors ((camera, mask) each) and ``measure(state) ->
        (z_hat (3p,), H (3p, n))``, the pairs' predictions in the layout ``ekf.update`` takes: an
        angle predicted on its measurement's branch, a tag's orientation as ``camloc.tags``
        aligns it. With ``in_front``, measure is a ``PairMeasurement`` that also says whether a
        state puts every landmark in front of its camera (the estimate's update)."""
        z = self.dataset.obs_z[obs].reshape(-1)
        cameras = self.obs_sensor[obs]
        if self.single_camera is not None:  # nothing to group (np.unique costs more than the algebra)
            groups = [(self.cameras[self.single_camera], slice(None))]
        elif obs.size == 1:  # one pair (the beam's most frequent update): its sensor
            groups = [(self.cameras[int(cameras[0])], slice(None))]
        else:
            groups = [(self.cameras[c], mask) for c in self.sensor_ids for mask in [cameras == c] if mask.any()]
        landmark_xyz = self.dataset.landmark_xyz[landmarks]
        heading = self.dataset.landmark_heading[landmarks]
        tag_quat = self.dataset.landmark_quat_xyzw[landmarks]
        kinds = self.dataset.obs_kind[obs]
        angles = self.angled and planar.has_angles(kinds)
        tag_rows = np.flatnonzero(kinds == measurement.TAG_ROTATION) if self.tagged else ()
        z_measured = z.reshape(obs.size, 3)

        rig = self.rig(cameras, groups, landmark_xyz)

        def measure(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if len(groups) == 1:
                camera = groups[0][0]
                z_hat, H = self.filter.observe(state, camera.T_robot_camera, camera.intrinsics, landmark_xyz, camera.kind, heading=heading,
                                               tag_quat=tag_quat)
            elif rig is not None:  # the cameras in one batch, the rows in their order
                order, *arguments = rig
                z_hat, H = np.empty((obs.size, 3)), np.empty((obs.size, 3, self.filter.dim))
                z_hat[order], H[order] = self.filter.observe_rig(state, *arguments)
            else:
                z_hat = np.empty((obs.size, 3))
                H = np.empty((obs.size, 3, self.filter.dim))
                for camera, mask in groups:
                    z_hat[mask], H[mask] = self.filter.observe(state, camera.T_robot_camera, camera.intrinsics, landmark_xyz[mask],
                                                               camera.kind, heading=heading[mask], tag_quat=tag_quat[mask])
            if angles:  # an angle predicted on the measurement's branch, so that z - z_hat is the wrapped residual
                z_hat = z_measured - planar.wrap_residuals(z_measured - z_hat, kinds)
            if len(tag_rows):  # a tag's orientation: the innovation is Log(R_pred^-1 R_meas) (camloc.tags)
                z_hat, H = z_hat.copy(), H.copy()
                z_hat[tag_rows], H[tag_rows] = tags.aligned(z_measured[tag_rows], geometry.so3_exp(z_hat[tag_rows]), H[tag_rows])
            return z_hat.reshape(-1), H.reshape(-1, H.shape[-1])

        if not in_front:
            return groups, measure

        def feasible(state: np.ndarray) -> bool:
            T_world_robot = self.filter.pose(state)
            return all(bool(measurement.in_front(T_world_robot @ camera.T_robot_camera, camera.kind, landmark_xyz[mask]).all())
                       for camera, mask in groups)

        return groups, PairMeasurement(measure, feasible)

    def rig(self, cameras: np.ndarray, groups: list, landmark_xyz: np.ndarray) -> Optional[tuple]:
        """(order, mounts, intrinsics, landmarks, sizes, kind): the pairs of several cameras of
        one kind in camera order, for the filter's ``observe_rig`` (the robot's part of the
        model computed once for all); None where they are of several kinds, or the filter has
        no such batch."""
        if len(groups) < 2:
            return None
        kinds = {camera.kind for camera, _ in groups}
        kind = kinds.pop()
        if kinds or not observed_as_rig(self.filter, kind):
            return None
        order = np.argsort(cameras, kind="stable")  # by sensor id, as groups are
        sizes = [int(mask.sum()) for _, mask in groups]
        mounts = [camera.T_robot_camera for camera, _ in groups]
        return order, mounts, intrinsics_by_row([camera for camera, _ in groups], sizes), landmark_xyz[order], sizes, kind

    def pair_spread(self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """What the chance that one of the pairs that updated (x, P) into this posterior is clutter
        adds to its covariance (``ekf.leave_one_out_spread``, at the posterior)."""
        z_hat, H = self.measurement_function(obs, landmarks)[1](x)
        z_hat, H = z_hat.reshape(obs.size, 3), H.reshape(obs.size, 3, -1)
        # a tag's orientation is no association of its own: it rides with its position's pair
        own = self.dataset.obs_kind[obs] != measurement.TAG_ROTATION
        return ekf.leave_one_out_spread(P, (self.dataset.obs_z[obs] - z_hat)[own], H[own], self.dataset.obs_cov[obs[own]],
                                        self.association_cov[obs[own]], self.association_log_det[obs[own]], self.null_cost[obs[own]])

    def point_step(self, x: np.ndarray, P: np.ndarray, obs: np.ndarray, groups: list, prior: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """x after one EKF update with the pairs' measurements as camera-frame points (those
        ``measurement.judged_as_point``; the others, a pixel's ray, as they are)."""
        z_hat, H = prior[0].reshape(-1, 3), prior[1].reshape(obs.size, 3, -1)
        y = planar.wrap_residuals(self.dataset.obs_z[obs] - z_hat, self.dataset.obs_kind[obs])
        Hp, R = H.copy(), self.association_cov[obs].copy()
        for camera, mask in groups:
            if not measurement.judged_as_point(camera.kind):
                continue
            mine = np.arange(obs.size)[mask]
            p_hat, J = models.back_project(z_hat[mine], camera.intrinsics, camera.kind)
            Hp[mine] = J @ H[mine]
            y[mine] = self.point[obs[mine]] - p_hat
            R[mine] = self.point_cov[obs[mine]]
        return self.filter.retract(x, ekf.correction(P, Hp.reshape(3 * obs.size, -1), R, y.reshape(-1)))

    def nis_bound(self, dof: int) -> float:
        """The 99.9% quantile of chi^2 with dof degrees of freedom."""
        if dof not in self.nis_bounds:
            self.nis_bounds[dof] = float(chi2_quantile(dof, 0.001))
        return self.nis_bounds[dof]
