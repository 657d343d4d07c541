"""Beam search over association hypotheses: the association that does not lock onto a wrong
alignment when the filter's uncertainty is larger than the spacing of landmarks.

A hypothesis is a filter (x, P) plus the assignments that produced it and their cost, the
negative log-likelihood (times two) of everything it has explained. At each pose every hypothesis
is predicted with the odometry, then the pose's observations are explained one at a time: each
observation either stays unassigned (a fixed ``null_cost``) or pairs with a landmark whose
prediction gates it, and the hypothesis is conditioned on that pair before the next observation
is looked at. Explaining observations one by one with conditioning sums, by the chain rule,
to the joint likelihood of the stacked innovation:

    cost += d^2 + ln det S - ln det R        for a pair (d^2 = y' S^-1 y)
    cost += null_cost                        for an unassigned observation

``ln det S - ln det R`` charges a pair for the uncertainty of its prediction, so that a vague
hypothesis does not win by gating everything. After every observation the children are pruned to
the ``beam_width`` cheapest within ``beam_delta`` of the best; hypotheses whose states coincide
are merged. Where the data are unambiguous the beam collapses to one hypothesis and costs little
more than a single filter.

The beam returns only the association of the best final hypothesis; the localizer then runs its
ordinary filter with those pairs (stacked, iterated updates), so that the estimate, covariance and
NIS are computed exactly as for any other association method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from camloc import association, ekf, geometry, models


@dataclass
class _Hypothesis:
    x: np.ndarray
    P: np.ndarray
    cost: float
    parent: int                                   # index of the hypothesis it grew from, previous pose
    pairs: list[tuple[int, int]] = field(default_factory=list)   # (observation, landmark index)


@dataclass(frozen=True)
class BeamSettings:
    """beam_width: hypotheses kept; beam_delta: drop hypotheses this much costlier than the best
    (2 x log-likelihood ratio); null_cost: cost of leaving an observation unassigned; gate: chi^2
    gate on a pair's d^2; merge_distance: hypotheses whose states differ by less than this
    Mahalanobis distance are merged."""

    beam_width: int
    beam_delta: float
    null_cost: float
    gate: float
    merge_distance: float = 0.05


class BeamSearch:
    """Runs the beam over a whole dataset; ``pairs_of_pose(k)`` exposes the chosen association."""

    def __init__(self, context, settings: BeamSettings):
        # context: the localizer (dataset, cameras, tree, candidate range, obs_of_pose, increments)
        self.ctx = context
        self.settings = settings
        self.history: list[list[_Hypothesis]] = []

    def run(self, x0: np.ndarray, P0: np.ndarray, on_pose: Optional[Callable[[int], None]] = None) -> list[np.ndarray]:
        """Process every pose; returns, per pose, the (p, 2) array of chosen (obs, landmark)."""
        beam = [_Hypothesis(x0, P0, 0.0, -1)]
        n = self.ctx.dataset.num_poses
        for k in range(n):
            if k > 0:
                beam = [self._predicted(h, k - 1, parent) for parent, h in enumerate(beam)]
            else:
                beam[0].parent = -1
            beam = self._explain_pose(beam, self.ctx.obs_of_pose[k])
            self.history.append(beam)
            if on_pose is not None:
                on_pose(k)
        return self._backtrack()

    def _predicted(self, h: _Hypothesis, edge: int, parent: int) -> _Hypothesis:
        x, F, G = models.motion(h.x, self.ctx.T_increments[edge])
        P = ekf.predict(h.P, F, G, self.ctx.dataset.odom_cov[edge])  # P = F P F' + G Q G'
        return _Hypothesis(x, P, h.cost, parent)

    def _explain_pose(self, beam: list[_Hypothesis], obs: np.ndarray) -> list[_Hypothesis]:
        if obs.size == 0 or self.ctx.tree is None:
            return beam
        candidates = [self._candidates(h, obs) for h in beam]
        roots = list(range(len(beam)))
        for o in self._order(obs, beam[0], candidates[0]):
            children, child_roots = [], []
            for h, root in zip(beam, roots):
                for child in self._branches(h, int(o), candidates[root]):
                    children.append(child)
                    child_roots.append(root)
            beam, roots = self._prune(children, child_roots)
        return beam

    def _candidates(self, h: _Hypothesis, obs: np.ndarray) -> dict[int, np.ndarray]:
        """Candidate landmark indices per camera at the hypothesis' predicted pose."""
        T_world_robot = geometry.pose_from_euler(h.x)
        out = {}
        for camera_id in np.unique(self.ctx.dataset.obs_camera[obs]):
            camera = self.ctx.cameras[int(camera_id)]
            out[int(camera_id)] = association.candidate_indices(
                self.ctx.tree, self.ctx.dataset.landmark_xyz, T_world_robot @ camera.T_robot_camera,
                min_depth=self.ctx.min_depth, max_depth=self.ctx.max_depth, max_angle_rad=self.ctx.max_angle,
            )
        return out

    def _order(self, obs: np.ndarray, h: _Hypothesis, candidates: dict[int, np.ndarray]) -> np.ndarray:
        """Least ambiguous observations first: conditioning on them sharpens the others."""
        counts = np.array([self._gated(h, int(o), candidates)[0].size for o in obs])
        return obs[np.argsort(counts, kind="stable")]

    def _gated(self, h: _Hypothesis, o: int, candidates: dict[int, np.ndarray]):
        """Candidates gating observation o under h: (landmarks, d2, ln det S, z_hat, H)."""
        ds = self.ctx.dataset
        camera_id = int(ds.obs_camera[o])
        cands = candidates.get(camera_id, np.zeros(0, np.int64))
        if h.pairs:
            cands = cands[~np.isin(cands, [lm for _, lm in h.pairs])]
        if cands.size == 0:
            return cands, np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 6))
        camera = self.ctx.cameras[camera_id]
        z_hat, H = models.observe(h.x, camera.T_robot_camera, camera.intrinsics, ds.landmark_xyz[cands])
        S = H @ h.P @ np.swapaxes(H, 1, 2) + ds.obs_cov[o]
        y = ds.obs_uvd[o] - z_hat
        L = np.linalg.cholesky(S)
        w = np.linalg.solve(L, y[..., None])[..., 0]
        d2 = np.einsum("ni,ni->n", w, w)
        log_det = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
        keep = d2 <= self.settings.gate
        return cands[keep], d2[keep], log_det[keep], z_hat[keep], H[keep]

    def _branches(self, h: _Hypothesis, o: int, candidates: dict[int, np.ndarray]) -> list[_Hypothesis]:
        ds = self.ctx.dataset
        landmarks, d2, log_det, z_hat, H = self._gated(h, o, candidates)
        log_det_R = float(np.linalg.slogdet(ds.obs_cov[o])[1])
        out = [_Hypothesis(h.x, h.P, h.cost + self.settings.null_cost, h.parent, h.pairs)]
        for j in range(landmarks.size):
            cost = h.cost + float(d2[j] + log_det[j] - log_det_R)
            if cost > h.cost + self.settings.null_cost + self.settings.beam_delta:
                continue
            K, _, _ = ekf.kalman_gain(h.P, H[j], ds.obs_cov[o])
            x = h.x + K @ (ds.obs_uvd[o] - z_hat[j])  # x+ = x + K y
            P = ekf.joseph_update(h.P, K, H[j], ds.obs_cov[o])
            out.append(_Hypothesis(_wrap(x), P, cost, h.parent, h.pairs + [(o, int(landmarks[j]))]))
        return out

    def _prune(self, children: list[_Hypothesis], roots: list[int]) -> tuple[list[_Hypothesis], list[int]]:
        order = np.argsort([c.cost for c in children], kind="stable")
        best = children[order[0]].cost
        kept: list[_Hypothesis] = []
        kept_roots: list[int] = []
        for i in order:
            c = children[i]
            if c.cost > best + self.settings.beam_delta or len(kept) >= self.settings.beam_width:
                break
            if any(self._same_state(c, other) for other in kept):
                continue
            kept.append(c)
            kept_roots.append(roots[i])
        return kept, kept_roots

    def _same_state(self, a: _Hypothesis, b: _Hypothesis) -> bool:
        d = a.x - b.x
        d[3:6] = geometry.wrap_angle(d[3:6])
        return float(d @ np.linalg.solve(b.P, d)) < self.settings.merge_distance**2

    def _backtrack(self) -> list[np.ndarray]:
        n = len(self.history)
        chosen: list[np.ndarray] = [np.zeros((0, 2), np.int64)] * n
        index = 0  # beams are kept sorted by cost: the first is the best
        for k in range(n - 1, -1, -1):
            h = self.history[k][index]
            chosen[k] = np.asarray(h.pairs, dtype=np.int64).reshape(-1, 2)
            index = h.parent
        return chosen


def _wrap(x: np.ndarray) -> np.ndarray:
    out = x.copy()
    out[3] = geometry.wrap_angle(out[3])
    out[5] = geometry.wrap_angle(out[5])
    return out
