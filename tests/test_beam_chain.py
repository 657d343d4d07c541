"""A chain of a pose's pair updates checked against the pose's prior (``camloc.beam_chain``, its
compiled twin ``camloc.kernels.beam_chain``; docs/beam.md, "Chained pairs under a wide prior"):
the trigger and the check tied to their plain numpy statement, and a wide pixel prior, built on
purpose, where the chain ends many of its own standard deviations off and the check brings both
engines back to the stacked update near the truth."""

from __future__ import annotations

import numpy as np
import pytest

from camloc import beam_chain, ekf, geometry
from camloc.beam_types import Hypothesis
from camloc.constants import RAY_NONLINEARITY
from camloc.kernels import _jit
from camloc.kernels import beam_chain as compiled_chain
from camloc.kernels import update
from camloc.kernels.recheck import predict_pairs
from camloc.localizer import LocalizerConfig, _Localizer
from camloc.scene import build_scene, build_settings
from camloc.simulate import SimulationConfig, simulate
from camloc.tails import chi2_quantile

# one step of three times the default odometry noise from a settled pose: about 0.3 m and 3.6 deg
WIDE = np.diag([0.3**2] * 3 + [np.radians(3.6) ** 2] * 3)
OFFSET = np.array([0.3, -0.25, 0.15, 0.04, -0.03, 0.05])   # the prior's error, about a sigma per axis


@pytest.fixture(scope="module")
def world():
    """Two pixel cameras under three times the default odometry noise (w1's kind, fewer poses)."""
    dataset = simulate(SimulationConfig(poses=20, cameras=2, measurement="pixel", intrinsics="pixel", trajectory="smooth3d",
                                        odometry_sigma_scale=3.0), seed=201)
    config = LocalizerConfig()
    return dataset, _Localizer(dataset, config), build_scene(dataset, config), build_settings(config)


def _pose(dataset, k):
    """Pose k's true state and its first four observations of a landmark (fewer where it has fewer), with their landmarks."""
    x = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
    obs = np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0))[:4].astype(np.int64)
    return x, obs, np.searchsorted(dataset.landmark_ids, dataset.obs_true_landmark[obs]).astype(np.int64)


def _chained(localizer, x, P, obs, landmarks):
    for o, lm in zip(obs, landmarks):
        result = localizer.updated(x, P, np.array([o]), np.array([lm]), for_association=True)
        x, P = result.state, result.cov
    return x, P


def test_the_bound_is_the_margin_of_the_99_9_percent_test_over_a_pixel_pair():
    assert RAY_NONLINEARITY == pytest.approx(np.sqrt(chi2_quantile(2, 0.001) - 2.0))
    assert 3.4 < RAY_NONLINEARITY < 3.5


@pytest.mark.parametrize("k", [2, 7])
def test_true_pairs_chained_under_a_wide_prior_end_far_off_and_the_check_restores_the_stacked_update(world, k):
    dataset, localizer, scene, settings = world
    x, obs, landmarks = _pose(dataset, k)
    prior = x + OFFSET
    chain_x, chain_P = _chained(localizer, prior, WIDE, obs, landmarks)
    sigma = lambda P: float(np.sqrt(np.trace(P[:3, :3]) / 3.0))    # noqa: E731
    off = lambda state: float(np.linalg.norm(state[:3] - x[:3]))    # noqa: E731
    assert off(chain_x) > 5.0 * sigma(chain_P)                      # millimetre-sure of a wrong state
    root = Hypothesis(prior, WIDE, 0.0, 0, ())
    pairs = tuple((int(o), int(lm)) for o, lm in zip(obs, landmarks))
    checked_x, checked_P = beam_chain.checked(localizer, chain_x, chain_P, root, pairs)
    assert off(checked_x) < 3.0 * sigma(checked_P) and off(checked_x) < 0.25 * off(chain_x)
    # the compiled twin: the same state to rounding
    model = update.pair_model(scene)
    rows = np.array(pairs, dtype=np.int64)
    again = _jit.from_python(compiled_chain.checked)(model, settings.iterations, chain_x, chain_P, prior, WIDE, rows, 0, rows.shape[0])
    np.testing.assert_allclose(again[0], checked_x, atol=1e-8)
    np.testing.assert_allclose(again[1], checked_P, atol=1e-10)
    # the check's cost is the MAP cost of ekf.posterior_cost in both engines
    measure = localizer.stacked.measurement_function(obs, landmarks)[1]
    plain = ekf.posterior_cost(chain_x, prior, WIDE, dataset.obs_z[obs].reshape(-1), localizer.association_cov[obs], measure,
                               localizer.filter.difference)
    assert beam_chain.map_cost(localizer.stacked, chain_x, root, obs, landmarks) == pytest.approx(plain, rel=1e-9)
    assert _jit.from_python(compiled_chain.map_cost)(model, chain_x, prior, WIDE, obs, landmarks) == pytest.approx(plain, rel=1e-9)
    assert plain > chi2_quantile(int(localizer.obs_dof[obs].sum()), 0.001)


