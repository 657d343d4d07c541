"""At a pose of rays only the beam's hypotheses are merged once predicted, before they explain it
(``kernels.beam.distinct_predictions``, ``BeamSearch._distinct_predictions``; docs/beam.md, "Merged
once predicted"): one within ``copy_sigma`` standard deviations of a cheaper one kept on every
axis (the kept one's) is dropped where it costs at least ``predicted_merge_margin`` more. Both
engines, on a hand-built beam and on a pose of a pixel world where two hypotheses meet on purpose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from camloc import LocalizerConfig, geometry
from camloc.beam_types import Hypothesis
from camloc.constants import MERGE_SIGMA, PREDICTED_MERGE_MARGIN
from camloc.simulate import SimulationConfig, simulate

SIGMA = np.array([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
ONES = np.ones(6)
# Four predicted hypotheses, given out of cost order (c, a, d, b). a's covariance is SIGMA^2, the
# others' a quarter of it (b's own sigma would put it 0.5 of its sigma from a: only the kept one's
# counts). b: 0.25 of a's sigma from a on every axis, 6 units dearer: merged into a. c: as near,
# 2 units dearer (under the margin of 4): kept. d: 0.35 of a's sigma from a on x and -0.35 on y
# (outside 0.3 there), and -0.6 of c's sigma from c on y: kept, though 10 units dearer than a.
STATES = np.array([0.25 * SIGMA, np.zeros(6), (0.35 * np.eye(6)[0] - 0.35 * np.eye(6)[1]) * SIGMA, 0.25 * SIGMA])
COSTS = np.array([12.0, 10.0, 20.0, 16.0])
COVARIANCES = np.array([np.diag((SIGMA / 2) ** 2), np.diag(SIGMA**2), np.diag((SIGMA / 2) ** 2), np.diag((SIGMA / 2) ** 2)])
KEPT = [1, 0, 2]          # a, c, d: by cost
KEPT_WITHOUT_MARGIN = [1, 2]   # c merges into a too


def test_the_hand_built_case_is_what_its_comment_says():
    a, b, c, d = STATES[1], STATES[3], STATES[0], STATES[2]
    assert PREDICTED_MERGE_MARGIN == 4.0 and MERGE_SIGMA == 0.3
    assert np.all(np.abs(b - a) / SIGMA <= MERGE_SIGMA) and np.any(np.abs(b - a) / (SIGMA / 2) > MERGE_SIGMA)
    assert COSTS[3] - COSTS[1] >= PREDICTED_MERGE_MARGIN > COSTS[0] - COSTS[1]
    assert np.abs((d - a) / SIGMA).max() > MERGE_SIGMA and np.abs((d - c) / (SIGMA / 2)).max() > MERGE_SIGMA


@pytest.fixture(scope="module")
def world():
    return simulate(SimulationConfig(trajectory="smooth3d", poses=30, cameras=2, measurement="pixel"), seed=2)


def _numpy_search(world, margin=PREDICTED_MERGE_MARGIN):
    from camloc.beam import BeamSearch
    from camloc.localizer import _Localizer

    localizer = _Localizer(world, LocalizerConfig())
    return localizer, BeamSearch(localizer, dataclasses.replace(localizer.beam_settings(), predicted_merge_margin=margin))


@pytest.mark.parametrize("margin, kept", [(PREDICTED_MERGE_MARGIN, KEPT), (0.0, KEPT_WITHOUT_MARGIN)])
def test_a_predicted_hypothesis_is_merged_into_a_cheaper_one_only_past_the_margin(world, margin, kept):
    from camloc.kernels import beam as kb
    from camloc.scene import build_settings

    settings = build_settings(LocalizerConfig())._replace(predicted_merge_margin=margin)
    assert list(kb.distinct_predictions(settings, STATES, COVARIANCES, COSTS, 4)) == kept
    beam = [Hypothesis(x, P, float(c), i) for i, (x, P, c) in enumerate(zip(STATES, COVARIANCES, COSTS))]
    assert [h.parent for h in _numpy_search(world, margin)[1]._distinct_predictions(beam)] == kept


def _met(world, localizer, k):
    """Two hypotheses at pose k - 1 whose predictions at pose k meet on purpose: the second's
    predicted state 0.2 of the predicted sigma from the first's on every axis (by the prediction's
    Jacobian), 6 units dearer; the first at the truth. A wide prior (2 cm, half a degree), which the
    pose's rays narrow several times, so that once explained they lie apart."""
    x = np.r_[world.truth_xyz[k - 1], geometry.matrix_to_euler(geometry.quat_to_matrix(world.truth_quat_xyzw[k - 1]))]
    P = np.diag(np.r_[np.full(3, 0.02**2), np.full(3, np.radians(0.5) ** 2)])
    search = _numpy_search(world)[1]
    first = search._predicted(Hypothesis(x, P, 0.0, 0), k - 1, 0)
    _, F, _ = localizer.filter.predict(x, search.ctx.T_increments[k - 1])
    step = 0.2 * np.sqrt(first.P.diagonal()) * np.array([1, -1, 1, -1, 1, -1])
    return [(x, P, 0.0), (x + np.linalg.solve(F, step), P, 6.0)]


