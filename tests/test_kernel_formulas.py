"""Each formula kernel on its own, against a plain numpy statement of the same formula (written here
with np.linalg, or camloc's numpy twin), on random well-conditioned inputs; each kernel that returns
a Jacobian against central finite differences. By kernel file, in the order the kernels call each
other (small, sym3, rotation, camera, motion, update, recheck, view, filtering, seeds, beam).

``tests/test_kernels.py`` holds the kernels already tested directly (rotations against
camloc.geometry, motion and observe with their Jacobians, sym3.mahalanobis, the update steps
against camloc.ekf, leave-one-out costs, seed ranking, the view query) and the whole-run parity
tests (compiled localizer == numpy localizer). Not tested here, left to those parity tests: the
loops (beam.run_poses, beam.explain_all, filtering.filter_poses, filtering.recheck, filtering.rechecked,
filtering.oracle_pairs, update.updated; update.iterated_update is tested here, against
camloc.ekf.update) and the beam's bookkeeping and decisions (new_generation, copy_hypothesis,
carry, gather, commit, settled, prune, prune_indices_into, prune_partials, options_for, condition,
condition_into, options_of, put_state, taken_by, is_taken, least_cost, clear_choices, viable_limit,
branch, settle, same_state, after_clear, predicted; filtering.record_state), whose
outcome is which hypotheses survive rather than a formula; also view.cone_members and view.cell_near_cone, steps of the view query, which
test_kernels.py compares landmark for landmark with a k-d tree.

Inputs are C-contiguous float64 arrays and int64 indices, as the production code passes them.
numba compiles a kernel once per signature, so each is called with one (small.solve with two: a
matrix and a vector right-hand side, as production calls it): about 35 s on a cold cache.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from camloc import association, ekf, filters, geometry, measurement, models
from camloc.kernels import _jit, beam, camera, filtering, motion, recheck, rotation, seeds, small, sym3, update, view

# the steps as Python calls them: most are compiled without numba's Python wrapper (``_jit.jit``)
beam, camera, filtering, motion, recheck, rotation, seeds, small, sym3, update, view = (
    _jit.FromPython(module) for module in (beam, camera, filtering, motion, recheck, rotation, seeds, small, sym3, update, view))
from camloc.kernels.types import SceneArrays
from camloc.sym3 import UPPER

# Tight enough that a wrong sign, index or transpose fails by orders of magnitude; loose enough for
# the rounding of sums in another order (loops here, BLAS / LAPACK in numpy).
RTOL = 1e-10

# Central differences of a smooth function: truncation ~ step^2, rounding ~ eps / step.
STEP = 1e-6

# A camera whose axes are not the robot's (x right, y down, z forward) and not centred on it.
T_ROBOT_CAMERA = geometry.pose_from_euler(np.array([0.1, -0.05, 0.3, -np.pi / 2, 0.1, -np.pi / 2]))
INTRINSICS = np.array([520.0, 510.0, 320.0, 240.0, measurement.DEPTH])  # fx fy cx cy, and the kind (camloc.measurement)


def _random_state(rng):
    return np.r_[rng.normal(0, 2, 3), rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)]


def _random_spd(rng, n, scale=1.0):
    A = rng.normal(0, scale, (n, n))
    return A @ A.T + scale**2 * np.eye(n)


def _pixel_noise(rng, p):
    """p covariances (p, 3, 3) of (u, v, depth) as files give them: pixels beside metres."""
    D = np.diag([2.0, 2.0, 0.05])
    return np.stack([D @ _random_spd(rng, 3, 0.6) @ D for _ in range(p)])


def _inverse(blocks):
    inverse = np.linalg.inv(blocks)
    return 0.5 * (inverse + np.swapaxes(inverse, -1, -2))   # exactly symmetric, as ekf.block_inverse


def _pairs(rng, p):
    """p pairs: Jacobians H (p, 3, 6), noise R and its inverse (p, 3, 3), innovations y (p, 3)."""
    H = rng.normal(0, 1, (p, 3, 6))
    R = np.stack([_random_spd(rng, 3, 0.3) for _ in range(p)])
    return H, R, _inverse(R), rng.normal(0, 1, (p, 3))


def _upper(S):
    """The upper triangle (a, b, c, d, e, f) of a 3x3 S, the order sym3's kernels take and return."""
    return tuple(S[i, j] for i, j in UPPER)


def _symmetric(a, b, c, d, e, f):
    return np.array([[a, b, c], [b, d, e], [c, e, f]])


def _central_difference(function, x0, step=STEP):
    """d function / d x at x0 by central differences, the derivative along the last axis."""
    columns = [(function(x0 + step * e) - function(x0 - step * e)) / (2 * step) for e in np.eye(x0.size)]
    return np.stack(columns, axis=-1)


def _scene(**arrays):
    """SceneArrays with the given fields; the kernels tested here read no other."""
    fields = dict.fromkeys(SceneArrays._fields, np.zeros((0, 3)))
    fields.update(arrays)
    return SceneArrays(**fields)


# ---------------------------------------------------------------------------------------------
# small: products and solves of small matrices

def test_loop_products_are_numpy_products(rng):
    A, B = rng.normal(size=(3, 6)), rng.normal(size=(6, 4))
    A[0, 1] = A[2, 5] = 0.0                      # the loops skip A's zero entries, which must change nothing
    np.testing.assert_allclose(small.mm(A, B), A @ B, rtol=RTOL, atol=1e-14)
    C = rng.normal(size=(3, 4))
    np.testing.assert_allclose(small.mtm(A, C), A.T @ C, rtol=RTOL, atol=1e-14)
    v = rng.normal(size=6)
    np.testing.assert_allclose(small.mv(A, v), A @ v, rtol=RTOL, atol=1e-14)


def test_solve_is_the_inverse_times_the_right_hand_side(rng):
    for _ in range(5):
        # a well-conditioned matrix whose rows are shuffled: its diagonal is small, so the
        # elimination must pivot
        A = (rng.normal(size=(6, 6)) + 6.0 * np.eye(6))[rng.permutation(6)]
        B, b = rng.normal(size=(6, 3)), rng.normal(size=6)
        np.testing.assert_allclose(small.solve(A, B), np.linalg.solve(A, B), rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(small.solve(A, b).ravel(), np.linalg.solve(A, b), rtol=RTOL, atol=1e-14)
    singular = rng.normal(size=(6, 6))
    singular[:, 2] = 0.0
    with pytest.raises(FloatingPointError, match="singular"):
        small.solve(singular, B)


def test_lu_factor_solves_as_small_solve_does_and_gives_the_log_determinant(rng):
    for _ in range(5):
        A = (rng.normal(size=(6, 6)) + 6.0 * np.eye(6))[rng.permutation(6)]    # must pivot
        B = rng.normal(size=(6, 3))
        M, pivots = A.copy(), np.empty(6, np.int64)
        small.lu_factor(M, pivots)
        X = B.copy()
        small.lu_solve(M, pivots, X)
        np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=RTOL, atol=1e-14)
        np.testing.assert_array_equal(X, small.solve(A, B))        # the same arithmetic, in two steps
        np.testing.assert_allclose(small.lu_log_det(M, pivots), np.linalg.slogdet(A), rtol=RTOL)
    singular = rng.normal(size=(6, 6))
    singular[:, 2] = 0.0
    with pytest.raises(FloatingPointError, match="singular"):
        small.lu_factor(singular, np.empty(6, np.int64))


