"""The numpy localizer's tag orientations: which observation is a tag's orientation, and how it
joins its position's pair in the update (``TagOrientations``); the model is ``camloc.tags``'."""

from __future__ import annotations

import numpy as np

from camloc import association, geometry
from camloc.tags import aligned
from camloc.tails import chi2_quantile

# A tag's orientation vetoes its position's pair beyond this d^2 (3 dof, 99.9%): a wrong tag's is
# off by tens of degrees, far beyond it, where the association's 99% gate would also refuse 1% of
# right ones (and their positions with them).
VETO_GATE = float(chi2_quantile(3, 0.001))


class TagOrientations:
    """The tags' orientation observations of a dataset (``measurement.TAG_ROTATION``), each the
    partner of its position's (``Dataset.obs_partner``): association pairs the positions, and a
    pair's tag orientation joins it in the update (``joined``). False when the dataset has none."""

    def __init__(self, dataset):
        self.dataset = dataset
        riders = np.flatnonzero(dataset.obs_partner >= 0)
        self.rotation_of = dict(zip(dataset.obs_partner[riders].tolist(), riders.tolist()))  # position -> orientation

    def __bool__(self) -> bool:
        return bool(self.rotation_of)

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