def test_two_hypotheses_that_meet_once_predicted_are_explained_once_and_the_pose_s_pairs_are_right(world):
    from camloc.dataset import observations_by_pose
    from camloc.kernels import beam as kb
    from camloc.scene import build_scene, build_settings
    from camloc.sparse_poses import sparse_poses

    k = 27
    localizer, search = _numpy_search(world)
    met = _met(world, localizer, k)
    obs = search.ctx.obs_of_pose[k]
    assert obs.size >= 8 and world.obs_kind[obs].tolist() == [1] * obs.size   # many rays: not a sparse pose
    order, bounds = observations_by_pose(world)
    sparse = sparse_poses(world.obs_kind[order], bounds, 6)
    truth = world.obs_true_landmark
    for margin in (PREDICTED_MERGE_MARGIN, np.inf):
        _, search = _numpy_search(world, margin)
        search.sparse = sparse
        beam = [search._predicted(Hypothesis(x, P, c, 0), k - 1, i) for i, (x, P, c) in enumerate(met)]
        kept = search._explain_pose(k, beam, obs)
        # merged, every hypothesis kept grew from the cheaper; without, the dearer's own survive
        assert {h.parent for h in kept} == ({0} if margin < np.inf else {0, 1})
        best = kept[0]
        assert len(best.pairs) >= 6 and all(world.landmark_ids[lm] == truth[o] for o, lm in best.pairs)

        config = LocalizerConfig()
        scene, settings = build_scene(world, config), build_settings(config)._replace(predicted_merge_margin=margin)
        gen = kb.new_generation(2, 1, 6)
        for i, (x, P, c) in enumerate(met):
            gen[0][i], gen[1][i], gen[2][i] = x, P, c
        n = world.num_poses
        width = 3 * settings.beam_width
        history = (np.zeros(n, np.int64), np.zeros((n, width), np.int64), np.zeros((n, width), np.bool_),
                   np.zeros((n, width + 1), np.int64), np.zeros((4096, 2), np.int64), np.zeros(1, np.int64),
                   np.zeros((n, width, 6)), np.zeros((n, width)))
        status = kb.run_poses(scene, settings, sparse, k, k + 1, gen, 2, history, np.zeros((n, 2), np.int64),
                              np.zeros(3, np.int64))[0]
        assert status == kb.DONE
        count, parent, pair_start, pairs = history[0][k], history[1][k], history[3][k], history[4]
        assert count == len(kept) and set(parent[:count].tolist()) == {h.parent for h in kept}
        assert [tuple(p) for p in pairs[pair_start[0]:pair_start[1]]] == [tuple(p) for p in best.pairs]
