"""The beam is wider at a pose of few observations (``camloc.sparse_poses``): a hypothesis that the
default beam drops (more than ``beam_delta`` costlier than the best) is kept at a pose whose
observations barely over-determine the state, in both engines, and dropped at a pose of many."""

from __future__ import annotations

import numpy as np
import pytest

from camloc import LocalizerConfig, measurement
from camloc.beam_types import BeamSettings
from camloc.constants import SPARSE_DELTA_EXTRA, SPARSE_DISTINCT_SIGMA, SPARSE_ROWS_PER_DIM, SPARSE_WIDTH_FACTOR
from camloc.simulate import SimulationConfig, simulate
from camloc.sparse_poses import carried, is_sparse, pose_beam

WIDTH, DELTA = BeamSettings.beam_width, BeamSettings.beam_delta


def test_a_pose_is_sparse_by_its_measurement_rows_against_the_state_s_dimension():
    assert is_sparse(2 * 6, 6) and not is_sparse(2 * 7, 6)    # six pixels against the 6-dof state
    assert is_sparse(3 * 4, 6) and not is_sparse(3 * 5, 6)    # four points
    assert is_sparse(2 * 3, 3) and not is_sparse(2 * 4, 3)    # the planar state: three 2-row observations
    assert pose_beam(True, WIDTH, DELTA) == (WIDTH * SPARSE_WIDTH_FACTOR, DELTA + SPARSE_DELTA_EXTRA)
    assert pose_beam(False, WIDTH, DELTA) == (WIDTH, DELTA)


def test_a_sparse_pose_s_extra_hypotheses_are_not_carried_into_a_pose_that_is_not():
    costs = 1.5 * np.arange(40)                    # the best first, as a pruned beam is
    assert carried(costs, 40, True, WIDTH, DELTA) == 40
    assert carried(costs, 40, False, WIDTH, DELTA) == int((costs <= DELTA).sum())    # within delta
    assert carried(np.zeros(40), 40, False, WIDTH, DELTA) == WIDTH                    # at most width
    assert carried(costs, 3, False, WIDTH, DELTA) == 3 and carried(costs, 0, False, WIDTH, DELTA) == 0


def _poses_of(dataset):
    """A pose of few observations (at most SPARSE_ROWS_PER_DIM rows per state dimension) and one of
    many, of the world's."""
    rows = np.bincount(dataset.obs_pose_index, weights=measurement.dof_of(dataset.obs_kind), minlength=dataset.num_poses)
    sparse = np.flatnonzero((rows > 0) & (rows <= SPARSE_ROWS_PER_DIM * 6))
    dense = np.flatnonzero(rows > SPARSE_ROWS_PER_DIM * 6)
    assert sparse.size and dense.size
    return int(sparse[0]), int(dense[0])


@pytest.fixture(scope="module")
def world():
    return simulate(SimulationConfig(poses=30, cameras=1, measurement="pixel", trajectory="aerial"), seed=3)


# 30 hypotheses far apart (no two merge), each 1.5 costlier than the one before: the default beam
# keeps those within 14 of the best (10), the wide one those within 30 (21)
COSTS = 1.5 * np.arange(30)
STATES = np.array([[0.5 * i, 0.0, 0.0, 0.0, 0.0, 0.0] for i in range(COSTS.size)])
COVARIANCE = 0.01 * np.eye(6)
KEPT_WIDE, KEPT_DEFAULT = int((COSTS <= DELTA + SPARSE_DELTA_EXTRA).sum()), int((COSTS <= DELTA).sum())


def test_the_compiled_beam_keeps_more_at_a_pose_of_few_observations(world):
    from camloc.kernels import beam as kb
    from camloc.scene import build_scene, build_settings

    config = LocalizerConfig()
    scene, settings = build_scene(world, config), build_settings(config)
    gen = kb.new_generation(COSTS.size, 1, 6)
    gen[0][:], gen[1][:], gen[2][:] = STATES, COVARIANCE, COSTS
    for pose, kept in zip(_poses_of(world), (KEPT_WIDE, KEPT_DEFAULT)):
        obs = np.flatnonzero(world.obs_pose_index == pose)
        width, delta = pose_beam(is_sparse(int(scene.obs_dof[obs].sum()), 6), settings.beam_width, settings.beam_delta)
        assert list(kb.prune(scene, settings, gen, COSTS.size, width, delta)) == list(range(kept))


