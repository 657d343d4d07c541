"""How well could any association pair pixel-only observations? (issue 35's precision target)

An association that knew the robot's **true pose** would still have to tell apart the landmarks
whose pixels lie within the noise of an observation. Given the true poses, the observations of
different poses are independent, so what such an association reaches bounds what a method that
must also estimate the pose can reach. Per world of ``pixel_worlds.WORLDS`` it prints:

- ``pose``: the true pose, every landmark in front of the camera a candidate; per pose and camera
  the one-to-one assignment of least total cost (squared Mahalanobis distance of the pixels, the
  library's null cost for an observation left unpaired: ``observation_space.observation_noise``);
- ``window``: the same within the view the localizer assumes for the file
  (``observation_space.candidate_range``: its depth and angle);
- ``view``: the same among the landmarks the camera really sees (the simulator reports every
  landmark in its range and cone, so these are the true landmarks of the pose's detections);
- ``ranked``: with the true pose and view, each observation's posterior over the seen landmarks
  and clutter (independent, not one-to-one), its pairs ranked by their posterior: the precision
  at recall 0.80, 0.90 and 0.95 (the best a method could do by leaving its least sure pairs out);
- with ``--beam``, the default association's own precision and recall on the same world.

    nice python benchmarks/pixel_ceiling.py s3d2c10,grid1,aerial1,dense,pix2c20,s3d1,aerial2c10,mono100 --poses 200 --seeds 1,2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

sys.path.insert(0, str(Path(__file__).resolve().parent))

import camloc  # noqa: E402
from camloc import measurement, models  # noqa: E402
from camloc.metrics import evaluate  # noqa: E402
from camloc.observation_space import candidate_range, observation_noise  # noqa: E402
from pixel_worlds import world  # noqa: E402

RECALLS = (0.80, 0.90, 0.95)


def pixel_costs(dataset, noise, k: int, camera_id: int, obs: np.ndarray, rows: np.ndarray, window=None):
    """(observations, candidates) squared Mahalanobis distances of the pixels at the true pose k,
    and the candidates kept (in front of the camera, within ``window`` = (min, max depth, max angle[, max
    distance from the camera]))."""
    camera = dataset.cameras[camera_id]
    _, p_camera = models.camera_points(dataset.T_world_truth[k], camera.T_robot_camera, dataset.landmark_xyz[rows])
    keep = p_camera[:, 2] > measurement.MIN_POINT_DEPTH
    if window is not None:
        distance = np.linalg.norm(p_camera, axis=1)
        angle = np.arccos(np.clip(p_camera[:, 2] / np.maximum(distance, 1e-12), -1.0, 1.0))
        keep &= (p_camera[:, 2] >= window[0]) & (p_camera[:, 2] <= window[1]) & (angle <= window[2])
        if len(window) > 3:
            keep &= distance <= window[3]
    rows, p_camera = rows[keep], p_camera[keep]
    uv = measurement.project(p_camera, (camera.fx, camera.fy, camera.cx, camera.cy), measurement.PIXEL)[:, :2]
    costs = np.empty((obs.size, rows.size))
    for i, o in enumerate(obs):
        d = uv - dataset.obs_z[o, :2]
        costs[i] = np.einsum("mi,mi->m", d, np.linalg.solve(noise.cov[o][:2, :2], d.T).T)
    return costs, rows


def poses_and_cameras(dataset):
    """Each (pose, camera, observation indices) with observations."""
    order = np.lexsort((dataset.obs_camera, dataset.obs_pose_index))
    keys = dataset.obs_pose_index[order] * 1_000_003 + dataset.obs_camera[order]
    for group in np.split(order, np.flatnonzero(np.diff(keys)) + 1):
        if group.size:
            yield int(dataset.obs_pose_index[group[0]]), int(dataset.obs_camera[group[0]]), group


def seen_rows(dataset, obs: np.ndarray) -> np.ndarray:
    """The map rows of the landmarks behind ``obs`` (clutter has none)."""
    ids = dataset.obs_true_landmark[obs]
    rows = np.searchsorted(dataset.landmark_ids, ids)
    rows = np.minimum(rows, dataset.landmark_ids.size - 1)
    return np.unique(rows[dataset.landmark_ids[rows] == ids])


def assigned(dataset, candidates: str, window=None) -> tuple[float, float]:
    """Precision and recall of the per-pose least-cost one-to-one assignment at the true pose."""
    noise = observation_noise(dataset, camloc.LocalizerConfig())
    right = wrong = 0
    every = np.argsort(dataset.landmark_ids)
    for k, camera_id, obs in poses_and_cameras(dataset):
        rows = seen_rows(dataset, obs) if candidates == "view" else every
        costs, rows = pixel_costs(dataset, noise, k, camera_id, obs, rows, window)
        unpaired = np.full((obs.size, obs.size), np.inf)
        np.fill_diagonal(unpaired, noise.null_cost[obs])
        r, c = linear_sum_assignment(np.hstack([costs, np.where(np.isfinite(unpaired), unpaired, 1e12)]))
        paired = c < rows.size
        hits = dataset.landmark_ids[rows[c[paired]]] == dataset.obs_true_landmark[obs[r[paired]]]
        right, wrong = right + int(hits.sum()), wrong + int((~hits).sum())
    real = int(np.isin(dataset.obs_true_landmark, dataset.landmark_ids).sum())
    return right / max(right + wrong, 1), right / max(real, 1)


def ranked(dataset) -> dict[float, float]:
    """Precision at each of ``RECALLS`` of the true pose and view's posterior-ranked pairs."""
    noise = observation_noise(dataset, camloc.LocalizerConfig())
    posterior, right = [], []
    for k, camera_id, obs in poses_and_cameras(dataset):
        rows = seen_rows(dataset, obs)
        if rows.size == 0:
            continue
        costs, rows = pixel_costs(dataset, noise, k, camera_id, obs, rows)
        options = np.hstack([costs, noise.null_cost[obs][:, None]])
        weights = np.exp(-(options - options.min(axis=1, keepdims=True)) / 2.0)
        weights /= weights.sum(axis=1, keepdims=True)
        best = np.argmax(weights[:, :-1], axis=1)
        posterior.extend(weights[np.arange(obs.size), best])
        right.extend(dataset.landmark_ids[rows[best]] == dataset.obs_true_landmark[obs])
    right = np.asarray(right)[np.argsort(-np.asarray(posterior), kind="stable")]
    real = int(np.isin(dataset.obs_true_landmark, dataset.landmark_ids).sum())
    found = np.cumsum(right)
    out = {}
    for recall in RECALLS:
        n = int(np.searchsorted(found, recall * real))
        out[recall] = float(right[:n + 1].mean()) if n < right.size else float("nan")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("worlds", help="comma-separated names of pixel_worlds.WORLDS")
    parser.add_argument("--poses", type=int, default=200)
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--beam", action="store_true", help="also run the default association (compiled engine)")
    args = parser.parse_args()
    for name in args.worlds.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            dataset = world(name, args.poses, seed)
            window = candidate_range(dataset, camloc.LocalizerConfig())
            line = f"{name:10s} seed {seed}"
            for label, candidates, w in (("pose", "all", None), ("window", "all", window), ("view", "view", None)):
                precision, recall = assigned(dataset, candidates, w)
                line += f" | {label} {precision:.4f} / {recall:.3f}"
            at = ranked(dataset)
            line += " | ranked " + ", ".join(f"{at[r]:.4f} @ {r:.2f}" for r in RECALLS)
            if args.beam:
                scores = evaluate(camloc.localize(dataset, camloc.LocalizerConfig(), engine="compiled", parallel=False))
                line += f" | beam {scores['association']['precision']:.4f} / {scores['association']['recall']:.3f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
