"""The association issue's figures: each association method against the oracle, case by case.

Methods (``--methods``): ``beam`` (the beam of hypotheses), ``jcbb`` (joint compatibility branch
and bound), ``best-friends`` (sequential best friends), ``bf-batch`` (best friends all at once without the re-check, the original method: ``--batch --no-recheck``), ``oracle``
(the file's true landmark ids, gated: what perfect association gives).

Cases (``--cases``; seeded, several seeds each; ``--quick`` uses fewer seeds and smaller worlds):

- ``dense``: grid walk, 2,000 poses, a 5,000-landmark map, the real file's camera. The fraction of
  observations with a rival landmark predicted within 3 sigma (from the true pose, under the
  observation noise R alone, so a lower bound of what the filter faces) is measured and printed.
- ``clutter``: smooth3d, 1,000 poses, 15% clutter (detections of nothing in the map) and 3% gross
  outliers (true id kept, measurement replaced): clutter accepted per 200 clutter observations.
- ``real-style``: grid walk, normalized camera, 300 poses, ten seeds: runs within 1.25x of the
  oracle's RMSE and the worst ratio.
- ``real``: the real file (``<repo>/../shared/datasets``), skipped when absent.
- ``aerial``: steep 3D motion (roll/pitch up to 60 deg), pixel intrinsics, two cameras, 500 poses.

Per case and method: position RMSE (mean over seeds), its ratio to the oracle's RMSE on the same
seed (mean, worst, and how many runs are within 1.25x), precision and recall pooled over the seeds
(correct / accepted, correct / observations of map landmarks), clutter accepted per 200 clutter
observations, and the mean localize time. Each run is printed as soon as it is done; results are
saved in the cache and ``--resume`` reuses those measured with the same library source.

Why this is not a ``camloc sweep`` spec: a sweep runs a product of options and reports each
run's own figures, and this script needs more than that. Its cases are five worlds of different
options, not a product; ``bf-batch`` is two coupled options (``--batch --no-recheck``) that a
product would also cross with the others; the real file and simulated worlds share one report;
and it measures what a sweep row does not hold (clutter accepted per 200 clutter observations,
precision and recall pooled over the seeds, how ambiguous each map is). One case is a plain
product, and ships as a spec: ``camloc sweep benchmarks/association-real-style.toml -o DIR``
gives the real-style rows (its summary has the ratio to the oracle; ``bf-batch`` is left out).

    nice python benchmarks/association.py --quick
    nice python benchmarks/association.py [--cases dense,clutter] [--seeds 5] [--size 0.5] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)

TARGETS = {"precision": 0.995, "recall": 0.95, "ratio": 1.25, "clutter_per_200": 1.0}
TARGET_TEXT = ("targets: precision >= 99.5%, recall >= 95% (dense), RMSE within 1.25x of the oracle's, "
               "clutter accepted <= 1 per 200 clutter observations")

METHODS = {
    "beam": {"association": "beam"},
    "jcbb": {"association": "jcbb"},
    "best-friends": {"association": "best-friends", "best-friends.sequential": True},
    "bf-batch": {"association": "best-friends", "best-friends.sequential": False, "recheck.enabled": False},
    "oracle": {"association": "oracle"},
}


@dataclasses.dataclass(frozen=True)
class Case:
    """A family of simulated worlds (``camloc simulate`` options, seeds), or the real file."""

    name: str
    label: str
    options: dict
    seeds: int
    quick_options: dict
    quick_seeds: int
    real: bool = False

    def worlds(self, *, quick: bool, seeds: Optional[int], size: float) -> tuple[dict, list[int]]:
        options = dict(self.quick_options if quick else self.options)
        for name in ("poses", "landmarks"):
            if name in options:
                options[name] = max(2, int(round(options[name] * size)))
        count = seeds if seeds is not None else (self.quick_seeds if quick else self.seeds)
        return options, list(range(count))


CASES = [
    Case("dense", "dense map, the real file's camera",
         dict(trajectory="grid", poses=2000, landmarks=5000), 3,
         dict(trajectory="grid", poses=500, landmarks=1250), 1),
    Case("clutter", "clutter and gross outliers",
         dict(trajectory="smooth3d", poses=1000, clutter_fraction=0.15, outlier_fraction=0.03), 3,
         dict(trajectory="smooth3d", poses=300, clutter_fraction=0.15, outlier_fraction=0.03), 1),
    Case("real-style", "real-file style, normalized camera",
         dict(trajectory="grid", poses=300), 10,
         dict(trajectory="grid", poses=300), 3),
    Case("real", "the real file", {}, 1, {}, 1, real=True),
    Case("aerial", "steep 3D motion (tilt up to 60 deg), pixel intrinsics, two cameras",
         dict(trajectory="aerial", poses=500, intrinsics="pixel", cameras=2), 3,
         dict(trajectory="aerial", poses=200, intrinsics="pixel", cameras=2), 1),
]


def main() -> None:
    args = parse_args()
    cache = args.cache.expanduser()
    store = _bench.ResultStore(cache / "results" / "association", enabled=args.resume)
    say = (lambda text: print(text, file=sys.stderr, flush=True))
    methods = ["oracle"] + [m for m in args.methods if m != "oracle"]  # the oracle first: ratios need it
    say(f"camloc association benchmark ({'quick' if args.quick else 'full'}); {TARGET_TEXT}; {_bench.source_note()}; cache: {cache}; {_bench.machine_load()}")
    if args.settings:
        say(f"every method also gets: {args.settings}")

    report = []
    for case in (c for c in CASES if c.name in args.cases):
        options, seeds = case.worlds(quick=args.quick, seeds=args.seeds, size=args.size)
        worlds = world_paths(case, options, seeds, cache, say)
        if not worlds:
            continue
        ambiguity = mean_ambiguity(worlds, cache)
        say(f"== {case.name}: {len(worlds)} world(s); rival within 3 sigma (true pose, R only): "
            f"{_bench.fmt(ambiguity, 1, percent=True)} of in-map observations")
        runs: dict[str, list[dict]] = {m: [] for m in methods}
        for seed, path in worlds:
            oracle_rmse = None
            for method in methods:
                config = {**METHODS[method], **_bench.options_for(METHODS[method]["association"], args.settings)}
                result = store.get(path, config)
                if result is None:
                    result = _bench.run_case(path, config, timeout=args.timeout)
                    store.put(path, config, result)
                run = run_of(seed, path, result, None if method == "oracle" else oracle_rmse, oracle=method == "oracle")
                if method == "oracle":
                    oracle_rmse = run.get("rmse_m")
                runs[method].append(run)
                world = "file" if seed is None else f"seed {seed}"
                say(f"   {case.name} {world} {method:>12}: {describe_run(run)}")
        title = f"{case.label}: " + (", ".join(f"{k}={v}" for k, v in options.items()) if options else str(worlds[0][1].name))
        entry = {"case": case.name, "title": title, "options": options, "seeds": seeds,
                 "ambiguity": ambiguity, "methods": {m: aggregate(runs[m]) for m in methods}, "runs": runs}
        report.append(entry)
        if not args.json:
            print_case(entry)

    say(f"done; {_bench.machine_load()}")
    if store.version != _bench.code_version():
        say("warning: the library's source (camloc/*.py) changed during this run: the rows mix versions")
    if args.json:
        print(json.dumps({"targets": TARGETS, "settings": args.settings, "machine": _bench.machine_load(),
                          "source": _bench.source_note(), "cases": report}, indent=2))
    else:
        print_summary(report, methods)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [c.name for c in CASES]
    parser.add_argument("--quick", action="store_true", help="fewer seeds, smaller worlds: a smoke run (default: full)")
    parser.add_argument("--cache", type=Path, default=_bench.DEFAULT_CACHE,
                        help=f"folder for generated worlds and saved results (default {_bench.DEFAULT_CACHE})")
    parser.add_argument("--cases", type=_names(names), default=names,
                        help=f"comma-separated cases to run (default all: {','.join(names)})")
    parser.add_argument("--methods", type=_names(list(METHODS)), default=list(METHODS),
                        help=f"comma-separated methods (default all: {','.join(METHODS)}; the oracle always runs)")
    parser.add_argument("--seeds", type=int, default=None,
                        help="seeds per simulated case, 0..N-1 (default: 3, ten for real-style; --quick: 1, 3)")
    parser.add_argument("--size", type=float, default=1.0,
                        help="multiplies every case's poses and landmark count (default 1)")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="a localizer option given to every method it is an option of, named as in a config file, "
                        "e.g. --set iterations=1 --set beam.width=8 (default: none)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed per run (default 1800)")
    parser.add_argument("--resume", action="store_true",
                        help="reuse results saved by an earlier run with the same library source (default: measure anew)")
    parser.add_argument("--json", action="store_true", help="print everything as JSON instead of tables (default: tables)")
    args = parser.parse_args()
    # The method sets the association; everything else applies to every method that has the option.
    args.settings = _bench.localizer_options(args.settings, forbidden=("association",))
    return args


def _names(allowed: list[str]):
    def parse(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",") if n.strip()]
        unknown = [n for n in names if n not in allowed]
        if unknown or not names:
            raise argparse.ArgumentTypeError(f"expected names among {', '.join(allowed)}, found {text!r}")
        return names
    return parse


def world_paths(case: Case, options: dict, seeds: list[int], cache: Path, say) -> list[tuple[Optional[int], Path]]:
    if case.real:
        real = _bench.real_dataset()
        if real is None:
            say(f"== real: skipped, {_bench.REAL_DATASET} is absent")
            return []
        return [(None, real)]
    say(f"== {case.name}: generating / finding {len(seeds)} world(s) ...")
    return [(seed, _bench.simulated(cache, options, seed=seed)) for seed in seeds]


def mean_ambiguity(worlds: list[tuple[Optional[int], Path]], cache: Path) -> Optional[float]:
    """The rival-within-3-sigma fraction of each world (cached beside the results), averaged."""
    import camloc

    values = []
    for _, path in worlds:
        key = cache / "results" / "ambiguity" / f"{path.stem}-{_bench._digest(str(path.stat().st_size).encode())}.json"
        if key.is_file():
            values.append(json.loads(key.read_text())["ambiguity"])
            continue
        value = _bench.ambiguity(camloc.load(path))
        _bench._write_atomically(key, json.dumps({"ambiguity": value}))
        values.append(value)
    values = [v for v in values if v is not None and math.isfinite(v)]
    return sum(values) / len(values) if values else None


# ------------------------------------------------------------------------------------ figures


def run_of(seed: Optional[int], path: Path, result: dict, oracle_rmse: Optional[float], *, oracle: bool) -> dict:
    """One run's figures; the ratio is to the oracle's RMSE on the same world (None when the
    oracle failed there)."""
    if "error" in result:
        return {"seed": seed, "dataset": path.name, "error": result["error"]}
    scores = result["association_scores"]
    rmse = result["rmse_m"]
    # The oracle is compared with itself (ratio 1) so that its row reads like the others.
    reference = rmse if oracle else oracle_rmse
    ratio = rmse / reference if rmse is not None and reference else None
    return {"seed": seed, "dataset": path.name, "rmse_m": rmse, "ratio": ratio,
            "seconds": result["filter_seconds"], "scores": scores, "saved": bool(result.get("saved"))}


def describe_run(run: dict) -> str:
    if "error" in run:
        return f"FAILED {run['error']}"
    s = run["scores"]
    clutter = f", clutter accepted {s['clutter_accepted']}/{s['clutter']}" if s["clutter"] else ""
    return (f"RMSE {_bench.fmt(run['rmse_m'])} m (x{_bench.fmt(run['ratio'], 2)}), precision "
            f"{_bench.fmt(s['precision'], 2, percent=True)}, recall {_bench.fmt(s['recall'], 2, percent=True)}"
            f"{clutter}, {run['seconds']:.1f} s{' (saved result, --resume)' if run['saved'] else ''}")


def aggregate(runs: list[dict]) -> dict:
    """Means over seeds, the worst ratio, and precision/recall/clutter pooled over the seeds."""
    done = [r for r in runs if "error" not in r]
    total = {k: sum(r["scores"][k] for r in done) for k in ("made", "correct", "in_map", "clutter", "clutter_accepted")}
    ratios = [r["ratio"] for r in done if r["ratio"] is not None]
    rmses = [r["rmse_m"] for r in done if r["rmse_m"] is not None]
    return {
        "runs": len(runs),
        "failed": len(runs) - len(done),
        "rmse_mean_m": sum(rmses) / len(rmses) if rmses else None,
        "ratio_mean": sum(ratios) / len(ratios) if ratios else None,
        "ratio_worst": max(ratios) if ratios else None,
        "within_target": sum(r <= TARGETS["ratio"] for r in ratios),
        "precision": total["correct"] / total["made"] if total["made"] else None,
        "recall": total["correct"] / total["in_map"] if total["in_map"] else None,
        "clutter_per_200": 200.0 * total["clutter_accepted"] / total["clutter"] if total["clutter"] else None,
        "clutter_accepted": total["clutter_accepted"],
        "clutter": total["clutter"],
        "seconds_mean": sum(r["seconds"] for r in done) / len(done) if done else None,
    }


def _mark(text: str, ok: Optional[bool]) -> str:
    """Green when a target is met, red when missed, plain when it does not apply."""
    if ok is None or text == "-":
        return text
    return f"[green]{text}[/]" if ok else f"[red]{text}[/]"


def _meets(a: dict, name: str) -> Optional[bool]:
    value = {"precision": a["precision"], "recall": a["recall"], "ratio": a["ratio_worst"],
             "clutter_per_200": a["clutter_per_200"]}[name]
    if value is None:
        return None
    return value >= TARGETS[name] if name in ("precision", "recall") else value <= TARGETS[name]


def _console():
    from rich.console import Console

    return Console(width=max(Console().width, 150))


def print_case(entry: dict) -> None:
    from rich.table import Table

    seeds = entry["seeds"]
    table = Table(title=f"{entry['case']}: {entry['title']} ({len(seeds)} world(s)); rival within 3 sigma: "
                        f"{_bench.fmt(entry['ambiguity'], 1, percent=True)} of in-map observations",
                  caption=TARGET_TEXT)
    for column in ("method", "runs", "RMSE (m)", "ratio mean", "ratio worst", "within 1.25x", "precision",
                   "recall", "clutter acc./200", "time (s)"):
        table.add_column(column, justify="left" if column == "method" else "right")
    for method, a in entry["methods"].items():
        table.add_row(
            method, f"{a['runs'] - a['failed']}/{a['runs']}", _bench.fmt(a["rmse_mean_m"]),
            _bench.fmt(a["ratio_mean"], 2), _mark(_bench.fmt(a["ratio_worst"], 2), _meets(a, "ratio")),
            f"{a['within_target']}/{a['runs']}",
            _mark(_bench.fmt(a["precision"], 2, percent=True), _meets(a, "precision")),
            _mark(_bench.fmt(a["recall"], 1, percent=True), _meets(a, "recall") if entry["case"] == "dense" else None),
            _mark(_per_200(a), _meets(a, "clutter_per_200")),
            _bench.fmt(a["seconds_mean"], 1),
        )
    _console().print(table)


def _per_200(a: dict) -> str:
    if a["clutter_per_200"] is None:
        return "-"
    return f"{a['clutter_per_200']:.2f} ({a['clutter_accepted']}/{a['clutter']})"


def print_summary(report: list[dict], methods: list[str]) -> None:
    """Method x case: worst ratio to the oracle and precision everywhere, plus the case's own target."""
    from rich.table import Table

    table = Table(title="summary: worst RMSE ratio to the oracle / precision (dense: + recall; clutter: + clutter "
                        "accepted per 200; real-style: + runs within 1.25x)", caption=TARGET_TEXT)
    table.add_column("method")
    for entry in report:
        table.add_column(entry["case"], justify="right")
    for method in methods:
        cells = []
        for entry in report:
            a = entry["methods"][method]
            parts = [_mark(f"x{_bench.fmt(a['ratio_worst'], 2)}", _meets(a, "ratio")),
                     _mark(_bench.fmt(a["precision"], 1, percent=True), _meets(a, "precision"))]
            if entry["case"] == "dense":
                parts.append(_mark("R " + _bench.fmt(a["recall"], 1, percent=True), _meets(a, "recall")))
            if a["clutter_per_200"] is not None:
                parts.append(_mark(f"{a['clutter_per_200']:.1f}/200", _meets(a, "clutter_per_200")))
            if len(entry["seeds"]) > 1:
                parts.append(f"{a['within_target']}/{a['runs']} ok")
            cells.append(" ".join(parts) if a["runs"] > a["failed"] else "failed")
        table.add_row(method, *cells)
    _console().print(table)


if __name__ == "__main__":
    _bench.run(main)
