"""The paper's Monte-Carlo experiments (section IV-A): ours vs RANSAC-6 vs the known-match oracle.

``linereg bench synthetic [--quick] [--trials 50] [--out DIR] [--methods vp,ransac6,oracle]``.

Sweeps (2 px endpoint noise throughout):
- ``lines``: 20, 50, 100, 200 map lines at 30 % 3D and 30 % 2D outliers (paper fig. analysis);
- ``outliers3d``: 3D outlier fraction 0 .. 0.6 at 100 lines, 30 % 2D outliers (paper fig. outlier a);
- ``outliers2d``: 2D outlier fraction 0, 0.2, 0.4, 0.6 at 100 lines, 30 % 3D outliers (paper fig. outlier b);
- ``outliers``: 3D and 2D outlier fractions together, 0.3 and 0.6, at 100 lines (the issue's target cells);
- ``building``: ``sim.building_scene.building_scene`` with its defaults.

Methods: ``vp`` (``linereg.register``, ours), ``ransac3`` (the paper's own translation stage: random 3-pair
RANSAC per rotation candidate), ``ransac6`` (RANSAC over 6 random line pairs + DLT-Lines, the paper's
baseline) and ``oracle`` (PnL with the true matches, the accuracy reference). Trial ``i`` of a cell
draws its scene from ``default_rng([seed, i])``, so every method sees the same scenes. Success follows the
paper: R_e < 0.1 rad and |t_e| / |t_GT| < 0.1; pose errors are summarised over successful trials only,
runtimes over all trials (wall clock around the call, scene generation excluded). For ``vp`` each trial
also gets the search check (``bench/search_check.py``): right, right but refused, the truth not scoring
best (a score problem) or scoring best and not returned (a search problem), tallied per cell.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import report, search_check
from ..config import RegisterConfig
from ..geometry import pose_errors
from ..registration import Registration
from ..sim import synthetic
from ..sim.building_scene import building_scene
from .baselines import BaselineConfig, ransac3, ransac6

log = logging.getLogger(__name__)

METHODS = ("vp", "ransac3", "ransac6", "oracle")
NOISE_PX = 2.0  # paper: sigma = 2 px on the 2D endpoints
DEFAULT_OUTLIERS = 0.3
DEFAULT_LINES = 100
FULL: dict[str, tuple[float, ...]] = {
    "lines": (20, 50, 100, 200),
    "outliers3d": (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6),
    "outliers2d": (0.0, 0.2, 0.4, 0.6),
    "outliers": (0.3, 0.6),
}
QUICK: dict[str, tuple[float, ...]] = {
    "lines": (20, 50),
    "outliers3d": (0.0, 0.6),
    "outliers2d": (0.0, 0.6),
    "outliers": (0.6,),
}
QUICK_LINES = 50  # --quick runs the outlier sweeps on smaller scenes too
QUICK_TRIALS = 3
QUICK_RANSAC6_ITERATIONS = 200


@dataclass(frozen=True)
class Cell:
    """One point of a sweep: which scenes to draw."""

    sweep: str  # "lines", "outliers3d", "outliers2d", "outliers" (both) or "building"
    x: float  # the swept value (number of lines or outlier fraction; 0 for building)
    num_lines: int = DEFAULT_LINES
    outlier3d: float = DEFAULT_OUTLIERS
    outlier2d: float = DEFAULT_OUTLIERS

    def scene(self, rng: np.random.Generator) -> synthetic.Scene:
        """Returns the scene of one trial."""
        if self.sweep == "building":
            return building_scene(rng)
        return synthetic.paper_scene(rng, self.num_lines, self.outlier3d, self.outlier2d, NOISE_PX)


@dataclass(frozen=True)
class Options:
    """What to run: ``trials`` per cell, ``methods`` among METHODS, the RegisterConfig for ours/ransac6."""

    quick: bool = False
    trials: int = 50
    methods: tuple[str, ...] = METHODS
    seed: int = 0
    config: RegisterConfig = dataclasses.field(default_factory=RegisterConfig)
    baseline: BaselineConfig = dataclasses.field(default_factory=BaselineConfig)


def cells(quick: bool) -> list[Cell]:
    """Returns the cells of every sweep, in table order."""
    grid, lines = (QUICK, QUICK_LINES) if quick else (FULL, DEFAULT_LINES)
    out = [Cell("lines", n, int(n)) for n in grid["lines"]]
    out += [Cell("outliers3d", f, lines, outlier3d=f) for f in grid["outliers3d"]]
    out += [Cell("outliers2d", f, lines, outlier2d=f) for f in grid["outliers2d"]]
    out += [Cell("outliers", f, lines, outlier3d=f, outlier2d=f) for f in grid["outliers"]]
    out.append(Cell("building", 0.0, num_lines=0, outlier3d=0.0, outlier2d=0.0))  # fields unused
    return out


def run_method(method: str, scene: synthetic.Scene, options: Options) -> tuple[Registration, float]:
    """Returns (Registration, seconds) of one method on one scene; an exception becomes a failure."""
    start = time.perf_counter()
    try:
        result = _RUNNERS[method](scene, options)
    except Exception as e:  # a crash is a failed trial, recorded with its cause, not a dead benchmark
        log.debug("%s raised", method, exc_info=True)
        result = Registration(False, reason=f"{type(e).__name__}: {e}")
    return result, time.perf_counter() - start


def _run_register(scene: synthetic.Scene, options: Options) -> Registration:
    from ..pipeline import register

    return register(scene.lines2d, scene.lines3d, scene.camera, options.config)


def _run_ransac3(scene: synthetic.Scene, options: Options) -> Registration:
    return ransac3(scene.lines2d, scene.lines3d, scene.camera, options.config, options.baseline)


def _run_ransac6(scene: synthetic.Scene, options: Options) -> Registration:
    return ransac6(scene.lines2d, scene.lines3d, scene.camera, options.config, options.baseline)


def _run_oracle(scene: synthetic.Scene, options: Options) -> Registration:
    from .oracle import pnl_known_correspondences

    pose = pnl_known_correspondences(
        scene.lines2d, scene.lines3d, scene.true_matches, scene.camera, options.config.score.distance_px
    )
    return Registration(True, cam_from_world=pose, num_inliers=len(scene.true_matches))


_RUNNERS = {"vp": _run_register, "ransac3": _run_ransac3, "ransac6": _run_ransac6, "oracle": _run_oracle}


def run_cell(cell: Cell, options: Options, progress: report.Progress | None = None) -> list[dict[str, Any]]:
    """Returns one trial record per (trial, method) of a cell; all methods share each trial's scene."""
    records = []
    for trial in range(options.trials):
        try:
            scene: synthetic.Scene | None = cell.scene(np.random.default_rng([options.seed, trial]))
        except Exception as e:  # a generator still being written must not end a long run: record it
            log.warning("%s scene of trial %d failed: %s", cell.sweep, trial, e)
            scene, failure = None, Registration(False, reason=f"scene generation: {type(e).__name__}: {e}")
        for method in options.methods:
            result, seconds = run_method(method, scene, options) if scene else (failure, 0.0)
            errors = (
                pose_errors(result.cam_from_world, scene.cam_from_world) if result.success and scene else None
            )
            record = report.trial_record(
                method, trial, result.success, errors, seconds, result.num_inliers, result.reason
            )
            if method == "vp" and scene is not None:
                record["search_check"] = _search_check(scene, result, options)
            records.append(record)
            if progress is not None:
                progress.advance(f"{cell.sweep}={cell.x:g} {method}")
    return records


