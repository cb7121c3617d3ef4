"""3D line extraction: time and peak memory on a ~1 M-point demo scan, recall of the building's true edges.

``linereg bench lines3d [--points 1000000] [--seed 0] [--rectangles] [--out DIR]``.

The demo building is scanned (``demo_scene``'s simulated terrestrial scanner, ``DEMO_SCAN``) and the scan
is subsampled to ``--points`` points (the scanner's own ``target_points``; a denser request than its
~2 M raw hits gets them all).
``lines3d.extract`` runs in a child process, so its peak resident memory (``ru_maxrss``) is not inflated by
this process (the scene, the renderer); the child's memory before extraction (Python, numpy, open3d, the
points) is reported too. Targets (issue 3): <= 10 s and <= 4 GB for 1 M points.

Recall: a true edge of the building (``Building.edges``) longer than ``--min-length-m`` (0.5) counts as
recovered when extracted segments within 2 deg of its direction pass within 5 cm of at least half of it
(sampled every 2 cm; distance point-to-segment). It is given over all such edges and over the ``scanned``
ones (at least half of the edge has a scan point within 15 cm, about the scan's spacing at 30 m: an edge
on faces no scanner saw cannot be found). Precision is the same test the other way round (extracted segments near a true edge). Target: >= 80 %.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import report

TARGETS = {"seconds": 10.0, "peak_gb": 2.0, "recall": 0.63}  # issue 10: per 10^6 points; keep 63 %
DISTANCE_M = 0.05
ANGLE_DEG = 2.0
STEP_M = 0.02
MIN_COVER = 0.5
SCANNED_RADIUS_M = 0.15  # the scan's point spacing reaches ~13 cm at 30 m (0.25 deg rays)
_CHILD = "import sys; from linereg.bench.lines3d import child_main; child_main(sys.argv[1], sys.argv[2], *sys.argv[3:])"


def child_main(
    points_path: str, map_path: str, overrides: str = "{}", intensity_path: str = "", rings_path: str = ""
) -> None:
    """Runs ``LineMap.build`` on the points of an .npy file (their intensities and rings, more .npy, if given)
    with MapBuildConfig fields overridden by a JSON object (nested per section); prints JSON (seconds, RSS
    KiB), saves the map. The clock starts after a small generated room is built (``warm.warm_up_map``): what a
    process pays once (imports, compiled kernels loaded from numba's cache) is reported on its own."""
    import resource
    import time

    from ..config import MapBuildConfig
    from ..map.linemap import LineMap
    from ..warm import warm_up_map

    points = np.load(points_path)
    intensity = np.load(intensity_path) if intensity_path else None
    rings = np.load(rings_path) if rings_path else None
    config = MapBuildConfig.from_dict(json.loads(overrides))
    start = time.perf_counter()
    warm_up_map(config)
    warm = time.perf_counter() - start
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    line_map = LineMap.build(points, config, intensity=intensity, rings=rings)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    line_map.save(map_path)
    # ru_maxrss is in KiB on Linux
    stats = {"seconds": seconds, "cpu_seconds": cpu, "warm_seconds": warm, "rss_before_kib": before.ru_maxrss}
    print(json.dumps(stats | {"peak_rss_kib": after.ru_maxrss}))


def build_in_child(
    points: np.ndarray,
    overrides: dict[str, Any] | None = None,
    intensity: np.ndarray | None = None,
    rings: np.ndarray | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Returns (LineMap, {seconds, cpu_seconds, warm_seconds, rss_before_gb, peak_gb}) of ``LineMap.build``
    (``warm_seconds``: the child's start before it, ``child_main``) in a child
    process, with MapBuildConfig fields ``overrides`` (nested per section) and the points' ``intensity`` and
    ``rings`` (a file's ring field)."""
    from ..errors import LineregError
    from ..map.linemap import LineMap

    with tempfile.TemporaryDirectory(prefix="linereg-bench-") as tmp:
        points_path, map_path = Path(tmp) / "points.npy", Path(tmp) / "map.npz"
        np.save(points_path, points)
        extra = ["", ""]
        for k, values in enumerate((intensity, rings)):
            if values is not None:
                extra[k] = str(Path(tmp) / f"field{k}.npy")
                np.save(extra[k], values)
        proc = subprocess.run(
            [
                sys.executable,
                "-c",
                _CHILD,
                str(points_path),
                str(map_path),
                json.dumps(overrides or {}),
                *extra,
            ],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise LineregError(
                f"map building child failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}"
            )
        stats = json.loads(proc.stdout.strip().splitlines()[-1])
        line_map = LineMap.load(map_path)
    return line_map, {
        "seconds": stats["seconds"],
        "cpu_seconds": stats["cpu_seconds"],
        "warm_seconds": stats["warm_seconds"],
        "rss_before_gb": stats["rss_before_kib"] / 2**20,
        "peak_gb": stats["peak_rss_kib"] / 2**20,
    }


def extract_in_child(
    points: np.ndarray, overrides: dict[str, Any] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Returns ((M, 6) segments, cost) of ``build_in_child`` with Lines3DConfig fields ``overrides``."""
    line_map, cost = build_in_child(points, {"lines3d": overrides or {}})
    return line_map.segments, cost


def coverage(
    truth: np.ndarray, found: np.ndarray, distance_m: float = DISTANCE_M, angle_deg: float = ANGLE_DEG
) -> np.ndarray:
    """Returns (E,) the fraction of each (E, 6) true segment within ``distance_m`` of a parallel found one.

    A point of a true segment (sampled every STEP_M) is covered when some (M, 6) found segment whose
    direction is within ``angle_deg`` lies within ``distance_m`` of it (point-to-segment distance).
    """
    out = np.zeros(len(truth))
    if not len(found):
        return out
    fa, fd = found[:, :3], found[:, 3:] - found[:, :3]
    f_len = np.linalg.norm(fd, axis=1)
    f_dir = fd / np.maximum(f_len, 1e-12)[:, None]
    cos_min = np.cos(np.radians(angle_deg))
    for e, seg in enumerate(truth):
        d = seg[3:] - seg[:3]
        length = float(np.linalg.norm(d))
        u = d / max(length, 1e-12)
        near = _near_line(fa, fd, seg[:3], u, distance_m) & (np.abs(f_dir @ u) >= cos_min)
        if not near.any():
            continue
        samples = seg[:3] + np.linspace(0.0, 1.0, max(2, int(length / STEP_M) + 1))[:, None] * d
        dist = _point_segment_distance(samples, fa[near], fd[near])
        out[e] = float((dist.min(axis=1) <= distance_m).mean())
    return out


def _near_line(a: np.ndarray, d: np.ndarray, p0: np.ndarray, u: np.ndarray, radius: float) -> np.ndarray:
    """Returns (M,) bool: does segment ``a + s d`` (s in [0, 1]) come within ``radius`` of line p0 + r u?"""
    w = a - p0
    w_perp = w - (w @ u)[:, None] * u  # the components across the line: distance is |w_perp + s d_perp|
    d_perp = d - (d @ u)[:, None] * u
    s = np.clip(
        -np.einsum("mk,mk->m", w_perp, d_perp) / np.maximum(np.einsum("mk,mk->m", d_perp, d_perp), 1e-18),
        0,
        1,
    )
    return np.linalg.norm(w_perp + s[:, None] * d_perp, axis=1) <= radius


def _point_segment_distance(points: np.ndarray, a: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Returns (S, C) distances of (S, 3) points to (C,) segments ``a + s d``, s in [0, 1]."""
    w = points[:, None, :] - a[None, :, :]
    s = np.clip(np.einsum("sck,ck->sc", w, d) / np.maximum(np.einsum("ck,ck->c", d, d), 1e-18), 0.0, 1.0)
    return np.linalg.norm(w - s[:, :, None] * d[None, :, :], axis=2)


def scanned(edges: np.ndarray, cloud: np.ndarray, distance_m: float = SCANNED_RADIUS_M) -> np.ndarray:
    """Returns (E,) bool: has at least half of each (E, 6) edge a cloud point within ``distance_m``?"""
    from scipy.spatial import cKDTree

    tree = cKDTree(cloud)
    out = np.zeros(len(edges), dtype=bool)
    for e, seg in enumerate(edges):
        n = max(2, int(np.linalg.norm(seg[3:] - seg[:3]) / (5 * STEP_M)) + 1)
        samples = seg[:3] + np.linspace(0.0, 1.0, n)[:, None] * (seg[3:] - seg[:3])
        dist, _ = tree.query(samples, distance_upper_bound=distance_m)
        out[e] = np.isfinite(dist).mean() >= MIN_COVER
    return out


def recall_table(
    building: Any, cloud: np.ndarray, segments: np.ndarray, min_length_m: float
) -> list[dict[str, Any]]:
    """Returns one row per edge kind and one for all: edges, scanned, recall over all and over scanned."""
    from ..geometry import segment_lengths

    long = segment_lengths(building.edges) > min_length_m
    edges, kinds = building.edges[long], building.edge_kind[long]
    recovered = coverage(edges, segments) >= MIN_COVER
    seen = scanned(edges, cloud)
    rows = []
    for kind in [*dict.fromkeys(kinds.tolist()), "all"]:
        mask = np.ones(len(edges), bool) if kind == "all" else kinds == kind
        rows.append(
            {
                "kind": kind,
                "edges": int(mask.sum()),
                "scanned": int((mask & seen).sum()),
                "recall": float(recovered[mask].mean()) if mask.any() else float("nan"),
                "recall_scanned": float(recovered[mask & seen].mean())
                if (mask & seen).any()
                else float("nan"),
            }
        )
    return rows


def precision(building: Any, segments: np.ndarray, min_length_m: float) -> float:
    """Returns the fraction of extracted segments longer than ``min_length_m`` lying on a true edge."""
    from ..geometry import segment_lengths

    long = segments[segment_lengths(segments) > min_length_m]
    return float((coverage(long, building.edges) >= MIN_COVER).mean()) if len(long) else float("nan")


def demo_scan(seed: int, num_points: int) -> tuple[Any, np.ndarray]:
    """Returns (building, scan): the demo scene's scan subsampled to at most ``num_points`` points."""
    from dataclasses import replace

    from ..sim.demo_scene import DEMO_SCAN, make_demo_scene

    scene = make_demo_scene(seed=seed, num_images=0, scan_config=replace(DEMO_SCAN, target_points=num_points))
    return scene.building, np.asarray(scene.cloud, dtype=np.float64)


RECALL_COLUMNS = (
    ("kind", "edge kind", ""),
    ("edges", "edges", "d"),
    ("scanned", "scanned", "d"),
    ("recall", "recall", ".1%"),
    ("recall_scanned", "recall (scanned)", ".1%"),
)


def configure(parser: argparse.ArgumentParser) -> None:
    """Adds the ``bench lines3d`` arguments and sets ``func=run``."""
    parser.add_argument("--points", type=int, default=1_000_000, help="points extracted (default 1000000)")
    parser.add_argument("--seed", type=int, default=0, help="demo scene seed (default 0)")
    parser.add_argument("--min-length-m", type=float, default=0.5, help="true edges longer than this count")
    parser.add_argument("--out", type=Path, default=Path("bench-results/lines3d"), help="output directory")
    parser.add_argument(
        "--rectangles", action="store_true", help="Lines3DConfig(rectangles=True): rectangle candidates too"
    )
    parser.add_argument(
        "--real",
        type=Path,
        default=None,
        metavar="DIR",
        help="also judge maps of the real scenes in DIR (folders with cameras.json + cloud.ply) at their photos' true poses",
    )
    parser.add_argument(
        "--overlay", action="store_true", help="with --real: write overlay PNGs of map vs photo"
    )
    parser.add_argument("--no-demo", action="store_true", help="with --real: skip the demo scan")
    parser.add_argument(
        "--intensity-edges",
        action="store_true",
        help="MapBuildConfig(intensity_edges=True): the steps of a sweep's intensity too",
    )
    parser.add_argument(
        "--map-config",
        default="{}",
        metavar="JSON",
        help='MapBuildConfig overrides, nested per section, e.g. \'{"lines3d": {"min_length_m": 0.2}}\'',
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Runs map building in a child, scores the segments, prints the tables, writes results.json."""
    from ..config import MapBuildConfig
    from ..errors import InvalidInputError

    if args.points < 1000:
        raise InvalidInputError(f"--points must be >= 1000, got {args.points}")
    try:
        overrides = json.loads(args.map_config)
        MapBuildConfig.from_dict(overrides)
    except ValueError as e:
        raise InvalidInputError(f"--map-config: a JSON object of MapBuildConfig fields ({e})") from None
    if args.rectangles:
        overrides.setdefault("lines3d", {})["rectangles"] = True
    if args.intensity_edges:
        overrides["intensity_edges"] = True
    results: dict[str, Any] = {"benchmark": "lines3d", "options": {"map_config": overrides}}
    if not (args.real and args.no_demo):
        results |= run_demo(args, overrides)
    if args.real:
        from .lines3d_real import run_real

        results["real"] = run_real(args.real, overrides, args.out, args.overlay)
    path = report.write_json_atomic(args.out / "results.json", results)
    print(f"wrote {path}", file=sys.stderr)
    return 0


def run_demo(args: argparse.Namespace, overrides: dict[str, Any]) -> dict[str, Any]:
    """Returns the demo scan's results (recall of the true edges, precision, cost); prints its tables."""
    print("scanning the demo building ...", file=sys.stderr, flush=True)
    building, points = demo_scan(args.seed, args.points)
    print(f"building the map of {len(points):,} points in a child process ...", file=sys.stderr, flush=True)
    line_map, cost = build_in_child(points, overrides)
    segments = line_map.segments
    rows = recall_table(building, points, segments, args.min_length_m)
    prec = precision(building, segments, args.min_length_m)
    print(report.format_table(rows, RECALL_COLUMNS))
    every = rows[-1]
    print()
    print(f"points {len(points):,} -> {len(segments):,} segments; precision {prec:.1%}")
    checks = (
        (
            "time",
            f"{cost['seconds']:.1f} s",
            f"<= {TARGETS['seconds']:g} s",
            cost["seconds"] <= TARGETS["seconds"],
        ),
        (
            "peak RSS",
            f"{cost['peak_gb']:.2f} GB",
            f"<= {TARGETS['peak_gb']:g} GB",
            cost["peak_gb"] <= TARGETS["peak_gb"],
        ),
        (
            "recall",
            f"{every['recall']:.1%}",
            f">= {TARGETS['recall']:.0%}",
            every["recall"] >= TARGETS["recall"],
        ),
    )
    for name, value, target, ok in checks:
        print(f"{name:>15}: {value:>9}  target {target:<9} {'met' if ok else 'NOT met'}")
    print(
        f"(child CPU time {cost['cpu_seconds']:.1f} s; child RSS before building {cost['rss_before_gb']:.2f} GB; "
        f"the child's start before it, imports and compiled kernels: {cost['warm_seconds']:.1f} s)"
    )
    buffer = io.BytesIO()
    np.save(buffer, segments)
    report.write_atomic(args.out / "segments.npy", buffer.getvalue())
    return {
        "demo": {
            "options": {"points": args.points, "seed": args.seed, "min_length_m": args.min_length_m},
            "criterion": {"distance_m": DISTANCE_M, "angle_deg": ANGLE_DEG, "min_cover": MIN_COVER},
            "targets": TARGETS,
            "num_points": len(points),
            "num_segments": len(segments),
            "kinds": line_map.info()["kinds"],
            "cost": cost,
            "recall": rows,
            "precision": prec,
        }
    }
