"""``linereg demo``: the whole job on the built-in scene, no download.

A procedural building is scanned (simulated terrestrial laser scanner) and photographed from known poses;
the cloud becomes a line map, every photo is localized in it, and a table compares the poses with the truth.
Overlays (photo, detected lines red, matched map lines green) go to ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .progress import Progress


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="localize the built-in demo scene's photos in its scan", description=__doc__
    )
    p.add_argument("--images", type=int, default=10, help="number of photos (default 10)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument(
        "--out", type=Path, default=Path("linereg-demo"), help="overlay folder (default linereg-demo)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io
    from ..demo_scene import make_demo_scene
    from ..geometry import pose_errors
    from ..linemap import LineMap
    from ..lines2d import detect
    from ..localization import localize_segments
    from ..overlay import draw_overlay

    t0 = time.perf_counter()
    say(f"building the demo scene (seed {args.seed}, {args.images} photos) ...")
    scene = make_demo_scene(seed=args.seed, num_images=args.images)
    say(f"  scan: {len(scene.cloud):,} points; building the line map ...")
    line_map = LineMap.build(scene.cloud, name="demo")
    say(f"  map: {len(line_map.segments):,} segments in {time.perf_counter() - t0:.1f} s")
    progress = Progress(len(scene.images), "localize")
    rows = []
    for k, (image, truth) in enumerate(zip(scene.images, scene.cam_from_world, strict=True)):
        lines2d = detect(image, scene.camera)
        start = time.perf_counter()
        result = localize_segments(lines2d, line_map, scene.camera)
        ms = 1e3 * (time.perf_counter() - start)
        errors = pose_errors(result.cam_from_world, truth) if result.success else (np.nan,) * 3
        rows.append((k, result, errors, ms))
        picture = draw_overlay(image, scene.camera, lines2d, line_map.segments, result)
        io.write_image_atomic(args.out / f"demo_{k:02d}.png", picture)
        progress.update(1, "ok" if result.success else "failed")
    progress.close()
    print_table(rows)
    say(f"overlays in {args.out}/   whole demo {time.perf_counter() - t0:.1f} s")
    return 0


def print_table(rows: list) -> None:
    print(f"{'image':>5} {'ok':>3} {'inliers':>7} {'ambig':>5} {'R_e deg':>8} {'pos m':>7} {'ms':>6}  reason")
    for k, res, (rot, pos, _), ms in rows:
        ok = "yes" if res.success else "no"
        line = f"{k:>5} {ok:>3} {res.num_inliers:>7} {res.ambiguity:>5.2f} {rot:>8.3f} {pos:>7.3f} {ms:>6.0f}"
        print(line + f"  {res.reason}")
    ok = [r for r in rows if r[1].success]
    if ok:
        rot = np.median([r[2][0] for r in ok])
        pos = np.median([r[2][1] for r in ok])
        print(f"localized {len(ok)}/{len(rows)}; median R_e {rot:.3f} deg, median position error {pos:.3f} m")
    else:
        print(f"localized 0/{len(rows)}")


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
