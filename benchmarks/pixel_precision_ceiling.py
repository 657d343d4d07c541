"""How much precision is possible on pixel-only worlds, per world kind? (issue 35, "precision at least 0.99")

At the **true** pose (covariance zero, the map exact) a pixel observation's cost against a
landmark is its squared Mahalanobis distance d^2 (S = R: no ``ln det`` term), the same cost the
beam's pairs reduce to once the pose is known. Two landmarks near one ray can be as close, in the
observation's own noise, as each other: no association, however it searches, tells them apart
from that pose's pixels. Per world of ``pixel_worlds.WORLDS`` this prints, over every (pose,
camera) of the run:

- ``notbest``: of the observations of a mapped landmark, the share whose true landmark is not the
  cheapest candidate of the run's window (``depth`` below) at the true pose (``out``: the share
  whose true landmark is outside that window);
- ``close``: the share whose cheapest other candidate is within ``--margin`` (4: a likelihood
  ratio of e^2 = 7.4) of the true one's cost, i.e. not clearly told apart;
- ``depth``: precision / recall of the per-pose, per-camera one-to-one assignment of least total
  cost at the true pose with a null option per observation at the library's null cost (what the
  true pose alone gives, all at once; ``scipy.optimize.linear_sum_assignment``), among the
  candidates of the window the run held before 2026-12-05: in front of the camera, depth up to
  1.1 times the simulator's range (the reach the run learns: 2.00-2.10 m where the cameras see
  2 m) or the guess, whichever is nearer, the widest ray + 10 deg;
- ``ball``: the same with the candidates' distance from the camera held to 1.1 times the range
  too, as the run holds them now (``ViewOptions.max_distance``);
- ``view``: the same among only the landmarks the camera really sees (the simulator's range and
  cone: a camera that knows exactly what it detects, the miss term's knowledge made perfect);
- after each, ``rank``: its pairs ranked by their margin (the cheapest alternative of the
  observation, another landmark or none, minus the pair's cost), the precision of the surest pairs
  up to recall 0.75, 0.80, 0.90 and 0.95 (nan: that recall is not reached): what leaving the
  least sure pairs out would reach;
- with ``--beam``: the default association's precision / recall on the same world, and the
  ``depth`` and ``view`` rankings' precision at the beam's own recall.

Nothing is asserted. Clutter detections paired count as wrong pairs (as ``metrics.evaluate``).

    nice python benchmarks/pixel_precision_ceiling.py s3d2c10,grid1,aerial1,dense,pix2c20,s3d1,aerial2c10,mono100,monodense --poses 500 --seeds 1,2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

sys.path.insert(0, str(Path(__file__).resolve().parent))

import camloc  # noqa: E402
from camloc.metrics import evaluate  # noqa: E402
from camloc.observation_space import candidate_range, observation_noise  # noqa: E402
from camloc.simulate import simulation_config  # noqa: E402
from pixel_ceiling import pixel_costs, poses_and_cameras, seen_rows  # noqa: E402
from pixel_worlds import WORLDS, world  # noqa: E402

RECALLS = (0.75, 0.80, 0.90, 0.95)
LEARNED_REACH_FACTOR = 1.1  # the run holds its candidates within 1.1 times the reach it learned


def window_of(name: str, dataset, ball: bool = False) -> tuple[float, float, float, float]:
    """The run's candidate window (min depth, max depth, max angle, max distance): depth up to the
    simulator's range (what the run learns, a distance) times 1.1 or the guess, whichever is
    nearer (``localizer._with_learned_reach``); with ``ball`` the distance from the camera held to
    1.1 times the range too, as the run holds it now (else unbounded)."""
    _, guess, angle = candidate_range(dataset, camloc.LocalizerConfig())
    reach = LEARNED_REACH_FACTOR * simulation_config({**WORLDS[name], "poses": 2}).max_range
    return 0.0, min(guess, reach), angle, reach if ball else np.inf


def hungarian(costs: np.ndarray, null: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(observation positions, candidate columns, margins) of the least-cost one-to-one assignment
    with a null option per observation; a margin is the observation's cheapest alternative (another
    candidate or none) minus its pair's cost."""
    n = null.size
    unpaired = np.full((n, n), 1e12)
    np.fill_diagonal(unpaired, null)
    r, c = linear_sum_assignment(np.hstack([costs, unpaired]))
    paired = c < costs.shape[1]
    r, c = r[paired], c[paired]
    options = np.hstack([costs[r], null[r, None]])
    options[np.arange(r.size), c] = np.inf
    return r, c, options.min(axis=1) - costs[r, c]


