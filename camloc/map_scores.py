"""How good an estimated map is, against the true map (``camloc eval RUN_DIR --true-map DATASET``).

A run's map (``map.csv``: a row per landmark, ``mapped`` or ``added``) is scored with what a
simulated world knows and a run cannot: the true position of every landmark and, in
``associations.csv``'s ``true_landmark`` column, which landmark each observation truly is (the
id written in the file: a withheld landmark's observations keep their true id; clutter's ids are
absent from the true map).

- A **mapped** landmark is its own id's true landmark; it was **moved** when the map the run was
  given (the run's map, ``RunResult.map_landmark_xyz``) put it elsewhere than the truth.
- An **added** landmark *stands for* the true landmark most of the observations assigned to it
  (``associations.csv``'s ``landmark`` column) truly are, all clutter counting as one kind
  ("clutter"), a tie going to a true landmark (the smallest id) over clutter; an added landmark no
  observation is assigned to stands for its own id when the true map has it (the smoother's added
  landmarks keep the file's id), for nothing otherwise.
- **Added twice**: two or more added landmarks that stand for one true landmark (each beyond the
  first counts); an added landmark standing for a landmark the given map has is a copy of a mapped one.
- **Clutter made into landmarks**: added landmarks that stand for clutter, and the clutter
  observations assigned to them as a share of every clutter observation.
- **Never added**: true landmarks the given map lacks, observed at least ``MIN_OBSERVATIONS_TO_ADD``
  times, that no added landmark stands for.
- **Orientation** (a map of tags, where the true map has their orientations): the angle between
  each estimated tag's orientation and its true landmark's (mapped, moved and added as above), and
  the NEES of the world rotation error ``e = Log(R_true R_est^T)`` under its covariance.

Pure numpy: no I/O; ``map_score`` returns a JSON-serializable dict (undefined values are None).
"""

from __future__ import annotations

import numpy as np

# A landmark the map lacks is expected to be added once it is observed this many times: one
# observation of a landmark cannot be told from clutter.
MIN_OBSERVATIONS_TO_ADD = 2
# A mapped landmark whose given position is this far (m) or more from the truth was moved; a g2o
# file's positions read back exactly, so any real displacement is far above it.
MOVED_FROM_M = 1e-6
CLUTTER = -1  # the "true landmark" of a clutter observation
NOTHING = -2  # what an added landmark without observations nor a true id stands for


def map_score(estimated, *, given_ids: np.ndarray, given_xyz: np.ndarray, true_ids: np.ndarray, true_xyz: np.ndarray,
              obs_landmark: np.ndarray, obs_true: np.ndarray, true_quat_xyzw: np.ndarray | None = None) -> dict:
    """The score of an estimated map (see the module for the definitions).

    Parameters
    ----------
    estimated : the run's map: ``ids`` (K,), ``xyz`` (K, 3), ``cov`` (K, 3, 3), ``added`` (K,) bool
        (``camloc.results.LandmarkMap``).
    given_ids, given_xyz : (G,), (G, 3) the map the run was given; ids the estimated map has as
        added are left out of it (a run may list its added landmarks in its map).
    true_ids, true_xyz : (T,), (T, 3) the true, complete map.
    obs_landmark : (O,) the landmark each observation was assigned (-1: none).
    obs_true : (O,) each observation's id in the file (its true landmark, or clutter's id).
    true_quat_xyzw : (T, 4) the true map's orientations (NaN: not a tag), None: not known.

    Returns
    -------
    dict with ``mapped``, ``moved``, ``added`` (position errors), ``added_twice``, ``clutter``
    and ``never_added`` (counts), ``orientation`` (tags' orientation errors, None without tags
    in the estimated map or orientations in the true one), keys as docs/json.md lists them.
    """
    ids, xyz, cov, added = (np.asarray(a) for a in (estimated.ids, estimated.xyz, estimated.cov, estimated.added))
    given = ~np.isin(given_ids, ids[added])
    given_ids, given_xyz = np.asarray(given_ids)[given], np.asarray(given_xyz)[given]
    truth = _Lookup(true_ids, true_xyz)
    category = np.where(truth.has(obs_true), obs_true, CLUTTER)
    stands = stands_for(ids[added], obs_landmark, category, truth)
    offset = _moved_offsets(ids, ~added, truth, _Lookup(given_ids, given_xyz))
    return {
        "mapped": _mapped(ids, xyz, cov, ~added, truth),
        "moved": _moved(ids, xyz, cov, offset, truth),
        "added": _added(xyz[added], cov[added], stands, truth),
        "added_twice": _added_twice(stands, given_ids),
        "clutter": _clutter(ids[added], stands, obs_landmark, category),
        "never_added": _never_added(stands, category, given_ids),
        "orientation": _orientations(estimated, stands, truth, true_quat_xyzw, offset >= MOVED_FROM_M),
    }


