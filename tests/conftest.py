"""Shared fixtures: the real dataset (skipped where ../shared is absent) and a seeded rng."""

from __future__ import annotations

import os

# one BLAS thread, as the command line sets (camloc/cli/__init__.py): before numpy loads
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

# A run with a cold kernel cache compiles in the foreground here, as the tests expect: no test may
# leave a background compile behind (camloc.warmup; its own tests switch it on where they need it).
os.environ["CAMLOC_BACKGROUND_COMPILE"] = "0"


def pytest_configure(config):
    """Where the kernels are not yet cached (a fresh clone, as in CI), compile them once before any
    test, as a first run does on two cores (the filter's kernels in a second process: about a minute
    rather than one and a half), instead of in one process in whichever test first calls them. With
    ``-n N`` (pytest-xdist, the README's command) this runs in the controlling process before its
    workers start, so they all find the cache warm; a worker never compiles here. The mapping
    pass's kernels (``camloc.slam_compiled``, which share none of the filter's) likewise, in a third
    process beside them: left to the tests, a worker's first test to map compiled them (64.7 s of a
    5-s test under load; both workers, where both got there before either had cached them;
    docs/performance.md, 2026-12-07, twenty-fifth session)."""
    if hasattr(config, "workerinput"):  # an xdist worker: its controller compiled already
        return
    from camloc import slam_compiled, warmup
    from camloc.kernels import cache_is_warm

    if cache_is_warm() and slam_compiled.cache_is_warm():
        return
    os.environ[warmup.ENVIRONMENT_SWITCH] = "1"   # the second and third processes start only so
    try:
        mapping = None if slam_compiled.cache_is_warm() else warmup.start_mapping_compile()
        try:
            if not cache_is_warm():
                warmup.compile_kernels()
        finally:
            warmup.wait_for(mapping)
    finally:
        os.environ[warmup.ENVIRONMENT_SWITCH] = "0"


REPO_ROOT = Path(__file__).resolve().parents[1]
REAL_DATASET = REPO_ROOT.parent / "shared" / "datasets" / "1b-3D-Camera-Localization.g2o"


@pytest.fixture
def real_dataset_path() -> Path:
    """The third-party course dataset, read in place from ../shared; never copied."""
    if not REAL_DATASET.is_file():
        pytest.skip("the real dataset ../shared/datasets is not present on this machine")
    return REAL_DATASET


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


