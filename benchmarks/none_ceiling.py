"""No map (issue 38): what the true association reaches, online and in batch, on the real file and on
sparse simulated worlds of its kind.

Issue 38 asks, with no map, for at most 0.5 m of position RMSE on the real file and 0.25 m after an
SE(3) alignment. This prints, for the real file (when ``../shared/datasets`` is present; measured,
never tuned on) and for ``mapping_sparse.py``'s worlds (``--kinds``, ``--seeds``), position RMSE
unaligned and after an SE(3) alignment of:
- ``filter``: the filter with the true association (``--association oracle --map none``);
- ``online MAP``: at each pose k (every ``--stride``-th), the batch MAP (``camloc.smoother``,
  ``--map none``, the start pose fixed) of the graph of poses 0..k with every observation paired by
  its true id, its last pose: the best any online estimator does with the data up to k;
- ``batch MAP``: the same graph over the whole run.

Where the online MAP is over a target, that target is beyond any online estimator on that file
with the true association; where the batch MAP is, beyond any estimator.

    nice python benchmarks/none_ceiling.py [--kinds grid,smooth3d,aerial] [--seeds 0,1,2,3] [--poses 100] [--stride 2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from camloc import metrics
from camloc.dataset import first_poses
from camloc.g2o import read_g2o
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.results import UNASSOCIATED
from camloc.smoother import SmootherConfig, smooth_run

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench import real_dataset  # noqa: E402
from mapping_sparse import world  # noqa: E402

NONE_TARGET, NONE_SE3_TARGET = 0.5, 0.25


def true_association(dataset, run):
    """``run`` with every observation paired by its true id (clutter's none)."""
    true = dataset.obs_true_landmark
    landmark = np.where(true >= 0, true, UNASSOCIATED).astype(np.int64)
    return replace(run, associations=replace(run.associations, landmark=landmark))


def map_estimate(dataset) -> np.ndarray:
    """(N, 3) positions of the batch MAP with no map and the true association."""
    run = localize(dataset, LocalizerConfig(association="oracle", map="none"))
    return smooth_run(dataset, true_association(dataset, run), SmootherConfig(map="none")).xyz


def online_map(dataset, at: list[int]) -> np.ndarray:
    """(len(at), 3): for each k of ``at``, the last position of the batch MAP over poses 0..k."""
    return np.array([map_estimate(first_poses(dataset, k + 1))[-1] if k else dataset.truth_xyz[0] for k in at])


def errors(path: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Position RMSE unaligned and after an SE(3) alignment."""
    aligned = metrics.align_trajectory(path, truth, method="se3")
    moved = path @ aligned.rotation.T + aligned.translation
    rmse = lambda p: float(np.sqrt(np.mean(np.sum((p - truth) ** 2, axis=1))))  # noqa: E731
    return rmse(path), rmse(moved)


def ceilings(dataset, stride: int) -> dict[str, tuple[float, float]]:
    at = list(range(0, dataset.num_poses, stride))
    truth = dataset.truth_xyz
    filtered = localize(dataset, LocalizerConfig(association="oracle", map="none")).estimate_xyz
    return {"filter": errors(filtered[at], truth[at]), "online MAP": errors(online_map(dataset, at), truth[at]),
            "batch MAP": errors(map_estimate(dataset)[at], truth[at])}


def real_without_map(folder: Path):
    source = real_dataset()
    if source is None:
        return None
    lines = [line for line in source.read_text().splitlines() if not line.startswith("VERTEX_TRACKXYZ")]
    path = folder / "none.g2o"
    path.write_text("\n".join(lines) + "\n")
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the file's empty map is the point
        return read_g2o(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="grid,smooth3d,aerial", help="simulated kinds (default grid,smooth3d,aerial)")
    parser.add_argument("--seeds", default="0,1,2,3", help="seeds of the simulated worlds (default 0,1,2,3)")
    parser.add_argument("--poses", type=int, default=100, help="poses of a simulated world (default 100, the real file's)")
    parser.add_argument("--detection", type=float, default=0.4, help="detection probability (default 0.4, mapping_sparse's)")
    parser.add_argument("--stride", type=int, default=2, help="online MAP every this many poses (default 2)")
    args = parser.parse_args()
    print(f"{'world':<16}" + "".join(f"{name + ' m':>14}{'se3 m':>8}" for name in ("filter", "online MAP", "batch MAP")))
    with tempfile.TemporaryDirectory(prefix="camloc-none-") as tmp:
        cases = []
        real = real_without_map(Path(tmp))
        if real is not None:
            cases.append(("real file", real))
        for kind in args.kinds.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                cases.append((f"{kind} {seed}", world(kind, seed, args.poses, args.detection, 0.0, False)[0]))
        for name, dataset in cases:
            row = ceilings(dataset, args.stride)
            print(f"{name:<16}" + "".join(f"{a:>14.3f}{b:>8.3f}" for a, b in row.values()), flush=True)
    print(f"targets: {NONE_TARGET} m, {NONE_SE3_TARGET} m after an SE(3) alignment (the real file)")


if __name__ == "__main__":
    main()
