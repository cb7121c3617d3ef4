"""A 10⁶-segment map: the demo block repeated on a grid; queries with a position prior and without one.

``linereg bench large [--grid 22] [--photos 4] [--radius 40] [--no-prior-grids 4 8] [--out DIR]``.

The demo scene of ``--seed`` (scan, line map, rendered photos with known poses) is copied on a
``--grid`` x ``--grid`` grid (``sim.tiled``; 22 x 22 copies of the 2,096-segment block: ~10⁶ segments),
and the map prepared for queries as a service worker prepares it (``localization.prepare_map``: corner
points, chunks, the occlusion scene; its time reported apart). Each photo is localized with
``Prior(position, radius_m=--radius)`` whose centre lies ``--prior-offset`` m from the true camera centre
(issue 9: ≤ 150 ms), the first query timed apart. Without a prior the photos are localized in smaller
grids (``--no-prior-grids``): a repeated map must never be claimed (issue 9: an answer, ambiguous, ≤ 10 s
at 10⁶ segments); the times show how the query grows with the map. Right is the paper's criterion
(``report.meets_criterion``); "wrong but claimed" is a success outside it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grid", type=int, default=22, help="copies per side with a prior (default 22)")
    parser.add_argument("--seed", type=int, default=0, help="demo scene seed (default 0)")
    parser.add_argument("--photos", type=int, default=4, help="photos localized per case (default 4)")
    parser.add_argument("--radius", type=float, default=40.0, help="the prior's radius m (default 40)")
    parser.add_argument(
        "--prior-offset", type=float, default=10.0, help="the prior's centre from the truth, m (default 10)"
    )
    parser.add_argument(
        "--no-prior-grids",
        type=int,
        nargs="*",
        default=[4, 8],
        help="copies per side of the maps queried without a prior (default 4 8; none: skip)",
    )
    parser.add_argument("--out", type=Path, default=Path("bench-results/large"), help="output directory")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import check_output_dir
    from ..errors import InvalidInputError
    from ..map.linemap import LineMap
    from ..sim.demo_scene import make_demo_scene

    counts = [("--grid", args.grid), ("--photos", args.photos)]
    for flag, value in counts + [("--no-prior-grids", n) for n in args.no_prior_grids]:
        if value < 1:
            raise InvalidInputError(f"{flag} must be >= 1, got {value}")
    if not args.radius > 0:
        raise InvalidInputError(f"--radius must be > 0, got {args.radius}")
    if not args.prior_offset >= 0:
        raise InvalidInputError(f"--prior-offset must be >= 0, got {args.prior_offset}")
    check_output_dir("--out", args.out)
    start = time.perf_counter()
    scene = make_demo_scene(seed=args.seed, num_images=args.photos)
    base = LineMap.build(scene.cloud)
    print(f"demo block: {len(base)} segments, {args.photos} photos in {time.perf_counter() - start:.0f} s")
    rows = [_case(scene, base, args.grid, args, prior=True)]
    rows += [_case(scene, base, n, args, prior=False) for n in args.no_prior_grids]
    _print(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(
        json.dumps({"args": _jsonable(vars(args)), "rows": rows}, indent=1)
    )
    print(f"wrote {args.out / 'results.json'}")
    return 0


def _case(scene: Any, base: Any, n: int, args: argparse.Namespace, prior: bool) -> dict[str, Any]:
    """Returns one row: the map of ``n`` x ``n`` copies, every photo localized (with or without a prior)."""
    from ..geometry import camera_center, pose_errors
    from ..localization import localize, prepare_map
    from ..priors import Prior
    from ..sim.tiled import tiled_map
    from . import report

    start = time.perf_counter()
    line_map, _ = tiled_map(base, n)
    made = time.perf_counter() - start
    start = time.perf_counter()
    prepare_map(line_map)  # as a service worker does before its first query (``warm_up`` with its map)
    prepared = time.perf_counter() - start
    print(f"  {n}x{n}: {len(line_map):,d} segments, prepared for queries in {prepared:.1f} s", flush=True)
    rng = np.random.default_rng(args.seed)
    trials = []
    for k, (image, truth) in enumerate(zip(scene.images, scene.cam_from_world, strict=True)):
        where = None
        if prior:
            direction = rng.normal(size=3)
            centre = camera_center(truth) + args.prior_offset * direction / np.linalg.norm(direction)
            where = Prior(position=centre, radius_m=args.radius)
        start = time.perf_counter()
        result = localize(image, line_map, scene.camera, prior=where)
        seconds = time.perf_counter() - start
        rot, pos, rel = pose_errors(result.cam_from_world, truth) if result.cam_from_world is not None else (
            float("nan"), float("nan"), float("nan"),
        )  # fmt: skip
        right = report.meets_criterion(rot, rel)
        trials.append({
            "photo": k, "seconds": seconds, "success": result.success, "right": bool(result.success and right),
            "wrong_claimed": bool(result.success and not right), "rot_deg": rot, "pos_m": pos,
            "alternatives": 0 if result.alternatives is None else len(result.alternatives),
            "reason": result.reason,
        })  # fmt: skip
        print(
            f"  {n}x{n} {'prior' if prior else 'no prior'} photo {k}: {seconds:.2f} s, "
            f"{'claimed' if result.success else 'not claimed'}, {rot:.2f} deg / {pos:.2f} m {result.reason[:70]}",
            flush=True,
        )
    times = np.array([t["seconds"] for t in trials])
    return {
        "grid": n, "segments": len(line_map), "prior": prior, "map_s": made, "prepare_s": prepared,
        "photos": len(trials),
        "right": sum(t["right"] for t in trials), "wrong_claimed": sum(t["wrong_claimed"] for t in trials),
        "first_s": float(times[0]), "median_s": float(np.median(times)),
        "median_after_first_s": float(np.median(times[1:])) if len(times) > 1 else None, "trials": trials,
    }  # fmt: skip


def _print(rows: list[dict[str, Any]]) -> None:
    print()
    print(f"{'map':>14s} {'segments':>10s} {'prior':>8s} {'right':>6s} {'wrong claimed':>14s} "
          f"{'first s':>8s} {'median s':>9s} {'later median s':>15s}")  # fmt: skip
    for r in rows:
        later = "-" if r["median_after_first_s"] is None else f"{r['median_after_first_s']:.2f}"
        print(
            f"{r['grid']:>6d} x {r['grid']:<5d} {r['segments']:>10,d} {'yes' if r['prior'] else 'no':>8s} "
            f"{r['right']:>3d}/{r['photos']:<2d} {r['wrong_claimed']:>14d} {r['first_s']:>8.2f} "
            f"{r['median_s']:>9.2f} {later:>15s}"
        )


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in d.items() if k != "func"}
