"""The pixel beam's miss term weighted by the chance that a landmark is on the ray (issue 35): the
variants that were tried (docs/performance.md, 2026-12-05); ``log`` is the library's since
(``camloc.miss_term``), ``flat`` the one it replaced. Reproduces the variants on the numpy engine, whose beam
gives the compiled one's pairs (tests/test_engine_parity.py; on aerial1 seed 2, s3d1 seed 2 and
mono100 seed 2 the two engines gave the same RMSE for the default term and the linear one), by
replacing ``PoseExpansion.expected`` and ``missed`` for the run.

The flat term (``--charge flat``, the library's until 2026-12-05; ``none``: no term) charges ``MISS_COST`` for each
landmark in the pool of a pixel observation, within the sure detection range, that an explanation leaves unclaimed. The
variants weigh it by p, the chance that the observation is that landmark rather than clutter:
with the pair's cost c (d^2 + ln det S - ln det R, twice a negative log-likelihood, computed for
every pool member, inside the gate or not) and the observation's null cost n, L = exp(-(c - n) / 2)
and p = L / (1 + L); a landmark in several pools takes its largest p.

- ``--charge linear``: MISS_COST * p.
- ``--charge log`` (the library's, ``camloc.miss_term``): -2 ln(1 - p_D p), the likelihood of not detecting a landmark that is where the
  camera would detect it with chance p, p_D = 1 - exp(-MISS_COST / 2) (a sure miss costs MISS_COST).
- ``--state parent``: c under the hypothesis the pose's explanation grew from (its predicted
  covariance); ``--state child``: under the explanation's own state, after its pairs.

    nice python benchmarks/pixel_miss.py aerial1:2,s3d1:2,mono100:2 --charge log --state parent
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import camloc
from camloc import measurement
from camloc.beam_expansion import PoseExpansion
from camloc.beam_types import Hypothesis
from camloc.metrics import evaluate
from camloc.pair_options import member

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pixel_worlds  # noqa: E402  (the benchmarks folder is not a package)


def on_ray(cost: np.ndarray, null_cost: np.ndarray) -> np.ndarray:
    """p = L / (1 + L), L = exp(-(c - n) / 2): the chance the observation is the landmark, not clutter."""
    return 1.0 / (1.0 + np.exp(np.clip((cost - null_cost) / 2.0, -50.0, 50.0)))


def charges(p: np.ndarray, kind: str, miss_cost: float) -> np.ndarray:
    if kind == "none":
        return np.zeros(p.size)
    if kind == "flat":
        return np.full(p.size, miss_cost)
    if kind == "linear":
        return miss_cost * p
    detect = 1.0 - np.exp(-miss_cost / 2.0)          # a sure miss (p = 1) costs miss_cost
    return -2.0 * np.log1p(-detect * p)


def pair_costs(expansion: PoseExpansion, h: Hypothesis, o: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """The cost of each pair (observation o[k], landmark landmarks[k]) under h, gate or not."""
    gating, out = expansion.gating, np.empty(o.size)
    for k in range(o.size):
        camera = int(expansion.ctx.obs_sensor[o[k]])
        z_hat, H = expansion.ctx.observe(h.x, camera, landmarks[k : k + 1])
        p_hat, _, HPH, JHPHJ = gating.spread(h.P, [camera], [1], z_hat, H)
        out[k] = gating.in_best_coordinates(o[k : k + 1], z_hat, p_hat, HPH, JHPHJ)[1][0]
    return out


def patch(kind: str, state: str) -> None:
    """Replace the numpy beam's miss term for this process."""

    def expected(self, h, obs, options):
        """(landmark, observation) of every pool member within the sure range, and p under h."""
        low, high = self.ctx.detect_range
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        if self.settings.miss_cost <= 0.0 or high <= 0.0:
            return none
        ds = self.ctx.dataset
        T = self.ctx.filter.pose(h.x)
        found, rays = [], []
        for i in np.flatnonzero(measurement.is_ray(ds.obs_kind[obs])):
            landmarks = options[i].landmarks
            centre = T[:3, :3] @ self.ctx.cameras[int(self.ctx.obs_sensor[obs[i]])].T_robot_camera[:3, 3] + T[:3, 3]
            distance = np.linalg.norm(ds.landmark_xyz[landmarks] - centre, axis=1)
            near = (distance >= low) & (distance <= high)
            found.append(landmarks[near])
            rays.append(np.full(int(near.sum()), obs[i]))
        if not found:
            return none
        landmarks, o = np.concatenate(found), np.concatenate(rays)
        p = on_ray(pair_costs(self, h, o, landmarks), self.null_cost[o]) if state == "parent" and kind in ("linear", "log") else None
        return landmarks, o, p

    def missed(self, h, expected, parent):
        landmarks, o, p = expected
        left = ~member(landmarks, np.array([lm for _, lm in h.pairs], dtype=np.int64))
        if not left.any():
            return h
        landmarks, o = landmarks[left], o[left]
        if kind in ("none", "flat"):
            p = np.ones(landmarks.size)
        elif state == "child":
            p = on_ray(pair_costs(self, h, o, landmarks), self.null_cost[o])
        else:
            p = p[left]
        distinct, index = np.unique(landmarks, return_inverse=True)
        largest = np.zeros(distinct.size)
        np.maximum.at(largest, index, p)
        if h is parent:  # never the parent's own cost
            h = Hypothesis(h.x, h.P, h.cost, h.parent, h.pairs, h.unassigned, h.slipped)
        h.cost += float(charges(largest, kind, self.settings.miss_cost).sum())
        return h

    PoseExpansion.expected = expected
    PoseExpansion.missed = missed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("worlds", help="comma-separated NAME:SEED of pixel_worlds.WORLDS")
    parser.add_argument("--poses", type=int, default=500)
    parser.add_argument("--charge", choices=("none", "flat", "linear", "log"), default="log", help="default: log")
    parser.add_argument("--state", choices=("parent", "child"), default="parent", help="default: parent")
    args = parser.parse_args()
    patch(args.charge, args.state)
    for item in args.worlds.split(","):
        name, seed = item.split(":")
        dataset = pixel_worlds.world(name, args.poses, int(seed))
        started = time.process_time()
        beam = evaluate(camloc.localize(dataset, camloc.LocalizerConfig(association="beam"), engine="numpy", parallel=False))
        seconds = time.process_time() - started
        oracle = pixel_worlds.run(dataset, "oracle")[1]
        rmse, oracle_rmse = beam["estimate"]["ate"]["rmse"], oracle["estimate"]["ate"]["rmse"]
        print(f"{args.charge}/{args.state} {name:10s} seed {seed} beam {rmse:.4f} oracle {oracle_rmse:.4f} ratio {rmse / oracle_rmse:5.2f} "
              f"prec {beam['association']['precision']:.4f} recall {beam['association']['recall']:.3f} cpu {seconds:.1f}s", flush=True)


if __name__ == "__main__":
    main()
