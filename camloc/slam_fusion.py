"""Landmark fusion: landmarks the mapping localizer added twice become one again.

Why (docs/performance.md, 2026-12-05, "Landmark fusion"): with no map, landmarks made while the
odometry drifted stay off after a loop closure brings the robot back (the filter does not
relinearize the past), and when the robot returns to them its observations miss them and make
copies, then a wrong return or two, then more copies. The classic fusion test, the Mahalanobis
distance of two landmarks' difference under their joint covariance within a tight gate, never
fired on the benchmark's worlds: the filter holds each copy and its original 0.3-1 m apart with a
relative covariance of centimetres (d2 of 30-900 on 2-3 dof, the smallest over the run), while
distinct landmarks never seen together come closer than that (d2 from 0.3). What the copies have
that chance pairs do not: **one displacement**. The part of the map made during the drift is off
by one shift, so each copy lies from its original at about the same offset.

The rule, after a pose's update (``LandmarkFusion._fuse_seen``):

- **young** landmarks: added ones, confirmed, born and seen within ``FUSION_WINDOW`` poses;
- each young landmark u's candidate **originals**: confirmed landmarks of its kind (not markers:
  their third coordinate is a heading) within ``FUSION_REACH`` metres, born more than
  ``slam_association.RETURN_GAP`` poses before u and unseen since before u was born;
- the largest one-to-one set of candidate pairs whose offsets ``l_v - l_u`` lie within
  ``FUSION_TOLERANCE`` of one of them (``displaced_group``), kept only where that many is beyond
  chance: originals spread evenly within the reach put an offset within the tolerance of a given
  one with probability ``(tolerance / reach)^dim`` (dim 2 for a planar robot, 3 otherwise), and
  the binomial tail of the group's size over the pairs, times the pairs tried, must be below
  ``FUSION_CHANCE``;
- each pair of the group that no pose saw together (a camera that saw both at once proved them
  distinct; read from the run's pairs, ``chosen``) is fused.

**The fusion** is the pseudo-measurement ``l_a - l_b = 0`` with a noise of ``FUSION_SIGMA`` (a
near-exact constraint, Joseph form: ``ekf.ColumnGain``), then landmark b leaves the state
(marginalized) and its observations point at a: the mapped one where one is, else the older. In
the invariant error (``camloc.slam``'s model card, ``l_i = Exp(xi_theta) l^_i + J xi_li``) the
residual is ``r = Exp(xi_theta) d + J (xi_la - xi_lb)``, ``d = l^_a - l^_b``, so ``d r / d xi =
(0 on xi_t, -[d]x on xi_theta, I on xi_la, -I on xi_lb)`` (checked against finite differences of
``slam.retract`` in tests/test_slam_fusion.py). A floor point's z is pinned (no variance; the
constraint takes x and y). Tags are not fused.

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np

from camloc import ekf, geometry, slam
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2
from camloc.slam_association import RETURN_GAP
from camloc.tails import binomial_tail

FUSION_WINDOW = 60       # poses: an added landmark born and seen within them is young
FUSION_REACH = 1.2       # metres: a young landmark's candidate originals lie within it
FUSION_TOLERANCE = 0.15  # metres: the offsets of one displacement agree within it
FUSION_MIN_PAIRS = 4     # a displacement is a group of at least this many pairs
FUSION_CHANCE = 0.01     # the chance, at most, that originals spread evenly make such a group
FUSION_SIGMA = 1e-4      # metres: the constraint's noise (near-exact; zero leaves S as singular as P)


def constraint(x: slam.SlamMean, a: int, b: int, kind: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The residual r = l_a - l_b (q,) of the state's landmarks a and b (rows of x.L), its Jacobian
    H (q, 12) and the error's columns (12,) it is on: the pose's six, a's three, b's three. A floor
    point's r is its x and y (q = 2; its z has no variance)."""
    d = x.L[a] - x.L[b]
    H = np.zeros((3, 12))
    H[:, 3:6] = -geometry.hat(d)
    H[:, 6:9] = np.eye(3)
    H[:, 9:12] = -np.eye(3)
    columns = np.concatenate([np.arange(slam.POSE_DIM), slam.POSE_DIM + 3 * a + np.arange(3),
                              slam.POSE_DIM + 3 * b + np.arange(3)])
    rows = slice(0, 2) if kind == LANDMARK_POINT2 else slice(0, 3)
    return d[rows], H[rows], columns


