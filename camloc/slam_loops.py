"""Closing a loop the filter has grown too sure to see, for the mapping localizer with no map
(``camloc.slam_run``).

Where the robot comes back to landmarks it mapped long before, their observations should pair
with them (a loop closure). Without a map the association makes wrong pairs now and then, and a
wrong pair moves the robot and the landmarks it sees next, with the covariance saying nothing of
it: coming back, the old landmarks are then predicted by more than their gate allows (measured:
squared Mahalanobis distances of 20-2,000 against a gate of 11, where the true association's
are 1.3 at the median), their observations fit no landmark, and each becomes a new one: the map
holds that place twice, and the loop is never closed. Landmarks added twice with no map were
almost all of this kind (docs/performance.md, 2026-12-04, "Landmarks added twice").

What is tried here (``LoopClosures._closed_loop``): the hypothesis of a **slip**, the robot and the
landmarks it saw lately turned and shifted together against the landmarks it saw long ago (the
slip's covariance ``SLIP_SIGMA_M`` and ``SLIP_SIGMA_RAD`` per axis added to the filter's,
``slam.slip_coefficients``), under which the pose's observations are associated again (JCBB, the
tentative landmarks left out: a landmark entered from one observation of an old one is the copy
the slip would explain away). It is taken only where it pairs at least ``LOOP_PAIRS`` old
landmarks, each unambiguously (``slam_association.unambiguous``): jointly compatible pairs with
three old landmarks fix the slip and check it, which a chance fit in a dense map rarely passes.
The filter then keeps the slip's covariance (the robot was less sure than it said) and updates
with those pairs: the loop is closed.

Pure computation: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np

from camloc import slam
from camloc.dataset import LANDMARK_MARKER
from camloc.slam_association import AMBIGUITY_MARGIN, jcbb, unambiguous

# A landmark is old when unseen for this many poses: where the robot sees it again it has been
# away (the landmarks seen since move with the robot under a slip).
LOOP_GAP = 20
# The slip's standard deviation per axis: the shift (metres) and the turn (radians).
SLIP_SIGMA_M = 0.5
SLIP_SIGMA_RAD = 0.05
# Old landmarks a slip must pair to be taken.
LOOP_PAIRS = 3


class LoopClosures:
    """A mix-in of ``slam_run.MappingLocalizer`` (its ``x``, ``P``, ``table``, ``state_landmark``,
    ``dataset`` and the association of ``slam_association.PoseAssociation``)."""

    def _closed_loop(self, k: int, obs: np.ndarray, pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """The pose's pairs under a slip where they close a loop (``P`` then holds the slip's
        covariance), else ``pairs`` unchanged."""
        table = self.table
        if obs.size < LOOP_PAIRS or not self.state_landmark:
            return pairs
        landmarks = np.array(self.state_landmark, np.int64)
        position = self._position_rows()
        old = position & ~table.tentative[landmarks] & (table.last_seen[landmarks] < k - LOOP_GAP)
        rows = [int(table.state_row[lm]) for _, lm in pairs]
        paired_old = sum(1 for row in rows if row >= 0 and old[row])
        reach = self.reach + 3.0 * SLIP_SIGMA_M
        near = np.linalg.norm(self.x.L[:, :2] - self.x.t[:2], axis=1) <= reach
        if paired_old >= LOOP_PAIRS or np.count_nonzero(old & near) < LOOP_PAIRS:
            return pairs
        moving = ~old  # (tags' orientation rows follow their centres below)
        if self.x.orientation is not None:
            moving = self._orientations_follow(landmarks, moving)
        markers = table.kind[landmarks] == LANDMARK_MARKER
        G = slam.slip_coefficients(self.x, moving, markers)
        P_slip = self.P + G @ self._slip_cov() @ G.T
        chosen = self._slipped_association(obs, landmarks[position & ~table.tentative[landmarks]], P_slip, reach)
        closing = [c for c in chosen if table.state_row[c.landmark] >= 0 and old[int(table.state_row[c.landmark])]]
        if len(closing) < LOOP_PAIRS:
            return pairs
        self.P = P_slip
        return [(c.obs, c.landmark) for c in chosen]

    def _slip_cov(self) -> np.ndarray:
        """The slip's covariance (6, 6) on (d_t, d_theta): a planar robot's in the plane and about z."""
        variances = np.r_[np.full(3, SLIP_SIGMA_M**2), np.full(3, SLIP_SIGMA_RAD**2)]
        if self.dataset.planar:
            variances[[2, 3, 4]] = 0.0
        return np.diag(variances)

    def _slipped_association(self, obs: np.ndarray, confirmed: np.ndarray, P_slip: np.ndarray, reach: float) -> list:
        """The unambiguous pairs of JCBB's set among the ``confirmed`` landmarks within ``reach``
        of the robot, judged under the slip's covariance."""
        offset = self.table.xyz[confirmed] - self.x.t
        nearby = confirmed[np.einsum("ij,ij->i", offset, offset) <= reach * reach]
        P = self.P
        self.P = P_slip  # the candidates' costs and gates read it
        try:
            candidates = self._candidates(obs, nearby, wide_view=True)
        finally:
            self.P = P
        if not any(candidates):
            return []
        chosen = jcbb(P_slip, candidates, self.config.gate)
        return unambiguous(P_slip, candidates, chosen, self.config.gate, AMBIGUITY_MARGIN)

    def _orientations_follow(self, landmarks: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """``moving`` with each tag's orientation row as its centre's row."""
        moving = moving.copy()
        for row in np.flatnonzero(self.x.orientation).tolist():
            moving[row] = moving[int(self.table.state_row[landmarks[row]])]
        return moving
