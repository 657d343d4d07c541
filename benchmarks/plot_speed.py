"""How long ``camloc plot`` takes to draw and save each figure of a run folder.

Times each figure of ``camloc.plotting.FIGURES`` and the report, drawn as ``camloc plot`` draws
them (Agg, constrained layout) and saved as PNG into a temporary directory, and prints the
seconds of drawing and of saving. Give it a large run (``camloc simulate --poses 20000 ...``,
``camloc run``, ``camloc smooth``) to check that the figures stay quick at scale.

    python benchmarks/plot_speed.py RUN_DIR [--dpi 150]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from camloc import plotting  # noqa: E402
from camloc.results import load_run  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--dpi", type=int, default=150)
    args = parser.parse_args()
    result = load_run(args.run_dir)
    print(f"{args.run_dir}: {len(result.pose_ids)} poses, {len(result.map_landmark_ids)} landmarks, "
          f"{result.associations.pose_id.size} observations")
    figures = dict(plotting.FIGURES) | {"report": (plotting.REPORT_SIZE, plotting.draw_report)}
    with tempfile.TemporaryDirectory() as folder:
        for name, (size, draw) in figures.items():
            start = time.perf_counter()
            fig = plt.figure(figsize=size, layout="constrained")
            draw(fig, result)
            drawn = time.perf_counter()
            fig.savefig(Path(folder) / f"fig-{name}.png", dpi=args.dpi)
            plt.close(fig)
            print(f"  {name:<13} draw {drawn - start:5.2f} s   save {time.perf_counter() - drawn:5.2f} s")


if __name__ == "__main__":
    main()