def test_a_covariance_check_passes_a_covariance(rng):
    P = _random_spd(rng, 6, 0.1)
    small.check_covariance(P)
    P[2, 2] = 1e-14 * np.max(np.diagonal(P))    # the simulator's noise-free files reach this: not broken
    small.check_covariance(P)


@pytest.mark.parametrize("where, value", [((3, 3), -1e-6), ((0, 0), 0.0), ((4, 4), 1e-120), ((1, 2), np.nan), ((5, 0), np.inf)],
                         ids=["negative variance", "zero variance", "variance beyond double precision", "nan", "inf"])
def test_a_covariance_check_stops_a_broken_covariance(rng, where, value):
    # what it checks are the variances (and finiteness), not definiteness: an indefinite matrix
    # with positive variances passes, as its docstring says
    P = _random_spd(rng, 6, 0.1)
    P[where] = value
    with pytest.raises(FloatingPointError):
        small.check_covariance(P)


# ---------------------------------------------------------------------------------------------
# sym3: closed-form algebra of one symmetric 3x3 matrix

def test_mahalanobis_components_are_the_quadratic_form_and_log_determinant(rng):
    for _ in range(20):
        S, y = _random_spd(rng, 3), rng.normal(size=3)
        d2, log_det = sym3.mahalanobis_components(*_upper(S), *y)
        np.testing.assert_allclose(d2, y @ np.linalg.solve(S, y), rtol=RTOL)
        np.testing.assert_allclose(log_det, np.linalg.slogdet(S)[1], rtol=RTOL, atol=1e-14)
    # a matrix without a positive determinant fits nothing
    assert sym3.mahalanobis_components(*_upper(np.diag([1.0, -1.0, 1.0])), 1.0, 1.0, 1.0) == (np.inf, np.inf)


def test_quadratic_and_determinant_are_the_adjugate_form(rng):
    for _ in range(20):
        S, y = _random_spd(rng, 3), rng.normal(size=3)
        det = np.linalg.det(S)
        quadratic, got_det = sym3.quadratic_and_det(*_upper(S), *y)
        np.testing.assert_allclose(got_det, det, rtol=RTOL)
        np.testing.assert_allclose(quadratic, det * (y @ np.linalg.solve(S, y)), rtol=RTOL)   # adj(S) = det S S^-1
    # indefinite: the adjugate form still holds, with det < 0
    S = np.diag([2.0, -3.0, 5.0])
    np.testing.assert_allclose(sym3.quadratic_and_det(*_upper(S), 1.0, 2.0, 3.0), (-15 * 1 + 10 * 4 - 6 * 9, -30.0), rtol=RTOL)


@pytest.mark.parametrize("scale", [1.0, 1e150, 1e-150])
def test_inverse_components_are_the_inverse(rng, scale):
    # at 1e+-150 the determinant (a cube of the entries) leaves the float range: the kernel scales first
    for _ in range(10):
        S = _random_spd(rng, 3)
        got = _symmetric(*sym3.inverse_components(*_upper(scale * S)))
        np.testing.assert_allclose(got * scale, np.linalg.inv(S), rtol=RTOL, atol=1e-14 * np.abs(np.linalg.inv(S)).max())
    assert not np.all(np.isfinite(sym3.inverse_components(*_upper(np.zeros((3, 3))))))


def test_log_determinant_is_numpy_s(rng):
    for _ in range(10):
        S = _random_spd(rng, 3, 0.3)
        np.testing.assert_allclose(sym3.log_det(S), np.linalg.slogdet(S)[1], rtol=RTOL)
    assert sym3.log_det(-np.eye(3)) == np.inf


def test_spread_is_h_p_h_transpose(rng):
    H, P = rng.normal(size=(5, 3, 6)), _random_spd(rng, 6, 0.3)
    for i in range(5):
        np.testing.assert_allclose(sym3.spread(H, i, P), _upper(H[i] @ P @ H[i].T), rtol=RTOL, atol=1e-14)


def test_innovation_mahalanobis_is_that_of_s_equal_h_p_h_transpose_plus_r(rng):
    H, R, _, y = _pairs(rng, 4)
    P = _random_spd(rng, 6, 0.3)
    for i in range(4):
        o = (i + 1) % 4                          # a prediction and another observation's noise
        S = H[i] @ P @ H[i].T + R[o]
        d2, log_det = sym3.innovation_mahalanobis(H, i, P, R, o, *y[i])
        np.testing.assert_allclose(d2, y[i] @ np.linalg.solve(S, y[i]), rtol=RTOL)
        np.testing.assert_allclose(log_det, np.linalg.slogdet(S)[1], rtol=RTOL)


# ---------------------------------------------------------------------------------------------
# rotation: Euler angles, the rate matrix E, retraction and difference