def fused(x: slam.SlamMean, P: np.ndarray, a: int, b: int, kind: int) -> tuple[slam.SlamMean, np.ndarray]:
    """The state after ``l_a - l_b = 0`` (noise ``FUSION_SIGMA``) with landmark b marginalized out:
    its row gone, the rows after it one up."""
    r, H, columns = constraint(x, a, b, kind)
    gain = ekf.ColumnGain(P, H, FUSION_SIGMA**2 * np.eye(r.size), columns=columns)
    drop = np.zeros(x.L.shape[0], bool)
    drop[b] = True
    return slam.without_landmarks(slam.retract(x, -gain.correction(r)), gain.posterior_cov(), drop)


def displaced_group(pairs: np.ndarray, offsets: np.ndarray, dim: int) -> np.ndarray:
    """The indices into ``pairs`` (P, 2) (young, original) of the largest one-to-one set whose
    ``offsets`` (P, 3) lie within ``FUSION_TOLERANCE`` of one of theirs, where it is at least
    ``FUSION_MIN_PAIRS`` and beyond chance (the module's docstring); empty otherwise."""
    n = pairs.shape[0]
    if n < FUSION_MIN_PAIRS:
        return np.zeros(0, np.int64)
    spread = np.linalg.norm(offsets[:, None, :] - offsets[None, :, :], axis=2)  # (P, P)
    within = spread < FUSION_TOLERANCE
    counts = within.sum(axis=1)
    best = np.zeros(0, np.int64)
    for i in np.argsort(-counts, kind="stable").tolist():  # the most crowded offsets first
        if counts[i] <= max(best.size, FUSION_MIN_PAIRS - 1):
            break  # (a group about offset i has at most counts[i] pairs)
        close = np.flatnonzero(within[i])
        group, young, old = [], set(), set()
        for j in close[np.argsort(spread[i, close], kind="stable")].tolist():  # the nearest offset first
            u, v = int(pairs[j, 0]), int(pairs[j, 1])
            if u not in young and v not in old:
                group.append(j)
                young.add(u)
                old.add(v)
        if len(group) > best.size:
            best = np.array(group, np.int64)
    if best.size < FUSION_MIN_PAIRS:
        return np.zeros(0, np.int64)
    p = (FUSION_TOLERANCE / FUSION_REACH) ** dim
    if binomial_tail(best.size - 1, n, p) * n > FUSION_CHANCE:
        return np.zeros(0, np.int64)
    return best


