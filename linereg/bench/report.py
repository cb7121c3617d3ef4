"""Helpers every benchmark shares: per-cell statistics, a text table, atomic JSON/PNG writes, line plots,
and the progress bar (the CLI's, ``linereg.cli.progress.Progress``: tqdm on stderr).

A benchmark records one dict per trial (see ``trial_record``) and summarises a cell with ``cell_stats``.
Plots use matplotlib's object API with the Agg canvas only (no pyplot, no global backend switch), so they
work headless and never disturb a caller's figures.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# the benchmarks' progress bar, one implementation for every entry point: advance(label), note(line), close()
from ..cli.progress import Progress as Progress

# the paper's success criterion (after Campbell et al. 2018): R_e < 0.1 rad and |t_e| / |t_GT| < 0.1
SUCCESS_ROTATION_RAD = 0.1
SUCCESS_REL_TRANSLATION = 0.1


def warm_up() -> float:
    """Makes the compiled kernels ready before a benchmark's clock starts (``linereg.warm_up``): a fresh
    install compiles them in its first localization (a first real photo took 13 s instead of 0.3 s), which
    is no photo's work. Prints and returns the seconds it took."""
    import sys

    from ..warm import warm_up as warm

    seconds = warm()
    print(f"warm-up (compiled kernels ready before the clock starts): {seconds:.1f} s", file=sys.stderr)
    return seconds


def meets_criterion(rotation_deg: float, rel_translation: float) -> bool:
    """Returns whether a pose's errors meet the paper's success criterion (False for NaN)."""
    return bool(
        math.radians(rotation_deg) < SUCCESS_ROTATION_RAD and rel_translation < SUCCESS_REL_TRANSLATION
    )


def trial_record(
    method: str,
    trial: int,
    reported: bool,
    errors: tuple[float, float, float] | None,
    seconds: float,
    num_inliers: int = 0,
    reason: str = "",
) -> dict[str, Any]:
    """Returns one trial as a flat dict; ``success`` applies the paper's criterion to ``errors``.

    errors: ``geometry.pose_errors`` (rotation deg, position m, relative translation) or None (no pose).
    """
    rot, pos, rel = errors if errors is not None else (math.nan, math.nan, math.nan)
    success = bool(reported and meets_criterion(rot, rel))
    return {
        "method": method,
        "trial": trial,
        "success": success,
        "reported": bool(reported),
        "rotation_deg": rot,
        "position_m": pos,
        "rel_translation": rel,
        "time_ms": 1e3 * seconds,
        "num_inliers": int(num_inliers),
        "reason": reason,
    }


def cell_stats(trials: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Returns success rate, pose errors over the successful trials, runtime over all trials.

    Keys: n, num_success, success_rate, wrong_claimed (a pose reported as success outside the criterion:
    the worst outcome, shown beside every success rate), rotation_deg_median/_rmse,
    rel_translation_median/_rmse, position_m_median (NaN without successes), time_ms_median, time_ms_p95.
    """
    ok = [t for t in trials if t["success"]]
    rot = np.array([t["rotation_deg"] for t in ok])
    rel = np.array([t["rel_translation"] for t in ok])
    pos = np.array([t["position_m"] for t in ok])
    ms = np.array([t["time_ms"] for t in trials])
    return {
        "n": len(trials),
        "num_success": len(ok),
        "success_rate": len(ok) / len(trials) if trials else math.nan,
        "wrong_claimed": sum(1 for t in trials if t.get("reported") and not t["success"]),
        "rotation_deg_median": _median(rot),
        "rotation_deg_rmse": _rmse(rot),
        "rel_translation_median": _median(rel),
        "rel_translation_rmse": _rmse(rel),
        "position_m_median": _median(pos),
        "time_ms_median": _median(ms),
        "time_ms_p95": float(np.percentile(ms, 95)) if len(ms) else math.nan,
    }


def failure_reasons(trials: Sequence[dict[str, Any]], top: int = 3) -> dict[str, int]:
    """Returns the ``top`` most frequent reasons of trials that were not successful, with their counts.

    A pose reported but outside the success criterion counts as "pose off" (it has no reason of its own).
    """
    reasons = Counter(t["reason"] or "pose off" for t in trials if not t["success"])
    return dict(reasons.most_common(top))


def _median(a: np.ndarray) -> float:
    return float(np.median(a)) if len(a) else math.nan


def _rmse(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2))) if len(a) else math.nan


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """Returns an aligned text table; columns are (key, header, format spec such as ``.1f``); NaN -> '-'."""
    cells = [[header for _, header, _ in columns]]
    for row in rows:
        cells.append([_format(row.get(key), spec) for key, _, spec in columns])
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _format(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, spec) if spec else str(value)


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Returns ``path`` after writing ``data`` atomically (``io.write_bytes_atomic``: temp file + rename)."""
    from ..io import write_bytes_atomic

    write_bytes_atomic(path, data)
    return Path(path)


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    """Returns ``path`` after ``io.write_json_atomic`` wrote ``obj`` there (the one JSON writer: NaN -> null)."""
    from ..io import write_json_atomic as write

    write(path, obj)
    return Path(path)


def plot_series(
    path: str | Path,
    series: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    xlabel: str,
    ylabel: str,
    title: str = "",
    logy: bool = False,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """Returns ``path`` after atomically saving a PNG with one marked line per series label -> (x, y)."""
    fig, ax = new_figure()
    for label, (x, y) in series.items():
        ax.plot(x, y, marker="o", label=label)
    style_axes(ax, xlabel, ylabel, title, logy, ylim)
    return save_figure(fig, path)


def new_figure(ncols: int = 1, width_in: float = 5.0, height_in: float = 3.6) -> tuple[Any, Any]:
    """Returns (figure, axes) drawn by the Agg canvas; several axes when ``ncols > 1``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in * ncols, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, ncols)


def style_axes(ax: Any, xlabel: str, ylabel: str, title: str = "", logy: bool = False, ylim=None) -> None:
    """Labels, grid and legend in the benchmarks' common style."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if logy:
        ax.set_yscale("log")
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()


def save_figure(fig: Any, path: str | Path, dpi: int = 120) -> Path:
    """Returns ``path`` after rendering ``fig`` to PNG and writing it atomically."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return write_atomic(path, buf.getvalue())


def by_key(rows: Iterable[dict[str, Any]], key: str) -> dict[Any, list[dict[str, Any]]]:
    """Returns rows grouped by ``row[key]``, groups in first-seen order."""
    groups: dict[Any, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(row[key], []).append(row)
    return groups