class Pairs:
    """The least-cost assignments' pairs over a world: whether each is right, and its margin."""

    def __init__(self):
        self.hits, self.margins = [], []

    def add(self, costs: np.ndarray, null: np.ndarray, ids: np.ndarray, true_ids: np.ndarray) -> None:
        r, c, m = hungarian(costs, null)
        self.hits.extend(ids[c] == true_ids[r])
        self.margins.extend(m)

    def scores(self, real: int) -> dict:
        """precision, recall, and precision at each of RECALLS of the pairs ranked by margin."""
        hits = np.asarray(self.hits, dtype=bool)
        ranked = hits[np.argsort(-np.asarray(self.margins), kind="stable")]
        found = np.cumsum(ranked)
        at = {}
        for recall in RECALLS:
            n = int(np.searchsorted(found, recall * real))
            at[recall] = float(ranked[:n + 1].mean()) if n < ranked.size else float("nan")
        return dict(precision=float(hits.mean()) if hits.size else float("nan"), recall=float(hits.sum()) / max(real, 1),
                    at=at, ranked=ranked, found=found)


def ceiling(name: str, dataset, margin: float) -> dict:
    """``Pairs.scores`` of the true pose's assignments among the run's window (``depth``), the
    window held to the reach as a distance (``ball``) and the landmarks seen (``view``), and the
    counts of observations whose true landmark is not the cheapest / not clearly the cheapest."""
    noise = observation_noise(dataset, camloc.LocalizerConfig())
    windows = dict(depth=window_of(name, dataset), ball=window_of(name, dataset, ball=True))
    every = np.argsort(dataset.landmark_ids)
    true_ids = dataset.obs_true_landmark
    counts = dict(real=int(np.isin(true_ids, dataset.landmark_ids).sum()), notbest=0, close=0, out=0)
    pairs = {label: Pairs() for label in ("depth", "ball", "view")}
    for k, camera_id, obs in poses_and_cameras(dataset):
        null = noise.null_cost[obs]
        for label, window in windows.items():
            costs, rows = pixel_costs(dataset, noise, k, camera_id, obs, every, window)
            pairs[label].add(costs, null, dataset.landmark_ids[rows], true_ids[obs])
            if label == "depth":
                is_true = dataset.landmark_ids[rows][None, :] == true_ids[obs][:, None]
                found = is_true.any(axis=1)
                counts["out"] += int((np.isin(true_ids[obs], dataset.landmark_ids) & ~found).sum())
                true_cost = np.where(is_true, costs, 0.0).sum(axis=1)
                rival = np.where(is_true, np.inf, costs).min(axis=1, initial=np.inf)
                counts["notbest"] += int((found & (rival < true_cost)).sum())
                counts["close"] += int((found & (rival < true_cost + margin)).sum())
        seen = seen_rows(dataset, obs)
        costs, seen = pixel_costs(dataset, noise, k, camera_id, obs, seen)
        pairs["view"].add(costs, null, dataset.landmark_ids[seen], true_ids[obs])
    return dict(counts=counts, **{label: p.scores(counts["real"]) for label, p in pairs.items()})


def precision_at(scores: dict, recall: float, real: int) -> float:
    n = int(np.searchsorted(scores["found"], recall * real))
    return float(scores["ranked"][:n + 1].mean()) if n < scores["ranked"].size else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("worlds", help="comma-separated names of pixel_worlds.WORLDS")
    parser.add_argument("--poses", type=int, default=500)
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--margin", type=float, default=4.0, help="cost units within which a rival is 'close'")
    parser.add_argument("--beam", action="store_true", help="also run the default association (compiled engine)")
    args = parser.parse_args()
    for name in args.worlds.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            dataset = world(name, args.poses, seed)
            out = ceiling(name, dataset, args.margin)
            c, real = out["counts"], max(out["counts"]["real"], 1)
            line = (f"{name:10s} seed {seed} obs/pose {dataset.num_observations / dataset.num_poses:5.1f} "
                    f"notbest {c['notbest'] / real:.4f} close {c['close'] / real:.4f} out {c['out'] / real:.4f}")
            for label in ("depth", "ball", "view"):
                sc = out[label]
                line += (f" | {label} {sc['precision']:.4f} / {sc['recall']:.3f} rank "
                         + " ".join(f"{sc['at'][r]:.4f}" for r in RECALLS))
            if args.beam:
                scores = evaluate(camloc.localize(dataset, camloc.LocalizerConfig(), engine="compiled", parallel=False))
                recall = scores["association"]["recall"]
                line += (f" | beam {scores['association']['precision']:.4f} / {recall:.3f} | at the beam's recall: depth "
                         f"{precision_at(out['depth'], recall, real):.4f} view {precision_at(out['view'], recall, real):.4f}")
            print(line, flush=True)


if __name__ == "__main__":
    main()
