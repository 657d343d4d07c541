"""``camloc run`` as a library call: read a dataset, localize it, score it, save the run folder."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path
from typing import Any, Callable, ContextManager, Mapping, Optional

from camloc.bundled import bundled_dataset
from camloc.diagnostics import rays_only, run_warnings
from camloc.ekf import FilterDivergedError
from camloc.localizer import ProgressCallback, localize, unmappable_reason
from camloc.localizer_config import LocalizerConfig
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
    force: bool = False,
    on_progress: Optional[ProgressCallback] = None,
    on_compile: Optional[Callable[[], None]] = None,
    on_background_compile: Optional[Callable[[bool], None]] = None,
    while_saving: Callable[[], ContextManager] = contextlib.nullcontext,
) -> tuple[RunResult, Path | None]:
    """Read, localize, evaluate and (when ``output_dir`` is given) save atomically.

    This is the one place that decides what happens to an existing output folder: it is refused
    before the run starts (so that a long run is not refused at its end) unless it is empty, or
    a run folder and ``force`` (``results.check_run_folder``); ``results.save_run`` then replaces
    it whole, keeping the files that are not camloc's. The save runs inside ``while_saving()``
    (the command line's: a Ctrl-C there waits for the folder to be whole, then changes nothing).

    Returns
    -------
    The result, whose summary (``run_summary``) holds the metrics of ``camloc eval``, and the
    folder written (None when nothing was saved).

    Raises
    ------
    CamlocError : the dataset cannot be read or localized, or ``output_dir`` may not be written.
    """
    from camloc.g2o import read_g2o
    from camloc.metrics import evaluate
    from camloc.results import check_run_folder, save_run

    if output_dir is not None:
        check_run_folder(output_dir, force=force)
    started = time.perf_counter()
    dataset = read_g2o(dataset_path)
    read_seconds = time.perf_counter() - started
    try:
        result = localize(dataset, config, on_progress=on_progress, on_compile=on_compile,
                          on_background_compile=on_background_compile)
    except FilterDivergedError as error:  # "pose N: ...": which file's pose, as a reader's error says
        raise FilterDivergedError(f"{dataset_path}: {error}") from None
    summary = dict(result.summary)
    # The path as given is relative to where the run started: the absolute one lets `camloc smooth`
    # find the file from any folder.
    summary["dataset_resolved"] = str(Path(dataset_path).resolve())
    summary["timing"] = {"read_seconds": read_seconds, **summary["timing"]}
    # What the numbers do not say by themselves (odometry alone, an incomplete map): said once,
    # in the summary's warnings, which the command line prints and summary.json keeps.
    summary["warnings"] = [*summary["warnings"], *run_warnings(summary["counts"], mapped=summary.get("map") is not None,
                                                                map_size=int(dataset.landmark_ids.size),
                                                                unmappable=unmappable_reason(dataset),
                                                                rays_only=rays_only(dataset.obs_kind),
                                                                map_mode=(summary.get("map") or {}).get("mode"))]
    result = dataclasses.replace(result, summary=run_summary(summary, evaluate(result)))
    if output_dir is None:
        return result, None
    with while_saving():
        save_run(output_dir, result, force=force)
    return result, Path(output_dir)


def run_summary(summary: Mapping[str, Any], evaluation: Mapping[str, Any]) -> dict:
    """The localizer's summary with the metrics of ``camloc eval`` beside it, under the same keys
    (``estimate.ate.rmse`` in both; ``docs/json.md``): what ``summary.json`` and ``run --json``
    hold. Where both name a key (``dataset``, ``counts``) the run's is kept; its ``counts`` has
    more than the evaluation's ``poses``."""
    return {**summary, **{key: value for key, value in evaluation.items() if key not in summary}}
