"""The numpy localizer's tag orientations: which observation is a tag's orientation, what it adds
to its position's pair in the association (``TagOrientations.pair_terms``) and how it joins that
pair in the update (``TagOrientations.joined``); the model is ``camloc.tags``'.

In the association a tag observation is one measurement of its position (3 dof, a pixel-only
camera's 2) and its orientation (3): a pair of it with a tag is judged by the joint d^2 of both,
gated at their dof (``TAG_GATE_TAIL``), and costs ``d^2 + ln det S - ln det R`` of the joint
innovation, split as the position's (what every pair costs) plus the orientation's given the
position (``conditional_terms``: the Schur complement of S's position block). Leaving it unassigned, or pairing it with a landmark that has
no orientation, leaves the orientation unexplained: clutter uniform over SO(3)
(``rotation_clutter_cost``). Two tags at nearly the same place are then told apart by their
orientations, which position alone cannot do.
"""

from __future__ import annotations

import numpy as np

from camloc import association, geometry, measurement, sym3
from camloc.tags import aligned
from camloc.tails import chi2_quantile

# A tag's orientation vetoes its position's pair beyond this d^2 (3 dof, 99.9%): a wrong tag's is
# off by tens of degrees, far beyond it, where the association's 99% gate would also refuse 1% of
# right ones (and their positions with them).
VETO_GATE = float(chi2_quantile(3, 0.001))

# A tag pair's joint gate (position and orientation, 6 dof) leaves out at most this share of
# right pairs (99.9%), or the association's own where that is wider: a wrong tag's orientation is
# tens of sigmas off, far beyond either, and with one or two tags a pose every right one left out
# costs (at the association's 99%, the filter's slight overconfidence in rotation left out 6-7% of
# right tags on worlds of one tag a pose, and the position error rose by up to 80%:
# benchmarks/tags.py filter, 2026-12-03).
TAG_GATE_TAIL = 0.001

# SO(3)'s volume in the measure of rotation vectors near the identity (the Haar measure,
# |d theta|^3 at small angles): the integral over the ball of radius pi of 2 (1 - cos a) / a^2, 8 pi^2
ROTATION_VOLUME = 8.0 * np.pi**2

# Whether the association judges a tag pair by its orientation too (False: by its position, the
# orientation only vetoing the pair afterwards); for comparisons (tests, benchmarks/tags.py nearby)
ORIENTATION_IN_ASSOCIATION = True


def rotation_clutter_cost(cov: np.ndarray) -> np.ndarray:
    """Cost (M,) of an orientation measurement with covariance cov (M, 3, 3) that no tag explains,
    in the units of a pair's cost (``observation_space.clutter_null_cost``): uniform over SO(3),
    ``2 ln V - ln det(2 pi R)``."""
    return 2.0 * np.log(ROTATION_VOLUME) - (3.0 * np.log(2.0 * np.pi) + sym3.log_abs_det(cov))


def conditional_terms(y, H, R, e, H_rot, R_rot, P) -> tuple[np.ndarray, np.ndarray]:
    """The orientation's share of M pairs' joint d^2 and ``ln det S - ln det R`` over position
    (innovation y (M, 3), Jacobian H (M, 3, n), noise R (M, 3, 3)) and orientation (e, H_rot,
    R_rot alike), under the state covariance P (n, n): both share the robot's error, so the joint
    S = [[S_p, C], [C', S_r]] (C = H P H_rot') is not block-diagonal. By its Schur complement
    ``S_r|p = S_r - C' S_p^-1 C``, ``d^2 = d^2_p + r' S_r|p^-1 r`` with ``r = e - C' S_p^-1 y``
    and ``ln det S = ln det S_p + ln det S_r|p``: returns (r' S_r|p^-1 r, ln det S_r|p - ln det R_rot),
    each (M,), the position's terms being what every pair already costs."""
    HP = H @ P
    S_p = HP @ np.swapaxes(H, 1, 2) + R
    C = HP @ np.swapaxes(H_rot, 1, 2)                          # cov(position innovation, orientation's)
    S_r = H_rot @ P @ np.swapaxes(H_rot, 1, 2) + R_rot
    gain = np.swapaxes(C, 1, 2) @ sym3.inverse(S_p)            # C' S_p^-1
    d2, log_det = association.mahalanobis_3x3(S_r - gain @ C, e - (gain @ y[:, :, None])[:, :, 0])
    return d2, log_det - sym3.log_abs_det(R_rot)