def make_synthetic_run(seed: int = 7, *, num_poses: int = 40, with_truth: bool = True):
    """A small, self-consistent RunResult built without the localizer (for results/metrics/plot tests).

    The robot drives most of a circle; odometry drifts as a random walk; the estimate is the truth
    perturbed by errors drawn from its own covariance (so NEES ~ chi2(6)); the first pose is known
    exactly (zero covariance). Observations: 3 map landmarks a pose (80% correct, 10% wrong, 10%
    rejected) and a clutter observation (true id 9999, not in the map) every 4th pose, half accepted.
    """
    from scipy.spatial.transform import Rotation

    from camloc import geometry
    from camloc.results import UNASSOCIATED, Associations, RunResult

    rng = np.random.default_rng(seed)
    n = num_poses
    angle = np.linspace(0.0, 1.6 * np.pi, n)
    truth_xyz = np.column_stack([3.0 * np.cos(angle), 3.0 * np.sin(angle), 0.1 * np.sin(3.0 * angle)])
    rpy = np.column_stack([0.02 * np.sin(angle), 0.01 * np.cos(angle), angle + np.pi / 2])
    R_true = geometry.euler_to_matrix(rpy)

    walk = np.cumsum(rng.normal(0.0, 0.03, (n, 3)), axis=0)
    walk_rot = np.cumsum(rng.normal(0.0, 0.004, (n, 3)), axis=0)
    walk[0], walk_rot[0] = 0.0, 0.0
    odometry_xyz = truth_xyz + walk
    R_odometry = geometry.so3_exp(walk_rot) @ R_true

    sigma = np.array([0.05, 0.05, 0.03, 0.01, 0.01, 0.02])
    growth = np.linspace(0.5, 1.5, n)[:, None, None]
    cov = growth * np.diag(sigma**2)[None]
    cov[0] = 0.0
    error = np.einsum("nij,nj->ni", np.sqrt(cov), rng.standard_normal((n, 6)))
    estimate_xyz = truth_xyz - error[:, :3]  # e = t_true - t_est
    R_estimate = geometry.so3_exp(-error[:, 3:]) @ R_true  # Exp(e_rot) = R_true R_est^T
    estimate_quat = geometry.matrix_to_quat(R_estimate)
    T_estimate = geometry.make_pose(R_estimate, estimate_xyz)

    map_ids = np.arange(100, 130, dtype=np.int64)
    map_xyz = rng.uniform([-4.0, -4.0, 0.0], [4.0, 4.0, 2.0], (map_ids.size, 3))

    pose_ids = np.arange(1000, 1000 + n, dtype=np.int64)
    rows = []
    for k in range(1, n):
        for true_id in rng.choice(map_ids, 3, replace=False):
            draw = rng.uniform()
            chosen = true_id if draw < 0.8 else (UNASSOCIATED if draw < 0.9 else map_ids[(true_id - 99) % map_ids.size])
            rows.append((k, true_id, chosen))
        if k % 4 == 0:
            rows.append((k, 9999, map_ids[k % map_ids.size] if k % 8 == 0 else UNASSOCIATED))
    pose_index = np.array([r[0] for r in rows])
    chosen = np.array([r[2] for r in rows], dtype=np.int64)
    accepted = chosen != UNASSOCIATED
    associations = Associations(
        pose_id=pose_ids[pose_index],
        camera=np.zeros(len(rows), dtype=np.int64),
        uvd=rng.uniform([-0.5, 0.0, 0.3], [1.5, 1.5, 2.0], (len(rows), 3)),
        landmark=chosen,
        true_landmark=np.array([r[1] for r in rows], dtype=np.int64),
        mahalanobis=np.where(accepted, np.sqrt(rng.chisquare(3, len(rows))), np.nan),
    )
    update_index = np.unique(pose_index[accepted])
    nis_dof = np.array([3 * np.count_nonzero(accepted & (pose_index == k)) for k in update_index], dtype=np.int64)

    filter_state = geometry.pose_to_euler(T_estimate)
    return RunResult(
        dataset=f"synthetic-circle-{seed}",
        pose_ids=pose_ids,
        estimate_xyz=estimate_xyz,
        estimate_quat_xyzw=estimate_quat,
        estimate_cov=cov,
        filter_state=filter_state,
        filter_cov=cov.copy(),
        odometry_xyz=odometry_xyz,
        odometry_quat_xyzw=Rotation.from_matrix(R_odometry).as_quat(),  # qw of either sign, on purpose
        truth_xyz=truth_xyz if with_truth else None,
        truth_quat_xyzw=geometry.matrix_to_quat(R_true) if with_truth else None,
        map_landmark_ids=map_ids,
        map_landmark_xyz=map_xyz,
        associations=associations,
        update_pose_ids=pose_ids[update_index],
        nis=rng.chisquare(nis_dof).astype(float),
        nis_dof=nis_dof,
        summary={
            "dataset": f"synthetic-circle-{seed}",
            "config": {"gate": np.float64(0.99), "seed": np.int64(seed)},
            "counts": {"poses": n, "observations": len(rows), "accepted": int(np.count_nonzero(accepted))},
            "timing": {"filter_seconds": np.float64(0.25), "poses_per_second": float("inf")},
            "warnings": [],
        },
    )


@pytest.fixture
def synthetic_run():
    """The factory ``make_synthetic_run(seed=7, *, num_poses=40, with_truth=True) -> RunResult``."""
    return make_synthetic_run


@pytest.fixture
def numpy_localizer(monkeypatch):
    """Run ``localize`` through the numpy localizer (``camloc.localizer._Localizer``, the compiled
    loop's reference), for tests that probe its internals."""
    from camloc import localizer

    monkeypatch.setattr(localizer, "COMPILED_ASSOCIATIONS", ())