def test_a_chain_consistent_with_its_prior_is_kept_as_it_is(world):
    dataset, localizer, scene, settings = world
    x, obs, landmarks = _pose(dataset, 9)
    tight = np.diag([0.01**2] * 3 + [np.radians(0.3) ** 2] * 3)
    prior = x + 0.5 * np.sqrt(np.diag(tight))
    chain_x, chain_P = _chained(localizer, prior, tight, obs, landmarks)
    pairs = tuple((int(o), int(lm)) for o, lm in zip(obs, landmarks))
    kept = beam_chain.checked(localizer, chain_x, chain_P, Hypothesis(prior, tight, 0.0, 0, ()), pairs)
    assert kept[0] is chain_x and kept[1] is chain_P
    rows = np.array(pairs, dtype=np.int64)
    again = _jit.from_python(compiled_chain.checked)(update.pair_model(scene), settings.iterations, chain_x, chain_P, prior, tight,
                                                     rows, 0, rows.shape[0])
    assert np.array_equal(again[0], chain_x) and np.array_equal(again[1], chain_P)
    assert beam_chain.checked(localizer, chain_x, chain_P, None, pairs)[0] is chain_x          # no root: not wide


@pytest.mark.parametrize("k", [2, 7, 12])
def test_the_trigger_is_its_plain_statement_in_both_engines(world, k):
    """``wide_for_rays``: each pixel observation's cheapest option, (H P H')_aa / (f_a sigma_a)
    beyond the bound: the numpy beam's and the compiled one's agree with the ratio written out,
    wide for the 3x prior, not for one of the default noise's size."""
    dataset, localizer, scene, settings = world
    x, obs, landmarks = _pose(dataset, k)
    z_hat, H = _jit.from_python(predict_pairs)(scene, x + OFFSET, obs, landmarks)
    focal = np.array([(dataset.cameras[int(c)].fx, dataset.cameras[int(c)].fy) for c in dataset.obs_camera[obs]])
    model = update.pair_model(scene)
    start, cost = np.arange(obs.size + 1, dtype=np.int64), np.zeros(obs.size)
    for P, wide in ((WIDE, True), (np.diag([0.01**2] * 3 + [np.radians(0.3) ** 2] * 3), False)):
        sigma = np.sqrt(np.array([np.diagonal(localizer.association_cov[o])[:2] for o in obs]))
        written_out = max(float(H[i, a] @ P @ H[i, a]) / (focal[i, a] * sigma[i, a]) for i in range(obs.size) for a in range(2))
        assert beam_chain.ray_spread(H, P, focal, sigma) == pytest.approx(written_out, rel=1e-12)
        assert (written_out > RAY_NONLINEARITY) == wide
        assert _jit.from_python(compiled_chain.wide_for_rays)(model, P, obs, start, cost, H) == wide
