"""The mapping pass beside the beam's run, in a second process (``camloc.mapping_follower``): the
same run as one pass after the other, a process that stops when the run does, its errors raised in
the caller, and a process lost leaving the pass to the caller."""

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
    monkeypatch.setattr(localizer, "_cpu_free", lambda: True)
    monkeypatch.setattr(localizer, "FOLLOW_MIN_POSES", 600)
    followed = []
    follow = MappingFollower.follow

    def spy(self, replay):
        followed.append(self)
        follow(self, replay)
    monkeypatch.setattr(MappingFollower, "follow", spy)
    beside = localize(world, LocalizerConfig(), engine="compiled", parallel=True)
    assert len(followed) == 1 and followed[0].sent == world.num_poses and followed[0].failure is None
    assert followed[0].taken and followed[0].worker.poll() == 0  # its run was taken, and it ended
    monkeypatch.setattr(localizer, "_follower", lambda dataset, config, hooks: MappingFollower(dataset, config, lambda: True,
                                                                                                enabled=False))
    after = localize(world, LocalizerConfig(), engine="compiled", parallel=True)
    assert len(followed) == 1
    assert beside.summary["map"]["added"] == after.summary["map"]["added"] > 0
    assert np.array_equal(beside.associations.landmark, after.associations.landmark)
    assert np.array_equal(beside.estimate_xyz, after.estimate_xyz)
    assert np.array_equal(beside.estimate_cov, after.estimate_cov)
    assert np.array_equal(beside.landmark_map.xyz, after.landmark_map.xyz)
    assert np.array_equal(beside.landmark_map.cov, after.landmark_map.cov)
    assert not any("second process" in w for w in beside.summary["warnings"])


def _source(world, filtered):
    return SimpleNamespace(chosen=np.full(world.num_observations, -1, np.int64), filtered=filtered)


def test_a_follower_whose_run_stops_ends_its_process():
    """A run stopped (an error, Ctrl-C) leaves the replay short of the last pose: the context's
    exit ends the process waiting for it, and the thread feeding it."""
    world = _world(poses=50)
    with MappingFollower(world, LocalizerConfig(map="exact"), lambda: False) as follower:
        follower.follow(_source(world, filtered=3))
        waited = 0.0
        while follower.sent < 3 and waited < 30.0:
            time.sleep(0.01)
            waited += 0.01
        assert follower.sent == 3 and follower.worker.poll() is None  # fed what was filtered, waiting for more
    assert follower.worker.poll() is not None
    assert not follower.feeder.is_alive()


def test_an_error_in_the_mapping_process_is_raised_by_its_result():
    """A pair with a landmark row the map does not have fails in the process's step: the
    caller gets the error, as from the pass in its own process."""
    world = _world(poses=50)
    source = _source(world, filtered=world.num_poses)
    source.chosen[:] = 10**9
    with MappingFollower(world, LocalizerConfig(map="exact"), lambda: False) as follower:
        follower.follow(source)
        with pytest.raises(IndexError):
            follower.result(source.chosen)


def test_a_mapping_process_lost_leaves_the_pass_to_its_caller_and_says_why():
    world = _world(poses=50)
    source = _source(world, filtered=10)
    with MappingFollower(world, LocalizerConfig(map="exact"), lambda: False) as follower:
        follower.follow(source)
        follower.worker.kill()
        assert follower.result(source.chosen) is None
        assert "ended without a result" in follower.failure


def test_a_short_run_maps_after_its_beam_s_run(monkeypatch):
    """Below ``FOLLOW_MIN_POSES`` the process would cost more than it saves: no follower starts."""
    monkeypatch.setattr(localizer, "_cpus", lambda: 2)
    monkeypatch.setattr(localizer, "_cpu_free", lambda: True)
    world = _world(poses=400)
    hooks = dict(parallel=True, engine="compiled", on_compile=None, on_background_compile=None)
    assert localizer._follower(world, localizer.resolved_config(LocalizerConfig(), world), hooks).on_replay is None
    monkeypatch.setattr(localizer, "FOLLOW_MIN_POSES", 400)
    assert localizer._follower(world, localizer.resolved_config(LocalizerConfig(), world), hooks).on_replay is not None
    monkeypatch.setattr(localizer, "_cpu_free", lambda: False)  # other work takes the second CPU
    assert localizer._follower(world, localizer.resolved_config(LocalizerConfig(), world), hooks).on_replay is None


def test_a_follower_that_did_not_follow_leaves_the_pass_to_its_caller():
    world = _world(poses=50)
    follower = MappingFollower(world, LocalizerConfig(map="exact"), lambda: False, enabled=False)
    assert follower.on_replay is None
    assert follower.result(np.full(world.num_observations, -1, np.int64)) is None and follower.failure is None
