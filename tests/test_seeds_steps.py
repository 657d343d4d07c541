"""The seeded search's steps in Python (``camloc.seeds``) against their plain statements, to the
bit: the stacked test against the prior, the median of a few, the concatenated generations."""

import numpy as np
import pytest

from camloc import seeds
from camloc.constants import STATE_GATE
from camloc.kernels import beam as kb
from camloc.kernels.state import difference


@pytest.mark.parametrize("dim", [6, 3])
def test_within_prior_decides_and_computes_as_a_solve_per_state(rng, dim):
    for _ in range(200):
        A = rng.normal(size=(dim, dim)) * rng.lognormal(0.0, 2.0, size=dim)
        P = A @ A.T + 1e-6 * np.eye(dim)
        x = rng.normal(size=dim)
        k = int(rng.integers(1, 17))
        # states about the gate's distance from x: some in, some out
        X = x + rng.normal(size=(k, dim)) @ np.linalg.cholesky(P).T * rng.uniform(0.5, 1.5, size=(k, 1)) * np.sqrt(STATE_GATE / dim)
        d2 = np.array([float(difference(X[c], x) @ np.linalg.solve(P, difference(X[c], x))) for c in range(k)])
        assert np.array_equal(seeds.within_prior(X, x, P), d2 <= STATE_GATE)
        D = np.array([difference(X[c], x) for c in range(k)])
        stacked = np.matmul(D[:, None, :], np.linalg.solve(np.broadcast_to(P, (k, dim, dim)), D[:, :, None]))[:, 0, 0]
        assert np.array_equal(stacked, d2)           # the same bits, not only the same decisions
    assert seeds.within_prior(np.zeros((0, dim)), np.zeros(dim), np.eye(dim)).shape == (0,)


def test_within_prior_keeps_the_near_and_drops_the_far():
    P = np.diag([1.0, 4.0, 0.01])
    x = np.zeros(3)
    X = np.array([[0.5, 1.0, 0.05], [10.0, 0.0, 0.0], [0.0, 0.0, 0.5]])
    assert seeds.within_prior(X, x, P).tolist() == [True, False, False]


def test_median_is_numpys_to_the_bit(rng):
    for size in range(1, 40):
        values = rng.lognormal(0.0, 3.0, size=size)
        assert seeds.median(values) == np.median(values)
        assert seeds.median(np.round(values)) == np.median(np.round(values))    # ties
    assert seeds.median(np.array([1.0, 2.0])) == 1.5
    assert seeds.median(np.array([3.0, 1.0, 2.0])) == 2.0


def _generation(rng, n, cap, dim):
    gen = kb.new_generation(n, cap, dim)
    gen[0][:] = rng.normal(size=gen[0].shape)
    gen[1][:] = rng.normal(size=gen[1].shape)
    gen[2][:] = rng.normal(size=n)
    gen[3][:] = rng.integers(0, 5, size=n)
    gen[4][:] = rng.integers(0, 5, size=n)
    gen[5][:] = rng.random(n) < 0.5
    gen[6][:] = rng.integers(0, cap + 1, size=n)
    gen[7][:] = rng.integers(0, 1000, size=gen[7].shape)
    return gen


def test_concatenated_copies_every_field_as_copy_hypothesis_does(rng):
    parts = [(_generation(rng, 5, 4, 6), 3), (_generation(rng, 4, 7, 6), 4), (_generation(rng, 2, 2, 6), 0), (_generation(rng, 3, 1, 6), 2)]
    out, sizes = seeds.concatenated(parts)
    assert sizes.tolist() == [3, 4, 0, 2]
    expected = kb.new_generation(9, 7, 6)
    at = 0
    for g, n in parts:
        for i in range(n):
            kb.copy_hypothesis(g, i, expected, at)
            at += 1
    for field in range(7):
        assert np.array_equal(out[field], expected[field])
    for j in range(9):                                # the pairs up to each hypothesis' count
        assert np.array_equal(out[7][j, :out[6][j]], expected[7][j, :expected[6][j]])
