"""Landmark fusion (camloc.slam_fusion): the constraint's Jacobian, the fused estimate, the
displacement test, a world whose run adds landmarks twice and fuses them, and landmarks seen
together never fused; of tags, the turn's constraint and rigid displacement, and a world of tags
that slips."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

from camloc import geometry, slam, slam_fusion
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3
from camloc.localizer import resolved_config
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
from camloc.simulate_tags import simulate_tags
from camloc.slam_association import RETURN_GAP
from camloc.slam_run import MappingLocalizer


def _state(rng, m: int = 4) -> slam.SlamMean:
    L = rng.normal(size=(m, 3))
    L[2] = L[1] + 0.3 * rng.normal(size=3)
    return slam.SlamMean(geometry.so3_exp(0.5 * rng.normal(size=3)), rng.normal(size=3), L)


@pytest.mark.parametrize("kind", [LANDMARK_POINT3, LANDMARK_POINT2, LANDMARK_MARKER])
def test_the_constraint_jacobian_matches_finite_differences_of_the_retraction(kind):
    x = _state(np.random.default_rng(kind))
    r0, H, columns = slam_fusion.constraint(x, 1, 2, kind)
    assert r0.size == (2 if kind == LANDMARK_POINT2 else 3)
    numeric = np.zeros((r0.size, x.dim))
    for i in range(x.dim):
        step = np.zeros(x.dim)
        step[i] = 1e-6
        plus = slam_fusion.constraint(slam.retract(x, step), 1, 2, kind)[0]
        minus = slam_fusion.constraint(slam.retract(x, -step), 1, 2, kind)[0]
        numeric[:, i] = (plus - minus) / 2e-6
    analytic = np.zeros_like(numeric)
    analytic[:, columns] = H
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)


def test_two_independent_landmarks_fuse_to_their_information_weighted_mean():
    """Landmarks uncorrelated with each other and with a pose whose heading is exact: the fused one
    is the product of the two Gaussians, and the state loses a landmark."""
    rng = np.random.default_rng(3)
    x = slam.SlamMean(np.eye(3), np.zeros(3), np.array([[5.0, 0.0, 0.0], [1.0, 2.0, 0.5], [1.1, 2.05, 0.4]]))
    P = np.zeros((15, 15))
    P[0:3, 0:3] = 0.01 * np.eye(3)  # the pose's translation; its heading exact (no lever arm)
    covs = []
    for i in range(3):
        A = rng.normal(size=(3, 3))
        covs.append(0.02 * (A @ A.T + np.eye(3)))
        P[6 + 3 * i:9 + 3 * i, 6 + 3 * i:9 + 3 * i] = covs[-1]
    x_new, P_new = slam_fusion.fused(x, P, 1, 2, LANDMARK_POINT3)
    info_a, info_b = np.linalg.inv(covs[1]), np.linalg.inv(covs[2])
    cov = np.linalg.inv(info_a + info_b)
    assert x_new.L.shape == (2, 3)
    np.testing.assert_allclose(x_new.L[0], x.L[0], atol=1e-12)  # the first landmark untouched
    np.testing.assert_allclose(x_new.L[1], cov @ (info_a @ x.L[1] + info_b @ x.L[2]), atol=1e-6)
    np.testing.assert_allclose(P_new[9:12, 9:12], cov, atol=1e-7)
    np.testing.assert_allclose(P_new[6:9, 6:9], covs[0], atol=1e-12)
    assert np.array_equal(P_new, P_new.T)


def test_a_floor_point_fuses_in_the_plane_only():
    x = slam.SlamMean(np.eye(3), np.zeros(3), np.array([[1.0, 2.0, 0.0], [1.2, 2.1, 0.0]]))
    P = np.zeros((12, 12))
    P[0:3, 0:3] = np.diag([0.01, 0.01, 0.0])
    P[6:9, 6:9] = P[9:12, 9:12] = np.diag([0.04, 0.04, 0.0])  # z pinned: no variance
    x_new, P_new = slam_fusion.fused(x, P, 0, 1, LANDMARK_POINT2)
    np.testing.assert_allclose(x_new.L[0], [1.1, 2.05, 0.0], atol=1e-6)
    assert P_new[8, 8] == 0.0 and np.isclose(P_new[6, 6], 0.02, atol=1e-7)


def test_a_common_displacement_is_a_group_and_scattered_offsets_are_not():
    rng = np.random.default_rng(0)
    shift = np.array([0.7, 0.2, 0.0])
    common = shift + 0.03 * rng.normal(size=(4, 3))
    pairs = np.array([[10, 1], [11, 2], [12, 3], [13, 4], [10, 5], [14, 6], [15, 7]])
    scattered = rng.uniform(-1.0, 1.0, size=(3, 3)) * np.array([1.0, 1.0, 0.0])
    offsets = np.vstack([common, scattered])
    group = slam_fusion.displaced_group(pairs, offsets, 2)
    assert sorted(group.tolist()) == [0, 1, 2, 3]
    assert slam_fusion.displaced_group(pairs[4:], offsets[4:], 2).size == 0
    # one to one: the same young landmark twice in a displacement counts once
    twice = np.array([[10, 1], [10, 2], [11, 3]])
    assert slam_fusion.displaced_group(twice, common[:3], 2).size == 0


def _copies(loc: MappingLocalizer, dataset) -> tuple[int, int]:
    """(added landmarks kept, of them a second of one true landmark)."""
    chosen, table = loc.chosen, loc.table
    live = [n for n in set(chosen[chosen >= 0].tolist()) if table.added[n] and not table.dead[n] and not table.tentative[n]]
    stands = [Counter(dataset.obs_true_landmark[chosen == n].tolist()).most_common(1)[0][0] for n in live]
    return len(live), sum(c - 1 for c in Counter(stands).values())


def _run(dataset, fusing: bool) -> MappingLocalizer:
    loc = MappingLocalizer(dataset, resolved_config(LocalizerConfig(map="none"), dataset), compiled=False)
    loc.fusing = fusing
    for k in range(dataset.num_poses):
        loc.step(k)
    return loc


def test_landmarks_added_twice_after_a_drift_are_fused_with_their_originals():
    """A planar world (seed 2) whose odometry drifts a metre at poses 80-120: the landmarks mapped
    then stay off after the loop closes, and coming back to them at 240-260 the run made 22
    copies (docs/performance.md). Fused: 3, and each fusion joins one true landmark's."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors="points", poses=300, no_map=True), seed=2)
    before = _copies(_run(dataset, False), dataset)
    loc = _run(dataset, True)
    after = _copies(loc, dataset)
    assert before[1] >= 15, before
    assert after[1] <= before[1] // 5, (before, after)
    assert loc.fusions
    true_of = dataset.obs_true_landmark
    for _, survivor, _ in loc.fusions:  # every observation the survivor took is of one true landmark, or nearly
        counts = Counter(true_of[loc.chosen == survivor].tolist())
        assert counts.most_common(1)[0][1] >= 0.8 * sum(counts.values()), counts