class TagOrientations:
    """The tags' orientation observations of a dataset (``measurement.TAG_ROTATION``), each the
    partner of its position's (``Dataset.obs_partner``): association pairs the positions, judging a
    tag pair by its orientation too (``pair_terms``, ``null_cost``), and a pair's tag orientation
    joins it in the update (``joined``). False when the dataset has none."""

    def __init__(self, dataset, association_cov: np.ndarray | None = None, gate: float = 0.99):
        """``association_cov`` (K, 3, 3): the noise association judges each observation by (None:
        the file's); ``gate``: the probability of the association's chi^2 gate."""
        self.dataset = dataset
        riders = np.flatnonzero(dataset.obs_partner >= 0)
        self.rotation_of = dict(zip(dataset.obs_partner[riders].tolist(), riders.tolist()))  # position -> orientation
        self.rotation = np.full(dataset.num_observations, -1, np.int64)  # the same as an array, -1: none
        self.rotation[dataset.obs_partner[riders]] = riders
        self.cov = dataset.obs_cov if association_cov is None else association_cov
        self.clutter = np.zeros(dataset.num_observations)  # the orientation's share of leaving a position unexplained
        self.clutter[dataset.obs_partner[riders]] = rotation_clutter_cost(self.cov[riders]) if riders.size else 0.0
        self.is_tag = np.isfinite(dataset.landmark_quat_xyzw[:, 0]) if len(dataset.landmark_ids) else np.zeros(0, bool)
        # a tag pair's gate, position and orientation: at the position's dof + 3 (a pixel's 2 + 3)
        dof = measurement.dof_of(dataset.obs_kind) + 3
        self.joint_gate = np.asarray(chi2_quantile(dof, min(1.0 - gate, TAG_GATE_TAIL)), dtype=float).reshape(-1)

    def __bool__(self) -> bool:
        return bool(self.rotation_of)

    def null_cost(self, null_cost: np.ndarray) -> np.ndarray:
        """The cost (K,) of leaving each observation unassigned in the association, from its
        position's (K,): a tag's orientation left unexplained too (``rotation_clutter_cost``)."""
        return null_cost + self.clutter if ORIENTATION_IN_ASSOCIATION else null_cost

    def orientation_rows(self, x, obs, landmarks, observe, obs_sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pairs (observations obs (g,), landmarks (g,)) that are a tag's position with a tag,
        ``both`` (b,) indices into them, and their orientations' innovations e (b, 3), Jacobians
        H_rot (b, 3, n) (``tags.aligned``: ``e = Log(R_pred^-1 R_meas)``) and noise (b, 3, 3) at x."""
        rotation = self.rotation[obs]
        both = np.flatnonzero((rotation >= 0) & self.is_tag[landmarks])
        e, H_rot = np.zeros((both.size, 3)), None
        for sensor in np.unique(obs_sensor[rotation[both]]):
            mine = obs_sensor[rotation[both]] == sensor
            z = self.dataset.obs_z[rotation[both[mine]]]
            z_hat, H = observe(x, int(sensor), landmarks[both[mine]])
            z_hat, H = aligned(z, geometry.so3_exp(z_hat), H)
            H_rot = np.zeros((both.size,) + H.shape[1:]) if H_rot is None else H_rot
            e[mine], H_rot[mine] = z - z_hat, H
        return both, e, H_rot, self.cov[rotation[both]]

    def pair_terms(self, x, P, obs, landmarks, y, H, R, observe, obs_sensor, gate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the tags' orientations add to g pairs (observations obs (g,), landmarks (g,))
        judged by their positions: innovation y (g, 3), Jacobian H (g, 3, n) and noise R (g, 3, 3)
        in the coordinates the pair was judged in, d^2 gate (g,). Returns the d^2 (g,) and cost (g,)
        to add to each pair's and the gate (g,) the sum must pass: a tag's position paired with a
        tag, its orientation's conditional terms (``conditional_terms``) and the joint gate; with
        a landmark without orientation, the orientation's clutter cost; any other, nothing."""
        if not ORIENTATION_IN_ASSOCIATION:
            return np.zeros(obs.size), np.zeros(obs.size), np.asarray(gate, dtype=float)
        d2, cost, gate = np.zeros(obs.size), self.clutter[obs].copy(), np.array(gate, dtype=float)
        both, e, H_rot, R_rot = self.orientation_rows(x, obs, landmarks, observe, obs_sensor)
        if both.size:
            d2[both], log_det = conditional_terms(y[both], H[both], R[both], e, H_rot, R_rot, P)
            cost[both] = d2[both] + log_det
            gate[both] = self.joint_gate[obs[both]]
        return d2, cost, gate

    def joined(self, obs, landmarks, x, P, observe, obs_sensor, association_cov) -> tuple[np.ndarray, np.ndarray]:
        """The pairs (p,) and, after them, the orientation observation of each pair whose observation
        is a tag's position paired with a tag, paired with the same tag. A pair whose tag's
        orientation fails ``VETO_GATE`` at the prior (x, P) (``observe(x, sensor, landmarks)``:
        the filter's prediction and Jacobian, aligned here), d^2 of ``Log(R_pred^-1 R_meas)``
        under ``association_cov``, is dropped with it: a tag's position alone can pair with the
        wrong tag nearby, its orientation then says so (and would pull the state by a wrong
        rotation)."""
        quat = self.dataset.landmark_quat_xyzw
        riders = [(n, self.rotation_of[o]) for n, (o, lm) in enumerate(zip(obs.tolist(), landmarks.tolist()))
                  if o in self.rotation_of and np.isfinite(quat[lm, 0])]
        if not riders:
            return obs, landmarks
        rows, rotation = np.array([n for n, _ in riders], np.int64), np.array([r for _, r in riders], np.int64)
        fits = np.ones(rows.size, dtype=bool)
        for sensor in np.unique(obs_sensor[rotation]):
            mine = obs_sensor[rotation] == sensor
            z = self.dataset.obs_z[rotation[mine]]
            z_hat, H = observe(x, int(sensor), landmarks[rows[mine]])
            z_hat, H = aligned(z, geometry.so3_exp(z_hat), H)
            S = H @ P @ np.swapaxes(H, 1, 2) + association_cov[rotation[mine]]
            d2, _ = association.mahalanobis_3x3(S, z - z_hat)
            fits[mine] = d2 <= VETO_GATE
        keep = np.ones(obs.size, dtype=bool)
        keep[rows[~fits]] = False
        return np.concatenate([obs[keep], rotation[fits]]), np.concatenate([landmarks[keep], landmarks[rows[fits]]])