def _search_check(scene: synthetic.Scene, result: Registration, options: Options) -> dict[str, Any]:
    """Returns ``search_check.check`` of linereg's answer on a scene: right, refused right, or where it
    failed (the truth does not score best: the score; it does and was not returned: the search)."""
    from ..pipeline import segments_view

    config = options.config
    right = False
    if result.cam_from_world is not None:
        rot, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
        right = report.meets_criterion(rot, rel)
    view = segments_view(scene.lines3d, config)
    return search_check.check(scene.lines2d, view, scene.camera, scene.cam_from_world, result, right, config)


def run_synthetic(options: Options, progress: report.Progress | None = None) -> dict[str, Any]:
    """Returns the results: options, criterion, and per (cell, method) statistics with their trials."""
    rows = []
    for cell in cells(options.quick):
        records = run_cell(cell, options, progress)
        for method, trials in report.by_key(records, "method").items():
            row = dataclasses.asdict(cell) | {"method": method} | report.cell_stats(trials)
            if any("search_check" in t for t in trials):
                counts = search_check.tally(trials)
                row["search_check"] = counts
                row["search_check_line"] = "/".join(str(counts[v]) for v in search_check.VERDICTS)
            rows.append(row | {"failure_reasons": report.failure_reasons(trials), "trials": trials})
        if progress is not None:
            progress.note(_cell_line(cell, rows[-len(options.methods) :]))
    return {
        "benchmark": "synthetic",
        "options": {k: v for k, v in dataclasses.asdict(options).items() if k != "config"},
        "config": dataclasses.asdict(options.config),
        "noise_px": NOISE_PX,
        "success_criterion": {
            "rotation_rad": report.SUCCESS_ROTATION_RAD,
            "rel_translation": report.SUCCESS_REL_TRANSLATION,
        },
        "errors_over": "successful trials only; runtimes over all trials",
        "rows": rows,
    }