def test_landmarks_seen_at_one_pose_are_never_fused():
    """Two landmarks an observation each paired at one pose are distinct, however close: they are
    never a candidate pair (the record of who was seen with whom), and are one without it."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors="points", poses=120, no_map=True), seed=0)
    loc = _run(dataset, True)
    table, k = loc.table, dataset.num_poses - 1
    live = [int(n) for n in loc.state_landmark if table.added[n] and not table.dead[n] and not table.tentative[n]]
    found = None
    for b in sorted(live, key=lambda n: -table.born[n]):  # a young landmark, then an older one seen with it
        met = loc._met_since_birth(b, k)
        older = [a for a in live if a in met and table.born[a] < table.born[b] - RETURN_GAP]
        if older:
            found = older[0], b, met
            break
    assert found is not None
    a, b, met = found
    loc.x.L[table.state_row[b]] = loc.x.L[table.state_row[a]] + 0.01  # as close as can be
    loc._met[b] = met
    pairs, _ = loc._candidate_pairs(np.array([b]))
    assert not any(int(v) == a for _, v in pairs)
    loc._met[b] = set()  # without the record they would be a pair
    pairs, _ = loc._candidate_pairs(np.array([b]))
    assert any(int(v) == a for _, v in pairs)


# -- tags: the copy's whole pose is the original's ----------------------------------------------


def _tag_state(rng) -> slam.SlamMean:
    """A state of two tags (rows 0-1 and 2-3: centre, orientation) and a point (row 4): tag 2's
    orientation 10 degrees off tag 1's."""
    L = rng.normal(size=(5, 3))
    L[3] = geometry.so3_log(geometry.so3_exp(np.radians(10.0) * np.array([0.6, 0.0, 0.8])) @ geometry.so3_exp(L[1]))
    return slam.SlamMean(geometry.so3_exp(0.5 * rng.normal(size=3)), rng.normal(size=3), L,
                         np.array([False, True, False, True, False]))


