"""The compiled kernels against their numpy twins (the formulas the rest of camloc states in numpy)
on random inputs, their Jacobians against finite differences, and the compiled localizer against
the numpy one on whole worlds."""

from __future__ import annotations

import importlib
import os
import pkgutil
from pathlib import Path

import numpy as np
import pytest

import camloc.kernels
from camloc import association, ekf, geometry, measurement, models
from camloc.kernels import _jit, camera, motion, recheck, rotation, seeds, sym3, update, view
from camloc.kernels._jit import OPTIONS

# the steps as Python calls them: most are compiled without numba's Python wrapper (``_jit.jit``)
camera, motion, recheck, rotation, seeds, sym3, update, view = (
    _jit.FromPython(module) for module in (camera, motion, recheck, rotation, seeds, sym3, update, view))

DATA = Path(__file__).resolve().parents[1] / "camloc" / "data"


def _random_state(rng):
    return np.r_[rng.normal(0, 2, 3), rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)]


def _random_spd(rng, n, scale=1.0):
    A = rng.normal(0, scale, (n, n))
    return A @ A.T + scale**2 * np.eye(n)


def test_every_kernel_carries_the_shared_options():
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    found = entries = 0
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                found += 1
                assert not isinstance(value._cache, NullCache), f"{module.__name__}.{name} is not cached"
                for key in ("nogil", "error_model"):
                    assert value.targetoptions[key] == OPTIONS[key], f"{module.__name__}.{name}: {key}"
                # an entry point: numba's Python wrapper, and not a step inlined into its callers
                entries += not value.targetoptions.get("no_cpython_wrapper", False) and value.targetoptions.get("inline") != "always"
    assert found >= 30 and 10 <= entries < found / 4   # most are steps that only compiled code calls


def test_what_python_calls_is_an_entry_point():
    # a step compiled without numba's Python wrapper cannot be called from Python: every kernel that
    # camloc's Python code (the loop, the slip search, the scene) names must be an entry point
    import ast

    from numba.core.registry import CPUDispatcher

    kernels = {}
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        kernels.update({name: value for name, value in vars(module).items() if isinstance(value, CPUDispatcher)})
    package = Path(camloc.__file__).parent
    named = set()
    for path in package.rglob("*.py"):
        if "kernels" in path.relative_to(package).parts:
            continue
        tree = ast.parse(path.read_text())
        aliases = set()                                   # the kernel modules it imports, by their local names
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("camloc.kernels"):
                for alias in node.names:
                    named.add(alias.name)
                    aliases.add(alias.asname or alias.name)
        named |= {node.attr for node in ast.walk(tree)
                  if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases}
    called = sorted(name for name in named if name in kernels)
    assert {"run_poses", "filter_poses", "options_for", "prune", "seeded_explanations"} <= set(called)
    for name in called:
        assert not kernels[name].targetoptions.get("no_cpython_wrapper", False), f"{name} is called from Python"


def test_every_compiled_sort_is_the_merge_sort():
    # numba compiles its quicksort apart for each kind it sorts (argsort of int64 and of float, sort
    # of int64 took ~4 s of a first compile, docs/performance.md 2026-12-05): compiled code sorts
    # with np.argsort(..., kind="mergesort") only (of floats, the kind the kernels compile)
    import ast

    compiled = {"jit", "entry", "inlined"}
    checked = 0
    for path in sorted(Path(camloc.kernels.__file__).parent.glob("*.py")):
        for function in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(function, ast.FunctionDef)
                    and any(isinstance(d, ast.Name) and d.id in compiled for d in function.decorator_list)):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ("sort", "argsort"):
                    kinds = [k.value.value for k in node.keywords if k.arg == "kind" and isinstance(k.value, ast.Constant)]
                    assert node.func.attr == "argsort" and kinds == ["mergesort"], f"{path.name}:{node.lineno}"
                    checked += 1
    assert checked >= 5


def test_no_kernel_passes_a_literal_flag_to_another():
    # numba types a literal True or False as a type of its own: a kernel passed both and a flag
    # computed at run time compiled three times, each with all it calls (``updated``'s map_cost,
    # docs/performance.md 2026-12-05): compiled code passes ``_jit.TRUE`` / ``_jit.FALSE``
    import ast

    from numba.core.registry import CPUDispatcher

    kernels, sources = set(), []
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        kernels |= {name for name, value in vars(module).items() if isinstance(value, CPUDispatcher)}
        sources.append((info.name, Path(module.__file__).read_text()))
    compiled = {"jit", "entry", "inlined"}
    calls = 0
    for name, source in sources:
        for function in ast.walk(ast.parse(source)):
            if not (isinstance(function, ast.FunctionDef)
                    and any(isinstance(d, ast.Name) and d.id in compiled for d in function.decorator_list)):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in kernels:
                    calls += 1
                    for argument in node.args + [k.value for k in node.keywords]:
                        assert not (isinstance(argument, ast.Constant) and isinstance(argument.value, bool)), \
                            f"{name}.py:{node.lineno}: {node.func.id} passed a literal {argument.value}"
    assert calls >= 100