def test_the_numpy_beam_keeps_more_at_a_pose_of_few_observations(world):
    from camloc.beam import BeamSearch
    from camloc.beam_types import Hypothesis
    from camloc.localizer import _Localizer

    search = BeamSearch(_Localizer(world, LocalizerConfig()), BeamSettings())
    hypotheses = [Hypothesis(x, COVARIANCE, float(c), 0) for x, c in zip(STATES, COSTS)]
    for pose, kept in zip(_poses_of(world), (KEPT_WIDE, KEPT_DEFAULT)):
        explained = search._use_pose_beam(np.flatnonzero(world.obs_pose_index == pose), hypotheses)
        assert search.expansion.prune(hypotheses) == hypotheses[:kept]
        assert explained == hypotheses[:None if kept == KEPT_WIDE else KEPT_DEFAULT]


# The same costs, but every other hypothesis past the run's beam (index 10 on) a variant of one
# kept in it: 1.5 standard deviations from it on one axis (it would not merge at 0.3), as a child
# that leaves one of the pose's few observations out is. A sparse pose keeps only the distinct
# extra ones (SPARSE_DISTINCT_SIGMA 2): 10 of the run's beam and 11, 13, ..., 19 (within 30).
VARIANTS = STATES.copy()
VARIANTS[10::2] = STATES[:10] + [0.15, 0.0, 0.0, 0.0, 0.0, 0.0]
KEPT_DISTINCT = list(range(10)) + [11, 13, 15, 17, 19]


def test_a_sparse_pose_keeps_no_variant_of_a_kept_hypothesis_beyond_the_run_s_beam(world):
    from camloc.beam import BeamSearch
    from camloc.beam_types import Hypothesis
    from camloc.kernels import beam as kb
    from camloc.localizer import _Localizer
    from camloc.scene import build_scene, build_settings

    assert SPARSE_DISTINCT_SIGMA > 1.5
    config = LocalizerConfig()
    scene, settings = build_scene(world, config), build_settings(config)
    gen = kb.new_generation(COSTS.size, 1, 6)
    gen[0][:], gen[1][:], gen[2][:] = VARIANTS, COVARIANCE, COSTS
    sparse, _ = _poses_of(world)
    obs = np.flatnonzero(world.obs_pose_index == sparse)
    width, delta = pose_beam(True, settings.beam_width, settings.beam_delta)
    assert list(kb.prune(scene, settings, gen, COSTS.size, width, delta)) == KEPT_DISTINCT
    search = BeamSearch(_Localizer(world, LocalizerConfig()), BeamSettings())
    hypotheses = [Hypothesis(x, COVARIANCE, float(c), 0) for x, c in zip(VARIANTS, COSTS)]
    search._use_pose_beam(obs, hypotheses)
    assert search.expansion.prune(hypotheses) == [hypotheses[i] for i in KEPT_DISTINCT]


def _pruned_episode():
    """issue 35's aerial1 world, seed 10 (one camera from above, ``benchmarks/pixel_worlds.py``), to
    pose 215: poses 191-201 see 2-7 landmarks each, and the beam of the run's width and delta
    (before 2026-12-06) lost the right hypothesis there: 22 of its 31 pairs at poses 185-204 were
    wrong, the estimate 1.66 m off; held, none is wrong and it stays within 0.4 m."""
    from camloc.dataset import first_poses
    from camloc.simulate import simulation_config

    config = simulation_config({"trajectory": "aerial", "cameras": 1, "measurement": "pixel", "poses": 500})
    return first_poses(simulate(config, seed=10), 215)


def _assert_the_episode_is_held(result, dataset):
    a = result.associations
    episode = (dataset.obs_pose_index >= 185) & (dataset.obs_pose_index < 205)
    paired = episode & (a.landmark >= 0)
    wrong = paired & (a.landmark != a.true_landmark)
    error = np.linalg.norm(result.estimate_xyz - dataset.truth_xyz, axis=1)
    assert paired.sum() >= 60 and wrong.sum() <= 3 and error[185:205].max() < 0.8


def test_the_compiled_beam_holds_the_right_hypothesis_through_an_episode_of_few_observations():
    from camloc import localize

    dataset = _pruned_episode()
    _assert_the_episode_is_held(localize(dataset, LocalizerConfig(), engine="compiled", parallel=False), dataset)


@pytest.mark.slow
def test_the_numpy_beam_holds_the_right_hypothesis_through_an_episode_of_few_observations():
    from camloc import localize

    dataset = _pruned_episode()   # about a minute and a half of CPU on this engine
    _assert_the_episode_is_held(localize(dataset, LocalizerConfig(), engine="numpy", parallel=False), dataset)