def test_the_turn_constraint_jacobian_matches_finite_differences_of_the_retraction():
    for seed in range(3):
        x = _tag_state(np.random.default_rng(seed))
        r0, H, columns = slam_fusion.turn_constraint(x, 1, 3)
        np.testing.assert_allclose(np.linalg.norm(r0), np.radians(10.0), atol=1e-12)
        numeric = np.zeros((3, x.dim))
        for i in range(x.dim):
            step = np.zeros(x.dim)
            step[i] = 1e-6
            plus = slam_fusion.turn_constraint(slam.retract(x, step), 1, 3)[0]
            minus = slam_fusion.turn_constraint(slam.retract(x, -step), 1, 3)[0]
            numeric[:, i] = (plus - minus) / 2e-6
        analytic = np.zeros_like(numeric)
        analytic[:, columns] = H
        np.testing.assert_allclose(analytic, numeric, atol=1e-7)  # (the rotations' rounding over a step of 1e-6)


def test_two_tags_fuse_to_one_pose():
    """Two tags independent of each other and of a pose whose heading is exact, each with the same
    covariance: the fused one sits at their mean, turned half way (to first order), and the state
    loses the second's two rows."""
    rng = np.random.default_rng(5)
    x = _tag_state(rng)
    P = np.zeros((21, 21))
    P[0:3, 0:3] = 0.01 * np.eye(3)
    for block in range(5):
        P[6 + 3 * block:9 + 3 * block, 6 + 3 * block:9 + 3 * block] = (0.04 if block % 2 == 0 else 0.01) * np.eye(3)
    x_new, P_new = slam_fusion.fused(x, P, 0, 2, LANDMARK_POINT3, turns=(1, 3))
    assert x_new.L.shape == (3, 3) and x_new.orientation.tolist() == [False, True, False]
    np.testing.assert_allclose(x_new.L[0], (x.L[0] + x.L[2]) / 2, atol=1e-6)
    half = geometry.so3_exp(0.5 * geometry.so3_log(geometry.so3_exp(x.L[3]) @ geometry.so3_exp(x.L[1]).T))
    turn_left = geometry.so3_log(geometry.so3_exp(x_new.L[1]) @ (half @ geometry.so3_exp(x.L[1])).T)
    assert np.linalg.norm(turn_left) < np.radians(0.1), np.degrees(turn_left)
    np.testing.assert_allclose(x_new.L[2], x.L[4], atol=1e-12)  # the point untouched
    np.testing.assert_allclose(P_new[6:9, 6:9], 0.02 * np.eye(3), atol=1e-7)
    assert np.array_equal(P_new, P_new.T) and np.linalg.eigvalsh(P_new).min() > -1e-12


def _rigid_pairs(rng, turn_deg: float, count: int):
    """``count`` young tags at random places within 2 m and their originals, the whole set moved
    by one rigid transform (a turn of ``turn_deg`` about z and a shift): (pairs, offsets, turns, at)."""
    at = rng.uniform(-2.0, 2.0, size=(count, 3))
    R = geometry.so3_exp(np.radians(turn_deg) * np.array([0.0, 0.0, 1.0]))
    originals = at @ R.T + np.array([0.5, -0.3, 0.1])
    turns = np.tile(geometry.so3_log(R), (count, 1)) + np.radians(0.5) * rng.normal(size=(count, 3))
    pairs = np.stack([100 + np.arange(count), np.arange(count)], axis=1)
    return pairs, originals - at + 0.02 * rng.normal(size=(count, 3)), turns, at


def test_tags_moved_by_one_rigid_transform_are_a_group():
    """Three tag copies turned 30 degrees and shifted with their part of the map: their offsets
    differ by the turn's lever (a metre), so no shift alone groups them, but one rigid transform
    does."""
    pairs, offsets, turns, at = _rigid_pairs(np.random.default_rng(1), 30.0, 3)
    assert np.ptp(offsets, axis=0).max() > 0.5
    assert slam_fusion.displaced_group(pairs, offsets, 3).size == 0
    assert sorted(slam_fusion.displaced_group(pairs, offsets, 3, turns, at).tolist()) == [0, 1, 2]


def test_nearby_tags_with_other_orientations_are_not_a_group():
    """Distinct tags whose offsets agree (a shifted row of tags, within the tolerance) but whose
    orientations differ: no group, however many; with the same orientations as their originals
    (the turn a pure shift has) they would be one."""
    rng = np.random.default_rng(2)
    pairs, offsets, _, at = _rigid_pairs(rng, 0.0, 6)
    turns = geometry.so3_log(geometry.so3_exp(rng.uniform(-np.pi, np.pi, size=(6, 3)) / np.sqrt(3)))
    assert slam_fusion.displaced_group(pairs, offsets, 3, turns, at).size == 0
    alike = np.radians(0.5) * rng.normal(size=(6, 3))
    assert slam_fusion.displaced_group(pairs, offsets, 3, alike, at).size == 6