@pytest.mark.parametrize("user_level, user_vectorize", [(None, None), ("3", "1")])
def test_kernels_compile_at_llvm_level_1_unless_the_user_sets_numba_opt(tmp_path, user_level, user_vectorize):
    """The kernels' modules are optimized at ``_jit.KERNEL_OPT_LEVEL`` without the loop vectorizer
    (numba reads its environment again before a compile, after ``_jit`` set it), and a
    ``NUMBA_OPT`` or ``NUMBA_LOOP_VECTORIZE`` the user set wins. In a fresh process: numba's
    settings are read after a compile."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_OPT", "NUMBA_LOOP_VECTORIZE")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path)
    if user_level is not None:
        env["NUMBA_OPT"], env["NUMBA_LOOP_VECTORIZE"] = user_level, user_vectorize
    code = ("import numba\nfrom numba.core import config\nimport camloc.kernels._jit\n"
            "numba.njit(lambda x: x + 1)(1)\nprint(int(config.OPT), int(config.LOOP_VECTORIZE))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [user_level or _jit.KERNEL_OPT_LEVEL, user_vectorize or _jit.KERNEL_LOOP_VECTORIZE]


def test_a_step_without_the_python_wrapper_is_callable_through_from_python(rng):
    from camloc.kernels import sym3 as compiled_only

    assert compiled_only.log_det.targetoptions["no_cpython_wrapper"]
    S = _random_spd(rng, 3)
    twin = _jit.from_python(compiled_only.log_det)
    assert twin is _jit.from_python(compiled_only.log_det)          # compiled once
    assert twin.py_func.__qualname__ != compiled_only.log_det.py_func.__qualname__   # cached apart
    np.testing.assert_allclose(twin(S), np.linalg.slogdet(S)[1], rtol=1e-12)
    assert _jit.from_python(update.updated) is update.updated      # an entry point is itself


def test_rotations_match_geometry(rng):
    for _ in range(20):
        rpy = _random_state(rng)[3:]
        R = rotation.euler_to_matrix(*rpy)
        np.testing.assert_allclose(R, geometry.euler_to_matrix(rpy), atol=1e-14)
        np.testing.assert_allclose(rotation.matrix_to_euler(R), geometry.matrix_to_euler(R), atol=1e-12)
        np.testing.assert_allclose(rotation.euler_rate(rpy[0], rpy[1]), geometry.euler_rate_matrix(rpy), atol=1e-14)
        np.testing.assert_allclose(rotation.euler_rate_inverse(rpy[0], rpy[1]), geometry.euler_rate_matrix_inverse(rpy), atol=1e-12)


def test_buffers_written_again_hold_only_the_last_state(rng):
    # an iterated update predicts every linearization into the same buffers: nothing of the state
    # before may remain (the rate matrix's zeros included)
    frame = (np.full((3, 3), np.nan), np.full((3, 3), np.nan), np.full(3, np.nan))
    moved, retracted = np.full(6, np.nan), np.full(6, np.nan)
    for _ in range(5):
        x, delta = _random_state(rng), rng.normal(0, 0.5, 6)
        camera.robot_frame_into(x, frame)
        np.testing.assert_allclose(frame[0], geometry.euler_to_matrix(x[3:]), atol=1e-14)
        np.testing.assert_allclose(frame[1], geometry.euler_rate_matrix(x[3:]), atol=1e-15)
        np.testing.assert_array_equal(frame[2], x[:3])
        rotation.retract_into(x, delta, retracted)
        rotation.difference_into(retracted, x, moved)
        np.testing.assert_array_equal(retracted, rotation.retract(x, delta))
        np.testing.assert_allclose(moved, delta, atol=1e-12)


def test_motion_matches_the_numpy_model_and_finite_differences(rng):
    for _ in range(10):
        x = _random_state(rng)
        T = geometry.pose_from_euler(np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.2, 3)])
        x_next, F, G = motion.motion(x, T)
        ref = models.motion(x, T)
        for a, b in zip((x_next, F, G), ref):
            np.testing.assert_allclose(a, b, atol=1e-12)
        eps = 1e-6
        F_fd = np.column_stack([rotation.difference(motion.motion(x + eps * e, T)[0], motion.motion(x - eps * e, T)[0]) / (2 * eps)
                                for e in np.eye(6)])
        np.testing.assert_allclose(F, F_fd, atol=1e-6)
        P, Q = _random_spd(rng, 6, 0.1), _random_spd(rng, 6, 0.01)
        x2, P2 = motion.predict(x, P, T, Q)
        np.testing.assert_allclose(P2, ekf.predict(P, F, G, Q), atol=1e-12)


def test_observe_matches_the_numpy_model_and_finite_differences(rng):
    T_rc = geometry.pose_from_euler(np.array([0.1, -0.05, 0.3, -np.pi / 2, 0.1, -np.pi / 2]))
    K = np.array([520.0, 510.0, 320.0, 240.0, measurement.DEPTH])  # fx fy cx cy, the sensor's kind
    for _ in range(10):
        x = _random_state(rng)
        T_wc = geometry.pose_from_euler(x) @ T_rc
        points = geometry.transform_points(T_wc, np.column_stack([rng.uniform(-1, 1, (8, 2)), rng.uniform(1, 4, 8)]))
        z_hat, H = camera.observe(x, T_rc[:3, :3].copy(), T_rc[:3, 3].copy(), K, points)
        ref_z, ref_H = models.observe(x, T_rc, tuple(K[:4]), points)
        np.testing.assert_allclose(z_hat, ref_z, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(H, ref_H, rtol=1e-10, atol=1e-8)
        eps = 1e-6
        H_fd = np.stack([(camera.observe(x + eps * e, T_rc[:3, :3].copy(), T_rc[:3, 3].copy(), K, points)[0]
                          - camera.observe(x - eps * e, T_rc[:3, :3].copy(), T_rc[:3, 3].copy(), K, points)[0]) / (2 * eps)
                         for e in np.eye(6)], axis=-1)
        np.testing.assert_allclose(H, H_fd, rtol=1e-5, atol=1e-4)


def test_mahalanobis_matches_the_batched_formula(rng):
    for _ in range(20):
        S, y = _random_spd(rng, 3), rng.normal(size=3)
        d2, log_det = sym3.mahalanobis(S, y)
        ref = association.mahalanobis_3x3(S[None], y[None])
        np.testing.assert_allclose([d2, log_det], [ref[0][0], ref[1][0]], rtol=1e-12)
    assert sym3.mahalanobis(-np.eye(3), np.ones(3)) == (np.inf, np.inf)


def _pairs(rng, p):
    H = rng.normal(0, 1, (p, 3, 6))
    R = np.stack([_random_spd(rng, 3, 0.3) for _ in range(p)])
    return H, R, np.linalg.inv(R), rng.normal(0, 1, (p, 3))


def test_iterated_update_matches_ekf_update(rng):
    """A linear measurement (z = H x + b): the iterated update is the Kalman update, in numpy."""
    for p in (1, 2, 5):
        H, R, R_inverse, _ = _pairs(rng, p)
        x, P = rng.normal(0, 0.1, 6), _random_spd(rng, 6, 0.2)
        z = rng.normal(0, 1, (p, 3))
        ref = ekf.update(x, P, z.reshape(-1), R, lambda s: ((H @ s).reshape(-1), H.reshape(-1, 6)), R_inverse=R_inverse)
        R_inverse_H, information, AP = np.empty((p, 3, 6)), np.empty((6, 6)), np.empty((6, 6))
        M, pivots, g, step, P_post = np.empty((6, 6)), np.empty(6, np.int64), np.empty(6), np.empty(6), np.empty((6, 6))
        update.information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP)
        y = z - H @ x
        update.gradient_into(R_inverse_H, y, g)
        nis = update.block_quadratic(y, R_inverse) - update.plain_step_into(AP, g, step)
        update.posterior_covariance_into(P, information, M, pivots, P_post, np.empty((6, 6)))
        np.testing.assert_allclose(x + step, ref.state, atol=1e-10)
        np.testing.assert_allclose(x + update.correction(P, H, R, R_inverse, y), ref.state, atol=1e-10)
        np.testing.assert_allclose(P_post, ref.cov, atol=1e-10)
        np.testing.assert_allclose(nis, ref.nis, rtol=1e-9)
        cost = update.innovation_cost(P, H, R, R_inverse, y)
        np.testing.assert_allclose(cost, ekf.innovation_cost(P, H.reshape(-1, 6), R, y.reshape(-1)), rtol=1e-9)


def test_leave_one_out_costs_and_margins_match_numpy(rng):
    n, m = 4, 7
    z, z_hat = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (m, 3))
    z_hat[:n] = z + rng.normal(0, 0.1, (n, 3))
    H = rng.normal(0, 0.3, (m, 3, 6))
    R = np.stack([_random_spd(rng, 3, 0.2) for _ in range(n)])
    chosen = np.array([0, 1, -1, 3])
    information = _random_spd(rng, 6, 1.0)
    ref = association.leave_one_out_costs(z, R, z_hat, H, chosen, information=information, gate=30.0)
    got = recheck.leave_one_out_costs(z, R, np.linalg.inv(R), np.linalg.slogdet(R)[1], z_hat, H, chosen, information, 30.0)
    np.testing.assert_allclose(got, ref, rtol=1e-9)
    assert np.isfinite(got).sum() > n
    null = rng.uniform(5, 15, n)
    for a, b in zip(recheck.assignment_margins(got, null, chosen), association.assignment_margins(ref, null, chosen)):
        np.testing.assert_allclose(a, b, rtol=1e-9)
    rival = recheck.rival_margins(got, chosen)
    np.testing.assert_allclose(rival, association.rival_margins(ref, chosen), rtol=1e-9)
    assert np.isfinite(rival).any() and rival[2] == np.inf     # a finite rival is compared; unassigned: inf


def test_restored_pairs_matches_numpy(rng):
    for d in (1, 2, 3, 4, 5):
        H, R, R_inverse, y = _pairs(rng, d)
        y *= rng.uniform(0.2, 3.0, (d, 1))
        P = _random_spd(rng, 6, 0.05)
        null = rng.uniform(6, 14, d)
        np.testing.assert_array_equal(recheck.restored_pairs(y, H, P, R, R_inverse, null), association.restored_pairs(y, H, P, R, null))


def test_seed_ranking_matches_numpy(rng):
    N, m = 40, 6
    H, R, _, y = _pairs(rng, N)
    y *= 0.5
    pair_obs = rng.integers(0, m, N)
    pair_landmark = rng.integers(0, 15, N)
    P = _random_spd(rng, 6, 0.1)
    null = rng.uniform(8, 12, m)
    chosen = np.arange(0, N, 3)
    ref = association.seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null, chosen, gate=11.34)
    got = seeds.seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null, chosen, np.full(pair_obs.size, 11.34))
    np.testing.assert_allclose(got, ref, rtol=1e-9)


@pytest.mark.parametrize("size", [200, 1500], ids=["scanned", "k-d tree"])
def test_shift_agreement_matches_numpy(rng, size):
    # the slip search's Hough vote: a crowd of right pairs among scattered wrong ones
    shifts = np.vstack([0.4 + rng.normal(scale=0.05, size=(size // 10, 3)), rng.uniform(-3.0, 3.0, size=(size - size // 10, 3))])
    got = seeds.shift_agreement(shifts, 0.15)
    np.testing.assert_array_equal(got, association.shift_agreement(shifts, 0.15))
    assert got.max() >= size // 20 and got.min() >= 1


@pytest.mark.parametrize("max_distance", [np.inf, 4.2], ids=["depth", "distance"])
@pytest.mark.parametrize("margin", [0.0, 0.7])
@pytest.mark.parametrize("dense", [True, False], ids=["table-by-key", "binary-search"])
def test_view_query_matches_the_kd_tree(rng, margin, dense, max_distance):
    landmarks = rng.uniform(-10, 10, (3000, 3))
    scene = _scene_with_map(landmarks, max_depth=4.0, max_angle=np.radians(55.0), max_distance=max_distance)
    if not dense:
        scene = scene._replace(grid_dense_start=np.zeros(0, np.int64))
    index = association.PointIndex(landmarks)
    for _ in range(20):
        T_wc = geometry.pose_from_euler(_random_state(rng))
        got = view.visible(scene, T_wc[:3, :3].copy(), T_wc[:3, 3].copy(), np.radians(55.0), margin)
        ref = association.candidate_indices(index, landmarks, T_wc, min_depth=0.0, max_depth=4.0, max_angle_rad=np.radians(55.0),
                                            margin=margin, max_distance=max_distance)
        np.testing.assert_array_equal(got, ref)
        distance = np.linalg.norm(landmarks[got] - T_wc[:3, 3], axis=1)
        assert np.all(distance <= max_distance + margin)
        if np.isinf(max_distance):  # at the cone's edge a depth of 4 m lies up to 4 / cos(55 deg) = 7 m away
            assert distance.max(initial=0.0) > 4.2 + margin or got.size < 5


def test_candidates_within_a_distance_leave_out_what_only_the_depth_held():
    """A landmark at depth 1.9 m, 50 deg off the axis (2.96 m away), is a candidate within a depth
    of 2.2 m, not within a distance of 2.2 m; one on the axis at 2.1 m is both."""
    angle = np.radians(50.0)
    landmarks = np.array([[1.9 * np.tan(angle), 0.0, 1.9], [0.0, 0.0, 2.1]])
    index, T = association.PointIndex(landmarks), np.eye(4)
    depth = association.candidate_indices(index, landmarks, T, min_depth=0.0, max_depth=2.2, max_angle_rad=np.radians(55.0))
    ball = association.candidate_indices(index, landmarks, T, min_depth=0.0, max_depth=2.2, max_angle_rad=np.radians(55.0),
                                         max_distance=2.2)
    np.testing.assert_array_equal(depth, [0, 1])
    np.testing.assert_array_equal(ball, [1])
    scene = _scene_with_map(landmarks, max_depth=2.2, max_angle=np.radians(55.0), max_distance=2.2)
    np.testing.assert_array_equal(view.visible(scene, np.eye(3), np.zeros(3), np.radians(55.0), 0.0), [1])


def _scene_with_map(landmarks, *, max_depth, max_angle, max_distance=np.inf):
    from camloc.kernels.types import SceneArrays

    grid = view.build_grid(landmarks, 1.5)
    empty = np.zeros((0, 3))
    fields = dict.fromkeys(SceneArrays._fields, empty)
    fields.update(zip(("grid_origin", "grid_cell", "grid_dims", "grid_keys", "grid_start", "grid_items", "grid_xyz",
                       "grid_dense_start"), grid))
    fields["landmark_xyz"] = landmarks
    fields["view_limits"] = np.array([0.0, max_depth, max_angle, 0.0, 0.0, 0.0, max_distance])
    return SceneArrays(**fields)


@pytest.mark.parametrize("name", ["grid-small", "smooth3d-clutter", "pixel-2cam"])
@pytest.mark.parametrize("association_method", ["beam", "oracle"])
def test_compiled_localizer_equals_the_numpy_one(name, association_method):
    """The same pairs and the same states to rounding on the bundled worlds (a clutter world whose
    slips exercise the seeded search, two pixel cameras)."""
    import camloc
    dataset = camloc.load(DATA / f"{name}.g2o")
    config = camloc.LocalizerConfig(association=association_method)
    compiled = camloc.localize(dataset, config, engine="compiled")
    reference = camloc.localize(dataset, config, parallel=False, engine="numpy")
    assert (compiled.summary["timing"]["engine"], reference.summary["timing"]["engine"]) == ("compiled", "numpy")
    np.testing.assert_array_equal(compiled.associations.landmark, reference.associations.landmark)
    np.testing.assert_allclose(compiled.filter_state, reference.filter_state, atol=1e-8)
    np.testing.assert_allclose(compiled.nis, reference.nis, rtol=1e-6)
    assert compiled.summary["slip_poses"] == reference.summary["slip_poses"]


@pytest.mark.parametrize("kind", [
    dict(poses=40, observation_sigma_scale=0.0, intrinsics="pixel"),                  # information 1e12
    dict(poses=80, trajectory="aerial", cameras=2, intrinsics="pixel"),
    dict(poses=120, trajectory="smooth3d", landmarks=1500, region=11, clutter_fraction=0.35),
    dict(poses=120, trajectory="smooth3d", cameras=2, measurement="pixel", clutter_fraction=0.1),  # with a slip
    dict(poses=20, trajectory="grid", measurement="pixel", dense=True),
    # the same dense pixel world 2.5 times as long, in the slow tests: the numpy beam over it took
    # 33 s of CPU, the fast suite's costliest test; the 20 poses above check the same equality on
    # the same kind of world in 14 s (docs/performance.md, 2026-12-07, twenty-fifth session)
    pytest.param(dict(poses=50, trajectory="grid", measurement="pixel", dense=True), marks=pytest.mark.slow),
], ids=["noise-free", "aerial-2cam", "dense-clutter", "pixel-2cam-clutter", "pixel-dense", "pixel-dense-50"])
def test_compiled_beam_equals_the_numpy_one_on_simulated_worlds(kind):
    import dataclasses

    import camloc
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(**kind), seed=3)
    if kind.get("clutter_fraction"):  # an odometry slip on one edge: the seeded search must run
        jumped = dataset.odom_translation.copy()
        jumped[60] += np.array([0.6, -0.5, 0.0])
        dataset = dataclasses.replace(dataset, odom_translation=jumped)
    compiled = camloc.localize(dataset, engine="compiled")
    reference = camloc.localize(dataset, parallel=False, engine="numpy")
    np.testing.assert_array_equal(compiled.associations.landmark, reference.associations.landmark)
    np.testing.assert_allclose(compiled.filter_state, reference.filter_state, atol=1e-7)
    assert compiled.summary["slip_poses"] == reference.summary["slip_poses"]



def test_the_filter_thread_gives_the_result_of_one_pass_after_the_other():
    """With ``parallel``, the compiled beam hands each stretch of poses it has settled (narrowed to
    one hypothesis) to the filter's thread: the same states, pairs, NIS and slips, bit for bit, on
    a world whose slip (a jump put on one edge) and clutter keep several hypotheses alive, and a
    progress bar that only grows and ends at the last pose."""
    import dataclasses

    import camloc
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=300, trajectory="smooth3d", landmarks=1500, region=11, clutter_fraction=0.1),
                       seed=5)
    jumped = dataset.odom_translation.copy()
    jumped[150] += np.array([0.6, -0.5, 0.0])
    dataset = dataclasses.replace(dataset, odom_translation=jumped)
    runs, reports = {}, {}
    for parallel in (False, True):
        reports[parallel] = []
        runs[parallel] = camloc.localize(dataset, parallel=parallel, engine="compiled",
                                         on_progress=lambda done, total, seen=reports[parallel]: seen.append((done, total)))
    sequential, threaded = runs[False], runs[True]
    assert threaded.summary["timing"]["replay_thread"] and not sequential.summary["timing"]["replay_thread"]
    assert threaded.summary["slip_poses"] == sequential.summary["slip_poses"] and sequential.summary["slip_poses"]
    np.testing.assert_array_equal(threaded.filter_state, sequential.filter_state)
    np.testing.assert_array_equal(threaded.filter_cov, sequential.filter_cov)
    np.testing.assert_array_equal(threaded.associations.landmark, sequential.associations.landmark)
    np.testing.assert_array_equal(threaded.nis, sequential.nis)
    for seen in reports.values():
        done = [d for d, _ in seen]
        assert done == sorted(done) and done[-1] == dataset.num_poses and {t for _, t in seen} == {dataset.num_poses}


def test_a_seeded_explanation_never_takes_its_seeds_landmark_again():
    """A slip's search grows explanations from a seed pair. A second detection of the seed's
    landmark (a clutter detection beside it) is clear to the pose's explanation, as the landmark
    is its only gated option; it must be left unassigned, not paired with the landmark the seed
    took (one landmark, one observation a pose). Both engines."""
    import dataclasses

    from camloc.beam import BeamSearch
    from camloc.kernels import beam as kb
    from camloc.localizer import LocalizerConfig, _Localizer
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=20), seed=3)
    k = 10
    first = int(np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0))[0])
    lm = int(np.flatnonzero(dataset.landmark_ids == dataset.obs_true_landmark[first])[0])
    twin = dict(obs_pose_index=k, obs_camera=dataset.obs_camera[first], obs_z=dataset.obs_z[first] + [1e-3, 0.0, 0.0],
                obs_info=dataset.obs_info[first], obs_cov=dataset.obs_cov[first], obs_true_landmark=10_000,
                obs_kind=dataset.obs_kind[first])
    dataset = dataclasses.replace(dataset, **{name: np.append(getattr(dataset, name), [value], axis=0) for name, value in twin.items()})
    second = dataset.num_observations - 1
    config = LocalizerConfig()
    x = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
    P = np.diag(np.r_[np.full(3, 0.01**2), np.full(3, np.radians(0.5) ** 2)])

    scene = build_scene(dataset, config)
    settings = build_settings(config)
    seeded = kb.new_generation(1, 2, 6)
    seeded[0][0], seeded[1][0], seeded[2][0] = x, P, 0.0
    seeded[7][0, 0] = (first, lm)
    seeded[6][0] = 1
    children, count = kb.explain_all(scene, settings, seeded, 1, np.array([second]))
    taken = [tuple(children[7][c, q]) for c in range(count) for q in range(children[6][c])]
    assert count >= 1 and (second, lm) not in taken and children[4][np.argmin(children[2][:count])] == 1

    from camloc.beam_types import Hypothesis

    localizer = _Localizer(dataset, config)
    explained = BeamSearch(localizer, localizer.beam_settings()).expansion.explain(Hypothesis(x, P, 0.0, 0, ((first, lm),)), np.array([second]))
    assert explained and all((second, lm) not in h.pairs for h in explained)
    assert min(explained, key=lambda h: h.cost).unassigned == 1


def test_poses_settle_only_through_the_last_pose_the_beam_kept_one_hypothesis_at():
    """Poses 0-4 kept 1, 2, 1, 3, 2 hypotheses: the beam's best at pose 3 or 4 may still lose to
    another, so only poses 0-2 are settled; their pairs are read along the parent links (pose 2's
    one hypothesis grew from pose 1's second, not its best), and pose 1's association spread is
    the best's weight times its squared distance from the second."""
    from camloc.loop import _backtrack, settled_through

    kept = np.array([1, 2, 1, 3, 2])
    assert settled_through(kept, 0, 5) == 2 and settled_through(kept, 3, 5) == 2 and settled_through(kept, 0, 2) == 0
    parent = np.array([[0, 0], [0, 0], [1, 0], [0, 0], [0, 0]])
    slipped = np.array([[False, False], [False, True], [False, False], [False, False], [False, False]])
    # pose 0: pairs (0, 10); pose 1: best (1, 11), second (1, 12); pose 2: (2, 13)
    pairs = np.array([[0, 10], [1, 11], [1, 12], [2, 13]])
    pair_start = np.array([[0, 1, 1], [1, 2, 3], [3, 4, 4], [4, 4, 4], [4, 4, 4]])
    # pose 1's two hypotheses: the best 0.1 m along x from the second, and 2 cost units cheaper
    state, cost = np.zeros((5, 2, 6)), np.zeros((5, 2))
    state[1, 0, 0], cost[1] = 0.1, [0.0, 2.0]
    chosen, slip, spread = _backtrack((kept, parent, slipped, pair_start, pairs, None, state, cost), 0, 2)
    assert [c.tolist() for c in chosen] == [[[0, 10]], [[1, 12]], [[2, 13]]] and slip.tolist() == [False, True, False]
    # the chosen second's covariance widens by the best's weight, 1 / (1 + e^-1), times 0.1 m squared
    expected = np.zeros((3, 6, 6))
    expected[1, 0, 0] = 0.01 / (1.0 + np.exp(-1.0))
    np.testing.assert_allclose(spread, expected, atol=1e-15)


def test_a_failure_in_the_filter_thread_is_raised_once_the_beam_is_done_and_stops_the_filter():
    """A stretch that fails in the filter's thread is raised by ``finish`` (after the beam, as when
    the two run one after the other), and the stretches after it are never filtered."""
    from camloc.loop import PoseFailure, _Progress, _Replay

    class Stretches:
        filtered = 0

        def __init__(self):
            self.ran = []

        def set_pairs(self, first, pairs, slipped, spread=None):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)

        def poses(self, first, last, pair_obs=None, pair_landmark=None):
            if first == 10:
                raise PoseFailure(13, "a covariance is no longer positive definite")
            self.ran.append((first, last))
            self.filtered = last

    stretches = Stretches()
    with _Replay(stretches, concurrent=True) as replay:
        for last in (10, 20, 30):
            replay.settle(last, [], np.zeros(0, np.bool_), np.zeros((0, 6, 6)))
        with pytest.raises(PoseFailure) as failure:
            replay.finish(_Progress(30, None, halves=2))
    assert failure.value.k == 13 and stretches.ran == [(0, 10)]


