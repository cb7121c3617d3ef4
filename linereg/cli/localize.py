"""``linereg localize --map MAP --camera CAMERA IMAGE... --out poses.json [--tum F] [--overlay DIR]``.

Localizes many images in one map: a process pool (each worker loads the map once), results saved
atomically every few images so a killed batch loses nothing and ``--resume`` skips what is done.
An image that cannot be used (unreadable, corrupt, another size than its camera) does not stop the batch:
it is recorded as failed, named on stderr, and the command exits with 2 at the end.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from ..errors import InvalidInputError, LineregError
from .progress import Progress

log = logging.getLogger(__name__)
_worker_state: dict = {}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("localize", help="localize images in a line map", description=__doc__)
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE")
    p.add_argument("--map", required=True, type=Path, help="line map from `linereg map build`")
    p.add_argument(
        "--camera", required=True, type=Path, help="camera JSON (shared or per image) or COLMAP cameras.txt"
    )
    p.add_argument("--out", type=Path, default=Path("poses.json"), help="JSON results (default poses.json)")
    p.add_argument("--tum", type=Path, help="also write the successful poses as a TUM trajectory")
    p.add_argument("--overlay", type=Path, metavar="DIR", help="write one overlay PNG per image here")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--resume", action="store_true", help="skip images already in --out")
    p.add_argument(
        "--config", type=Path, help="JSON file of registration overrides, nested per section (default: none)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io

    if args.workers < 1:
        raise InvalidInputError(f"--workers must be >= 1, got {args.workers}")
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:
        raise InvalidInputError(f"image file(s) not found: {', '.join(missing[:5])}")
    cameras = io.read_cameras(args.camera)
    jobs = [(str(p), _camera_for(cameras, p, args.camera)) for p in args.images]
    results = io.read_json(args.out) if args.resume and args.out.exists() else {}
    jobs = [j for j in jobs if j[0] not in results]
    overlay_dir = str(args.overlay) if args.overlay else None
    progress = Progress(len(jobs), "localize")
    init = (str(args.map), overlay_dir, str(args.config) if args.config else None)
    last_save = time.monotonic()
    with _executor(args.workers, init) as pool:
        for path, record in pool.map(_localize_one, jobs):
            results[path] = record
            progress.update(1, f"{Path(path).name}: {'ok' if record['success'] else 'failed'}")
            if time.monotonic() - last_save > 5.0:  # periodic atomic save: a killed batch resumes here
                io.write_json_atomic(args.out, results)
                last_save = time.monotonic()
    progress.close()
    io.write_json_atomic(args.out, results)
    if args.tum:
        ok = [(p, r) for p, r in results.items() if r["success"]]
        io.write_tum(args.tum, [Path(p).name for p, _ in ok], [r["cam_from_world"] for _, r in ok])
    done = sum(r["success"] for r in results.values())
    print(f"localized {done}/{len(results)} images -> {args.out}", file=sys.stderr)
    bad = {p: r["reason"] for p, r in results.items() if r.get("input_error")}
    for reason in bad.values():
        print(f"linereg localize: error: {reason}", file=sys.stderr)
    return 2 if bad else 0


def _camera_for(cameras, image: Path, source: Path):
    if not isinstance(cameras, dict):
        return cameras
    for key in (str(image), image.name, image.stem):
        if key in cameras:
            return cameras[key]
    raise InvalidInputError(f"{source}: no camera for image {image.name}")


class _InlineExecutor:
    """The same interface as a process pool, in this process (workers=1: no pickling, easy debugging)."""

    def __init__(self, init: tuple) -> None:
        _init_worker(*init)

    def map(self, fn, items):
        return map(fn, items)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None


def _executor(workers: int, init: tuple):
    if workers == 1:
        return _InlineExecutor(init)
    return ProcessPoolExecutor(workers, initializer=_init_worker, initargs=init)


def _init_worker(map_path: str, overlay_dir: str | None, config_path: str | None) -> None:
    from .. import io
    from ..config import RegisterConfig
    from ..map.linemap import LineMap

    _worker_state["map"] = LineMap.load(map_path)
    _worker_state["config"] = io.read_config(config_path) if config_path else RegisterConfig()
    _worker_state["overlay_dir"] = overlay_dir


def _localize_one(job: tuple) -> tuple[str, dict]:
    from .. import io
    from ..lines2d import detect
    from ..localization import localize
    from ..overlay import draw_overlay

    path, camera = job
    line_map = _worker_state["map"]
    try:
        image = io.read_image(path)
        result = localize(image, line_map, camera, _worker_state["config"])
    except LineregError as e:  # a bad input file: named at the end, the batch goes on
        message = str(e) if path in str(e) else f"{path}: {e}"
        return path, {"success": False, "reason": message, "input_error": True}
    except Exception as e:  # one failing image must not end a batch of thousands
        log.exception("%s: localization failed", path)
        return path, {"success": False, "reason": f"{path}: {type(e).__name__}: {e}"}
    overlay_dir = _worker_state["overlay_dir"]
    if overlay_dir:
        lines2d = detect(image, camera)  # the same segments localize found (detection is deterministic)
        picture = draw_overlay(image, camera.undistorted(), lines2d, line_map.segments, result)
        io.write_image_atomic(os.path.join(overlay_dir, Path(path).stem + ".png"), picture)
    record = result.to_dict()
    record.pop("matches")
    return path, record
