"""``camloc run`` as a library call: read a dataset, localize it, score it, save the run folder."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

from camloc.bundled import bundled_dataset
from camloc.localizer import LocalizerConfig, ProgressCallback, localize
from camloc.results import RunResult

DEFAULT_DATASET = bundled_dataset()
RUNS_FOLDER = Path("runs")


def default_output_dir(dataset_path: str | Path) -> Path:
    """``runs/<dataset file name without extension>``, relative to the working directory."""
    return RUNS_FOLDER / Path(dataset_path).stem


def run_dataset(
    dataset_path: str | Path,
    config: LocalizerConfig,
    output_dir: Optional[str | Path],
    *,
    on_progress: Optional[ProgressCallback] = None,
) -> tuple[RunResult, Path | None]:
    """Read, localize, evaluate and (when ``output_dir`` is given) save atomically.

    Returns the result, its summary holding the headline metrics when there is ground truth, and
    the folder written (None when nothing was saved).
    """
    from camloc.g2o import read_g2o
    from camloc.metrics import evaluate
    from camloc.results import save_run

    started = time.perf_counter()
    dataset = read_g2o(dataset_path)
    read_seconds = time.perf_counter() - started
    result = localize(dataset, config, on_progress=on_progress)
    summary = dict(result.summary)
    summary["timing"] = {"read_seconds": read_seconds, **summary["timing"]}
    if dataset.has_ground_truth:
        summary["metrics"] = evaluate(result)
    result = dataclasses.replace(result, summary=summary)
    if output_dir is None:
        return result, None
    save_run(output_dir, result)
    return result, Path(output_dir)