def test_the_engine_is_chosen_by_size_and_method_and_can_be_forced():
    import camloc
    from camloc.errors import ConfigError
    from camloc.localizer import COMPILED_MIN_POSES

    small = camloc.load(DATA / "grid-small.g2o")
    assert small.num_poses < COMPILED_MIN_POSES
    assert camloc.localize(small).summary["timing"]["engine"] == "numpy"       # starting numba costs more
    calls = []
    was_warm = camloc.kernels.cache_is_warm()
    forced = camloc.localize(small, engine="compiled", on_compile=lambda: calls.append(1))
    assert forced.summary["timing"]["engine"] == "compiled"
    assert calls == ([] if was_warm else [1])                  # told once, only when it compiles
    assert camloc.kernels.cache_is_warm()
    with pytest.raises(ConfigError, match="runs in numpy"):
        camloc.localize(small, camloc.LocalizerConfig(filter="se3"), engine="compiled")
    with pytest.raises(ConfigError, match="engine must be one of"):
        camloc.localize(small, engine="gpu")


def test_numba_starts_in_a_thread_of_its_own_while_a_fresh_process_builds_its_first_scene():
    # about 0.5 s of a fresh process's start (numba's registries, a first kernel) overlaps the
    # observations' numpy work; once the kernel is loaded, no thread is started, and the scene is
    # the same either way
    import subprocess
    import sys

    code = """
import threading, numpy as np
import camloc
from camloc.scene import build_scene
started = []
start = threading.Thread.start
threading.Thread.start = lambda self: (started.append(self.name), start(self))[1]
dataset, config = camloc.load(camloc.bundled_dataset("grid-small")), camloc.LocalizerConfig()
first = build_scene(dataset, config)
second = build_scene(dataset, config)
print(started, all(np.array_equal(a, b) for a, b in zip(first, second)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['camloc-numba-start'] True"


def test_the_numba_start_thread_leaves_a_kernel_s_error_to_the_scene_s_own_call():
    from camloc.scene import _load_first_kernel

    def failing(*args):
        raise RuntimeError("a kernel that does not load")

    assert _load_first_kernel(failing) is None


def test_a_cold_cache_is_told_apart_from_a_warm_one(tmp_path):
    # the first run after an install says that it compiles: cache_is_warm must see an empty cache
    # (it read a name numba 0.68 no longer has, fell back to "warm", and the notice never showed)
    import subprocess
    import sys

    from camloc.kernels import cache_is_warm

    code = "from camloc.kernels import cache_is_warm; print(cache_is_warm())"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.strip() == "False"
    camloc.localize(camloc.load(DATA / "grid-small.g2o"), engine="compiled")  # compiles, or loads the cache
    assert cache_is_warm()


def test_a_changed_kernel_source_clears_the_cache_of_every_kernel(tmp_path):
    # numba checks a cached function against its own file only: a callee changed in another file
    # would leave its callers' cache stale, so any change to the folder clears the folder's cache,
    # as does a change to a module of constants the kernels read (``KERNEL_INPUTS``)
    from camloc.kernels.stale_cache import SOURCE_STAMP, clear_stale_cache

    source, cache = tmp_path / "kernels", tmp_path / "cache"
    source.mkdir()
    cache.mkdir()
    (source / "beam.py").write_text("x = 1\n")
    (source / "sym3.py").write_text("y = 2\n")
    compiled = [cache / "beam.run_poses-565.py311.nbi", cache / "beam.run_poses-565.py311.1.nbc", cache / "sym3.spread-9.py311.nbi"]
    foreign = cache / "other.f-1.py311.nbi"  # another package's, in a shared NUMBA_CACHE_DIR
    for path in [*compiled, foreign]:
        path.write_bytes(b"")
    assert clear_stale_cache(cache, source)                  # no stamp: compiled from unknown sources
    assert not any(path.exists() for path in compiled) and foreign.exists()
    assert (cache / SOURCE_STAMP).exists()
    compiled[0].write_bytes(b"")
    assert not clear_stale_cache(cache, source) and compiled[0].exists()   # same sources: kept
    (source / "sym3.py").write_text("y = 3\n")               # a callee's file changes
    assert clear_stale_cache(cache, source) and not compiled[0].exists()
    compiled[0].write_bytes(b"")
    (tmp_path / "constants.py").write_text("Z = 4\n")        # a constant the kernels read, beside them
    assert clear_stale_cache(cache, source) and not compiled[0].exists()


def test_the_stale_cache_check_looks_where_numba_caches_the_kernels():
    from camloc.kernels import _jit, beam

    assert _jit.CACHE_FOLDER == Path(beam.run_poses._cache._cache_path)


def test_the_numpy_engine_never_imports_numba(tmp_path):
    # a small file runs in numpy, where starting numba (0.2 s, 50 MB) would be all cost: the
    # kernels' cache check once imported it through camloc.kernels.types
    import subprocess
    import sys

    code = ("import sys, camloc; r = camloc.localize(camloc.load(camloc.bundled_dataset())); "
            "print(r.summary['timing']['engine'], 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    assert out.stdout.split() == ["numpy", "False"]


def test_a_clutter_detection_beside_a_landmark_s_own_does_not_take_it_first():
    """Two detections at one pose gate one landmark: a clutter detection two standard deviations
    off its prediction, listed first, and the landmark's own, exact. Alone, the clutter one's
    pair is far cheaper than leaving it unassigned, so branch_delta would not keep that option,
    and taken first it would leave the landmark's own detection unassigned; the explanation that
    leaves it gives the landmark to its own detection and is cheaper. Both engines."""
    import dataclasses

    from camloc.beam import BeamSearch
    from camloc.beam_types import Hypothesis
    from camloc.kernels import beam as kb
    from camloc.localizer import LocalizerConfig, _Localizer
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=20), seed=3)
    k = 10
    own = int(np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0))[0])
    lm = int(np.flatnonzero(dataset.landmark_ids == dataset.obs_true_landmark[own])[0])
    x = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
    P = np.diag(np.r_[np.full(3, 0.01**2), np.full(3, np.radians(0.5) ** 2)])
    exact = _Localizer(dataset, LocalizerConfig()).observe(x, int(dataset.obs_camera[own]), np.array([lm]))[0][0]
    sigma_u = float(np.sqrt(dataset.obs_cov[own][0, 0]))
    z = dataset.obs_z.copy()
    z[own] = exact
    twin = dict(obs_pose_index=k, obs_camera=dataset.obs_camera[own], obs_z=exact + [2.0 * sigma_u, 0.0, 0.0],
                obs_info=dataset.obs_info[own], obs_cov=dataset.obs_cov[own], obs_true_landmark=10_000, obs_kind=dataset.obs_kind[own])
    dataset = dataclasses.replace(dataset, obs_z=z)
    dataset = dataclasses.replace(dataset, **{name: np.insert(getattr(dataset, name), own, [value], axis=0) for name, value in twin.items()})
    clutter, own = own, own + 1  # the clutter detection comes first
    config = LocalizerConfig()
    localizer = _Localizer(dataset, config)
    search = BeamSearch(localizer, localizer.beam_settings())
    alone = search.gating.options(Hypothesis(x, P, 0.0, 0), np.array([clutter]))[0]
    assert alone.costs.min() + config.beam.branch_delta < localizer.null_cost[clutter]  # alone, its pair is clear

    scene, settings = build_scene(dataset, config), build_settings(config)
    start = kb.new_generation(1, 2, 6)
    start[0][0], start[1][0], start[2][0] = x, P, 0.0
    children, count = kb.explain_all(scene, settings, start, 1, np.array([clutter, own]))
    best = int(np.argmin(children[2][:count]))
    assert [tuple(pair) for pair in children[7][best, :children[6][best]]] == [(own, lm)] and children[4][best] == 1

    explained = search.expansion.explain(Hypothesis(x, P, 0.0, 0), np.array([clutter, own]))
    best = min(explained, key=lambda h: h.cost)
    assert best.pairs == ((own, lm),) and best.unassigned == 1


def test_the_update_reads_the_scene_through_its_pair_model():
    """``updated`` is passed what it reads of the scene (``update.pair_model``: 16 of its 31
    arrays, the same arrays, not copies) and gives what it gives with the whole scene, bit for bit,
    with and without the restart from the pairs' points."""
    from camloc.kernels import update
    from camloc.kernels.recheck import predict_pairs
    from camloc.localizer import LocalizerConfig
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=20, cameras=2, intrinsics="pixel"), seed=2)
    config = LocalizerConfig()
    scene, settings = build_scene(dataset, config), build_settings(config)
    model = update.pair_model(scene)
    assert all(getattr(model, name) is getattr(scene, name) for name in model._fields)
    k = 10
    obs = np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0))[:3].astype(np.int64)
    landmarks = scene.true_index[obs]
    x = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
    for offset, spread in ((0.01, 0.02), (0.5, 1.0)):   # a prior near the truth, and one far enough to restart
        prior, P = x + offset, np.eye(6) * spread**2
        z_hat, H = _jit.from_python(predict_pairs)(scene, prior, obs, landmarks)
        args = (settings.iterations, prior, P, obs, landmarks, z_hat, H, scene.R_assoc, scene.R_assoc_inverse, np.empty(0), True, 0.0)
        whole, through = update.updated(scene, *args), update.updated(model, *args)
        restarted = whole[2] > scene.nis_bound[scene.obs_dof[obs].sum()]
        assert restarted == (offset > 0.1)
        for a, b in zip(whole, through):
            assert np.array_equal(a, b)