def _cell_line(cell: Cell, rows: list[dict[str, Any]]) -> str:
    rates = ", ".join(
        f"{r['method']} {100 * r['success_rate']:.0f}% {r['time_ms_median']:.0f}ms" for r in rows
    )
    return f"{cell.sweep:>10} {cell.x:<5g}: {rates}"


TABLE_COLUMNS = (
    ("sweep", "sweep", ""),
    ("x", "x", "g"),
    ("method", "method", ""),
    ("n", "n", "d"),
    ("success_rate", "success", ".0%"),
    ("wrong_claimed", "wrong claimed", "d"),
    ("rotation_deg_median", "rot med°", ".2f"),
    ("rotation_deg_rmse", "rot rmse°", ".2f"),
    ("rel_translation_median", "|te|/|t| med", ".4f"),
    ("position_m_median", "pos med m", ".3f"),
    ("time_ms_median", "ms med", ".0f"),
    ("time_ms_p95", "ms p95", ".0f"),
    # vp only: right / refused right / the truth does not score best / the search missed it
    ("search_check_line", "check r/rr/score/search", ""),
)


def write_results(results: dict[str, Any], out: Path) -> list[Path]:
    """Returns the files written to ``out``: results.json and the figures of the paper."""
    written = [report.write_json_atomic(out / "results.json", results)]
    written += plot_results(results["rows"], out)
    return written


