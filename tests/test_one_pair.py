"""The one-pair update in scalars (``kernels.one_pair``) against the general iterated update
(``update.iterated_update``) it stands in for: the same posterior state, covariance, NIS, cost and
innovation, bit for bit, on random pairs of every measurement model (pixel, depth and disparity
cameras on the Euler and the planar robot; the planar robot's point2 and marker), from priors
near and far, for 1-4 linearizations with and without the ray's step sigma; and through
``update.updated``, which dispatches a costless one-pair update to it."""

from __future__ import annotations

import numpy as np
import pytest

from camloc import geometry
from camloc.kernels import _jit, camera, one_pair, update
from camloc.kernels.planar import SE2_DIM
from camloc.kernels.types import PairModel
from camloc.measurement import DEPTH, DISPARITY, MARKER, PIXEL, POINT2

EULER_KINDS = (PIXEL, DEPTH, DISPARITY)
PLANAR_KINDS = (PIXEL, DEPTH, DISPARITY, POINT2, MARKER)


def _world(rng, kind, n):
    """Two sensors (the second of ``kind``), a few landmarks in front of them, a true state of
    size n and noisy measurements of every landmark by the second sensor: (x_true, landmarks (L,
    4), camera_R, camera_t, camera_K, z (L, 3), noise (L, 3, 3))."""
    camera_R = np.stack([np.eye(3), geometry.so3_exp(rng.normal(0.0, 0.05, 3))])
    camera_t = rng.normal(0.0, 0.1, (2, 3))
    intrinsics = (1.0, 1.0, 0.5, 0.5) if kind in (DEPTH, DISPARITY) else (525.0, 525.0, 320.0, 240.0)
    camera_K = np.array([(525.0, 525.0, 320.0, 240.0, PIXEL), (*intrinsics, kind)])
    if kind in (POINT2, MARKER):
        camera_R[1], camera_t[1] = np.eye(3), 0.0
    x_true = rng.normal(0.0, [0.5, 0.5, 0.2, 0.05, 0.05, 0.3])[:n] if n == 6 else rng.normal(0.0, [0.5, 0.5, 0.3])
    landmarks = np.c_[rng.uniform(-1.0, 1.0, (6, 2)), rng.uniform(3.0, 6.0, 6), rng.uniform(-np.pi, np.pi, 6)]
    z_true, _ = _jit.from_python(camera.observe_pairs)(x_true, landmarks, np.ones(6, np.int64), camera_R, camera_t, camera_K)
    scale = np.array([2.0, 2.0, 1.0]) if kind == PIXEL else np.array([0.02, 0.02, 0.05])
    noise = np.empty((6, 3, 3))
    for o in range(6):
        A = rng.normal(0.0, 0.3, (3, 3)) * scale[:, None] * scale[None, :]
        noise[o] = np.diag(scale**2) + A @ A.T
        if kind == PIXEL:                          # the inert third row: measured 0, unit variance
            noise[o, 2, :2] = noise[o, :2, 2] = 0.0
            noise[o, 2, 2] = 1.0
    z = z_true + rng.normal(0.0, 1.0, (6, 3)) * scale
    if kind == PIXEL:
        z[:, 2] = 0.0
    return x_true, landmarks, camera_R, camera_t, camera_K, z, noise


def _cases():
    return [(kind, 6) for kind in EULER_KINDS] + [(kind, SE2_DIM) for kind in PLANAR_KINDS]