def test_an_update_without_its_map_cost_keeps_the_same_posterior():
    """The beam's scratch updates read only the state, so ``updated`` leaves their MAP cost out
    (NaN): the posterior, NIS and innovation are bit for bit those of an update that computes it,
    and where the update restarts (an innovation beyond its bound, or a start given) the cost it
    compares is still computed, so the same posterior is kept, with its cost. Where that cost is
    beyond its chi^2 bound, the estimate's update (with its MAP cost) is sought again by damped
    Gauss-Newton (``damped_start``), which the scratch updates skip: its cost is then no higher."""
    from camloc.kernels.recheck import predict_pairs
    from camloc.localizer import LocalizerConfig
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=20, cameras=2, intrinsics="pixel"), seed=2)
    config = LocalizerConfig()
    scene, settings = build_scene(dataset, config), build_settings(config)
    model = update.pair_model(scene)
    k = 10
    obs = np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0))[:3].astype(np.int64)
    landmarks = scene.true_index[obs]
    x = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
    for offset, spread, start in ((0.01, 0.02, False), (0.5, 1.0, False), (0.01, 0.02, True)):
        prior, P = x + offset, np.eye(6) * spread**2
        z_hat, H = _jit.from_python(predict_pairs)(scene, prior, obs, landmarks)
        given = x + 0.005 if start else np.empty(0)
        args = (settings.iterations, prior, P, obs, landmarks, z_hat, H, scene.R_assoc, scene.R_assoc_inverse, given)
        costed, costless = update.updated(model, *args, True, 0.0), update.updated(model, *args, False, 0.0)
        bound = scene.nis_bound[scene.obs_dof[obs].sum()]
        restarted = start or costed[2] > bound
        assert restarted == (offset > 0.1 or start)
        assert np.isfinite(costed[3])
        if restarted and costless[3] > bound:  # the estimate's update also searched by damped Gauss-Newton
            assert costed[3] <= costless[3] and np.array_equal(costed[2], costless[2]) and np.array_equal(costed[4], costless[4])
            continue
        for a, b in zip(costed[:3] + costed[4:], costless[:3] + costless[4:]):
            assert np.array_equal(a, b)
        assert costless[3] == costed[3] if restarted else np.isnan(costless[3])


