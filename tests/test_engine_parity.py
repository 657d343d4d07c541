"""The two engines run the same algorithms (docs/kernels.md, "Two engines"): the compiled loop
(``camloc.loop`` over ``camloc.kernels``) and the numpy localizer, its reference. Generated over
every model both run: each kind of measurement (depth, pixel, disparity, and cameras of two kinds
in one file), each association the compiled loop runs (the beam, the oracle), each kind of
trajectory, with and without clutter, and with an odometry slip where the beam searches from
seeds; and the planar robot's (the se2 filter) with each of its sensors (points, markers, 3-D
cameras, the three at once). Both must give the same pairs, the same slips, states and
covariances to rounding, the same NIS and the same estimate covariance (the beam's association
spread included)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

import camloc
from camloc.localizer import COMPILED_ASSOCIATIONS
from camloc.simulate import TRAJECTORIES, SimulationConfig, simulate
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

MEASUREMENTS = ("depth", "pixel", "disparity", "depth,pixel")
CASES = list(itertools.product(MEASUREMENTS, COMPILED_ASSOCIATIONS, TRAJECTORIES))
# a planar robot's sensors (camloc.simulate_planar): its own (point2, marker), 3-D cameras on it, all three
PLANAR_SENSORS = ("points", "markers", "cameras", "points,markers,cameras")
PLANAR_CASES = list(itertools.product(PLANAR_SENSORS, COMPILED_ASSOCIATIONS))


def _world(measurement: str, trajectory: str, seed: int):
    """A small world of two cameras (one kind each where ``measurement`` names two), a tenth of
    its detections clutter, its odometry slipped on one edge (the seeded search runs there)."""
    config = SimulationConfig(trajectory=trajectory, poses=70, cameras=2, measurement=measurement, clutter_fraction=0.1)
    dataset = simulate(config, seed=seed)
    jumped = dataset.odom_translation.copy()
    jumped[40] += np.array([0.4, -0.3, 0.0])
    return dataclasses.replace(dataset, odom_translation=jumped)


def _planar_world(sensors: str, seed: int):
    """A small planar world of these sensors, a tenth of its detections clutter, its odometry
    slipped on one edge (the seeded search runs there)."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors=sensors, poses=60, clutter_fraction=0.1), seed=seed)
    jumped = dataset.odom_translation.copy()
    jumped[30] += np.array([0.4, -0.3, 0.0])
    return dataclasses.replace(dataset, odom_translation=jumped)


@pytest.mark.parametrize("measurement, association, trajectory", CASES, ids=["-".join(case) for case in CASES])
def test_both_engines_give_the_same_run(measurement, association, trajectory):
    _assert_same_run(_world(measurement, trajectory, seed=11), association)


@pytest.mark.parametrize("sensors, association", PLANAR_CASES, ids=["-".join(case) for case in PLANAR_CASES])
def test_both_engines_give_the_same_planar_run(sensors, association):
    _assert_same_run(_planar_world(sensors, seed=11), association)


def test_both_engines_widen_the_beam_alike_at_poses_of_few_observations():
    # one camera from above: one to seven pixel observations a pose, most poses sparse
    # (``camloc.sparse_poses``), their beam three times as wide; the slip's seeded search at pose 40
    dataset = simulate(SimulationConfig(trajectory="aerial", poses=70, cameras=1, measurement="pixel", clutter_fraction=0.1), seed=11)
    jumped = dataset.odom_translation.copy()
    jumped[40] += np.array([0.4, -0.3, 0.0])
    _assert_same_run(dataclasses.replace(dataset, odom_translation=jumped), "beam")


def test_both_engines_check_chained_pairs_alike_under_a_wide_pixel_prior(monkeypatch):
    # two pixel cameras under three times the default odometry noise: the poses' priors are wide
    # for the rays, and the chains of pairs are checked against them (``camloc.beam_chain``:
    # thousands of states replaced by the stacked update in the numpy run, 2026-12-06), the seeded
    # search's too, against the prior it started from (it runs at most of this world's first poses)
    from camloc import beam_chain, beam_seeded
    checked, replaced, seeding = beam_chain.checked, [], [False]
    explain_from_seeds = beam_seeded.SeededSearch.explain_from_seeds

    def counted(ctx, x, P, root, pairs):
        out = checked(ctx, x, P, root, pairs)
        replaced.append((out[0] is not x, seeding[0]))
        return out

    def seeded(self, *args, **kwargs):
        seeding[0] = True
        try:
            return explain_from_seeds(self, *args, **kwargs)
        finally:
            seeding[0] = False

    monkeypatch.setattr(beam_chain, "checked", counted)
    monkeypatch.setattr(beam_seeded.SeededSearch, "explain_from_seeds", seeded)
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=40, cameras=2, measurement="pixel", intrinsics="pixel",
                                        odometry_sigma_scale=3.0, clutter_fraction=0.1), seed=201)
    _assert_same_run(dataset, "beam")
    assert sum(r for r, _ in replaced) > 100
    assert sum(r for r, in_seeded in replaced if in_seeded) > 100


def _assert_same_run(dataset, association: str) -> None:
    config = camloc.LocalizerConfig(association=association)
    compiled = camloc.localize(dataset, config, engine="compiled")
    reference = camloc.localize(dataset, config, engine="numpy", parallel=False)
    assert (compiled.summary["timing"]["engine"], reference.summary["timing"]["engine"]) == ("compiled", "numpy")
    np.testing.assert_array_equal(compiled.associations.landmark, reference.associations.landmark)
    assert compiled.summary["slip_poses"] == reference.summary["slip_poses"]
    np.testing.assert_allclose(compiled.filter_state, reference.filter_state, atol=1e-8)
    np.testing.assert_allclose(compiled.filter_cov, reference.filter_cov, atol=1e-10)
    np.testing.assert_allclose(compiled.estimate_cov, reference.estimate_cov, atol=1e-10)
    np.testing.assert_allclose(compiled.nis, reference.nis, rtol=1e-6)
    np.testing.assert_array_equal(compiled.nis_dof, reference.nis_dof)
    assert np.count_nonzero(compiled.associations.landmark >= 0) > 0.5 * dataset.num_observations  # a run that localized