@pytest.mark.parametrize("kind, n", _cases())
def test_the_one_pair_update_is_the_iterated_update_bit_for_bit(rng, kind, n):
    x_true, landmarks, camera_R, camera_t, camera_K, z, noise = _world(rng, kind, n)
    noise_inverse = np.linalg.inv(noise)
    iterated = _jit.from_python(update.iterated_update)
    scalar = _jit.from_python(one_pair.one_pair_update)
    compared = 0
    for o in range(6):
        for spread in (0.01, 0.1, 0.4):
            x = x_true + rng.normal(0.0, spread, n)
            P = np.diag(rng.uniform(0.5, 2.0, n) * spread**2)
            A = rng.normal(0.0, 0.2 * spread, (n, n))
            P = P + A @ A.T
            z_hat, H = _jit.from_python(camera.observe_pairs)(x, landmarks[o:o + 1], np.ones(1, np.int64), camera_R, camera_t, camera_K)
            for iterations in (1, 2, 3, 4):
                for step_sigma in (0.0, 0.1):
                    general = iterated(x, P, z[o:o + 1], noise[o:o + 1], noise_inverse[o:o + 1], landmarks[o:o + 1], np.ones(1, np.int64),
                                       camera_R, camera_t, camera_K, iterations, z_hat, H, x[:0], np.bool_(False), step_sigma,
                                       np.bool_(False))
                    one = scalar(x, P, z, np.int64(o), landmarks, np.int64(o), np.int64(1), camera_R, camera_t, camera_K, noise,
                                 iterations, z_hat, H, step_sigma)
                    for a, b in zip(general[:2] + general[4:], one[:2] + one[4:]):
                        assert a.shape == b.shape and np.array_equal(a, b)
                    assert general[2] == one[2] and np.isnan(general[3]) and np.isnan(one[3])
                    compared += 1
    assert compared == 6 * 3 * 4 * 2


def _model(landmarks, camera_R, camera_t, camera_K, z, noise):
    """A ``types.PairModel`` of the pairs' world: every observation by the second sensor."""
    K = z.shape[0]
    dof = np.full(K, 2 if camera_K[1, 4] == PIXEL else 3, np.int64)
    bound = np.r_[0.0, np.full(12, 1e6)]                              # no restart: the first update is the one compared
    return PairModel(z, np.ones(K, np.int64), dof, bound, np.full(K, 16.0), landmarks, camera_R, camera_t, camera_K,
                     noise, np.linalg.inv(noise), np.zeros(K), z.copy(), noise.copy(), np.linalg.inv(noise), np.zeros(K))


@pytest.mark.parametrize("kind, n", _cases())
def test_updated_dispatches_a_costless_one_pair_update_to_the_scalar_path(rng, kind, n):
    """``updated`` with one pair and no MAP cost (the beam's settling) gives what the general
    update of that pair gives."""
    x_true, landmarks, camera_R, camera_t, camera_K, z, noise = _world(rng, kind, n)
    model = _model(landmarks, camera_R, camera_t, camera_K, z, noise)
    for o in range(6):
        x, P = x_true + rng.normal(0.0, 0.05, n), np.eye(n) * 0.05**2
        z_hat, H = _jit.from_python(camera.observe_pairs)(x, landmarks[o:o + 1], np.ones(1, np.int64), camera_R, camera_t, camera_K)
        obs, lm = np.array([o], np.int64), np.array([o], np.int64)
        through = update.updated(model, 3, x, P, obs, lm, z_hat, H, model.R_assoc, model.R_assoc_inverse, x[:0], np.bool_(False), 0.1)
        general = _jit.from_python(update.iterated_update)(x, P, z[o:o + 1], noise[o:o + 1], model.R_assoc_inverse[o:o + 1],
                                                             landmarks[o:o + 1], np.ones(1, np.int64), camera_R, camera_t, camera_K, 3,
                                                             z_hat, H, x[:0], np.bool_(False), 0.1, np.bool_(False))
        for a, b in zip(general[:3] + general[4:], through[:3] + through[4:]):
            assert np.array_equal(a, b)


def test_the_one_pair_update_refuses_an_innovation_covariance_that_is_not_positive_definite(rng):
    x_true, landmarks, camera_R, camera_t, camera_K, z, noise = _world(rng, DEPTH, 6)
    z_hat, H = _jit.from_python(camera.observe_pairs)(x_true, landmarks[:1], np.ones(1, np.int64), camera_R, camera_t, camera_K)
    noise[0, 2, 2] = -1e3
    with pytest.raises(FloatingPointError, match="not positive definite"):
        _jit.from_python(one_pair.one_pair_update)(x_true, np.eye(6) * 1e-4, z, np.int64(0), landmarks, np.int64(0), np.int64(1),
                                                   camera_R, camera_t, camera_K, noise, 3, z_hat, H, 0.0)