class _Lookup:
    """Positions (n, 3) by id (n,)."""

    def __init__(self, ids: np.ndarray, xyz: np.ndarray):
        self.ids = np.asarray(ids, dtype=np.int64)
        self.xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
        self._order = np.argsort(self.ids, kind="stable")

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """(m,) the row of each id, -1 where it has none."""
        ids = np.asarray(ids, dtype=np.int64)
        if not len(self.ids):
            return np.full(ids.shape, -1)
        at = np.clip(np.searchsorted(self.ids[self._order], ids), 0, len(self.ids) - 1)
        return np.where(self.ids[self._order][at] == ids, self._order[at], -1)

    def has(self, ids: np.ndarray) -> np.ndarray:
        return self.rows(ids) >= 0


def stands_for(added_ids: np.ndarray, obs_landmark: np.ndarray, category: np.ndarray, truth: _Lookup) -> np.ndarray:
    """(A,) the true id each added landmark stands for, ``CLUTTER`` or ``NOTHING`` (see the module).

    ``category`` (O,) is each observation's true id, or ``CLUTTER``.
    """
    out = np.where(truth.has(added_ids), added_ids, NOTHING).astype(np.int64)
    mine = np.isin(obs_landmark, added_ids)
    if not mine.any():
        return out
    pairs, counts = np.unique(np.stack([obs_landmark[mine], category[mine]], axis=1), axis=0, return_counts=True)
    # Per landmark, the most frequent category; of equally frequent ones a true landmark over
    # clutter, the smallest true id first: the last of the order landmark, count, preference.
    preference = np.where(pairs[:, 1] >= 0, -pairs[:, 1], np.iinfo(np.int64).min)
    order = np.lexsort((preference, counts, pairs[:, 0]))
    last = np.r_[pairs[order, 0][1:] != pairs[order, 0][:-1], True]
    winners = pairs[order][last]
    out[_Lookup(added_ids, np.zeros((len(added_ids), 3))).rows(winners[:, 0])] = winners[:, 1]
    return out


def _errors(xyz: np.ndarray, cov: np.ndarray, true_xyz: np.ndarray) -> dict:
    """``count``, ``rmse``, ``max`` of the position errors (m), ``nees``: mean ``e^T C^-1 e`` over the
    landmarks with a positive definite covariance (3 where consistent; None when none). A point of
    a planar robot's floor (its z pinned: zero variance and no correlation in z, on the floor as
    its truth is) is scored on its x and y, that 2-dof NEES times 3/2 (so 3 where consistent too)."""
    error = xyz - true_xyz
    distance = np.linalg.norm(error, axis=1)
    definite, nees = _nees(error, cov)
    floor = ~definite & np.all(cov[:, 2, :] == 0.0, axis=1) & (error[:, 2] == 0.0) if len(cov) else definite
    floor &= np.linalg.eigvalsh(cov[:, :2, :2])[:, 0] > 0.0 if len(cov) else floor
    if np.any(floor):
        planar = np.einsum("ni,ni->n", error[floor, :2], np.linalg.solve(cov[floor, :2, :2], error[floor, :2][:, :, None])[:, :, 0])
        nees = np.concatenate([nees, 1.5 * planar])
    return {
        "count": int(len(distance)),
        "rmse": _number(np.sqrt(np.mean(distance**2))) if len(distance) else None,
        "max": _number(distance.max()) if len(distance) else None,
        "nees": _number(nees.mean()) if len(nees) else None,
    }


def _mapped(ids, xyz, cov, mapped, truth: _Lookup) -> dict:
    """Mapped landmarks against their own id's truth; ``unknown``: ids the true map lacks."""
    rows = truth.rows(ids)
    scored = mapped & (rows >= 0)
    return {**_errors(xyz[scored], cov[scored], truth.xyz[rows[scored]]), "unknown": int(np.count_nonzero(mapped & (rows < 0)))}


def _moved_offsets(ids, mapped, truth: _Lookup, given: _Lookup) -> np.ndarray:
    """(K,) how far the given map put each mapped landmark from the truth (0: not known)."""
    rows, given_rows = truth.rows(ids), given.rows(ids)
    both = mapped & (rows >= 0) & (given_rows >= 0)
    offset = np.zeros(len(ids))
    offset[both] = np.linalg.norm(given.xyz[given_rows[both]] - truth.xyz[rows[both]], axis=1)
    return offset


def _moved(ids, xyz, cov, offset: np.ndarray, truth: _Lookup) -> dict:
    """Mapped landmarks the given map put away from the truth (``offset``: ``_moved_offsets``):
    their error after the run, and ``given_rmse``, how far the given map had them."""
    rows = truth.rows(ids)
    moved = offset >= MOVED_FROM_M
    report = _errors(xyz[moved], cov[moved], truth.xyz[rows[moved]])
    report["given_rmse"] = _number(np.sqrt(np.mean(offset[moved] ** 2))) if moved.any() else None
    return report


def _added(xyz, cov, stands: np.ndarray, truth: _Lookup) -> dict:
    """Added landmarks against the true landmark each stands for; ``unknown``: those standing for
    clutter or nothing."""
    real = stands >= 0
    return {**_errors(xyz[real], cov[real], truth.xyz[truth.rows(stands[real])]), "unknown": int(np.count_nonzero(~real))}


