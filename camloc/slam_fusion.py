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
  ``slam_association.RETURN_GAP`` poses before u and never paired at one pose with it (a camera
  that saw both at once proved them distinct; read from the run's pairs, ``chosen``);
- the largest one-to-one set of candidate pairs whose offsets ``l_v - l_u`` lie within
  ``FUSION_TOLERANCE`` of one of them (``displaced_group``), kept only where it has at least
  ``FUSION_MIN_PAIRS`` pairs and that many is beyond chance: originals spread evenly within the
  reach put an offset within the tolerance of a given one with probability ``(tolerance /
  reach)^dim`` (dim 2 for a planar robot, 3 otherwise), and the binomial tail of the group's size over the pairs, times the pairs tried, must be below
  ``FUSION_CHANCE``;
- each pair of the group is fused.

**Tags** (a tag's orientation in the state, ``camloc.slam_tags``): a copy's whole pose is its
original's, and the part of the map made during a drift is off by one **rigid** transform, not a
shift: the heading errors that make tag copies are 15-45 degrees, so the offsets of one group
differ by the turn's lever (a metre over a few metres). A tag pair (young u, original v) gives the
whole transform, its turn ``R_v R_u'`` and its offset; pairs agree where the turns are within
``FUSION_TURN_TOLERANCE`` and the offset pair i's transform predicts at j, ``d_i + (R_i - I)
(l_uj - l_ui)``, is within ``FUSION_TOLERANCE`` of j's (``agreement``). So the group's chance is
far smaller, and two pairs make one (``FUSION_MIN_TAG_PAIRS``), within ``FUSION_TAG_REACH`` (such
copies lay 1-6 m from their originals); a tag world's state holds a few hundred tags, and most
copies are made after their original left it, so tags' originals are sought in the whole table
and enter the state to be fused (``slam_run.MappingLocalizer._enter``).

**The fusion** is the pseudo-measurement ``l_a - l_b = 0`` with a noise of ``FUSION_SIGMA`` (a
near-exact constraint, Joseph form: ``ekf.ColumnGain``), then landmark b leaves the state
(marginalized) and its observations point at a: the mapped one where one is, else the older. In
the invariant error (``camloc.slam``'s model card, ``l_i = Exp(xi_theta) l^_i + J xi_li``) the
residual is ``r = Exp(xi_theta) d + J (xi_la - xi_lb)``, ``d = l^_a - l^_b``, so ``d r / d xi =
(0 on xi_t, -[d]x on xi_theta, I on xi_la, -I on xi_lb)``. A floor point's z is pinned (no
variance; the constraint takes x and y). Two tags' orientations join it in the same update,
``Log(R_a R_b') = 0`` (``turn_constraint``: ``-[phi]x`` on xi_theta, ``J_l(phi)^-1`` and
``-J_l(phi)^-1 D`` on theirs), and b's orientation row leaves with its centre. Every Jacobian is
checked against finite differences of ``slam.retract`` in tests/test_slam_fusion.py.

**Covariance matching first** (``matched``; docs/performance.md, 2026-12-05, "Fusion without
overconfidence"): where the constraint's ``d2 = r' S^-1 r`` exceeds its dof q (the filter held the
copies' disagreement impossible: d2 in the hundreds on tag worlds), the disagreement is taken as
one draw of the displacement of the **recent** part of the state (the robot pose, the young
landmarks and the copy: made while the drift lasted) against the older map, a shift, and of tags a
rigid one (``displacement_basis``), and added to P along that one direction, ``P + c g g'``, with
c such that d2 becomes q. Without it the fusion moved the pose by metres and kept a covariance
that never held such an error (tags on smooth3d: mean NEES 18.5 with no fusion, 32.8 fused, 27.4
matched); scaling the whole P by d2 / q instead (tried) widened every landmark's gate and paired
more returns. **Tags only**: on points it took planar points' copies 0.9% -> 0.2% (NEES 7.3 ->
5.6) but on points, markers and a camera seed 7 it moved the robot with a copy it had left (RMSE
0.46 -> 1.77 m, NEES 21 -> 162), and the copy alone (no pose) fused 84 pairs on seed 2 (copies
19 -> 34): not kept, points are fused as before. Every row of G is checked against finite
differences of a rigid move of the state.

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from camloc import ekf, geometry, slam
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2
from camloc.slam_association import RETURN_GAP
from camloc.slam_landmarks import with_state_estimates
from camloc.tails import binomial_tail

FUSION_WINDOW = 60       # poses: an added landmark born and seen within them is young
FUSION_REACH = 1.2       # metres: a young landmark's candidate originals lie within it
FUSION_TAG_REACH = 6.0   # ... a young tag's (copies made with the robot 4-5 m and 20-40 degrees off lay 1-6 m from their originals)
FUSION_TOLERANCE = 0.15  # metres: the offsets of one displacement agree within it
FUSION_TURN_TOLERANCE = 0.1  # radians: a tag pair's turns (``R_original R_young'``) of one displacement agree within it
FUSION_MIN_PAIRS = 4     # a displacement is a group of at least this many pairs
FUSION_MIN_TAG_PAIRS = 2  # ... of tags (each pair gives the whole rigid transform, turn and shift)
FUSION_CHANCE = 0.01     # the chance, at most, that originals spread evenly make such a group
FUSION_SIGMA = 1e-4      # metres (radians for a tag's turn): the constraint's noise (near-exact; zero leaves S as singular as P)


def constraint(x: slam.SlamMean, a: int, b: int, kind: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The residual r = l_a - l_b (q,) of the state's landmarks a and b (rows of x.L), its Jacobian
    H (q, 12) and the error's columns (12,) it is on: the pose's six, a's three, b's three. A floor
    point's r is its x and y (q = 2; its z has no variance)."""
    d = x.L[a] - x.L[b]
    H = np.zeros((3, 12))
    H[:, 3:6] = -geometry.hat(d)
    H[:, 6:9] = np.eye(3)
    H[:, 9:12] = -np.eye(3)
    rows = slice(0, 2) if kind == LANDMARK_POINT2 else slice(0, 3)
    return d[rows], H[rows], _columns(a, b)


def turn_constraint(x: slam.SlamMean, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The residual r = Log(R_a R_b') (3,) of the tag orientations in the state's rows a and b (the
    world turn between them, zero where they are one), its Jacobian H (3, 12) and its columns (12,):
    the pose's six, a's three, b's three. In the tags' error (``slam_tags``: ``R_i = Exp(xi_theta)
    Exp(xi_oi) R^_i``), with ``D = R^_a R^_b'`` and ``phi = Log(D)``: ``R_a R_b' = E Exp(xi_oa) D
    Exp(-xi_ob) E' ~ E Exp(xi_oa - D xi_ob) D E'``, so to first order ``r = phi - [phi]x xi_theta
    + J_l(phi)^-1 (xi_oa - D xi_ob)``: the position constraint's form with phi for d."""
    D = geometry.so3_exp(x.L[a]) @ geometry.so3_exp(x.L[b]).T
    phi = geometry.so3_log_one(D)
    J_inverse = geometry.so3_left_jacobian_inverse_one(phi)
    H = np.zeros((3, 12))
    H[:, 3:6] = -geometry.hat(phi)
    H[:, 6:9] = J_inverse
    H[:, 9:12] = -J_inverse @ D
    return phi, H, _columns(a, b)


def _columns(a: int, b: int) -> np.ndarray:
    """The error's columns (12,) of a constraint between the state's rows a and b: the pose's, a's, b's."""
    return np.concatenate([np.arange(slam.POSE_DIM), slam.POSE_DIM + 3 * a + np.arange(3), slam.POSE_DIM + 3 * b + np.arange(3)])


def displacement_basis(x: slam.SlamMean, recent: np.ndarray, turn: bool) -> np.ndarray:
    """G (dim, 3), or (dim, 6) where ``turn``: the error xi = G delta that moves the **recent** part
    of the state (the robot pose and the rows of L marked in ``recent`` (m,) bool) rigidly by
    delta = (s, omega), world shift and turn, relative to the rest (the older map), to first order:
    ``R -> Exp(omega) R``, ``t -> Exp(omega) t + s``, a recent landmark ``l -> Exp(omega) l + s``, a
    recent tag ``R_tag -> Exp(omega) R_tag``, the rest unmoved. In the error (``slam``'s model card)
    a turn of the pose is xi_theta, which turns every row: so xi_theta = omega, xi_t = s, a recent
    position's xi_l = s (its orientation's xi_o = 0), and an older row is turned back, its position
    by ``xi_l = -omega x l^ = [l^]x omega``, its orientation by ``xi_o = -omega``. (3-D tags only:
    points, planar ones included, are not matched; ``_fuse``.)"""
    G = np.zeros((x.dim, 6 if turn else 3))
    G[0:3, 0:3] = np.eye(3)
    rows = x.orientation_rows() if x.orientation is not None else np.zeros(0, np.int64)
    is_orientation = np.zeros(x.L.shape[0], bool)
    is_orientation[rows] = True
    for i in range(x.L.shape[0]):
        block = slice(slam.POSE_DIM + 3 * i, slam.POSE_DIM + 3 * i + 3)
        if recent[i] and not is_orientation[i]:
            G[block, 0:3] = np.eye(3)
        if turn and not recent[i]:
            G[block, 3:6] = -np.eye(3) if is_orientation[i] else geometry.hat(x.L[i])
    if turn:
        G[3:6, 3:6] = np.eye(3)
    return G


def matched(P: np.ndarray, r: np.ndarray, H: np.ndarray, columns: np.ndarray, R: np.ndarray, G: np.ndarray) -> np.ndarray:
    """P with the constraint's disagreement added as a displacement of the recent part (covariance
    matching), where the filter holds it beyond chance. The constraint r = h(x) (q,), Jacobian H
    (q, k) on the error's ``columns``, noise R; S = H P H' + R, d2 = r' S^-1 r. Where d2 > q the
    copies lie further apart than P allows (a drift the filter did not know: d2 in the hundreds
    on tag worlds), and the fusion would pull the pose and the recent map by r while keeping a
    covariance that never held such an error. So the displacement delta (G's, ``displacement_basis``)
    that explains r, ``A delta = -r`` with A = H G (least squares: a floor point's r has two rows),
    is taken as a draw of the recent part's displacement, and its covariance c delta delta' is
    added: ``P + c g g'``, g = G delta. Then ``H g = -r`` and S becomes S + c r r', whose
    ``r' (S + c r r')^-1 r = d2 / (1 + c d2)`` is q where ``c = 1/q - 1/d2``: the disagreement is as
    likely as its dof say, and nothing else of P moves (only the pose, the recent part's rows
    and, through the turn's gauge, the older rows' turn). Where d2 <= q, P as it is."""
    S = H @ P[np.ix_(columns, columns)] @ H.T + R
    d2 = float(r @ np.linalg.solve(S, r))
    q = r.size
    if d2 <= q:
        return P
    delta = np.linalg.lstsq(H @ G[columns], -r, rcond=None)[0]
    g = G @ delta
    return P + (1.0 / q - 1.0 / d2) * np.outer(g, g)


def fused(x: slam.SlamMean, P: np.ndarray, a: int, b: int, kind: int,
          turns: tuple[int, int] | None = None, recent: np.ndarray | None = None) -> tuple[slam.SlamMean, np.ndarray]:
    """The state after ``l_a - l_b = 0`` (noise ``FUSION_SIGMA``) with landmark b marginalized out:
    its row gone, the rows after it one up. ``turns``: two tags' orientation rows (a's, b's), whose
    ``Log(R_a R_b') = 0`` is stacked with it (one update: the copy's whole pose is the original's)
    and b's of which leaves too. ``recent`` (m,) bool: the rows displaced with b (the young map; b
    among them, a not), whose displacement the disagreement is taken for first (``matched``), a
    shift, and a rigid one of tags; None: P as it is."""
    r, H, columns = constraint(x, a, b, kind)
    drop = np.zeros(x.L.shape[0], bool)
    drop[b] = True
    if turns is not None:
        r_turn, H_turn, columns_turn = turn_constraint(x, *turns)
        columns = np.concatenate([columns, columns_turn[slam.POSE_DIM:]])
        H = np.vstack([np.hstack([H, np.zeros((r.size, 6))]),
                       np.hstack([H_turn[:, :slam.POSE_DIM], np.zeros((3, 6)), H_turn[:, slam.POSE_DIM:]])])
        r = np.concatenate([r, r_turn])
        drop[turns[1]] = True
    noise = FUSION_SIGMA**2 * np.eye(r.size)
    if recent is not None:
        P = matched(P, r, H, columns, noise, displacement_basis(x, recent, turns is not None))
    gain = ekf.ColumnGain(P, H, noise, columns=columns)
    return slam.without_landmarks(slam.retract(x, -gain.correction(r)), gain.posterior_cov(), drop)


def agreement(offsets: np.ndarray, turns: np.ndarray | None = None, at: np.ndarray | None = None) -> list[np.ndarray]:
    """For each of P candidate pairs (offsets (P, 3) ``l_original - l_young``), the pairs (its own
    included) whose offsets lie within ``FUSION_TOLERANCE`` of its displacement's, nearest first.
    Tags' pairs (``turns`` (P, 3): ``Log(R_original R_young')``, ``at`` (P, 3): the young tags'
    positions) are a rigid displacement each: pair i's turn R_i moves the offset it predicts at j by
    ``(R_i - I) (at_j - at_i)``, and j's turn must be within ``FUSION_TURN_TOLERANCE`` of i's too.
    A tag world tries thousands of pairs a pose: only those whose rotation vectors lie within twice
    the tolerance (a k-d tree's pairs; below a radian the angle between two turns is within 1.1
    times that distance) are compared."""
    n = offsets.shape[0]
    if turns is None:
        spread = np.linalg.norm(offsets[:, None, :] - offsets[None, :, :], axis=2)
        i, j = np.nonzero(spread < FUSION_TOLERANCE)
        spread = spread[i, j]
    else:
        near = cKDTree(turns).query_pairs(2.0 * FUSION_TURN_TOLERANCE, output_type="ndarray")
        i = np.concatenate([near[:, 0], near[:, 1], np.arange(n)])
        j = np.concatenate([near[:, 1], near[:, 0], np.arange(n)])
        R = geometry.so3_exp(turns)  # (P, 3, 3)
        lever = np.einsum("kab,kb->ka", R[i] - np.eye(3), at[j] - at[i])
        turn = np.linalg.norm(geometry.so3_log(np.swapaxes(R[i], 1, 2) @ R[j]), axis=1)
        spread = np.linalg.norm(offsets[j] - offsets[i] - lever, axis=1)
        keep = (turn < FUSION_TURN_TOLERANCE) & (spread < FUSION_TOLERANCE)
        i, j, spread = i[keep], j[keep], spread[keep]
    order = np.lexsort((j, spread, i))  # by pair, then nearest first, then in pair order
    return np.split(j[order], np.searchsorted(i[order], np.arange(1, n)))


def displaced_group(pairs: np.ndarray, offsets: np.ndarray, dim: int, turns: np.ndarray | None = None,
                    at: np.ndarray | None = None) -> np.ndarray:
    """The indices into ``pairs`` (P, 2) (young, original) of the largest one-to-one set whose
    ``offsets`` (P, 3) (and, of tags, ``turns``: ``agreement``) lie within the tolerance of one of
    theirs, where it is at least ``FUSION_MIN_PAIRS`` (of tags ``FUSION_MIN_TAG_PAIRS``) and beyond
    chance (the module's docstring); empty otherwise."""
    n = pairs.shape[0]
    least = FUSION_MIN_PAIRS if turns is None else FUSION_MIN_TAG_PAIRS
    if n < least:
        return np.zeros(0, np.int64)
    close = agreement(offsets, turns, at)
    counts = np.array([c.size for c in close])
    best = np.zeros(0, np.int64)
    for i in np.argsort(-counts, kind="stable").tolist():  # the most crowded offsets first
        if counts[i] <= max(best.size, least - 1):
            break  # (a group about offset i has at most counts[i] pairs)
        group, young, old = [], set(), set()
        for j in close[i].tolist():  # the nearest offset first
            u, v = int(pairs[j, 0]), int(pairs[j, 1])
            if u not in young and v not in old:
                group.append(j)
                young.add(u)
                old.add(v)
        if len(group) > best.size:
            best = np.array(group, np.int64)
    if best.size < least or binomial_tail(best.size - 1, n, _chance(dim, turns is not None)) * n > FUSION_CHANCE:
        return np.zeros(0, np.int64)
    return best


def _chance(dim: int, tags: bool) -> float:
    """The probability that a chance original's offset lies within the tolerance of a given one:
    spread evenly within the reach, ``(tolerance / reach)^dim``; a tag's turn too, its orientation
    taken as spread evenly over one axis only (tags on walls share their other two: a turn within
    ``FUSION_TURN_TOLERANCE`` of a given one has ``tolerance / pi`` of them, where orientations
    spread over SO(3) would give ``(a - sin a) / pi``, 3e-4 as much)."""
    if not tags:
        return (FUSION_TOLERANCE / FUSION_REACH) ** dim
    return (FUSION_TOLERANCE / FUSION_TAG_REACH) ** dim * FUSION_TURN_TOLERANCE / np.pi


class LandmarkFusion:
    """A mix-in of ``slam_run.MappingLocalizer`` (its ``x``, ``P``, ``table``, ``state_landmark``,
    ``chosen``, ``dataset``, ``_enter``, ``LandmarkAdditions._rows_left`` and ``TagStates``'
    ``has_tags``, ``_is_tag``, ``_position_rows``): landmarks added twice fused after a pose's update."""

    def _init_fusion(self, on: bool) -> None:
        self.fusing = on
        self.fusions: list[tuple[int, int, int]] = []  # (pose, survivor, fused away), table indices
        self._young: dict[int, int] = {}  # added landmark -> the last pose it was seen, while young
        self._met: dict[int, set] = {}  # young landmark -> the landmarks paired at a pose with it

    def _fuse_seen(self, k: int, landmarks) -> None:
        """After pose k's update of ``landmarks`` (table indices): the young landmarks displaced by
        one offset from originals (``displaced_group``) fused with them."""
        if len(self.state_landmark) < 2:
            return
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
        dim = 2 if self.dataset.planar else 3
        if self.has_tags:
            group = displaced_group(pairs, offsets, dim, self._turns(pairs), self._positions(pairs[:, 0]))
        else:
            group = displaced_group(pairs, offsets, dim)
        for j in group.tolist():
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
        none that a pose saw together. Tags' originals outside the state too: a state of tags holds
        some 300 (two rows each), and most of their copies are made after the original left it."""
        table = self.table
        if self.has_tags:  # tags with tags only (a tag observation without its orientation makes a point)
            candidates = np.flatnonzero(~table.dead & ~table.tentative & self._is_tag(np.arange(len(table))))
            young = young[self._is_tag(young)]
        else:
            state = np.array(self.state_landmark, np.int64)
            candidates = state[~table.dead[state] & ~table.tentative[state] & (table.kind[state] != LANDMARK_MARKER)]
        offsets = self._positions(candidates)[None, :, :] - self._positions(young)[:, None, :]  # (Y, C, 3)
        near = np.einsum("ymi,ymi->ym", offsets, offsets) < (FUSION_TAG_REACH if self.has_tags else FUSION_REACH)**2
        near &= table.kind[candidates][None, :] == table.kind[young][:, None]
        near &= table.born[candidates][None, :] < (table.born[young] - RETURN_GAP)[:, None]
        y, r = np.nonzero(near)
        pairs = np.stack([young[y], candidates[r]], axis=1)
        apart = np.array([v not in self._met[u] for u, v in pairs.tolist()], bool)
        return pairs[apart], offsets[y[apart], r[apart]]

    def _positions(self, landmarks: np.ndarray) -> np.ndarray:
        """The estimated positions (L, 3) of table ``landmarks`` (L,): the state's where it holds them."""
        return with_state_estimates(self.table.xyz, self.table.state_row, landmarks, self.x.L)

    def _turns(self, pairs: np.ndarray) -> np.ndarray:
        """Each tag pair's (young, original) turn ``Log(R_original R_young')`` (P, 3), world."""
        R = geometry.so3_exp(with_state_estimates(self.table.rotvec, self.table.rot_row, pairs, self.x.L))  # (P, 2, 3, 3)
        return geometry.so3_log(R[:, 1] @ np.swapaxes(R[:, 0], 1, 2))

    def _fuse_pair(self, k: int, u: int, v: int) -> None:
        """Fuse young landmark u and original v (``_candidate_pairs``: never seen together), unless
        an earlier fusion of the group took one of them. A tag original outside the state enters it
        first (as a sighting would bring it)."""
        table = self.table
        if table.dead[u] or table.dead[v] or table.state_row[u] < 0:
            return
        if table.state_row[v] < 0:
            if not self.has_tags or not np.any(table.cov[v] != 0.0):
                return
            self._enter([v])
        a, b = (v, u) if not table.added[v] or v < u else (u, v)  # the mapped one, else the older, survives
        self._fuse(k, a, b)

    def _recent_rows(self, a: int, b: int) -> np.ndarray:
        """The state's rows (m,) bool displaced with the copy b: the young landmarks' (``_young``: added
        and seen within ``FUSION_WINDOW``, made while the drift lasted) and b's, their orientations'
        too; not a's."""
        table = self.table
        young = np.array([u for u in self._young if u != a and table.state_row[u] >= 0] + [b], np.int64)
        rows = np.zeros(self.x.L.shape[0], bool)
        rows[table.state_row[young]] = True
        if self.has_tags:
            orientation = table.rot_row[young]
            rows[orientation[orientation >= 0]] = True
        return rows

    def _fuse(self, k: int, a: int, b: int) -> None:
        """``fused`` on the state, and b's records moved to a (its observations, its sightings)."""
        table = self.table
        row_b = int(table.state_row[b])
        turns = None
        if self.has_tags and self._is_tag(a) and self._is_tag(b):  # the copy's orientation is the original's too
            turns = (int(table.rot_row[a]), int(table.rot_row[b]))
            if min(turns) < 0:
                return
        position = self._position_rows()  # (before the state loses b's rows)
        recent = self._recent_rows(a, b) if turns is not None else None  # (points: matching measured, not kept)
        self.x, self.P = fused(self.x, self.P, int(table.state_row[a]), row_b, int(table.kind[a]), turns, recent)
        landmarks = np.array(self.state_landmark, np.int64)
        drop = np.arange(landmarks.size) == row_b
        if turns is not None:
            drop[turns[1]] = True
        self._rows_left(landmarks, drop, position)  # (``LandmarkAdditions``')
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