def test_tags_added_twice_after_a_slip_are_fused_with_their_originals():
    """A tag world (grid, seed 1) whose odometry slips 15 degrees about z at pose 130, which the
    filter cannot know: the tags mapped after it are turned and shifted from those before by one
    rigid transform, and the robot's return to the first ones (from pose 150) copies them. Fused
    (the turn in the constraint), most copies are gone and each fusion joins one true tag's
    observations."""
    dataset = simulate_tags(SimulationConfig(trajectory="grid", poses=200, no_map=True), seed=1, sigma_rad=np.radians(1.0))
    quat = dataset.odom_quat_xyzw.copy()
    quat[130] = geometry.matrix_to_quat(geometry.quat_to_matrix(quat[130]) @ geometry.so3_exp(np.radians([0.0, 0.0, 15.0])))
    dataset = dataclasses.replace(dataset, odom_quat_xyzw=quat)
    before = _copies(_run(dataset, False), dataset)
    loc = _run(dataset, True)
    after = _copies(loc, dataset)
    assert before[1] >= 20, before
    assert after[1] <= before[1] // 4, (before, after)
    assert len(loc.fusions) >= 5
    true_of = dataset.obs_true_landmark
    for _, survivor, _ in loc.fusions:
        counts = Counter(true_of[loc.chosen == survivor].tolist())
        assert counts.most_common(1)[0][1] >= 0.8 * sum(counts.values()), counts


# -- covariance matching: the disagreement a fusion absorbs, first added as the recent part's displacement --


def _displaced(x: slam.SlamMean, recent: np.ndarray, shift: np.ndarray, omega: np.ndarray) -> slam.SlamMean:
    """x with its pose and ``recent`` rows moved rigidly (turn omega, then shift), the rest kept."""
    E = geometry.so3_exp(omega)
    L = x.L.copy()
    rows = x.orientation_rows() if x.orientation is not None else np.zeros(0, np.int64)
    for i in np.flatnonzero(recent):
        L[i] = geometry.so3_log(E @ geometry.so3_exp(x.L[i])) if i in rows else E @ x.L[i] + shift
    return slam.SlamMean(E @ x.R, E @ x.t + shift, L, x.orientation)


@pytest.mark.parametrize("turn", [False, True])
def test_the_displacement_basis_matches_finite_differences_of_a_rigid_move(turn):
    recent = np.array([False, False, True, True, False])  # the second tag (rows 2-3) moves with the pose
    for seed in range(3):
        x = _tag_state(np.random.default_rng(seed))
        G = slam_fusion.displacement_basis(x, recent, turn)
        numeric = np.zeros_like(G)
        for i in range(G.shape[1]):
            step = np.zeros(6)
            step[i] = 1e-6
            plus = slam.difference(_displaced(x, recent, step[:3], step[3:]), x)
            minus = slam.difference(_displaced(x, recent, -step[:3], -step[3:]), x)
            numeric[:, i] = (plus - minus) / 2e-6
        np.testing.assert_allclose(G, numeric[:, :G.shape[1]], atol=1e-7)


def _random_cov(rng, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + 0.1 * np.eye(n))


def test_matching_makes_the_disagreement_as_likely_as_its_dof_and_keeps_a_plausible_one():
    """Two tags 10 degrees and ~1 m apart under a covariance of centimetres (d2 in the thousands):
    after ``matched`` the stacked constraint's r' S^-1 r is its dof, 6, and only the pose's, the
    recent rows' and the older rows' turn columns moved. Under a covariance that allows the
    disagreement, P is returned as it is."""
    rng = np.random.default_rng(7)
    x = _tag_state(rng)
    recent = np.array([False, False, True, True, False])
    r, H, columns = slam_fusion.constraint(x, 0, 2, LANDMARK_POINT3)
    r_turn, H_turn, columns_turn = slam_fusion.turn_constraint(x, 1, 3)
    H = np.vstack([np.hstack([H, np.zeros((3, 6))]), np.hstack([H_turn[:, :6], np.zeros((3, 6)), H_turn[:, 6:]])])
    columns, r = np.concatenate([columns, columns_turn[6:]]), np.concatenate([r, r_turn])
    R = 1e-8 * np.eye(6)
    G = slam_fusion.displacement_basis(x, recent, True)
    P = _random_cov(rng, x.dim, 1e-4)
    P_new = slam_fusion.matched(P, r, H, columns, R, G)
    S = H @ P_new[np.ix_(columns, columns)] @ H.T + R
    assert r @ np.linalg.solve(H @ P[np.ix_(columns, columns)] @ H.T + R, r) > 1000.0
    np.testing.assert_allclose(r @ np.linalg.solve(S, r), 6.0, rtol=1e-6)
    assert np.array_equal(P_new, P_new.T) and np.all(np.linalg.eigvalsh(P_new) > 0.0)
    wide = _random_cov(rng, x.dim, 10.0)
    assert slam_fusion.matched(wide, r, H, columns, R, G) is wide