def test_euler_rate_is_the_body_frame_derivative_of_the_rotation(rng):
    # R(rpy + d) = R(rpy) Exp(E d) to first order: the derivative of R' R(rpy + t e_k) at t = 0 is
    # hat(E e_k), and E^-1 undoes E
    for _ in range(10):
        rpy = _random_state(rng)[3:]
        R = rotation.euler_to_matrix(*rpy)
        E, E_inverse = rotation.euler_rate(rpy[0], rpy[1]), rotation.euler_rate_inverse(rpy[0], rpy[1])
        body = _central_difference(lambda a: R.T @ geometry.euler_to_matrix(a), rpy, step=1e-5)   # (3, 3, 3)
        np.testing.assert_allclose(body, np.moveaxis(geometry.hat(E.T), 0, -1), atol=1e-9)
        np.testing.assert_allclose(E, geometry.euler_rate_matrix(rpy), rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose(E_inverse, np.linalg.inv(E), rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(E_inverse @ E, np.eye(3), atol=1e-14)


def test_wrap_angle_keeps_the_angle_modulo_two_pi_in_minus_pi_to_pi(rng):
    for a in np.r_[rng.uniform(-20.0, 20.0, 50), -np.pi, np.pi, 0.0, 3 * np.pi]:
        wrapped = rotation.wrap_angle(a)
        assert -np.pi <= wrapped < np.pi
        turns = (a - wrapped) / (2 * np.pi)
        assert abs(turns - round(turns)) < 1e-12
        assert wrapped == geometry.wrap_angle(a)
    assert rotation.wrap_angle(np.pi) == -np.pi


def test_retract_adds_and_wraps_roll_and_yaw_and_difference_undoes_it(rng):
    for _ in range(20):
        x = _random_state(rng)
        delta = np.r_[rng.normal(0, 1, 3), rng.normal(0, 2, 3)]
        delta[4] = rng.uniform(-0.3, 0.3)            # pitch stays within (-pi/2, pi/2), where it is not wrapped
        moved = rotation.retract(x, delta)
        expected = x + delta
        expected[[3, 5]] = geometry.wrap_angle(expected[[3, 5]])
        np.testing.assert_allclose(moved, expected, rtol=RTOL, atol=1e-15)
        assert moved[4] == x[4] + delta[4]
        np.testing.assert_allclose(rotation.difference(moved, x), np.r_[delta[:3], geometry.wrap_angle(delta[3:])],
                                   rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(rotation.retract(x, rotation.difference(moved, x)), moved, rtol=RTOL, atol=1e-14)


# ---------------------------------------------------------------------------------------------
# camera: the camera model, the camera's pose, back-projection

def test_camera_pose_is_the_robot_pose_composed_with_the_mount(rng):
    for _ in range(5):
        x = _random_state(rng)
        R_wc, centre = camera.camera_pose(x, T_ROBOT_CAMERA[:3, :3].copy(), T_ROBOT_CAMERA[:3, 3].copy())
        T_wc = geometry.pose_from_euler(x) @ T_ROBOT_CAMERA
        np.testing.assert_allclose(R_wc, T_wc[:3, :3], rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose(centre, T_wc[:3, 3], rtol=RTOL, atol=1e-15)


def _pairs_in_view(rng, mounts):
    """A random state, and five landmarks in front of the cameras of pair_camera: (x, pair_camera,
    their camera-frame points, landmarks)."""
    x = _random_state(rng)
    pair_camera = np.array([0, 1, 1, 0, 1], dtype=np.int64)
    p_camera = np.column_stack([rng.uniform(-1, 1, (5, 2)), rng.uniform(1, 4, 5)])
    landmarks = np.stack([geometry.transform_points(geometry.pose_from_euler(x) @ mounts[c], p_camera[i])
                          for i, c in enumerate(pair_camera)])
    return x, pair_camera, p_camera, landmarks


def _two_cameras():
    """Mounts (2, 3, 3), (2, 3), intrinsics (2, 4) and poses (2, 4, 4): the test camera and a second,
    turned and with other intrinsics."""
    second = geometry.pose_from_euler(np.array([-0.2, 0.1, 0.25, -np.pi / 2 + 0.2, -0.1, -np.pi / 2 - 0.3]))
    mounts = np.stack([T_ROBOT_CAMERA, second])
    K = np.array([INTRINSICS, [600.0, 600.0, 300.0, 250.0, measurement.DEPTH]])
    return np.ascontiguousarray(mounts[:, :3, :3]), np.ascontiguousarray(mounts[:, :3, 3]), K, mounts


@pytest.mark.parametrize("kinds", [(measurement.PIXEL, measurement.PIXEL), (measurement.DISPARITY, measurement.PIXEL),
                                   (measurement.DEPTH, measurement.DISPARITY)])
def test_observing_pairs_of_every_measurement_kind_is_its_numpy_model(rng, kinds):
    """The kernel's camera model reads the sensor's kind from its intrinsics' fifth column: each
    pair's prediction and Jacobian are numpy's (``models.observe``) for that kind, the inert row
    of a pixel is zero, and H matches central differences."""
    camera_R, camera_t, camera_K, mounts = _two_cameras()
    camera_K[:, 4] = kinds
    x, pair_camera, p_camera, landmarks = _pairs_in_view(rng, mounts)
    z_hat, H = camera.observe_pairs(x, landmarks, pair_camera, camera_R, camera_t, camera_K)
    for i, c in enumerate(pair_camera):
        ref_z, ref_H = models.observe(x, mounts[c], tuple(camera_K[c][:4]), landmarks[i:i + 1], int(camera_K[c][4]))
        np.testing.assert_allclose(z_hat[i], ref_z[0], rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose(H[i], ref_H[0], rtol=RTOL, atol=1e-9)
        kind = int(camera_K[c][4])
        third = {measurement.DEPTH: p_camera[i, 2], measurement.DISPARITY: 1.0 / p_camera[i, 2], measurement.PIXEL: 0.0}[kind]
        assert z_hat[i, 2] == pytest.approx(third, rel=1e-12, abs=0.0)
        if kind == measurement.PIXEL:
            assert not H[i, 2].any()  # the inert row
    numeric = _central_difference(lambda s: camera.observe_pairs(s, landmarks, pair_camera, camera_R, camera_t, camera_K)[0], x)
    np.testing.assert_allclose(H, numeric, rtol=1e-6, atol=1e-6)


def test_back_projecting_a_disparity_is_numpy_s_and_its_jacobian_is_the_derivative(rng):
    K = INTRINSICS.copy()
    K[4] = measurement.DISPARITY
    p_camera = np.column_stack([rng.uniform(-1, 1, (4, 2)), rng.uniform(0.5, 4.0, 4)])
    z = models.project_points(p_camera, tuple(K[:4]), measurement.DISPARITY)
    ref_points, ref_J = models.back_project(z, tuple(K[:4]), measurement.DISPARITY)
    np.testing.assert_allclose(ref_points, p_camera, rtol=1e-12)
    for i in range(4):
        p, J = camera.back_project(z[i], K)
        np.testing.assert_allclose(p, ref_points[i], rtol=RTOL)
        np.testing.assert_allclose(J, ref_J[i], rtol=RTOL)
        np.testing.assert_allclose(J, _central_difference(lambda w: camera.back_project(w, K)[0], z[i]), rtol=1e-6, atol=1e-8)


def test_observing_pairs_is_observing_each_through_its_own_camera(rng):
    camera_R, camera_t, camera_K, mounts = _two_cameras()
    x, pair_camera, p_camera, landmarks = _pairs_in_view(rng, mounts)
    z_hat, H = camera.observe_pairs(x, landmarks, pair_camera, camera_R, camera_t, camera_K)
    for i, c in enumerate(pair_camera):
        ref_z, ref_H = models.observe(x, mounts[c], tuple(camera_K[c][:4]), landmarks[i:i + 1])
        np.testing.assert_allclose(z_hat[i], ref_z[0], rtol=RTOL)
        np.testing.assert_allclose(H[i], ref_H[0], rtol=RTOL, atol=1e-9)   # entries that cancel to near zero
    np.testing.assert_allclose(z_hat[:, 2], p_camera[:, 2], rtol=RTOL)
    numeric = _central_difference(lambda s: camera.observe_pairs(s, landmarks, pair_camera, camera_R, camera_t, camera_K)[0], x)
    # pixels of 500 / metre: rounding of z_hat (1e-13) over the step leaves about 1e-7
    np.testing.assert_allclose(H, numeric, rtol=1e-6, atol=1e-6)


def test_the_cameras_of_observations_are_numpy_unique_of_their_cameras(rng):
    obs_camera = rng.integers(0, 5, 40).astype(np.int64)
    for size in (0, 1, 7, 40):
        obs = rng.choice(40, size, replace=False).astype(np.int64)
        np.testing.assert_array_equal(camera.cameras_of(obs_camera, obs, 5), np.unique(obs_camera[obs]))


def test_back_projection_inverts_the_projection_with_its_jacobian(rng):
    p_camera = np.column_stack([rng.uniform(-1, 1, (6, 2)), rng.uniform(0.5, 4.0, 6)])
    uvd = models.project_points(p_camera, tuple(INTRINSICS[:4]))
    ref_points, ref_J = models.back_project(uvd, tuple(INTRINSICS[:4]))
    for i in range(6):
        p, J = camera.back_project(uvd[i], INTRINSICS)
        np.testing.assert_allclose(p, p_camera[i], rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(p, ref_points[i], rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose(J, ref_J[i], rtol=RTOL, atol=1e-15)
        # p is bilinear in (u, v, depth): central differences are exact but for rounding
        numeric = _central_difference(lambda z: camera.back_project(z, INTRINSICS)[0], uvd[i])
        np.testing.assert_allclose(J, numeric, rtol=1e-8, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# motion: the prediction

def test_prediction_is_the_motion_model_and_f_p_f_transpose_plus_g_q_g_transpose(rng):
    for _ in range(5):
        x = _random_state(rng)
        T = geometry.pose_from_euler(np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.2, 3)])
        P, Q = _random_spd(rng, 6, 0.1), _random_spd(rng, 6, 0.01)
        x_next, P_next = motion.predict(x, P, T, Q)
        ref_x, F, G = models.motion(x, T)          # the numpy model, not the kernel's own F and G
        np.testing.assert_allclose(x_next, ref_x, rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(P_next, F @ P @ F.T + G @ Q @ G.T, rtol=RTOL, atol=1e-15)
        np.testing.assert_array_equal(P_next, P_next.T)


# ---------------------------------------------------------------------------------------------
# update: the stacked update, in covariance form (few pairs) and information form (many)

def _textbook(P, H, R):
    """(S, K, H stacked) of the textbook update in numpy: S = H P H' + R, K = P H' S^-1."""
    Hs = H.reshape(-1, 6)
    S = Hs @ P @ Hs.T + ekf.block_diagonal(R)
    return S, np.linalg.solve(S, Hs @ P).T, Hs


@pytest.mark.parametrize("m", [3, 6])
def test_cholesky_factor_and_stacked_quadratic(rng, m):
    S = _random_spd(rng, m)
    L = np.full((m, m), np.nan)                                     # every entry written, zeros above
    update.cholesky_into(S, L)
    np.testing.assert_allclose(L, np.linalg.cholesky(S), rtol=RTOL, atol=1e-14)
    y = rng.normal(size=(m // 3, 3))
    v = y.reshape(-1)
    np.testing.assert_allclose(update.stacked_quadratic(L, y, np.empty(m)), v @ np.linalg.solve(S, v), rtol=RTOL)
    S[0, 0] = -1.0
    with pytest.raises(FloatingPointError, match="positive definite"):
        update.cholesky_into(S, L)


def _gain_kernel(P, H, R):
    """update.gain_into with fresh arrays: (K (6, 3p), S (3p, 3p), L)."""
    m = 3 * H.shape[0]
    PHt, S, L, K = np.empty((6, m)), np.empty((m, m)), np.full((m, m), np.nan), np.empty((6, m))
    update.gain_into(P, H, R, PHt, S, L, K)
    return K, S, L


def _information_kernel(P, H, R_inverse):
    """update.information_into with fresh arrays: (R^-1 H, Lambda, (M, pivots) the factors of
    I + P Lambda, A P)."""
    R_inverse_H, information, AP = np.empty(H.shape), np.empty((6, 6)), np.empty((6, 6))
    M, pivots = np.empty((6, 6)), np.empty(6, np.int64)
    update.information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP)
    return R_inverse_H, information, M, pivots, AP


@pytest.mark.parametrize("p", [1, 2])
def test_kalman_gain_is_p_h_transpose_s_inverse(rng, p):
    H, R, _, _ = _pairs(rng, p)
    P = _random_spd(rng, 6, 0.2)
    K, S, L = _gain_kernel(P, H, R)
    ref_S, ref_K, _ = _textbook(P, H, R)
    np.testing.assert_allclose(S, ref_S, rtol=RTOL, atol=1e-14)
    np.testing.assert_array_equal(S, S.T)
    np.testing.assert_allclose(K, ref_K, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(L @ L.T, ref_S, rtol=RTOL, atol=1e-14)
    np.testing.assert_array_equal(L, np.tril(L))


def test_cholesky_solve_is_s_inverse_b(rng):
    S, b = _random_spd(rng, 9), rng.normal(size=9)
    L = np.empty((9, 9))
    update.cholesky_into(S, L)
    got = b.copy()
    update.cho_solve_into(L, got)
    np.testing.assert_allclose(got, np.linalg.solve(S, b), rtol=RTOL, atol=1e-14)


@pytest.mark.parametrize("m", [3, 6])
def test_cholesky_solve_of_rows_is_each_row_solved_alone(rng, m):
    # the gain's rows solved in one call (``cho_solve_rows_into``): bit for bit ``cho_solve_into``
    # on each row (the beam's results do not move), and S^-1 b
    S, B = _random_spd(rng, m), rng.normal(size=(6, m))
    L = np.empty((m, m))
    update.cholesky_into(S, L)
    got = B.copy()
    update.cho_solve_rows_into(L, got)
    for c in range(6):
        row = B[c].copy()
        update.cho_solve_into(L, row)
        assert np.array_equal(got[c], row)
    np.testing.assert_allclose(got, np.linalg.solve(S, B.T).T, rtol=RTOL, atol=1e-14)


def test_joseph_posterior_is_its_formula_for_any_gain_and_p_minus_k_s_k_transpose_for_the_optimal_one(rng):
    H, R, _, _ = _pairs(rng, 2)
    P = _random_spd(rng, 6, 0.2)
    S, K_optimal, Hs = _textbook(P, H, R)
    R_full = ekf.block_diagonal(R)
    K_any = np.ascontiguousarray(K_optimal + rng.normal(0, 0.05, K_optimal.shape))

    def joseph(K):
        out = np.empty((6, 6))
        update.covariance_posterior_into(P, np.ascontiguousarray(K), H, R, out, np.empty((6, 6)), np.empty((6, 6)))
        return out

    I_KH = np.eye(6) - K_any @ Hs
    np.testing.assert_allclose(joseph(K_any), I_KH @ P @ I_KH.T + K_any @ R_full @ K_any.T, rtol=RTOL, atol=1e-14)
    got = joseph(K_optimal)
    np.testing.assert_allclose(got, P - K_optimal @ S @ K_optimal.T, rtol=RTOL, atol=1e-13)
    np.testing.assert_array_equal(got, got.T)


def _information(P, H, R_inverse):
    """(R^-1 H, Lambda = sum H_i' R_i^-1 H_i, I + P Lambda) in numpy."""
    R_inverse_H = R_inverse @ H
    information = np.einsum("pai,pab,pbj->ij", H, R_inverse, H)
    return R_inverse_H, information, np.eye(6) + P @ information


@pytest.mark.parametrize("p", [3, 7])
def test_information_step_gives_the_covariance_form_posterior(rng, p):
    H, R, R_inverse, _ = _pairs(rng, p)
    P = _random_spd(rng, 6, 0.2)
    R_inverse_H, information, M, pivots, posterior_plain = _information_kernel(P, H, R_inverse)
    ref_R_inverse_H, ref_information, ref_I_P_information = _information(P, H, R_inverse)
    np.testing.assert_allclose(R_inverse_H, ref_R_inverse_H, rtol=RTOL, atol=1e-14)
    np.testing.assert_allclose(information, ref_information, rtol=RTOL, atol=1e-13)
    B = rng.normal(size=(6, 2))                        # (M, pivots) factor I + P Lambda
    X = B.copy()
    small.lu_solve(M, pivots, X)
    np.testing.assert_allclose(X, np.linalg.solve(ref_I_P_information, B), rtol=RTOL, atol=1e-13)
    S, K, Hs = _textbook(P, H, R)
    # A P = (P^-1 + Lambda)^-1 = P - K S K' (the covariance form, with the (3p, 3p) S)
    np.testing.assert_allclose(posterior_plain, P - K @ S @ K.T, rtol=RTOL, atol=1e-13)
    np.testing.assert_allclose(posterior_plain, np.linalg.inv(np.linalg.inv(P) + ref_information), rtol=RTOL, atol=1e-14)
    np.testing.assert_array_equal(posterior_plain, posterior_plain.T)


def test_a_non_finite_information_is_refused(rng):
    H, _, R_inverse, _ = _pairs(rng, 3)
    H[1, 0, 2] = np.inf
    with pytest.raises(FloatingPointError, match="positive definite"):
        _information_kernel(_random_spd(rng, 6, 0.2), H, R_inverse)


@pytest.mark.parametrize("p", [3, 7])
def test_information_form_joseph_posterior_is_the_covariance_form_one(rng, p):
    H, R, R_inverse, _ = _pairs(rng, p)
    P = _random_spd(rng, 6, 0.2)
    _, information, M, pivots, _ = _information_kernel(P, H, R_inverse)
    S, K, Hs = _textbook(P, H, R)
    I_KH = np.eye(6) - K @ Hs
    joseph = I_KH @ P @ I_KH.T + K @ ekf.block_diagonal(R) @ K.T
    got = np.empty((6, 6))
    update.posterior_covariance_into(P, information, M, pivots, got, np.empty((6, 6)))
    np.testing.assert_allclose(got, joseph, rtol=RTOL, atol=1e-13)
    np.testing.assert_array_equal(got, got.T)


@pytest.mark.parametrize("p", [1, 2, 5])    # the covariance form up to 2 pairs, the information form beyond
def test_correction_is_kalman_gain_times_innovation(rng, p):
    H, R, R_inverse, y = _pairs(rng, p)
    P = _random_spd(rng, 6, 0.2)
    _, K, _ = _textbook(P, H, R)
    np.testing.assert_allclose(update.correction(P, H, R, R_inverse, y), K @ y.reshape(-1), rtol=RTOL, atol=1e-13)


@pytest.mark.parametrize("p", [1, 2, 5])
def test_innovation_cost_is_nis_plus_log_det_s_minus_log_det_r(rng, p):
    H, R, R_inverse, y = _pairs(rng, p)
    P = _random_spd(rng, 6, 0.2)
    S, _, _ = _textbook(P, H, R)
    v = y.reshape(-1)
    expected = v @ np.linalg.solve(S, v) + np.linalg.slogdet(S)[1] - np.linalg.slogdet(R)[1].sum()
    np.testing.assert_allclose(update.innovation_cost(P, H, R, R_inverse, y), expected, rtol=RTOL)


def test_normalized_innovation_is_y_s_inverse_y_by_woodbury(rng):
    # y' S^-1 y = y' R^-1 y - g' A P g, the information form's NIS; K y = A P g its correction
    H, R, R_inverse, y = _pairs(rng, 5)
    P = _random_spd(rng, 6, 0.2)
    R_inverse_H, _, _, _, posterior_plain = _information_kernel(P, H, R_inverse)
    g, step = np.empty(6), np.empty(6)
    update.gradient_into(R_inverse_H, y, g)
    nis = update.block_quadratic(y, R_inverse) - update.plain_step_into(posterior_plain, g, step)
    S, K, _ = _textbook(P, H, R)
    v = y.reshape(-1)
    np.testing.assert_allclose(nis, v @ np.linalg.solve(S, v), rtol=RTOL)
    np.testing.assert_allclose(step, K @ v, rtol=RTOL, atol=1e-13)


def test_block_sums_are_the_stacked_products(rng):
    H, _, R_inverse, y = _pairs(rng, 4)
    v, R_inverse_full = y.reshape(-1), ekf.block_diagonal(R_inverse)
    np.testing.assert_allclose(update.block_quadratic(y, R_inverse), v @ R_inverse_full @ v, rtol=RTOL)
    g = np.full(6, np.nan)
    update.gradient_into(R_inverse @ H, y, g)
    np.testing.assert_allclose(g, H.reshape(-1, 6).T @ R_inverse_full @ v, rtol=RTOL, atol=1e-13)
    K = rng.normal(size=(6, 12))
    step = np.empty(6)
    update.gain_step_into(K, y, step)
    np.testing.assert_allclose(step, K @ v, rtol=RTOL, atol=1e-13)


def test_prior_quadratic_is_the_mahalanobis_distance_of_a_correction(rng):
    P, d = _random_spd(rng, 6, 0.05), rng.normal(0, 0.1, 6)
    got = update.prior_quadratic(P, d, np.empty((6, 6)), np.empty(6, np.int64), np.empty((6, 1)))
    np.testing.assert_allclose(got, d @ np.linalg.solve(P, d), rtol=RTOL)


@pytest.mark.parametrize("p", [2, 5])
@pytest.mark.parametrize("across_the_wrap", [False, True])
def test_iterated_update_is_the_numpy_iterated_update_through_the_camera_model(rng, p, across_the_wrap):
    # Gauss-Newton on the MAP cost (camloc.ekf.update with the numpy camera model, the Euler
    # state's retraction and difference), from a prior 0.05 m and 0.05 rad off the truth; across
    # the wrap, the prior's yaw is just below pi and the truth's just above (-pi + 0.01)
    camera_R, camera_t, camera_K, mounts = _two_cameras()
    truth = _random_state(rng)
    x = rotation.retract(truth, rng.normal(0, 0.05, 6))
    if across_the_wrap:
        truth[5], x[5] = -np.pi + 0.01, np.pi - 0.02
    pair_camera = (np.arange(p) % 2).astype(np.int64)
    p_camera = np.column_stack([rng.uniform(-1, 1, (p, 2)), rng.uniform(1, 4, p)])
    landmarks = np.stack([geometry.transform_points(geometry.pose_from_euler(truth) @ mounts[c], p_camera[i])
                          for i, c in enumerate(pair_camera)])
    R = _pixel_noise(rng, p)

    def measure(state):
        predictions = [models.observe(state, mounts[c], tuple(camera_K[c][:4]), landmarks[i:i + 1]) for i, c in enumerate(pair_camera)]
        return (np.concatenate([z for z, _ in predictions]).reshape(-1),
                np.concatenate([H for _, H in predictions]).reshape(-1, 6))

    z = measure(truth)[0].reshape(p, 3) + rng.normal(0, 1, (p, 3)) * [2.0, 2.0, 0.05]
    P = _random_spd(rng, 6, 0.05)
    z_hat, H = camera.observe_pairs(x, landmarks, pair_camera, camera_R, camera_t, camera_K)
    euler = filters.EulerFilter()
    ref = ekf.update(x, P, z.reshape(-1), R, measure, retract=euler.retract, difference=euler.difference, iterations=4,
                     map_cost=True, R_inverse=_inverse(R))
    x_post, P_post, nis, cost, y = update.iterated_update(x, P, z, R, _inverse(R), landmarks, pair_camera, camera_R, camera_t,
                                                          camera_K, 4, z_hat, H, np.empty(0), True, 0.0, False)
    np.testing.assert_allclose(y.reshape(-1), ref.innovation, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(x_post, ref.state, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(P_post, ref.cov, rtol=RTOL, atol=1e-16)
    np.testing.assert_allclose([nis, cost], [ref.nis, ref.map_cost], rtol=RTOL)
    assert np.max(np.abs(rotation.difference(x_post, x))) > 1e-3    # the update moved the state
    if across_the_wrap:
        assert x_post[5] < 0.0 < x[5]                                # its correction wrapped


@pytest.mark.parametrize("step_sigma", [0.03, 1e3])
def test_iterated_update_stops_where_a_step_is_negligible_against_the_prior_s_sigma(rng, step_sigma):
    # the beam's update of one ray (constants.RAY_STEP_SIGMA): both engines stop once a
    # linearization moved the state by less than step_sigma prior standard deviations on every axis;
    # a huge one stops after the second linearization (its first step is the plain EKF's)
    camera_R, camera_t, camera_K, mounts = _two_cameras()
    truth = _random_state(rng)
    x = rotation.retract(truth, rng.normal(0, 0.05, 6))
    landmarks = geometry.transform_points(geometry.pose_from_euler(truth) @ mounts[0], np.array([[0.3, -0.2, 1.5]]))
    pair_camera = np.zeros(1, np.int64)
    R = _pixel_noise(rng, 1)
    moves = []

    def measure(state):
        moves.append(state)
        z_hat, H = models.observe(state, mounts[0], tuple(camera_K[0][:4]), landmarks)
        return z_hat.reshape(-1), H.reshape(-1, 6)

    z = measure(truth)[0].reshape(1, 3) + rng.normal(0, 1, (1, 3)) * [2.0, 2.0, 0.0]
    P = _random_spd(rng, 6, 0.05)
    z_hat, H = camera.observe_pairs(x, landmarks, pair_camera, camera_R, camera_t, camera_K)
    euler = filters.EulerFilter()
    moves.clear()
    options = dict(retract=euler.retract, difference=euler.difference, R_inverse=_inverse(R))
    ref = ekf.update(x, P, z.reshape(-1), R, measure, iterations=6, step_sigma=step_sigma, **options)
    x_post, P_post = update.iterated_update(x, P, z, R, _inverse(R), landmarks, pair_camera, camera_R, camera_t, camera_K, 6,
                                            z_hat, H, np.empty(0), False, step_sigma, False)[:2]
    np.testing.assert_allclose(x_post, ref.state, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(P_post, ref.cov, rtol=RTOL, atol=1e-16)
    sigma = np.sqrt(np.diagonal(P))
    iterates = moves[1:] + [ref.state]                               # moves[0]: the prior's linearization
    changes = [np.abs(rotation.difference(b, a)) / sigma for a, b in zip(iterates, iterates[1:])]
    assert 2 <= len(moves) < 6                                       # linearizations: stopped before the last allowed
    assert changes[-1].max() < step_sigma * (1 + 1e-9) and all(c.max() >= step_sigma * (1 - 1e-9) for c in changes[:-1])
    if step_sigma > 1.0:
        plain = ekf.update(x, P, z.reshape(-1), R, measure, iterations=2, **options)
        np.testing.assert_array_equal(ref.state, plain.state)


@pytest.mark.parametrize("p", [1, 4])
def test_point_step_is_one_update_with_the_measurements_as_camera_frame_points(rng, p):
    # the measurements back-projected (observation o as scene.point[o] with scene.point_cov[o]),
    # predictions back-projected the same way with H carried through d p / d z
    K_obs = np.array([INTRINSICS, [600.0, 600.0, 300.0, 250.0, measurement.DEPTH]])
    obs_camera = np.array([1, 0, 0, 1, 1, 0], dtype=np.int64)
    point = np.column_stack([rng.uniform(-1, 1, (6, 2)), rng.uniform(1, 4, 6)])
    point_cov = np.stack([_random_spd(rng, 3, 0.05) for _ in range(6)])
    scene = _scene(camera_K=K_obs, obs_camera=obs_camera, point=point, point_cov=point_cov, point_cov_inverse=_inverse(point_cov),
                   z=np.zeros((6, 3)), R_assoc=np.zeros((6, 3, 3)), R_assoc_inverse=np.zeros((6, 3, 3)))
    obs = rng.choice(6, p, replace=False).astype(np.int64)
    x, P = _random_state(rng), _random_spd(rng, 6, 0.1)
    z_hat = models.project_points(point[obs] + rng.normal(0, 0.1, (p, 3)), tuple(INTRINSICS[:4]))   # any (u, v, depth)
    H = rng.normal(0, 100, (p, 3, 6))
    got = update.point_step(scene, x, P, obs, z_hat, H)
    p_hat, J = models.back_project(z_hat, K_obs[obs_camera[obs]][:, :4].T)
    S, K, _ = _textbook(P, J @ H, point_cov[obs])
    expected = x + K @ (point[obs] - p_hat).reshape(-1)
    expected[[3, 5]] = geometry.wrap_angle(expected[[3, 5]])
    np.testing.assert_allclose(got, expected, rtol=RTOL, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# recheck: the assignment margins

def test_assignment_margins_are_the_cost_of_the_nearest_single_change(rng):
    # The docstring, stated over whole assignments: total(a) sums each observation's cost (its
    # null cost where unassigned). row: the cheapest change of observation i alone (another
    # landmark, or none). steal: a rival i2 takes i's landmark c while i takes its next best,
    # against the better of the current assignment and the one where i2 goes unassigned.
    n, m = 5, 7
    cost = rng.uniform(0, 10, (n, m))
    cost[rng.uniform(size=(n, m)) < 0.4] = np.inf    # pairs beyond the gate
    chosen = np.array([2, -1, 0, 5, 6])
    null = rng.uniform(3, 12, n)
    cost[0, 2], cost[3, 5] = 1.0, 2.0
    cost[:, 6] = np.inf                             # observation 4's landmark has no rival
    cost[4, 6] = 3.0
    cost[:, 0] = np.inf                             # observation 2's has one, observation 3, whose
    cost[2, 0], cost[3, 0] = 0.5, 1.5               # null cost is below that of its own pair: it
    null[3] = 1.0                                   # gives up its null, not its pair

    def total(assignment):
        return sum(null[i] if a < 0 else cost[i, a] for i, a in enumerate(assignment))

    def changed(*moves):
        """The chosen assignment with observation i moved to landmark a (-1: none), for each (i, a)."""
        out = list(chosen)
        for i, a in moves:
            out[i] = a
        return out

    row, steal = recheck.assignment_margins(cost, null, chosen)
    now = total(chosen)
    for i, c in enumerate(chosen):
        if c < 0:
            assert row[i] == steal[i] == np.inf
            continue
        alternatives = [a for a in range(-1, m) if a != c]
        next_best = min(alternatives, key=lambda a: total(changed((i, a))))
        expected_row = total(changed((i, next_best))) - now
        expected_steal = min(total(changed((i, next_best), (i2, c))) - min(now, total(changed((i2, -1))))
                             for i2 in range(n) if i2 != i)
        np.testing.assert_allclose(row[i], expected_row, rtol=RTOL)
        np.testing.assert_allclose(steal[i], expected_steal, rtol=RTOL)
    assert steal[4] == np.inf and np.isfinite(row[4])   # the case with no rival is exercised
    assert np.isfinite(steal).sum() >= 2


# ---------------------------------------------------------------------------------------------
# view: the view's ball and its widening

def test_widened_view_adds_three_standard_deviations_of_position_and_orientation(rng):
    max_angle = math.radians(30.0)
    P = _random_spd(rng, 6, 0.02)
    margin, half_angle = view.widened_view(P, max_angle)
    np.testing.assert_allclose(margin, 3.0 * math.sqrt(np.linalg.eigvalsh(P[:3, :3]).max()), rtol=RTOL)
    np.testing.assert_allclose(half_angle, max_angle + 3.0 * math.sqrt(np.linalg.eigvalsh(P[3:, 3:]).max()), rtol=RTOL)
    assert half_angle > max_angle
    wide = np.diag([0.0, 0.0, 0.0, 4.0, 4.0, 4.0])
    assert view.widened_view(wide, max_angle) == (0.0, math.radians(89.0))   # never past 89 degrees


@pytest.mark.parametrize("half_angle_deg", [30.0, 45.0, 60.0])
def test_view_cone_ball_is_the_numpy_one_and_holds_the_cone(rng, half_angle_deg):
    apex, axis = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half_angle = math.radians(half_angle_deg)
    centre, radius = view.view_cone_ball(apex, axis, 4.0, half_angle)
    ref_centre, ref_radius = association.view_cone_ball(apex, axis, 4.0, half_angle)
    np.testing.assert_allclose(centre, ref_centre, rtol=RTOL)
    np.testing.assert_allclose(radius, ref_radius, rtol=RTOL)
    # the apex and the base's rim lie in it
    side = np.cross(axis, rng.normal(size=3))
    side /= np.linalg.norm(side)
    rim = apex + 4.0 * axis + 4.0 * math.tan(half_angle) * side
    for point in (apex, rim):
        assert np.linalg.norm(point - centre) <= radius


@pytest.mark.parametrize("size", [0, 1, 5, 64, 65, 300])
def test_a_view_s_landmarks_sorted_in_place_are_numpy_s_sort(rng, size):
    # by insertion up to SMALL_VIEW_SORT (64), by sorted_ints past it: both np.sort's order
    values = rng.permutation(10 * size + 1)[:size].astype(np.int64)
    got = view.sort_distinct_in_place(values.copy())
    np.testing.assert_array_equal(got, np.sort(values))


# ---------------------------------------------------------------------------------------------
# filtering: a pair's distance

def test_pair_distance_is_the_mahalanobis_distance_of_an_observation_to_a_prediction(rng):
    H, R, _, _ = _pairs(rng, 3)
    z, z_hat = rng.normal(size=(4, 3)), rng.normal(size=(3, 3))
    noise = np.concatenate([R, _random_spd(rng, 3, 0.3)[None]])       # one noise per observation
    P = _random_spd(rng, 6, 0.2)
    for o, i in [(0, 0), (3, 1), (1, 2)]:
        y, S = z[o] - z_hat[i], H[i] @ P @ H[i].T + noise[o]
        np.testing.assert_allclose(filtering.pair_distance(noise, o, z, z_hat, H, i, P), y @ np.linalg.solve(S, y), rtol=RTOL)


# ---------------------------------------------------------------------------------------------
# seeds: a pair's cost conditioned on a seed pair

def test_conditioned_costs_are_those_under_the_schur_complement(rng):
    # conditioning on a seed s moves every innovation by H_q c_s and shrinks its covariance to
    # S_q|s = S_q - H_q U U' H_q', with U U' = P H_s' S_s^-1 H_s P
    N = 6
    H, R, _, y = _pairs(rng, N)
    P = _random_spd(rng, 6, 0.2)
    s = 2
    S = H @ P @ np.swapaxes(H, 1, 2) + R
    L_s = np.linalg.cholesky(S[s])
    U = np.ascontiguousarray(np.linalg.solve(L_s, H[s] @ P).T)            # (6, 3): U U' = P H_s' S_s^-1 H_s P
    correction = P @ H[s].T @ np.linalg.solve(S[s], y[s])                 # K_s y_s
    H_rows = np.ascontiguousarray(H.transpose(1, 2, 0).reshape(18, N))
    S_rows = np.ascontiguousarray(np.stack([S[:, i, j] for i, j in UPPER]))                 # (6, N) upper triangles
    S_inverse = np.linalg.inv(S)
    S_inverse_rows = np.ascontiguousarray(np.stack([S_inverse[:, i, j] for i, j in UPPER]))
    bound, quadratic, det = np.empty(N), np.empty(N), np.empty(N)
    seeds.conditioned_costs(H_rows, np.ascontiguousarray(y.T), S_rows, S_inverse_rows, correction, U, bound, quadratic, det)
    for q in range(N):
        r = y[q] - H[q] @ correction
        conditioned = S[q] - H[q] @ P @ H[s].T @ np.linalg.solve(S[s], H[s] @ P @ H[q].T)
        np.testing.assert_allclose(bound[q], r @ np.linalg.solve(S[q], r), rtol=RTOL)
        np.testing.assert_allclose(det[q], np.linalg.det(conditioned), rtol=RTOL)
        np.testing.assert_allclose(quadratic[q] / det[q], r @ np.linalg.solve(conditioned, r), rtol=RTOL)
    assert np.all(det < np.linalg.det(S))          # conditioning only ever narrows a spread


# ---------------------------------------------------------------------------------------------
# beam: a pair's cost in the coordinates where its linearization explains it best

def test_as_point_is_the_back_projection_with_its_jacobian(rng):
    z_hat = models.project_points(np.column_stack([rng.uniform(-1, 1, (4, 2)), rng.uniform(0.5, 4.0, 4)]), tuple(INTRINSICS[:4]))
    ref_points, ref_J = models.back_project(z_hat, tuple(INTRINSICS[:4]))
    for q in range(4):
        p0, p1, p2, j00, j02, j11, j12 = beam.as_point(z_hat, q, INTRINSICS)
        J = np.array([[j00, 0.0, j02], [0.0, j11, j12], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose([p0, p1, p2], ref_points[q], rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose(J, ref_J[q], rtol=RTOL, atol=1e-15)

        def point_of(z):
            return np.array(beam.as_point(z[None], 0, INTRINSICS)[:3])

        np.testing.assert_allclose(J, _central_difference(point_of, z_hat[q]), rtol=1e-8, atol=1e-9)


def test_point_spread_is_j_a_j_transpose(rng):
    for _ in range(5):
        A = _random_spd(rng, 3, 10.0)
        j00, j02, j11, j12 = rng.normal(size=4)
        J = np.array([[j00, 0.0, j02], [0.0, j11, j12], [0.0, 0.0, 1.0]])
        got = beam.point_spread(tuple(float(a) for a in _upper(A)), j00, j02, j11, j12)
        np.testing.assert_allclose(got, _upper(J @ A @ J.T), rtol=RTOL, atol=1e-12)


def test_spread_row_is_the_row(rng):
    spreads = rng.normal(size=(3, 6))
    assert beam.spread_row(spreads, 1) == tuple(spreads[1])


def test_a_pair_is_judged_in_pixels_or_as_a_point_whichever_costs_less(rng):
    # cost = d^2 + ln det S - ln det R in (u, v, depth), S = H P H' + R; and as camera-frame points,
    # S = J H P H' J' + C with J = d p / d z at the prediction and C the measured point's covariance
    x, P = _random_state(rng), _random_spd(rng, 6, 0.08)
    n = 12
    p_camera = np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.uniform(0.5, 4.0, n)])
    landmarks = geometry.transform_points(geometry.pose_from_euler(x) @ T_ROBOT_CAMERA, p_camera)
    z_hat, H = models.observe(x, T_ROBOT_CAMERA, tuple(INTRINSICS[:4]), landmarks)
    R = _pixel_noise(rng, n)
    z = z_hat + rng.normal(0, 1, (n, 3)) * rng.uniform(1, 30, (n, 1)) * [2.0, 2.0, 0.05]
    point, point_cov = models.measured_points(z, R, tuple(INTRINSICS[:4]))
    scene = _scene(camera_K=INTRINSICS[None].copy(), obs_camera=np.zeros(n, np.int64), z=z, R_assoc=R, point=point,
                   point_cov=point_cov, log_det_R=np.linalg.slogdet(R)[1], log_det_point_cov=np.linalg.slogdet(point_cov)[1])
    y, Hc = np.zeros((n, 3)), np.zeros((n, 3, 6))
    branches, d2_both = set(), []
    for o in range(n):
        q = (o + 1) % n if o % 3 == 0 else o          # some observations against another landmark
        spread_q = sym3.spread(H, q, P)
        d2, cost, in_point = beam.pair_in_best_coordinates(scene, o, z_hat, H, q, spread_q, y, Hc, o, np.inf)
        A = H[q] @ P @ H[q].T
        S_pixels, y_pixels = A + R[o], z[o] - z_hat[q]
        d2_pixels = y_pixels @ np.linalg.solve(S_pixels, y_pixels)
        cost_pixels = d2_pixels + np.linalg.slogdet(S_pixels)[1] - np.linalg.slogdet(R[o])[1]
        p_hat, J = models.back_project(z_hat[q:q + 1], tuple(INTRINSICS[:4]))
        S_point, y_point = J[0] @ A @ J[0].T + point_cov[o], point[o] - p_hat[0]
        d2_point = y_point @ np.linalg.solve(S_point, y_point)
        cost_point = d2_point + np.linalg.slogdet(S_point)[1] - np.linalg.slogdet(point_cov[o])[1]
        assert in_point == (cost_point < cost_pixels)
        expected = (d2_point, cost_point, y_point, J[0] @ H[q]) if in_point else (d2_pixels, cost_pixels, y_pixels, H[q])
        np.testing.assert_allclose([d2, cost], expected[:2], rtol=RTOL)
        np.testing.assert_allclose(y[o], expected[2], rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(Hc[o], expected[3], rtol=RTOL, atol=1e-12)
        branches.add(bool(in_point))
        d2_both.append((d2_pixels, d2_point))
    assert branches == {True, False}                  # both coordinates were chosen somewhere
    # with a gate, a pair beyond it in both coordinates is rejected unpriced, any other priced as before
    gate = float(np.median(np.min(d2_both, axis=1)))
    outcomes = set()
    for o in range(n):
        q = (o + 1) % n if o % 3 == 0 else o
        spread_q = sym3.spread(H, q, P)
        ungated = beam.pair_in_best_coordinates(scene, o, z_hat, H, q, spread_q, y, Hc, o, np.inf)
        gated = beam.pair_in_best_coordinates(scene, o, z_hat, H, q, spread_q, y, Hc, o, gate)
        beyond = min(d2_both[o]) > gate
        assert gated == ((np.inf, np.inf, False) if beyond else ungated)
        outcomes.add(beyond)
    assert outcomes == {True, False}


def test_the_seeded_search_trigger_is_the_numpy_beam_s_rule_on_every_history():
    # Generated: every (unassigned, observed) of poses of up to 12 observations, against
    # histories whose unexplained rate runs from none to past the cap, shorter and longer than
    # the window, and none at all.
    from camloc.beam_seeded import seeds_worth_trying
    from camloc.tails import binomial_tail

    rng = np.random.default_rng(5)
    histories = [np.zeros((0, 2), np.int64)]
    for rows, rate in itertools.product((1, 7, 50, 120), (0.0, 0.05, 0.2, 0.5, 0.9)):
        observed = rng.integers(1, 15, rows)
        histories.append(np.stack([rng.binomial(observed, rate), observed], axis=1).astype(np.int64))
    decisions = []
    for history, observed in itertools.product(histories, range(1, 13)):
        for unassigned in range(observed + 1):
            compiled = beam.seeds_worth_trying(np.int64(unassigned), np.int64(observed), history, np.int64(history.shape[0]))
            assert compiled == seeds_worth_trying(unassigned, observed, history), (unassigned, observed, history[-50:].sum(axis=0))
            decisions.append(compiled)
    assert 0.1 < np.mean(decisions) < 0.9  # both answers are tested
    for n in (1, 5, 12, 40):
        for u in range(n + 2):
            for p in (0.0, 0.03, 0.3, 0.6, 1.0):
                assert beam.binomial_upper_tail(np.int64(u), np.int64(n), p) == pytest.approx(
                    float(binomial_tail(u - 1, n, p)), rel=1e-9, abs=1e-15)


# ---------------------------------------------------------------------------------------------
# beam: the small sorts that allocate nothing numba's merge sort would

@pytest.mark.parametrize("size", [0, 1, 2, 7, 20, 21, 60])
def test_sort_by_is_numpy_s_stable_argsort_ties_included(rng, size):
    # keys with many ties (a few distinct costs, inf among them) over items in a scrambled order:
    # up to 20 items sorted by insertion, past it by numba's merge sort; both numpy's stable order
    keys = rng.choice([0.5, 1.5, 2.0, np.inf], size=3 * size + 2)
    items = rng.permutation(keys.size)[:size].astype(np.int64)
    expected = items[np.argsort(keys[items], kind="mergesort")]
    beam.sort_by(keys, items)
    np.testing.assert_array_equal(items, expected)
    if size > 2:
        assert np.unique(keys[items]).size < size      # ties were there to keep in order


@pytest.mark.parametrize("size", [0, 1, 6, 64, 65, 200])
def test_expected_landmarks_distinct_sort_is_numpy_s_unique_and_minimum(rng, size):
    # the landmarks claimed several times (ties) each at its least excess: in place up to
    # SMALL_EXPECTED_SORT (64), by merge sort past it; both np.unique's landmarks and np.minimum.at's
    found = rng.integers(0, max(size // 2, 1), size).astype(np.int64)
    excess = rng.normal(size=size)
    landmarks = np.unique(found)
    least = np.full(landmarks.size, np.inf)
    np.minimum.at(least, np.searchsorted(landmarks, found), excess)
    got = beam.distinct_least_in_place(found.copy(), excess.copy(), np.int64(size))
    np.testing.assert_array_equal(got[0], landmarks)
    np.testing.assert_array_equal(got[1], least)
