"""A chain of a pose's pair updates checked against the pose's prior, compiled: the twin of
``camloc.beam_chain`` (which says why), for ``camloc.kernels.beam``. ``model``: what the updates
read of the scene (``update.pair_model``)."""

from __future__ import annotations

import math

import numpy as np

from camloc.constants import RAY_NONLINEARITY
from camloc.kernels._jit import FALSE, called, inlined, jit
from camloc.kernels.camera import observe_pairs
from camloc.kernels.update import restart_cost, updated_at
from camloc.measurement import PIXEL


@jit
def wide_for_rays(model, P, obs, start, cost, H):
    """``beam_chain.wide_for_rays``: whether the cheapest gated option (cost finite, the first of
    equal ones) of some pixel observation of obs, of the options ``start``, ``cost``, ``H``
    (``beam.options_for``'s), has (H P H')_aa / (f_a sigma_a) beyond ``RAY_NONLINEARITY`` on its u
    or v row."""
    n = P.shape[0]
    for i in range(obs.size):
        o = obs[i]
        K = model.camera_K[model.obs_camera[o]]
        if K[4] != PIXEL:
            continue
        j = -1
        for q in range(start[i], start[i + 1]):
            if np.isfinite(cost[q]) and (j < 0 or cost[q] < cost[j]):
                j = q
        if j >= 0:
            for a in range(2):
                spread = 0.0
                for b in range(n):
                    s = 0.0
                    for c in range(n):
                        s += P[b, c] * H[j, a, c]
                    spread += H[j, a, b] * s
                if spread / (K[a] * math.sqrt(model.R_assoc[o, a, a])) > RAY_NONLINEARITY:
                    return True
    return False


@inlined
def pairs_of(model, obs, landmarks):
    """What ``update.map_cost_into`` reads of the pairs (obs, landmarks): their measurements z (p, 3),
    the inverse of the noise association judges them by (p, 3, 3), their landmarks and cameras."""
    p = obs.size
    z, R_inverse = np.empty((p, 3)), np.empty((p, 3, 3))
    landmark_xyz, pair_camera = np.empty((p, model.landmark_xyz.shape[1])), np.empty(p, np.int64)
    for i in range(p):
        o = obs[i]
        for a in range(3):
            z[i, a] = model.z[o, a]
            for b in range(3):
                R_inverse[i, a, b] = model.R_assoc_inverse[o, a, b]
        pair_camera[i] = model.obs_camera[o]
        for a in range(landmark_xyz.shape[1]):
            landmark_xyz[i, a] = model.landmark_xyz[landmarks[i], a]
    return z, R_inverse, landmark_xyz, pair_camera


@jit
def map_cost(model, state, x, P, obs, landmarks):
    """``beam_chain.map_cost``: the MAP cost of ``state`` as the posterior of (x, P) with the
    pairs (obs, landmarks), under the noise association judges them by."""
    z, R_inverse, landmark_xyz, pair_camera = pairs_of(model, obs, landmarks)
    return restart_cost(model, x, P, z, R_inverse, landmark_xyz, pair_camera, state)


@jit
def checked(model, iterations, x, P, root_x, root_P, pairs, first, count):
    """``beam_chain.checked``: (x, P), the end of a chain of updates from (root_x, root_P) with
    the pairs[first:count] (rows of (observation, landmark)), or, where its MAP cost as their
    posterior is beyond the 99.9% chi^2 quantile of their degrees of freedom, the stacked update of
    the root with them where its MAP cost is lower. The caller checks that the root is wide and
    that the chain has two pairs or more."""
    p = count - first
    obs, landmarks = np.empty(p, np.int64), np.empty(p, np.int64)
    dof = 0
    for i in range(p):
        obs[i], landmarks[i] = pairs[first + i, 0], pairs[first + i, 1]
        dof += model.obs_dof[obs[i]]
    z, R_inverse, landmark_xyz, pair_camera = pairs_of(model, obs, landmarks)
    cost = restart_cost(model, root_x, root_P, z, R_inverse, landmark_xyz, pair_camera, x)
    if cost <= model.nis_bound[dof]:
        return x, P
    z_hat, H = observe_pairs(root_x, landmark_xyz, pair_camera, model.camera_R, model.camera_t, model.camera_K)
    try:
        again = updated_at(model, iterations, root_x, root_P, obs, landmarks, z_hat, H, model.R_assoc, model.R_assoc_inverse,
                        np.empty(0), FALSE, 0.0)
    except Exception:  # Gauss-Newton from a wide prior run off (behind a camera): the chain's
        return x, P
    if restart_cost(model, root_x, root_P, z, R_inverse, landmark_xyz, pair_camera, again[0]) < cost:
        return again[0], again[1]
    return x, P


# ``checked`` as the beam calls it: by its address, compiled once in its own module, where linked it
# was optimized and generated again in ``explain_from``'s module and ``run_poses``' (``_jit.called``);
# and only where a run first reaches it (``deferred``): at the default noise no chain is wide enough
# to check (none on the 3,000-pose world), so a first compile left 1.7 s of CPU to it for
# nothing; a compile's second process compiles it for the runs after (``warmup.deferred_kernels``)
checked_at = called(checked, deferred=True)
