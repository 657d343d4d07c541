"""No map, the true association: a landmark seen again long after, from a pose whose heading is
unsure by more than ten degrees, no longer turns the robot by the iterated update's overshoot
(``ekf.update``'s ``monotone``, which ``slam_run`` sets without a map; docs/performance.md,
2026-12-05, "No map: what is overconfident, and why")."""

from __future__ import annotations

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled


def test_a_return_after_151_poses_no_longer_turns_the_robot_with_the_true_association():
    """``benchmarks/mapping_sparse.py``'s smooth3d world, seed 16 (300 poses, a depth camera, no
    map). At pose 177 the robot sees again a landmark last seen at pose 26, 3.2 m away, its
    rotation unsure by 11-13 degrees an axis: the (pose, landmark) prior was consistent (NEES 7.1
    of 9 dof) and the innovation small (NIS 0.9 of 3), but the second and third Gauss-Newton
    iterates overshot (MAP cost 59,000 against the first iterate's about 1) and turned the robot
    by 35 degrees: the pose's NEES 2.4 -> 125 there, the run's mean 26.8 (dead reckoning on the
    same world: 6.9). The update is now the cheapest iterate: the run's mean NEES 6.6."""
    dataset = simulate_labelled(SimulationConfig(trajectory="smooth3d", poses=300, detection_probability=1.0,
                                                 no_map=True), seed=16).dataset
    result = localize(dataset, LocalizerConfig(map="none", association="oracle"))
    nees = metrics.run_nees(result)
    assert np.nanmean(nees) < 10.0  # main: 26.8
    assert np.nanmax(nees[170:200]) < 40.0  # main: up to 140 after the return