class LandmarkFusion:
    """A mix-in of ``slam_run.MappingLocalizer`` (its ``x``, ``P``, ``table``, ``state_landmark``,
    ``chosen``, ``dataset``, and ``LandmarkAdditions._rows_left``): landmarks added twice fused after
    a pose's update."""

    def _init_fusion(self, on: bool) -> None:
        self.fusing = on
        self.fusions: list[tuple[int, int, int]] = []  # (pose, survivor, fused away), table indices
        self._young: dict[int, int] = {}  # added landmark -> the last pose it was seen, while young
        self._met: dict[int, set] = {}  # young landmark -> the landmarks paired at a pose with it

    def _fuse_seen(self, k: int, landmarks) -> None:
        """After pose k's update of ``landmarks`` (table indices): the young landmarks displaced by
        one offset from originals (``displaced_group``) fused with them."""
        if self.x.orientation is not None or len(self.state_landmark) < 2:
            return  # (tags: not fused)
        table = self.table
        seen = {int(u) for u in landmarks}
        for u in seen:
            if table.added[u] and table.born[u] >= k - FUSION_WINDOW:
                self._young[u] = k
                if u in self._met:  # (read from the pairs when first asked: ``_candidate_pairs``)
                    self._met[u] |= seen
        for u in [u for u, s in self._young.items() if s < k - FUSION_WINDOW or table.dead[u] or table.state_row[u] < 0]:
            del self._young[u]
            self._met.pop(u, None)
        young = np.array([u for u in self._young if not table.tentative[u]], np.int64)
        if young.size < FUSION_MIN_PAIRS or not seen.intersection(young.tolist()):
            return  # (the offsets move most where a young landmark is seen: searched then)
        for u in young.tolist():
            if u not in self._met:
                self._met[u] = self._met_since_birth(u, k)
        pairs, offsets = self._candidate_pairs(young)
        for j in displaced_group(pairs, offsets, 2 if self.dataset.planar else 3).tolist():
            self._fuse_pair(k, int(pairs[j, 0]), int(pairs[j, 1]))

    def _met_since_birth(self, u: int, k: int) -> set:
        """The landmarks paired at a pose with u, up to pose k: read from the pairs since its birth
        (a young landmark's: a window, not the run) when first needed; then kept up pose by pose."""
        since = self.obs_order[self.obs_bounds[max(int(self.table.born[u]), 0)]:self.obs_bounds[k + 1]]
        chosen, pose = self.chosen[since], self.dataset.obs_pose_index[since]
        together = chosen[np.isin(pose, pose[chosen == u])]
        return set(together[together >= 0].tolist())

    def _candidate_pairs(self, young: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pairs (P, 2) of table indices (young, original), offsets (P, 3) ``l_original - l_young``),
        none that a pose saw together."""
        table = self.table
        state = np.array(self.state_landmark, np.int64)
        original = ~table.dead[state] & ~table.tentative[state] & (table.kind[state] != LANDMARK_MARKER)
        offsets = self.x.L[None, :, :] - self.x.L[table.state_row[young]][:, None, :]  # (Y, m, 3)
        near = np.einsum("ymi,ymi->ym", offsets, offsets) < FUSION_REACH**2
        near &= original[None, :] & (table.kind[state][None, :] == table.kind[young][:, None])
        near &= table.born[state][None, :] < (table.born[young] - RETURN_GAP)[:, None]
        y, r = np.nonzero(near)
        pairs = np.stack([young[y], state[r]], axis=1)
        apart = np.array([v not in self._met[u] for u, v in pairs.tolist()], bool)
        return pairs[apart], offsets[y[apart], r[apart]]

    def _fuse_pair(self, k: int, u: int, v: int) -> None:
        """Fuse young landmark u and original v (``_candidate_pairs``: never seen together), unless
        an earlier fusion of the group took one of them."""
        table = self.table
        if table.dead[u] or table.dead[v] or table.state_row[u] < 0 or table.state_row[v] < 0:
            return
        a, b = (v, u) if not table.added[v] or v < u else (u, v)  # the mapped one, else the older, survives
        self._fuse(k, a, b)

    def _fuse(self, k: int, a: int, b: int) -> None:
        """``fused`` on the state, and b's records moved to a (its observations, its sightings)."""
        table = self.table
        row_b = int(table.state_row[b])
        self.x, self.P = fused(self.x, self.P, int(table.state_row[a]), row_b, int(table.kind[a]))
        landmarks = np.array(self.state_landmark, np.int64)
        self._rows_left(landmarks, np.arange(landmarks.size) == row_b)  # (``LandmarkAdditions``')
        self.chosen[self.chosen == b] = a
        table.observations[a] += table.observations[b]
        if table.added[a]:  # (a mapped landmark keeps no birth)
            table.born[a] = min(int(table.born[a]), int(table.born[b]))
        table.last_seen[a] = max(int(table.last_seen[a]), int(table.last_seen[b]))
        table.drop(np.array([b]))  # out of the map and of every search
        self._young.pop(b, None)
        self._met.pop(b, None)
        for u, met in self._met.items():  # b's pairs are a's now: read again where they met either
            if u == a or a in met or b in met:
                self._met[u] = self._met_since_birth(u, k)
        self.fusions.append((k, a, b))
