"""The mapping pass beside the beam's run (``camloc.mapping_follower``): the same run as one pass
after the other, a thread that stops when the run does, and its errors raised in the caller."""

import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from camloc import localizer
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.mapping_follower import MappingFollower
from camloc.simulate import SimulationConfig, simulate_labelled


def _world(withheld=0.3, poses=700):
    return simulate_labelled(SimulationConfig(poses=poses, trajectory="smooth3d", withhold_map=withheld), seed=1).dataset


@pytest.mark.parametrize("screened", ["start", "after"])
def test_the_mapping_pass_beside_the_beam_gives_the_run_of_one_pass_after_the_other(monkeypatch, screened):
    """The mapping pass beside the beam's run whose pairs it takes: a long run whose start shows
    the map lacking (the prefix shortened to fit a test), or the beam's second run of a run
    screened after it. Every pair, pose and landmark is the sequential run's, bit for bit."""
    world = _world()
    if screened == "start":
        monkeypatch.setattr(localizer, "LACKING_PREFIX_MIN_POSES", 600)
        monkeypatch.setattr(localizer, "LACKING_PREFIX_SHARE", 0.5)
    monkeypatch.setattr(localizer, "_cpus", lambda: 2)
    followed = []
    follow = MappingFollower.follow
    monkeypatch.setattr(MappingFollower, "follow", lambda self, replay: (followed.append(replay), follow(self, replay))[1])
    interval = sys.getswitchinterval()
    beside = localize(world, LocalizerConfig(), engine="compiled", parallel=True)
    assert len(followed) == 1 and followed[0].filtered == world.num_poses
    assert sys.getswitchinterval() == interval
    monkeypatch.setattr(localizer, "_follower", lambda dataset, config, hooks: MappingFollower(dataset, config, lambda: True,
                                                                                                enabled=False))
    after = localize(world, LocalizerConfig(), engine="compiled", parallel=True)
    assert len(followed) == 1
    assert beside.summary["map"]["added"] == after.summary["map"]["added"] > 0
    assert np.array_equal(beside.associations.landmark, after.associations.landmark)
    assert np.array_equal(beside.estimate_xyz, after.estimate_xyz)
    assert np.array_equal(beside.landmark_map.xyz, after.landmark_map.xyz)
    assert np.array_equal(beside.landmark_map.cov, after.landmark_map.cov)


def test_a_follower_whose_run_stops_ends_its_thread_and_restores_the_switch_interval():
    """A run stopped (an error, Ctrl-C) leaves the replay short of the last pose: ``cancel``
    (the context's exit) ends the thread that waits for it."""
    world = _world(poses=50)
    source = SimpleNamespace(chosen=np.full(world.num_observations, -1, np.int64), filtered=3)
    interval = sys.getswitchinterval()
    with MappingFollower(world, LocalizerConfig(map="exact"), lambda: False) as follower:
        follower.follow(source)
        assert sys.getswitchinterval() < interval
        waited = 0.0
        while follower.done < 3 and waited < 30.0:   # it steps the poses the replay has filtered, then waits
            time.sleep(0.01)
            waited += 0.01
        time.sleep(0.05)
        assert follower.thread.is_alive()
    assert not follower.thread.is_alive()
    assert follower.outcome is None and follower.done == 3
    assert sys.getswitchinterval() == interval


def test_an_error_in_the_mapping_thread_is_raised_by_its_result(monkeypatch):
    from camloc import slam_run

    world = _world(poses=50)
    source = SimpleNamespace(chosen=np.full(world.num_observations, -1, np.int64), filtered=world.num_poses)

    def failing(self, k):
        if k == 7:
            raise FloatingPointError("pose 7")
    monkeypatch.setattr(slam_run.MappingLocalizer, "step", failing)
    with MappingFollower(world, LocalizerConfig(map="exact"), lambda: False) as follower:
        follower.follow(source)
        with pytest.raises(FloatingPointError, match="pose 7"):
            follower.result(source.chosen)


def test_a_follower_that_did_not_follow_leaves_the_pass_to_its_caller():
    world = _world(poses=50)
    follower = MappingFollower(world, LocalizerConfig(map="exact"), lambda: False, enabled=False)
    assert follower.on_replay is None
    assert follower.result(np.full(world.num_observations, -1, np.int64)) is None
