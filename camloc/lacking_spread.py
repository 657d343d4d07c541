"""What the chance that a pair with a mapped landmark is of a landmark the map lacks adds to the
mapping localizer's covariance (issue 38, half the map withheld; docs/mapping.md, "The
association").

Where the map lacks landmarks, the beam decides the map's pairs (``slam_run.MappingLocalizer``
takes them as given), and some of them are an observation of a landmark the map lacks given to
a mapped neighbour: it lies within the gate, and before a landmark is added for it, the beam, which
knows only the map, has no other explanation than "unexplained" at the null cost. Such a pair's
Mahalanobis distance is that of a right one, so no gate tells them apart; the estimate after it
is the wrong one's, with the covariance of a right one (mean NEES above its bound on every
simulated world with half the map withheld, 9-24 in the ten poses after such a pair).

So the update's covariance is the moment of a two-way mixture per pair, as the localizer's is for
clutter (``ekf.leave_one_out_spread``, docs/beam.md "Each pair's chance of being clutter"): the
update as made, weight 1, and "this pair is not of its landmark", the posterior of the other pairs,
weighed by the pair's cost under that posterior against the null cost as the beam priced it where
the map lacks landmarks (``LACKING_NULL_OFFSET`` below the clutter's). Here the mixture's moment
stays in the filter's own covariance (not only the pose's reported one): a wrong pair's shift stays
in the estimate for the poses after it, and so must its doubt.

Pure computation on arrays (``GivenPairsDoubt``: on the mapping localizer's).
"""

from __future__ import annotations

import numpy as np

from camloc import measurement, slam
from camloc.constants import NEGLIGIBLE_MARGIN
from camloc.ekf import left_out_weights, symmetrize

# Where the map lacks landmarks, the beam decides the map's pairs again with the cost of leaving an
# observation unexplained lowered by this much. The default null cost prices an unexplained
# observation as rare clutter spread over all the camera measures; a map that lacks landmarks
# makes them common and near the mapped ones (the same places hold landmarks), and the beam, to
# explain them, pairs them with mapped neighbours and loses the robot where it sees few landmarks.
# Measured (docs/performance.md, "A map that lacks landmarks: the beam decides its pairs again"):
# 300-pose depth worlds, grid/smooth3d/aerial x seeds 0-3, half withheld: runs over 3x the complete
# map's 5 of 12 -> 1 under exact; an offset of 2 lost another (aerial 2: 12 m), 6 cost the grid ones (grid 1: 0.34 m).
# The mapping pass prices "a landmark the map lacks" as the beam's run did: its pairs' doubt
# (``fixed_landmark_spread``) against the same lowered null cost (measured: docs/performance.md, 2026-12-05,
# "The chance that a beam pair is of a landmark the map lacks").
LACKING_NULL_OFFSET = 4.0

POSE_COLUMNS = 6  # the error's pose block (translation, rotation) leads the state (``camloc.slam``)


def fixed_landmark_spread(P: np.ndarray, residuals: np.ndarray, H: np.ndarray, R_update: np.ndarray,
                          R_judged: np.ndarray, log_det_R_judged: np.ndarray, null_cost: np.ndarray) -> np.ndarray:
    """``ekf.leave_one_out_spread`` of pairs whose landmarks are held fixed (an exact map's):
    their Jacobians H (p, 3, 6) touch the pose's columns only, so each alternative's widening and
    shift are ``P[:, :6] (.) P[:6, :]`` and the whole spread is ``P[:, :6] M P[:6, :]`` with one
    6x6 M: O(n^2) for a state of n, not O(p n^2).

    P (n, n) the update's posterior; residuals ``z_i - h_i(x)`` (p, 3) at it; R_update, R_judged
    (p, 3, 3) the noise the update used and the one association judges with, log_det_R_judged (p,);
    null_cost (p,) the alternative's cost. With ``B_i = R_i - H_i P66 H_i'``, pair i left out is
    ``P + P H_i' B_i^-1 H_i P`` about ``x - P H_i' B_i^-1 r_i`` (Woodbury), weighed by
    ``exp(-(null - cost_i) / 2)`` beside the update's 1; returns
    ``sum_i w_i (P H_i' B_i^-1 H_i P + d_i d_i')`` (n, n), ``d_i = P H_i' B_i^-1 r_i``.
    """
    n = P.shape[0]
    if residuals.shape[0] == 0:
        return np.zeros((n, n))
    P_pose = P[:POSE_COLUMNS, :POSE_COLUMNS]
    A = H @ P_pose @ np.swapaxes(H, 1, 2)                            # (p, 3, 3) H P H'
    B = R_update - A
    usable = np.linalg.eigvalsh(B)[:, 0] > 0.0  # B not positive definite by rounding: the pair adds nothing
    if not usable.any():
        return np.zeros((n, n))
    H, A, B = H[usable], A[usable], B[usable]
    w, B_inverse_r = left_out_weights(A, B, residuals[usable], R_update[usable], R_judged[usable], log_det_R_judged[usable],
                                      null_cost[usable])
    # B^-1 (widening) + B^-1 r r' B^-1 (the shift's outer product), each taken to the pose's columns
    inner = np.linalg.solve(B, np.broadcast_to(np.eye(3), B.shape)) + B_inverse_r[:, :, None] * B_inverse_r[:, None, :]
    M = np.einsum("p,pai,pab,pbj->ij", w, H, inner, H)
    P_cols = P[:, :POSE_COLUMNS]
    return symmetrize(P_cols @ M @ P_cols.T)


class GivenPairsDoubt:
    """The doubt in the beam's pairs, a mix-in of ``slam_run.MappingLocalizer`` (whose state it
    reads and whose P it widens: ``x``, ``P``, ``table``, ``sensors``, ``compiled``, the noise)."""

    def _doubt_given(self, obs: np.ndarray, landmarks: np.ndarray) -> None:
        """P widened by the chance that each of the beam's pairs (with the exact map's landmarks,
        held fixed) is of a landmark the map lacks: ``lacking_spread.fixed_landmark_spread`` at
        the update's posterior, the alternative priced at the lacking map's null cost."""
        ds = self.dataset
        given = (landmarks < self.table.num_mapped) & (ds.obs_kind[obs] != measurement.TAG_ROTATION)
        obs, xyz = obs[given], self.table.xyz[landmarks[given]]
        if obs.size == 0:
            return
        if self.compiled is not None:  # the compiled steps' twin (``slam_compiled.fixed_spread_into``; no tag there)
            self.P = np.ascontiguousarray(self.P, float)
            self.compiled.spread_into(self.x, self.P, obs, xyz, self.obs_sensor, ds.obs_z, ds.obs_cov, self.association_cov,
                                      self.log_det_R, self.null_cost, LACKING_NULL_OFFSET, NEGLIGIBLE_MARGIN)
            return
        null_cost = self.null_cost[obs] - LACKING_NULL_OFFSET
        for sensor_id in np.unique(self.obs_sensor[obs]).tolist():
            mine = self.obs_sensor[obs] == sensor_id
            o = obs[mine]
            z_hat, H = slam.observe_columns(self.x, self.sensors[sensor_id], xyz[mine], np.full(o.size, -1), POSE_COLUMNS)
            residuals = ds.obs_z[o] - slam.wrapped_predictions(z_hat, ds.obs_z[o], ds.obs_kind[o])
            self.P = self.P + fixed_landmark_spread(self.P, residuals, H, ds.obs_cov[o], self.association_cov[o],
                                                    self.log_det_R[o], null_cost[mine])
