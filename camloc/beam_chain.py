"""A chain of a pose's pair updates checked against the pose's prior, in the numpy beam
(docs/beam.md, "Chained pairs under a wide prior"; the compiled twin is
``camloc.kernels.beam_chain``).

The beam conditions a partial explanation's pairs one after another (a branched pair on the
state its earlier pairs left, a round of clear pairs on the round before). The chain rule that
makes this the posterior of the pose's prior with all of them holds for a linear model; a pixel
pair linearized at a state still decimetres off carries that linearization into its posterior's
covariance, and the chain can end millimetre-sure of a wrong state (w1 of docs/performance.md,
2026-12-06: three true pairs chained 0.108 m off at a sigma of 0.015 m, stacked from the prior
0.011 m off). So, where the pose's prior is wide for the rays (``RAY_NONLINEARITY``), the state of
a chain of two pairs or more since that prior is tested as the posterior the model defines: its MAP
cost from the prior with all the pairs, against the 99.9% chi^2 quantile of their degrees of
freedom; where it fails, the stacked update of the prior with them replaces it where its MAP cost
is lower.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from camloc import ekf, measurement
from camloc.constants import RAY_NONLINEARITY


def ray_spread(H: np.ndarray, P: np.ndarray, focal: np.ndarray, sigma: np.ndarray) -> float:
    """The largest (H P H')_aa / (f_a sigma_a) over the u and v rows of the options H (g, 3, n)
    of pixel observations, f (g, 2) their cameras' focal lengths and sigma (g, 2) their noise's
    standard deviations (0 without options). A pinhole's second-order term over one standard
    deviation of the prior (position along and across the ray, or a turn) is about the first-order
    spread squared over f, (H P H')_aa / f pixels; at a ratio of 1 it is the noise's own size,
    and a pair's linearization at the prior no longer stands for it."""
    if H.shape[0] == 0:
        return 0.0
    rows = H[:, :2, :]
    spread = np.einsum("gan,nm,gam->ga", rows, P, rows)
    return float((spread / (focal * sigma)).max())


def wide_for_rays(ctx, P: np.ndarray, obs: np.ndarray, options: list) -> bool:
    """Whether the prior of covariance P is wide for the pose's rays (``ray_spread`` of each pixel
    observation's cheapest gated option, the pair that stands for its ray, beyond
    ``RAY_NONLINEARITY``): where it is not, a chain of pairs from it equals their stacked update
    to well within the noise, and is not checked. Depth and disparity pairs pin the position with
    one pair and are not tested. (One option per ray, not its whole pool: the compiled beam asks
    this of every hypothesis at every pose.)"""
    rays = np.flatnonzero(measurement.is_ray(ctx.dataset.obs_kind[obs]))
    H, focal, sigma = [], [], []
    for i in rays:
        costs = options[i].costs
        if not np.isfinite(costs).any():
            continue
        o = int(obs[i])
        H.append(options[i].H[int(np.argmin(costs))])     # the first of equal ones; inf never the least here
        focal.append(ctx.cameras[int(ctx.obs_sensor[o])].intrinsics[:2])
        sigma.append(np.sqrt(np.diagonal(ctx.association_cov[o])[:2]))
    if not H:
        return False
    return ray_spread(np.array(H), P, np.array(focal, dtype=float), np.array(sigma)) > RAY_NONLINEARITY


def checked(ctx, x: np.ndarray, P: np.ndarray, root, pairs: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(x, P), the end of a chain of updates from ``root`` (a Hypothesis: the pose's prior, or
    None where it is not wide) with the pose's ``pairs`` (root's own first), or, where the chain
    has two pairs or more since root and x's MAP cost as the posterior of root with all of them is
    beyond the 99.9% chi^2 quantile of their degrees of freedom, the stacked update of root with
    them where its MAP cost is lower."""
    if root is None or len(pairs) - len(root.pairs) < 2:
        return x, P
    since = np.array(pairs[len(root.pairs):], dtype=np.int64)
    obs, landmarks = since[:, 0], since[:, 1]
    stacked = ctx.stacked
    cost = map_cost(stacked, x, root, obs, landmarks)
    if cost <= stacked.nis_bound(int(ctx.obs_dof[obs].sum())):
        return x, P
    try:
        again = ctx.updated(root.x, root.P, obs, landmarks, for_association=True)
    except ekf.NUMERICAL_FAILURES:  # Gauss-Newton from a wide prior run off (behind a camera): the chain's
        return x, P
    if map_cost(stacked, again.state, root, obs, landmarks) < cost:
        return again.state, again.cov
    return x, P


def map_cost(stacked, state: np.ndarray, root, obs: np.ndarray, landmarks: np.ndarray) -> float:
    """The MAP cost of ``state`` as the posterior of root's (x, P) with the pairs, under the noise
    association judges them by (``ekf.posterior_cost``)."""
    measure = stacked.measurement_function(obs, landmarks)[1]
    return ekf.posterior_cost(state, root.x, root.P, stacked.dataset.obs_z[obs].reshape(-1), stacked.association_cov[obs], measure,
                              stacked.filter.difference, stacked.association_info[obs])


def root_if_wide(ctx, root, obs: np.ndarray, options: list) -> Optional[object]:
    """root where its prior is wide for the pose's rays (``wide_for_rays``), else None."""
    return root if wide_for_rays(ctx, root.P, obs, options) else None
