"""What each observation of a pose may be under one of the numpy beam's hypotheses
(``camloc.beam``): its pool of nearby landmarks, each pair's cost and its innovation in the
coordinates where the hypothesis' linearization explains it best (the measured (u, v, depth) or
the camera-frame point they back-project to), computed in one batch per camera (``PairGating``)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate

import numpy as np

from camloc import association, measurement, models, planar
from camloc.beam_types import BeamContext, Hypothesis
from camloc.constants import POOL_GATE_FACTOR


@dataclass
class PairOptions:
    """What one observation may be under one hypothesis: its pool of nearby landmarks (d^2 within
    ``POOL_GATE_FACTOR`` gates) with their pair costs, infinite where the pair fails the gate."""

    landmarks: np.ndarray   # (g,) landmark indices
    costs: np.ndarray       # (g,) d^2 + ln det S - ln det R, inf outside the gate
    z_hat: np.ndarray       # (g, 3) predicted u, v, depth (for the filter's update)
    H: np.ndarray           # (g, 3, 6) their Jacobian
    y: np.ndarray           # (g, 3) the innovation in the pair's coordinates (``in_best_coordinates``)
    Hc: np.ndarray          # (g, 3, 6) its Jacobian
    Rc: np.ndarray          # (g, 3, 3) the observation's covariance in them
    # (g,) d^2 + ln det S - ln det R inside the gate or not, under the hypothesis the pose's options
    # were first made for (``PairGating.options``; ``conditioned`` keeps them): the miss term judges
    # every explanation of a pose by its parent's pools (``PoseExpansion.expected``, camloc.miss_term)
    pool_costs: np.ndarray


class PairGating:
    """The options of a pose's observations under a hypothesis (``options``), and again under the
    hypothesis conditioned on some of the pose's pairs (``conditioned``), for the run ``ctx``."""

    def __init__(self, context: BeamContext):
        self.ctx = context
        self.R = context.association_cov        # the noise association judges each observation by
        self.log_det_R = context.log_det_R      # ln det R of every observation
        self.point, self.point_cov = context.point, context.point_cov  # every observation in its camera's frame
        self.log_det_point_cov = context.log_det_point_cov
        # which observations have a point (``measurement.judged_as_point``; a pixel is a ray)
        self.ranged = measurement.judged_as_point(context.dataset.obs_kind)
        # whether any measurement has an angle to wrap (``planar.wrap_residuals``; a camera's has none)
        self.angled = planar.has_angles(context.dataset.obs_kind)
        # the sensors in ascending order, as ``np.unique`` of a pose's would give those it has (cheaper for a few)
        self.sensor_ids = np.unique(context.obs_sensor).tolist()

    def options(self, h: Hypothesis, obs: np.ndarray, *, widened_view: bool = False) -> list[PairOptions]:
        """Gated landmarks of every observation under h, computed in one batch per camera; with
        ``widened_view``, among the landmarks within three standard deviations of h's view."""
        out: list[PairOptions] = [None] * obs.size  # type: ignore[list-item]
        cameras = self.ctx.obs_sensor[obs]
        for camera_id in self.sensor_ids:
            rows = np.flatnonzero(cameras == camera_id)
            if rows.size == 0:
                continue
            gate = float(self.ctx.obs_gate[obs[rows[0]]])  # a sensor's observations share their dof
            pool_gate = POOL_GATE_FACTOR * gate
            candidates = self.ctx.visible(h.x, camera_id, h.P if widened_view else None)
            if candidates.size == 0:
                for r in rows:
                    out[r] = empty_options(h.P.shape[0])  # the error's dimension: the SE(3) state is a 4x4 matrix
                continue
            z_hat, H = self.ctx.observe(h.x, camera_id, candidates)
            o = obs[rows]
            spread = self.spread(h.P, camera_id, z_hat, H)
            j, g = self.plausible_pairs(o, z_hat, spread, pool_gate)  # row by row
            p_hat, Hp, HPH, JHPHJ = (part[g] for part in spread)
            d2, costs, in_point = self.in_best_coordinates(o[j], z_hat[g], p_hat, HPH, JHPHJ)
            pool = d2 <= pool_gate  # each observation's pool
            j, g, d2, costs, in_point, p_hat, Hp = (part[pool] for part in (j, g, d2, costs, in_point, p_hat, Hp))
            y, Hc, Rc = self.chosen(in_point, o[j], z_hat[g], H[g], p_hat, Hp)
            pool_costs = costs
            costs = self.with_orientations(h, o[j], candidates[g], d2, costs, (y, Hc, Rc), np.full(d2.size, gate))
            bounds = np.searchsorted(j, np.arange(rows.size + 1))
            for k, r in enumerate(rows):
                part = slice(bounds[k], bounds[k + 1])
                pool = g[part]
                out[r] = PairOptions(candidates[pool], costs[part], z_hat[pool], H[pool], y[part], Hc[part], Rc[part],
                                     pool_costs[part])
        return out

    def spread(
        self, P: np.ndarray, camera_id: int, z_hat: np.ndarray, H: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predictions (z_hat (m, 3), H (m, 3, n)) of camera camera_id under covariance P, also
        as camera-frame points: (p_hat (m, 3), their Jacobian Hp (m, 3, n), the spread of the
        predictions H P H' (m, 3, 3) and of the points Hp P Hp' (m, 3, 3)). A sensor that does not
        measure range has no point: zeros, a singular spread, which fits nothing
        (``in_best_coordinates`` keeps its pixels)."""
        camera = self.ctx.cameras[int(camera_id)]
        HPH = H @ P @ np.swapaxes(H, -1, -2)
        if not measurement.judged_as_point(camera.kind):
            return np.zeros_like(z_hat), np.zeros_like(H), HPH, np.zeros_like(HPH)
        p_hat, J = models.back_project(z_hat, camera.intrinsics, camera.kind)
        return p_hat, J @ H, HPH, J @ HPH @ np.swapaxes(J, -1, -2)

    def plausible_pairs(self, o: np.ndarray, z_hat: np.ndarray, spread: tuple, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """(rows into o, rows into z_hat) of the pairs whose d^2 may be within ``limit`` in either
        coordinates of ``in_best_coordinates``, row-major; the others are surely beyond it. For
        S positive definite, ``y' S^-1 y >= |y|^2 / trace(S)``, and the trace of S = H P H' + R
        is a sum of traces: a bound for every pair from a few numbers per observation and per
        prediction, where d^2 itself needs a 3x3 system per pair (most of a dense view's pairs
        are far out of every gate)."""
        p_hat, _, HPH, JHPHJ = spread
        spread_pixels = np.trace(HPH, axis1=1, axis2=2)[None, :] + np.trace(self.R[o], axis1=1, axis2=2)[:, None]
        spread_point = np.trace(JHPHJ, axis1=1, axis2=2)[None, :] + np.trace(self.point_cov[o], axis1=1, axis2=2)[:, None]
        y_pixels = self.residuals(o[:, None], z_hat[None, :, :])
        y_point = self.point[o][:, None, :] - p_hat[None, :, :]
        near = ((np.einsum("ijk,ijk->ij", y_pixels, y_pixels) <= limit * spread_pixels)
                | ((np.einsum("ijk,ijk->ij", y_point, y_point) <= limit * spread_point) & self.ranged[o][:, None]))
        return np.nonzero(near)

    def in_best_coordinates(
        self, o: np.ndarray, z_hat: np.ndarray, p_hat: np.ndarray, HPH: np.ndarray, JHPHJ: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pairs of observations o (g,) with predictions z_hat (g, 3) (``spread``: as points
        p_hat, their spreads HPH and JHPHJ), each judged in the coordinates where its
        linearization explains it best: the measured (u, v, depth), or the camera-frame point
        they back-project to.

        The two agree to first order and part where the prior is wide. A point is linear in the
        robot's position, so a prediction a few decimetres off (noisy odometry in a dense map)
        keeps a Gaussian spread there while in pixels it bends; pixels can fit better where the
        spread is mostly rotation. The likelier of the two (the smaller
        ``d^2 + ln det S - ln det R``, the same quantity in either) is kept; a joint cost of
        several pairs may take each in its own coordinates.

        Returns d^2 and the cost of each pair, and whether it is judged as a point.
        """
        d2_pixels, log_det_pixels = association.mahalanobis_3x3(HPH + self.R[o], self.residuals(o, z_hat))
        d2_point, log_det_point = association.mahalanobis_3x3(JHPHJ + self.point_cov[o], self.point[o] - p_hat)
        cost_pixels = d2_pixels + log_det_pixels - self.log_det_R[o]
        cost_point = d2_point + log_det_point - self.log_det_point_cov[o]
        in_point = cost_point < cost_pixels
        return np.where(in_point, d2_point, d2_pixels), np.where(in_point, cost_point, cost_pixels), in_point

    def chosen(
        self, in_point: np.ndarray, o: np.ndarray, z_hat: np.ndarray, H: np.ndarray, p_hat: np.ndarray, Hp: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The innovation (g, 3), its Jacobian (g, 3, n) and the observation's covariance (g, 3, 3)
        of g pairs (observations o, predictions z_hat, H and as points p_hat, Hp), each in the
        coordinates ``in_best_coordinates`` chose for it."""
        point = in_point[:, None]
        y = np.where(point, self.point[o] - p_hat, self.residuals(o, z_hat))
        Hc = np.where(point[:, :, None], Hp, H)
        Rc = np.where(point[:, :, None], self.point_cov[o], self.R[o])
        return y, Hc, Rc

    def residuals(self, o: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """``z - z_hat`` of observations o against predictions z_hat (broadcast), angles wrapped."""
        ds = self.ctx.dataset
        y = ds.obs_z[o] - z_hat
        return planar.wrap_residuals(y, ds.obs_kind[o]) if self.angled else y

    def with_orientations(
        self, h: Hypothesis, o: np.ndarray, landmarks: np.ndarray, d2: np.ndarray, costs: np.ndarray, judged: tuple, gate: np.ndarray,
    ) -> np.ndarray:
        """The costs (g,) of g pairs (observations o, landmarks) under h, infinite outside their
        gate, from their positions' d^2 and costs: a tag's orientation judged with its position
        (``tag_orientations.TagOrientations.pair_terms``; ``judged``: the pairs' (y, Hc, Rc))."""
        tags = self.ctx.tag_orientations
        if tags:
            more_d2, more_cost, gate = tags.pair_terms(h.x, h.P, o, landmarks, *judged, self.ctx.observe, self.ctx.obs_sensor, gate)
            d2, costs = d2 + more_d2, costs + more_cost
        return np.where(d2 <= gate, costs, np.inf)

    def conditioned(self, h: Hypothesis, obs: np.ndarray, options: list[PairOptions]) -> list[PairOptions]:
        """Options of observations obs under h, a hypothesis conditioned on some of the pose's
        pairs, from their options before: the same pools of landmarks predicted again from h, one
        batch per camera, less the landmarks h has taken. (Moving the old predictions to first
        order is not enough: with landmarks a metre away, a pair's correction moves the
        predictions by pixels more than the linear term says.) Their ``pool_costs`` are kept."""
        taken = np.array([lm for _, lm in h.pairs], dtype=np.int64)
        out = list(options)
        cameras = self.ctx.obs_sensor[obs]
        for camera_id in self.sensor_ids:
            rows = [r for r in np.flatnonzero(cameras == camera_id) if options[r].landmarks.size]
            if not rows:
                continue
            sizes = [options[r].landmarks.size for r in rows]
            landmarks = np.concatenate([options[r].landmarks for r in rows])
            z_hat, H = self.ctx.observe(h.x, int(camera_id), landmarks)
            owner = np.repeat(obs[rows], sizes)
            p_hat, Hp, HPH, JHPHJ = self.spread(h.P, camera_id, z_hat, H)
            d2, costs, in_point = self.in_best_coordinates(owner, z_hat, p_hat, HPH, JHPHJ)
            y, Hc, Rc = self.chosen(in_point, owner, z_hat, H, p_hat, Hp)
            costs = self.with_orientations(h, owner, landmarks, d2, costs, (y, Hc, Rc), self.ctx.obs_gate[owner])
            costs = np.where(member(landmarks, taken), np.inf, costs)
            # the parts' bounds as Python ints (np.cumsum of a short list costs more)
            for r, start, stop in zip(rows, accumulate([0] + sizes[:-1]), accumulate(sizes)):
                part = slice(start, stop)
                out[r] = PairOptions(landmarks[part], costs[part], z_hat[part], H[part], y[part], Hc[part], Rc[part],
                                     options[r].pool_costs)
        return out


def member(values: np.ndarray, few: np.ndarray) -> np.ndarray:
    """``np.isin(values, few)`` for the handful of landmarks a hypothesis has taken at a pose,
    by direct comparison (isin sorts, which costs more than comparing with a few)."""
    if few.size == 0:
        return np.zeros(values.shape, dtype=bool)
    return (values[:, None] == few[None, :]).any(axis=1)


def empty_options(dim: int) -> PairOptions:
    """No option, for an error state of ``dim`` entries (6: Euler and SE(3); 3: planar): its Jacobians' columns
    match the other observations' options, which a pose's seeded search concatenates."""
    return PairOptions(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, dim)), np.zeros((0, 3)),
                       np.zeros((0, 3, dim)), np.zeros((0, 3, 3)), np.zeros(0))