def test_a_landmark_behind_its_camera_at_the_hypothesis_state_is_no_option_in_either_engine():
    """The beam's candidates are the view widened by three standard deviations of the position,
    so a landmark the state puts behind the camera is one; there its projection's Jacobian grows
    as 1/depth^2 and so does its pair's S: on main the true landmark of a disparity observation
    gated (cost 27) from a state 0.15 m past it. Behind the camera it stays in the observation's
    pool, no option (infinite cost and pool cost); 0.15 m short of it, in front, it is one, at the
    same cost in both engines."""
    from camloc.beam import BeamSearch
    from camloc.beam_types import Hypothesis
    from camloc.kernels import beam as kb
    from camloc.localizer import LocalizerConfig, _Localizer
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=20, measurement="disparity"), seed=3)
    k = 10
    obs = np.flatnonzero(dataset.obs_pose_index == k)
    o = int(obs[dataset.obs_true_landmark[obs] >= 0][0])
    lm = int(np.flatnonzero(dataset.landmark_ids == dataset.obs_true_landmark[o])[0])
    config = LocalizerConfig()
    localizer = _Localizer(dataset, config)
    scene, settings = build_scene(dataset, config), build_settings(config)
    gating = BeamSearch(localizer, localizer.beam_settings()).gating
    R_wr = geometry.quat_to_matrix(dataset.truth_quat_xyzw[k])
    T_wr = np.eye(4)
    T_wr[:3, :3], T_wr[:3, 3] = R_wr, dataset.truth_xyz[k]
    T_wc = T_wr @ localizer.scene.cameras[int(localizer.obs_sensor[o])].T_robot_camera
    depth = (dataset.landmark_xyz[lm] - T_wc[:3, 3]) @ T_wc[:3, 2]
    P = np.diag(np.r_[np.full(3, 0.2**2), np.full(3, np.radians(2.0) ** 2)])
    margin, max_angle = view.widened_view(P, scene.view_limits[2])
    for shift, in_front in ((depth + 0.15, False), (depth - 0.15, True)):
        x = np.r_[dataset.truth_xyz[k] + shift * T_wc[:3, 2], geometry.matrix_to_euler(R_wr)]
        numpy_options = gating.options(Hypothesis(x, P, 0.0, 0), np.array([o]), widened_view=True)[0]
        _, landmarks, cost, *_, pool_cost = kb.options_for(scene, settings, x, P, np.array([o]), margin, max_angle)
        assert np.array_equal(np.sort(landmarks), np.sort(numpy_options.landmarks)) and lm in landmarks
        mine, numpy_mine = landmarks == lm, numpy_options.landmarks == lm
        assert np.isfinite(cost[mine][0]) == np.isfinite(pool_cost[mine][0]) == in_front
        np.testing.assert_allclose(cost[mine], numpy_options.costs[numpy_mine], rtol=1e-9)
        np.testing.assert_allclose(pool_cost[mine], numpy_options.pool_costs[numpy_mine], rtol=1e-9)


