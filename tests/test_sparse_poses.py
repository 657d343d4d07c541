"""The beam is wider at a pose of few observations (``camloc.sparse_poses``): a hypothesis that the
default beam drops (more than ``beam_delta`` costlier than the best) is kept at a pose whose
observations barely over-determine the state, in both engines, and dropped at a pose of many."""

from __future__ import annotations

import numpy as np
import pytest

from camloc import LocalizerConfig, measurement
from camloc.beam_types import BeamSettings
from camloc.constants import SPARSE_DELTA_EXTRA, SPARSE_ROWS_PER_DIM, SPARSE_WIDTH_FACTOR
from camloc.simulate import SimulationConfig, simulate
from camloc.sparse_poses import pose_beam

WIDTH, DELTA = BeamSettings.beam_width, BeamSettings.beam_delta


def test_a_pose_is_sparse_by_its_measurement_rows_against_the_state_s_dimension():
    wide = (WIDTH * SPARSE_WIDTH_FACTOR, DELTA + SPARSE_DELTA_EXTRA)
    assert pose_beam(2 * 6, 6, WIDTH, DELTA) == wide         # six pixels against the 6-dof state
    assert pose_beam(2 * 7, 6, WIDTH, DELTA) == (WIDTH, DELTA)
    assert pose_beam(3 * 4, 6, WIDTH, DELTA) == wide         # four points
    assert pose_beam(3 * 5, 6, WIDTH, DELTA) == (WIDTH, DELTA)
    assert pose_beam(2 * 3, 3, WIDTH, DELTA) == wide         # the planar state: three 2-row observations
    assert pose_beam(2 * 4, 3, WIDTH, DELTA) == (WIDTH, DELTA)


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
        width, delta = pose_beam(int(scene.obs_dof[obs].sum()), 6, settings.beam_width, settings.beam_delta)
        assert list(kb.prune(scene, settings, gen, COSTS.size, width, delta)) == list(range(kept))


def test_the_numpy_beam_keeps_more_at_a_pose_of_few_observations(world):
    from camloc.beam import BeamSearch
    from camloc.beam_types import Hypothesis
    from camloc.localizer import _Localizer

    search = BeamSearch(_Localizer(world, LocalizerConfig()), BeamSettings())
    hypotheses = [Hypothesis(x, COVARIANCE, float(c), 0) for x, c in zip(STATES, COSTS)]
    for pose, kept in zip(_poses_of(world), (KEPT_WIDE, KEPT_DEFAULT)):
        search._use_pose_beam(np.flatnonzero(world.obs_pose_index == pose), 6)
        assert search.expansion.prune(hypotheses) == hypotheses[:kept]
