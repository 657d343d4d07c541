"""The beam with its replay in a second process (``camloc.replay``): the same result as the
sequential run, decided poses handed over exactly once and in order, errors raised in the caller."""

import io
import pickle

import numpy as np
import pytest

pytestmark = pytest.mark.usefixtures("numpy_localizer")  # the replay process serves the numpy localizer

from camloc.beam import BeamSearch
from camloc.beam_types import BeamSettings
from camloc.localizer import LocalizerConfig, _Localizer, localize
from camloc.replay import _replay
from camloc.simulate import SimulationConfig, simulate

CLUTTERED = SimulationConfig(trajectory="smooth3d", poses=150, clutter_fraction=0.15, outlier_fraction=0.03)


@pytest.mark.parametrize(
    "config",
    [CLUTTERED, SimulationConfig(trajectory="aerial", poses=130, intrinsics="pixel", cameras=2)],
    ids=["smooth3d with clutter", "aerial, two cameras"],
)
def test_parallel_replay_gives_the_sequential_result_exactly(config):
    dataset = simulate(config, seed=5)
    sequential = localize(dataset, parallel=False)
    parallel = localize(dataset, parallel=True)
    for field in ("estimate_xyz", "estimate_quat_xyzw", "estimate_cov", "filter_state", "filter_cov",
                  "odometry_xyz", "nis", "nis_dof", "update_pose_ids"):
        np.testing.assert_array_equal(getattr(parallel, field), getattr(sequential, field), err_msg=field)
    np.testing.assert_array_equal(parallel.associations.landmark, sequential.associations.landmark)
    np.testing.assert_array_equal(parallel.associations.mahalanobis, sequential.associations.mahalanobis)
    assert parallel.summary["warnings"] == sequential.summary["warnings"]
    assert parallel.summary["slip_poses"] == sequential.summary["slip_poses"]
    assert parallel.summary["timing"]["replay_process"] and not sequential.summary["timing"]["replay_process"]


def test_beam_hands_over_every_pose_once_in_order_as_it_is_decided():
    dataset = simulate(CLUTTERED, seed=6)
    localizer = _Localizer(dataset, LocalizerConfig())
    calls = []
    search = BeamSearch(localizer, BeamSettings())
    poses_seen = []
    chosen, slipped = search.run(
        localizer.x, localizer.P, on_pose=poses_seen.append,
        on_decided=lambda first, pairs, slips: calls.append((first, len(poses_seen), pairs, slips)), decided_stride=8,
    )
    firsts = [c[0] for c in calls]
    lengths = [len(c[2]) for c in calls]
    assert firsts[0] == 0 and all(a + n == b for a, n, b in zip(firsts, lengths, firsts[1:]))
    assert firsts[-1] + lengths[-1] == dataset.num_poses
    assert len(calls) > dataset.num_poses // 8 // 2  # handed over as the beam goes, not all at the end
    for first, seen, pairs, slips in calls:
        assert first + len(pairs) <= seen  # only poses the beam has already processed
        for offset, p in enumerate(pairs):
            np.testing.assert_array_equal(p, chosen[first + offset])  # what the final backtrack chose
        np.testing.assert_array_equal(slips, slipped[first : first + len(pairs)])


def _replay_answer(messages):
    incoming, outgoing = io.BytesIO(), io.BytesIO()
    for message in messages:
        pickle.dump(message, incoming)
    incoming.seek(0)
    _replay(incoming, outgoing, _Localizer)
    outgoing.seek(0)
    return pickle.load(outgoing)


def test_replay_process_protocol_filters_the_batches_it_is_sent():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=40), seed=3)
    config = LocalizerConfig()
    localizer = _Localizer(dataset, config)
    localizer.search_beam()
    chosen, slipped = localizer.beam_pairs, localizer.beam_slipped
    status, payload = _replay_answer([(dataset, config, 0.0), (0, chosen[:25], slipped[:25]), (25, chosen[25:], slipped[25:]), None])
    assert status == "ok"
    sequential = localize(dataset, config, parallel=False)
    np.testing.assert_array_equal(payload["states"], sequential.filter_state)
    np.testing.assert_array_equal(payload["covs"], sequential.filter_cov)


def test_replay_process_reports_an_error_instead_of_dying_silently():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=20), seed=3)
    bad_pairs = [np.array([[0, 10**9]])] * dataset.num_poses  # a landmark index beyond the map
    status, error = _replay_answer([(dataset, LocalizerConfig(), 0.0), (0, bad_pairs, np.zeros(dataset.num_poses, bool)), None])
    assert status == "error" and isinstance(error, IndexError)


def test_a_replay_process_that_cannot_start_falls_back_to_this_process(monkeypatch):
    import camloc.replay

    dataset = simulate(SimulationConfig(trajectory="grid", poses=30), seed=3)
    sequential = localize(dataset, parallel=False)
    monkeypatch.setattr(camloc.replay.sys, "executable", "/bin/false")  # exits at once, says nothing
    result = localize(dataset, parallel=True)
    np.testing.assert_array_equal(result.filter_state, sequential.filter_state)
    np.testing.assert_array_equal(result.associations.landmark, sequential.associations.landmark)
    assert any("replay process ended without a result" in w for w in result.summary["warnings"])
    assert not result.summary["timing"]["replay_process"]


def test_a_filter_error_in_the_replay_process_is_raised_in_the_caller(monkeypatch):
    import camloc.replay

    dataset = simulate(SimulationConfig(trajectory="grid", poses=30), seed=3)
    localizer = _Localizer(dataset, LocalizerConfig())
    # the beam decides a pair with a landmark beyond the map: the replay's IndexError comes back
    original = localizer.search_beam

    def corrupt_search(on_pose=None, on_decided=None):
        def corrupted(first, chosen, slipped):
            on_decided(first, [np.array([[0, 10**9]])] * len(chosen), slipped)
        original(on_pose, on_decided=corrupted)

    monkeypatch.setattr(localizer, "search_beam", corrupt_search)
    with pytest.raises(IndexError):
        camloc.replay.search_and_replay(localizer)
