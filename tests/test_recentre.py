"""A world far from the origin (a map in UTM metres) localizes as the same world at the origin:
``camloc.recentre`` runs it in a frame at its start pose. Before it, the mapping pass's innovation
covariance stopped being positive definite at 10^6 m (its Jacobians carry world positions)."""

from dataclasses import replace

import numpy as np
import pytest

from camloc.ekf import FilterDivergedError
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate, simulate_labelled
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

FAR = np.array([1.0e6, 2.0e6, 0.0])


def _moved(dataset, offset):
    return replace(dataset, landmark_xyz=dataset.landmark_xyz + offset, start_xyz=dataset.start_xyz + offset,
                   truth_xyz=dataset.truth_xyz + offset)


@pytest.mark.parametrize("mode", ["exact", "none"])
def test_a_world_far_from_the_origin_runs_as_at_the_origin(mode):
    """60 poses, a third of the map withheld: ``--map exact`` (which adds what the map lacks) and
    ``--map none`` give, 10^6 m away, the estimate, map and association of the origin's run."""
    dataset = simulate_labelled(SimulationConfig(poses=60, withhold_map=0.3), seed=5).dataset
    config = LocalizerConfig(map=mode)
    near, far = localize(dataset, config, engine="numpy"), localize(_moved(dataset, FAR), config, engine="numpy")
    np.testing.assert_allclose(far.estimate_xyz - FAR, near.estimate_xyz, atol=1e-6)
    np.testing.assert_allclose(far.filter_state[:, :3] - FAR, near.filter_state[:, :3], atol=1e-6)
    np.testing.assert_allclose(far.landmark_map.xyz - FAR, near.landmark_map.xyz, atol=1e-6)
    np.testing.assert_array_equal(far.associations.landmark, near.associations.landmark)
    np.testing.assert_array_equal(far.map_landmark_xyz, dataset.landmark_xyz + FAR)  # the map given, as given


def test_a_planar_world_far_from_the_origin_keeps_its_floor():
    """A planar robot 10^6 m away: moved in the floor's plane only (its landmarks stay at z = 0) and
    its stored (x, y, theta) moved back in x and y, not in theta."""
    dataset = simulate_planar(PlanarSimulationConfig(poses=40, withhold_map=0.3), seed=3)
    near, far = localize(dataset, LocalizerConfig(map="none")), localize(_moved(dataset, FAR), LocalizerConfig(map="none"))
    np.testing.assert_allclose(far.filter_state - np.r_[FAR[:2], 0.0], near.filter_state, atol=1e-6)
    np.testing.assert_allclose(far.estimate_xyz - FAR, near.estimate_xyz, atol=1e-6)


def test_a_path_that_jumps_far_from_its_start_says_so_when_the_mapping_pass_fails():
    """One odometry step of 10^8 m (a world of 20 poses, seed 3): the recentring at the start does
    not help a path that goes that far; the mapping pass fails as before, and the error names the
    distance rather than information matrices many orders of magnitude apart."""
    dataset = simulate(SimulationConfig(poses=20), seed=3)
    translation = dataset.odom_translation.copy()
    translation[2, 0] = 1e8
    with pytest.raises(FilterDivergedError, match=r"is 1e\+08 m from where the run's frame starts") as caught:
        localize(replace(dataset, odom_translation=translation), LocalizerConfig(), engine="numpy")
    assert "orders of magnitude" not in str(caught.value)
