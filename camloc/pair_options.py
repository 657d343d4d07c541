"""What each observation of a pose may be under one of the numpy beam's hypotheses
(``camloc.beam``): its pool of nearby landmarks, each pair's cost and its innovation in the
coordinates where the hypothesis' linearization explains it best (the measured (u, v, depth) or
the camera-frame point they back-project to), computed in one batch per kind of sensor (``PairGating``)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate

import numpy as np

from camloc import association, measurement, models, planar
from camloc.beam_types import BeamContext, Hypothesis
from camloc.constants import POOL_GATE_FACTOR
from camloc.sensors import intrinsics_by_row, observed_as_rig


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
        # the sensors in ascending order, grouped by kind: a group's observations are gated in one
        # batch (a pose's calls are most of the numpy engine's time, not their sizes)
        kinds: dict[int, list[int]] = {}
        for camera_id in np.unique(context.obs_sensor).tolist():
            kinds.setdefault(int(context.cameras[camera_id].kind), []).append(camera_id)
        self.sensor_groups = list(kinds.values())

    def options(self, h: Hypothesis, obs: np.ndarray, *, widened_view: bool = False) -> list[PairOptions]:
        """Gated landmarks of every observation under h, computed in one batch per kind of
        sensor; with ``widened_view``, among the landmarks within three standard deviations of
        h's view."""
        out: list[PairOptions] = [None] * obs.size  # type: ignore[list-item]
        cameras = self.ctx.obs_sensor[obs]
        for group in self.sensor_groups:
            seen = []  # (camera, its rows of obs, the landmarks it may see) of the group's cameras
            for camera_id in group:
                rows = np.flatnonzero(cameras == camera_id)
                if rows.size == 0:
                    continue
                candidates = self.ctx.visible(h.x, camera_id, h.P if widened_view else None)
                if candidates.size == 0:
                    for r in rows:
                        out[r] = empty_options(h.P.shape[0])  # the error's dimension: the SE(3) state is a 4x4 matrix
                    continue
                seen.append((camera_id, rows, candidates))
            if seen:
                self.gate(h, obs, seen, out)
        return out

    def gate(self, h: Hypothesis, obs: np.ndarray, seen: list, out: list) -> None:
        """``options`` of one kind of sensor's observations, written into ``out``: ``seen``
        (camera, rows of obs, candidates) of each of its cameras, one batch for all of them (each
        observation paired only with its own camera's candidates)."""
        ids, sizes = [c for c, _, _ in seen], [c.size for _, _, c in seen]
        rows = seen[0][1] if len(seen) == 1 else np.concatenate([r for _, r, _ in seen])
        candidates = seen[0][2] if len(seen) == 1 else np.concatenate([c for _, _, c in seen])
        z_hat, H = self.observe(h.x, ids, candidates, sizes)
        o = obs[rows]
        gate = self.ctx.obs_gate[o]  # a sensor's observations share their dof
        pool_gate = POOL_GATE_FACTOR * gate
        spread = self.spread(h.P, ids, sizes, z_hat, H)
        own = None if len(seen) == 1 else self.ctx.obs_sensor[o][:, None] == np.repeat(ids, sizes)[None, :]
        j, g = self.plausible_pairs(o, z_hat, spread, pool_gate[:, None], own)  # row by row
        p_hat, Hp, HPH, JHPHJ = (part[g] for part in spread)
        d2, costs, in_point = self.in_best_coordinates(o[j], z_hat[g], p_hat, HPH, JHPHJ)
        pool = d2 <= pool_gate[j]  # each observation's pool
        j, g, d2, costs, in_point, p_hat, Hp = (part[pool] for part in (j, g, d2, costs, in_point, p_hat, Hp))
        y, Hc, Rc = self.chosen(in_point, o[j], z_hat[g], H[g], p_hat, Hp)
        # a landmark h puts behind its camera stays in the pool, no option under h (``in_front``)
        front = self.in_front(h.x, ids, candidates, sizes)[g]
        pool_costs = np.where(front, costs, np.inf)
        costs = np.where(front, self.with_orientations(h, o[j], candidates[g], d2, costs, (y, Hc, Rc), gate[j]), np.inf)
        bounds = np.searchsorted(j, np.arange(rows.size + 1))
        for k, r in enumerate(rows):
            part = slice(bounds[k], bounds[k + 1])
            pool = g[part]
            out[r] = PairOptions(candidates[pool], costs[part], z_hat[pool], H[pool], y[part], Hc[part], Rc[part],
                                 pool_costs[part])

    def in_front(self, x: np.ndarray, camera_ids: list[int], landmarks: np.ndarray, sizes: list[int]) -> np.ndarray:
        """Which landmarks (m,) x puts in front of their camera, the first ``sizes[0]`` of camera
        ``camera_ids[0]``, ... of one kind (``AssociationScene.in_front_of``): behind it, a pair's S,
        formed at x, grows as 1/depth^2 and its gate passes nonsense, so the pair is no option at
        x. A sensor whose pairs may be judged as points (depth) is not judged so: a point is linear
        in the position, its gate sound behind the camera, where a 3x-noise prior may put a landmark
        the camera sees (docs/performance.md, 2026-12-06, fourteenth session)."""
        if measurement.judged_as_point(self.ctx.cameras[int(camera_ids[0])].kind):
            return np.ones(landmarks.size, dtype=bool)
        if len(camera_ids) == 1:
            return self.ctx.in_front_of(x, camera_ids[0], landmarks)
        parts = np.split(landmarks, np.cumsum(sizes)[:-1])
        return np.concatenate([self.ctx.in_front_of(x, c, part) for c, part in zip(camera_ids, parts)])

    def observe(self, x: np.ndarray, camera_ids: list[int], landmarks: np.ndarray, sizes: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (m, 3) and Jacobians (m, 3, n) from x of landmarks seen by sensors of one
        kind, the first ``sizes[0]`` by camera ``camera_ids[0]``, the next ``sizes[1]`` by the
        second, ...: in one batch where the filter has one (``models.observe_rig``, the robot's
        part of the model once for all)."""
        if len(camera_ids) == 1:
            return self.ctx.observe(x, camera_ids[0], landmarks)
        cameras = [self.ctx.cameras[int(c)] for c in camera_ids]
        if not observed_as_rig(self.ctx.filter, cameras[0].kind):
            parts = [self.ctx.observe(x, c, part) for c, part in zip(camera_ids, np.split(landmarks, np.cumsum(sizes)[:-1]))]
            return np.concatenate([z for z, _ in parts]), np.concatenate([H for _, H in parts])
        return self.ctx.filter.observe_rig(x, [c.T_robot_camera for c in cameras], intrinsics_by_row(cameras, sizes),
                                           self.ctx.dataset.landmark_xyz[landmarks], sizes, cameras[0].kind)

    def spread(
        self, P: np.ndarray, camera_ids: list[int], sizes: list[int], z_hat: np.ndarray, H: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predictions (z_hat (m, 3), H (m, 3, n)) of cameras camera_ids of one kind (``sizes``:
        how many consecutive rows each) under covariance P, also as camera-frame points: (p_hat
        (m, 3), their Jacobian Hp (m, 3, n), the spread of the predictions H P H' (m, 3, 3) and of
        the points Hp P Hp' (m, 3, 3)). A sensor that does not measure range has no point: zeros,
        a singular spread, which fits nothing (``in_best_coordinates`` keeps its pixels)."""
        cameras = [self.ctx.cameras[int(c)] for c in camera_ids]
        HPH = H @ P @ H.swapaxes(-1, -2)
        if not measurement.judged_as_point(cameras[0].kind):
            return np.zeros_like(z_hat), np.zeros_like(H), HPH, np.zeros_like(HPH)
        intrinsics = cameras[0].intrinsics if len(cameras) == 1 else intrinsics_by_row(cameras, sizes)
        p_hat, J = models.back_project(z_hat, intrinsics, cameras[0].kind)
        return p_hat, J @ H, HPH, J @ HPH @ J.swapaxes(-1, -2)

    def plausible_pairs(self, o: np.ndarray, z_hat: np.ndarray, spread: tuple, limit, own=None) -> tuple[np.ndarray, np.ndarray]:
        """(rows into o, rows into z_hat) of the pairs whose d^2 may be within ``limit`` (each
        row's) in either coordinates of ``in_best_coordinates``, row-major, among those ``own``
        allows (None: all); the others are surely beyond it. For
        S positive definite, ``y' S^-1 y >= |y|^2 / trace(S)``, and the trace of S = H P H' + R
        is a sum of traces: a bound for every pair from a few numbers per observation and per
        prediction, where d^2 itself needs a 3x3 system per pair (most of a dense view's pairs
        are far out of every gate)."""
        p_hat, _, HPH, JHPHJ = spread
        spread_pixels = HPH.trace(axis1=1, axis2=2)[None, :] + self.R[o].trace(axis1=1, axis2=2)[:, None]
        spread_point = JHPHJ.trace(axis1=1, axis2=2)[None, :] + self.point_cov[o].trace(axis1=1, axis2=2)[:, None]
        y_pixels = self.residuals(o[:, None], z_hat[None, :, :])
        y_point = self.point[o][:, None, :] - p_hat[None, :, :]
        near = ((np.einsum("ijk,ijk->ij", y_pixels, y_pixels) <= limit * spread_pixels)
                | ((np.einsum("ijk,ijk->ij", y_point, y_point) <= limit * spread_point) & self.ranged[o][:, None]))
        return np.nonzero(near if own is None else near & own)

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
        # both coordinates' distances in one batch (each pair's arithmetic is its own: the same
        # bits as two calls, at half their numpy calls)
        d2, log_det = association.mahalanobis_3x3(np.concatenate([HPH + self.R[o], JHPHJ + self.point_cov[o]]),
                                                  np.concatenate([self.residuals(o, z_hat), self.point[o] - p_hat]))
        d2_pixels, d2_point, log_det_pixels, log_det_point = d2[: o.size], d2[o.size :], log_det[: o.size], log_det[o.size :]
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
        batch per kind of sensor, less the landmarks h has taken. (Moving the old predictions to first
        order is not enough: with landmarks a metre away, a pair's correction moves the
        predictions by pixels more than the linear term says.) Their ``pool_costs`` are kept."""
        taken = np.array([lm for _, lm in h.pairs], dtype=np.int64)
        out = list(options)
        cameras = self.ctx.obs_sensor[obs]
        for group in self.sensor_groups:
            ids, rows = [], []
            for camera_id in group:
                mine = [r for r in np.flatnonzero(cameras == camera_id) if options[r].landmarks.size]
                if mine:
                    ids.append(camera_id)
                    rows.append(mine)
            if not ids:
                continue
            sizes = [sum(options[r].landmarks.size for r in mine) for mine in rows]
            rows = [r for mine in rows for r in mine]
            self.conditioned_group(h, obs, options, ids, rows, sizes, taken, out)
        return out

    def conditioned_group(self, h: Hypothesis, obs: np.ndarray, options: list[PairOptions], ids: list[int], rows: list[int],
                          sizes: list[int], taken: np.ndarray, out: list) -> None:
        """``conditioned`` of one kind of sensor's observations (``rows`` of obs, camera by camera
        of ``ids``, ``sizes`` landmarks each camera), one batch for all, written into ``out``."""
        counts = [options[r].landmarks.size for r in rows]
        landmarks = np.concatenate([options[r].landmarks for r in rows])
        z_hat, H = self.observe(h.x, ids, landmarks, sizes)
        owner = np.repeat(obs[rows], counts)
        p_hat, Hp, HPH, JHPHJ = self.spread(h.P, ids, sizes, z_hat, H)
        d2, costs, in_point = self.in_best_coordinates(owner, z_hat, p_hat, HPH, JHPHJ)
        y, Hc, Rc = self.chosen(in_point, owner, z_hat, H, p_hat, Hp)
        costs = self.with_orientations(h, owner, landmarks, d2, costs, (y, Hc, Rc), self.ctx.obs_gate[owner])
        costs = np.where(self.in_front(h.x, ids, landmarks, sizes), costs, np.inf)
        if taken.size:
            costs = np.where(member(landmarks, taken), np.inf, costs)
        # the parts' bounds as Python ints (np.cumsum of a short list costs more)
        for r, start, stop in zip(rows, accumulate([0] + counts[:-1]), accumulate(counts)):
            part = slice(start, stop)
            out[r] = PairOptions(landmarks[part], costs[part], z_hat[part], H[part], y[part], Hc[part], Rc[part],
                                 options[r].pool_costs)


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