def test_in_front_matches_the_numpy_scene(rng):
    """The one test of whether a pair's landmark lies in front of its camera (the oracle's, the
    beam's and the re-check's: ``kernels.camera.in_front_of``) and its numpy twin
    (``AssociationScene.in_front_of``) agree on random states of a two-camera rig, landmarks on
    both sides of the cameras."""
    from camloc.kernels import filtering
    from camloc.localizer import LocalizerConfig, _Localizer
    from camloc.scene import build_scene
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=10, cameras=2, measurement="pixel"), seed=5)
    config = LocalizerConfig()
    scene, localizer = build_scene(dataset, config), _Localizer(dataset, config)
    compiled = _jit.FromPython(filtering)
    seen = []
    for _ in range(20):
        x = np.r_[rng.uniform(dataset.landmark_xyz.min(axis=0), dataset.landmark_xyz.max(axis=0)), rng.uniform(-np.pi, np.pi),
                  rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)]
        pair_obs = rng.integers(0, dataset.num_observations, 30)
        pair_landmarks = rng.integers(0, dataset.landmark_xyz.shape[0], 30)
        front = localizer.scene.in_front(x, pair_obs, pair_landmarks)
        assert np.array_equal(compiled.in_front(scene, x, pair_obs, pair_landmarks), front)
        seen.extend(front.tolist())
    assert 0.2 < np.mean(seen) < 0.8
