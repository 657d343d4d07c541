"""The compiled run's Python bookkeeping, computed as arrays: the same numbers as the pose-by-pose
forms they replaced (``loop._spreads_about`` against ``ekf.mixture_spread``), and the map's
density remembered by its contents (``observation_space.neighbour_radius``)."""

from __future__ import annotations

import numpy as np

from camloc import observation_space
from camloc.ekf import mixture_spread
from camloc.filters import make_filter
from camloc.loop import _spreads_about


def _pose_by_pose(state, cost, count, path):
    """The spreads as ``loop._backtrack`` computed them before: one pose at a time."""
    d = state.shape[2]
    model = make_filter("euler" if d == 6 else "se2")
    spread = np.zeros((state.shape[0], d, d))
    for k in range(state.shape[0]):
        if count[k] > 1:
            differences = np.array([model.difference(state[k, h], state[k, path[k]]) for h in range(count[k])])
            spread[k] = mixture_spread(differences, cost[k, :count[k]])
    return spread


def _history(rng, poses, width, d):
    state = rng.normal(size=(poses, width, d))
    if d == 6:   # angles about the wrap, so that a difference crosses it
        state[:, :, 3:] = np.pi + rng.normal(scale=0.3, size=(poses, width, 3))
    cost = rng.uniform(0.0, 40.0, size=(poses, width))
    count = rng.integers(1, width + 1, size=poses)
    path = np.array([rng.integers(0, c) for c in count])
    return state, cost, count, path


def test_the_spreads_as_arrays_equal_the_pose_by_pose_mixture_spreads_to_the_bit():
    rng = np.random.default_rng(35)
    for d in (6, 3):
        state, cost, count, path = _history(rng, 400, 12, d)
        expected = _pose_by_pose(state, cost, count, path)
        got = _spreads_about(state, cost, count, path)
        assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))
        assert np.count_nonzero(got.reshape(len(count), -1).any(axis=1)) == np.count_nonzero(count > 1)


def test_the_neighbour_radius_is_remembered_for_its_map_only():
    rng = np.random.default_rng(7)
    first, second = rng.uniform(0, 10, size=(500, 3)), rng.uniform(0, 20, size=(500, 3))
    from scipy.spatial import cKDTree

    def fresh(xyz):
        k = observation_space.DENSITY_NEIGHBOURS + 1
        return float(np.median(cKDTree(xyz).query(xyz, k)[0][:, -1]))

    assert observation_space.neighbour_radius(first) == fresh(first)
    assert observation_space.neighbour_radius(first.copy()) == fresh(first)          # the same contents
    assert observation_space.neighbour_radius(second) == fresh(second) != fresh(first)
    moved = first.copy()
    moved[0, 0] += 5.0
    assert observation_space.neighbour_radius(moved) == fresh(moved)