def _added_twice(stands: np.ndarray, given_ids: np.ndarray) -> dict:
    """``landmarks``: added landmarks beyond the first that stand for one true landmark the given
    map lacks; ``true_landmarks``: how many such true landmarks; ``share``: landmarks / added
    landmarks; ``mapped_copies``: added landmarks standing for a landmark the given map has."""
    real = stands[stands >= 0]
    copies = np.isin(real, given_ids)
    _, counts = np.unique(real[~copies], return_counts=True)
    extra = int(np.sum(counts - 1))
    return {"landmarks": extra, "true_landmarks": int(np.count_nonzero(counts > 1)),
            "share": _ratio(extra, len(stands)), "mapped_copies": int(np.count_nonzero(copies))}


def _clutter(added_ids, stands: np.ndarray, obs_landmark: np.ndarray, category: np.ndarray) -> dict:
    """``landmarks``: added landmarks standing for clutter; ``observations``: the clutter
    observations assigned to them; ``clutter_observations``: every clutter observation; ``share``:
    observations / clutter_observations."""
    made = np.asarray(added_ids)[stands == CLUTTER]
    clutter = category == CLUTTER
    involved = int(np.count_nonzero(clutter & np.isin(obs_landmark, made)))
    total = int(np.count_nonzero(clutter))
    return {"landmarks": int(len(made)), "observations": involved, "clutter_observations": total,
            "share": _ratio(involved, total)}


def _never_added(stands: np.ndarray, category: np.ndarray, given_ids: np.ndarray) -> dict:
    """``count``: true landmarks the given map lacks, observed at least ``MIN_OBSERVATIONS_TO_ADD``
    times, that no added landmark stands for; ``of``: how many such landmarks were observed that
    often; ``share``: count / of."""
    seen, times = np.unique(category[category >= 0], return_counts=True)
    candidates = seen[(times >= MIN_OBSERVATIONS_TO_ADD) & ~np.isin(seen, given_ids)]
    missing = int(np.count_nonzero(~np.isin(candidates, stands)))
    return {"count": missing, "of": int(len(candidates)), "share": _ratio(missing, len(candidates))}


def _orientations(estimated, stands: np.ndarray, truth: _Lookup, true_quat: np.ndarray | None, moved: np.ndarray) -> dict | None:
    """The tags' orientation errors (``mapped``, ``moved``, ``added``: ``_angle_errors``) of the
    estimated map against the true one's, None where either has no orientation."""
    rotvec = getattr(estimated, "orientation", None)
    if rotvec is None or true_quat is None or not np.any(np.isfinite(np.asarray(true_quat, dtype=float)[:, 0])):
        return None
    from camloc import geometry

    ids, added = np.asarray(estimated.ids), np.asarray(estimated.added, dtype=bool)
    rows = truth.rows(ids)
    rows[added] = np.where(stands >= 0, truth.rows(np.maximum(stands, 0)), -1)
    true_quat = np.asarray(true_quat, dtype=float)
    scored = (rows >= 0) & np.isfinite(rotvec[:, 0])
    scored[scored] &= np.isfinite(true_quat[rows[scored], 0])
    error = np.full((len(ids), 3), np.nan)
    if np.any(scored):
        R_true = geometry.quat_to_matrix(true_quat[rows[scored]])
        error[scored] = geometry.so3_log(R_true @ np.swapaxes(geometry.so3_exp(rotvec[scored]), -1, -2))
    cov = np.asarray(estimated.orientation_cov, dtype=float)
    return {name: _angle_errors(error[mask & scored], cov[mask & scored])
            for name, mask in (("mapped", ~added), ("moved", moved & ~added), ("added", added))}


def _angle_errors(error: np.ndarray, cov: np.ndarray) -> dict:
    """``count``, ``rmse_deg``, ``max_deg`` of rotation errors (M, 3) (world rotation vectors), and
    ``nees``: mean ``e^T C^-1 e`` over those with a positive definite covariance (3 if consistent)."""
    angle = np.degrees(np.linalg.norm(error, axis=1))
    _, nees = _nees(error, cov)
    return {"count": int(len(angle)), "rmse_deg": _number(np.sqrt(np.mean(angle**2))) if len(angle) else None,
            "max_deg": _number(angle.max()) if len(angle) else None, "nees": _number(nees.mean()) if len(nees) else None}


def _nees(error: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which errors (M, 3) have a positive definite covariance (M, 3, 3) (M,), and their
    ``e^T C^-1 e``."""
    definite = np.linalg.eigvalsh(cov)[:, 0] > 0.0 if len(cov) else np.zeros(0, dtype=bool)
    return definite, np.einsum("ni,ni->n", error[definite], np.linalg.solve(cov[definite], error[definite][:, :, None])[:, :, 0])


def _number(value: float) -> float | None:
    """A Python float, or None for NaN/inf (JSON has no NaN)."""
    value = float(value)
    return value if np.isfinite(value) else None


def _ratio(numerator: float, denominator: float) -> float | None:
    return _number(numerator / denominator) if denominator > 0 else None
