"""``linereg demo``: the whole job on the built-in scene, no download.

A procedural building is scanned (simulated terrestrial laser scanner) and photographed from known poses;
the cloud becomes a line map, a localization service (zenoh on loopback, one worker process) loads it, every
photo is sent to it as a PNG query, and a table compares the returned poses with the truth. The map
(demo.linemap) and one overlay per photo (detected lines red, matched map lines green, other map lines
grey, with a legend and the outcome) go to ``--out``. ``--in-process`` skips the service. The compiled
kernels of the localization are made ready (``linereg.warm_up``) in a process of their own while the scene
is scanned and mapped.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import check_output_dir, description
from .progress import Progress

CORRECT_DEG, CORRECT_M = 2.0, 0.5  # a returned pose this close to the truth counts as right


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="localize the built-in demo scene's photos in its scan",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--images", type=int, default=10, help="number of photos (default 10)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("linereg-demo"),
        help="folder for the map and the overlays (default linereg-demo)",
    )
    p.add_argument("--in-process", action="store_true", help="call linereg.localize directly, no service")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io
    from ..geometry import pose_errors
    from ..lines2d import detect
    from ..map.linemap import LineMap
    from ..overlay import draw_overlay
    from ..sim.demo_scene import make_demo_scene

    check_output_dir("--out", args.out)
    t0 = time.perf_counter()
    # the localization's compiled kernels are compiled (a fresh install) or loaded by a process of their own
    # while the scene is scanned and mapped, instead of in the first photo's query
    warming = multiprocessing.get_context("spawn").Process(target=_warm_up, daemon=True)
    try:
        warming.start()
    except OSError as e:  # an optimisation: the service's worker compiles them itself
        say(f"  (no warm-up process: {e})")
    say(f"building the demo scene (seed {args.seed}, {args.images} photos) ...")
    scene = make_demo_scene(seed=args.seed, num_images=args.images)
    say(f"  scan: {len(scene.cloud):,} points; building the line map ...")
    line_map = LineMap.build(scene.cloud, name="demo")
    say(f"  map: {len(line_map.segments):,} segments in {time.perf_counter() - t0:.1f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    map_path = args.out / "demo.linemap"
    line_map.save(map_path)
    if warming.pid is not None:  # what it has not compiled yet, the service's worker would compile again
        warming.join(timeout=600.0)
        if warming.is_alive():
            warming.terminate()
    with _localizer(map_path, line_map, args.in_process) as localize_image:
        rows = []
        with Progress(len(scene.images), "localize") as progress:
            for k, (image, truth) in enumerate(zip(scene.images, scene.cam_from_world, strict=True)):
                start = time.perf_counter()
                result = localize_image(image, scene.camera)
                ms = 1e3 * (time.perf_counter() - start)
                errors = pose_errors(result.cam_from_world, truth) if result.success else (np.nan,) * 3
                rows.append((k, result, errors, ms))
                lines2d = detect(image, scene.camera)
                picture = draw_overlay(image, scene.camera, lines2d, line_map.segments, result)
                io.write_image_atomic(args.out / f"demo_{k:02d}.png", picture)
                progress.update(1, "ok" if result.success else "failed")
    print_table(rows)
    say(f"overlays in {args.out}/   whole demo {time.perf_counter() - t0:.1f} s")
    return 0


def _warm_up() -> None:
    from ..warm import warm_up

    warm_up()


@contextmanager
def _localizer(map_path: Path, line_map, in_process: bool) -> Iterator[Callable]:
    """Yields ``localize(image, camera) -> Registration``: through a loopback service, or in this process."""
    if in_process:
        from ..localization import localize

        yield lambda image, camera: localize(image, line_map, camera)
        return
    from service.local import local_service  # the service layer, imported only by this entry point

    say("  starting the localization service on loopback ...")
    with local_service(str(map_path), workers=1) as client:
        yield lambda image, camera: client.localize(image, camera, timeout=60.0)


def print_table(rows: list) -> None:
    print(f"{'image':>5} {'ok':>3} {'inliers':>7} {'ambig':>5} {'R_e deg':>8} {'pos m':>7} {'ms':>6}  reason")
    for k, res, (rot, pos, _), ms in rows:
        flag = "yes" if res.success else "no"
        line = (
            f"{k:>5} {flag:>3} {res.num_inliers:>7} {res.ambiguity:>5.2f} {rot:>8.3f} {pos:>7.3f} {ms:>6.0f}"
        )
        print(line + f"  {res.reason}")
    ok = [r for r in rows if r[1].success]
    if not ok:
        print(f"localized 0/{len(rows)}")
        return
    rot = float(np.median([r[2][0] for r in ok]))
    pos = float(np.median([r[2][1] for r in ok]))
    right = sum(r[2][0] < CORRECT_DEG and r[2][1] < CORRECT_M for r in ok)
    print(
        f"localized {len(ok)}/{len(rows)} photos, {right} of them right "
        f"(R_e < {CORRECT_DEG:g} deg, position < {CORRECT_M:g} m); "
        f"median R_e {rot:.3f} deg, median position error {pos:.3f} m"
    )


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