def plot_results(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Returns the PNGs written: success / runtime / pose errors vs #lines, success vs outlier fractions."""
    sweeps = report.by_key(rows, "sweep")
    written = []
    lines = sweeps.get("lines", [])
    if lines:
        written.append(
            _plot(lines, "success_rate", out / "success_vs_lines.png", "number of 3D lines", "success rate")
        )
        written.append(
            _plot(
                lines,
                "time_ms_median",
                out / "runtime_vs_lines.png",
                "number of 3D lines",
                "median runtime (ms)",
                logy=True,
            )
        )
        written.append(_plot_errors(lines, out / "pose_errors_vs_lines.png"))
    for sweep, label in (("outliers3d", "3D outlier fraction"), ("outliers2d", "2D outlier fraction")):
        if sweep in sweeps:
            written.append(
                _plot(sweeps[sweep], "success_rate", out / f"success_vs_{sweep}.png", label, "success rate")
            )
    return written


def _series(rows: list[dict[str, Any]], key: str) -> dict[str, tuple[list[float], list[float]]]:
    return {
        m: ([r["x"] for r in rs], [r[key] for r in rs]) for m, rs in report.by_key(rows, "method").items()
    }


def _plot(rows, key: str, path: Path, xlabel: str, ylabel: str, logy: bool = False) -> Path:
    ylim = (-0.02, 1.02) if key == "success_rate" else None
    return report.plot_series(path, _series(rows, key), xlabel, ylabel, logy=logy, ylim=ylim)


def _plot_errors(rows: list[dict[str, Any]], path: Path) -> Path:
    """Returns ``path`` after plotting rotation RMSE (deg) and median position error (m) per method."""
    fig, (ax_r, ax_t) = report.new_figure(ncols=2)
    for method, (x, y) in _series(rows, "rotation_deg_rmse").items():
        ax_r.plot(x, y, marker="o", label=method)
    for method, (x, y) in _series(rows, "position_m_median").items():
        ax_t.plot(x, y, marker="o", label=method)
    report.style_axes(ax_r, "number of 3D lines", "rotation error RMSE (deg)", "successful trials")
    report.style_axes(ax_t, "number of 3D lines", "median position error (m)", "successful trials")
    return report.save_figure(fig, path)


def configure(parser: argparse.ArgumentParser) -> None:
    """Adds the ``bench synthetic`` arguments and sets ``func=run``."""
    parser.add_argument("--quick", action="store_true", help="few cells and trials (seconds; for CI)")
    parser.add_argument(
        "--trials", type=int, default=None, help=f"trials per cell (default 50, quick {QUICK_TRIALS})"
    )
    parser.add_argument("--out", type=Path, default=Path("bench-results/synthetic"), help="output directory")
    parser.add_argument(
        "--methods", default=",".join(METHODS), help=f"comma-separated subset of {','.join(METHODS)}"
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed; trial i uses the rng of [seed, i]")
    parser.add_argument(
        "--ransac6-iterations",
        type=int,
        default=None,
        help=f"ransac3/ransac6 iteration cap (default {BaselineConfig.max_iterations}, quick {QUICK_RANSAC6_ITERATIONS})",
    )
    parser.add_argument("--config", type=Path, help="JSON overrides of RegisterConfig, per section")
    parser.set_defaults(func=run)


def options_from_args(args: argparse.Namespace) -> Options:
    """Returns the Options of parsed ``bench synthetic`` arguments (raises InvalidInputError if bad)."""
    from ..errors import InvalidInputError

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        raise InvalidInputError(
            f"--methods: unknown {', '.join(unknown) or '(none)'}; choose from {', '.join(METHODS)}"
        )
    trials = args.trials if args.trials is not None else (QUICK_TRIALS if args.quick else 50)
    if trials < 1:
        raise InvalidInputError(f"--trials must be >= 1, got {trials}")
    config = _read_config(args.config) if args.config else RegisterConfig()
    iterations = args.ransac6_iterations or (
        QUICK_RANSAC6_ITERATIONS if args.quick else BaselineConfig().max_iterations
    )
    baseline = BaselineConfig(max_iterations=iterations)
    return Options(
        quick=args.quick, trials=trials, methods=methods, seed=args.seed, config=config, baseline=baseline
    )


def _read_config(path: Path) -> RegisterConfig:
    """Returns the RegisterConfig of a JSON file of nested section overrides (``{"match": {...}}``)."""
    import json

    from ..errors import FileFormatError

    try:
        return RegisterConfig.from_dict(json.loads(Path(path).read_text()))
    except (OSError, json.JSONDecodeError) as e:
        raise FileFormatError(f"--config {path}: {e}") from None


def run(args: argparse.Namespace) -> int:
    """Runs the benchmark, prints the table, writes results; returns the exit code."""
    import sys

    options = options_from_args(args)
    report.warm_up()
    progress = report.Progress(len(cells(options.quick)) * options.trials * len(options.methods))
    try:
        results = run_synthetic(options, progress)
    finally:
        progress.close()
    print(report.format_table(results["rows"], TABLE_COLUMNS))
    print("errors over successful trials only; runtimes over all trials")
    for path in write_results(results, args.out):
        print(f"wrote {path}", file=sys.stderr)
    return 0
