"""``linereg localize``: the pose of every image in a line map, as JSON (and a TUM trajectory).

Example:
  linereg localize --map site.linemap --camera cameras.json photos/*.png --out poses.json --tum poses.tum

A local process pool (``--workers``; each worker loads the map once) or an existing Dask cluster
(``--scheduler ADDRESS``, needs ``pip install 'linereg[cluster]'``; workers must reach the map and images
under the same paths) localizes the images. Each result is saved atomically as it arrives, one small file
per image in a hidden folder beside ``--out`` (``.poses.json.parts/``), so a killed batch loses nothing:
``--resume`` skips every image already in ``--out`` or in that folder and localizes only the rest. An
image that cannot be used (unreadable, corrupt, another size than its camera) does not stop the batch:
it is recorded as failed, named on stderr, and the command exits with 2 at the end.

Each JSON record has a ``timestamp``: the image's time in the ``--tum`` file (the file stems when every
stem is a number, as in TUM datasets, else the image's position on the command line: 0, 1, 2, ...).

What is known beforehand narrows the search (``--prior FILE``): a JSON prior for every image (a site's
GNSS position and radius, a rough camera-LiDAR extrinsic with its sigmas), JSON priors per image, or a
TUM trajectory of rough poses (a SLAM run, the odometry) with ``--prior-sigma DEG M``. Poses outside a
prior are neither answers nor rivals: give a radius that holds the truth. Examples:
  {"position": [412.0, 87.5, 1.6], "radius_m": 30}
  {"cam_from_world": [[...], [...], [...], [0, 0, 0, 1]], "sigma_rot_deg": 5, "radius_m": 0.5}
  {"img_0001.png": {"position": [...], "radius_m": 10}, "img_0002.png": {...}}
  linereg localize --map site.linemap --camera cam.json photos/*.png --prior slam.tum --prior-sigma 5 1
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import os
import re
import shutil
import sys
import threading
from collections.abc import Sequence
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from .. import batch
from ..errors import InvalidInputError, LineregError
from . import check_output_dir, check_output_file, description
from .progress import Progress

log = logging.getLogger(__name__)
_worker_state: dict = {}
_worker_lock = threading.Lock()  # Dask workers may run tasks in threads: the map is loaded once
_NUMBER = re.compile(r"\d+(\.\d+)?")  # a file stem that is a timestamp: 1305031102.175304


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "localize",
        help="localize images in a line map",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE")
    p.add_argument("--map", required=True, type=Path, help="line map from `linereg map build`")
    p.add_argument(
        "--camera", required=True, type=Path, help="camera JSON (shared or per image) or COLMAP cameras.txt"
    )
    p.add_argument("--out", type=Path, default=Path("poses.json"), help="JSON results (default poses.json)")
    p.add_argument("--tum", type=Path, help="also write the successful poses as a TUM trajectory")
    p.add_argument("--overlay", type=Path, metavar="DIR", help="write one overlay PNG per image here")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on this dask.distributed scheduler (tcp://host:8786) instead of local processes",
    )
    p.add_argument("--resume", action="store_true", help="skip images already done (in --out or saved)")
    p.add_argument(
        "--config", type=Path, help="JSON file of registration overrides, nested per section (default: none)"
    )
    add_prior_arguments(p)
    p.set_defaults(func=run)


def add_prior_arguments(p: argparse.ArgumentParser) -> None:
    """``--prior FILE`` and ``--prior-sigma DEG M`` (``linereg localize``, ``linereg query``)."""
    p.add_argument(
        "--prior",
        type=Path,
        metavar="FILE",
        help="what is known of the poses: a JSON prior (for every image or per image) or a TUM file of "
        "rough poses (see above)",
    )
    p.add_argument(
        "--prior-sigma",
        type=float,
        nargs=2,
        metavar=("DEG", "M"),
        help="how rough the --prior poses are: rotation sigma (degrees) and radius (metres); needed for a TUM "
        "file, fills what a JSON prior leaves out",
    )


def read_prior_arguments(args: argparse.Namespace, images: Sequence[Path], stamps: Sequence[float]) -> list:
    """Returns the Prior (or None) of each image from ``--prior`` / ``--prior-sigma``, every image checked:
    one without a prior is an error before anything is localized."""
    if args.prior is None:
        if args.prior_sigma is not None:
            raise InvalidInputError("--prior-sigma needs --prior FILE (the poses it qualifies)")
        return [None for _ in images]
    from ..prior_files import read_priors

    table = read_priors(args.prior, args.prior_sigma)
    return [table.for_image(path, stamp) for path, stamp in zip(images, stamps, strict=True)]


def run(args: argparse.Namespace) -> int:
    from .. import io
    from ..map.linemap import check_map_file

    if args.workers < 1:
        raise InvalidInputError(f"--workers must be >= 1, got {args.workers}")
    # every argument is checked before the first image is localized: a typo must not cost a batch
    check_output_file("--out", args.out)
    if args.tum:
        check_output_file("--tum", args.tum)
    if args.overlay:
        check_output_dir("--overlay", args.overlay)
    check_map_file(args.map)
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:
        raise InvalidInputError(f"image file(s) not found: {', '.join(missing[:5])}")
    if args.config:
        io.read_config(args.config)  # read again by each worker; a bad file is reported once, here
    cameras = io.read_cameras(args.camera)
    times = tum_timestamps(args.images)
    priors = read_prior_arguments(args, args.images, times)
    jobs = [
        (str(p), io.camera_for_image(cameras, p, args.camera), prior)
        for p, prior in zip(args.images, priors, strict=True)
    ]
    stamps = dict(zip((j[0] for j in jobs), times, strict=True))
    results = io.read_json(args.out) if args.resume and args.out.exists() else {}
    for path, record in results.items():
        if path in stamps:
            record["timestamp"] = stamps[path]
    parts = ResultParts(args.out)
    if args.resume:
        results |= {path: record | {"timestamp": stamps.get(path)} for path, record in parts.load().items()}
    else:
        parts.clear()
    jobs = [j for j in jobs if j[0] not in results]
    overlay_dir = str(args.overlay) if args.overlay else None
    shared = (str(args.map), overlay_dir, str(args.config) if args.config else None)
    with (
        Progress(len(jobs), "localize", log_steps=True) as progress,
        batch.runner(args.workers, args.scheduler) as runner,
    ):
        try:
            for _, (path, record) in runner.unordered(_localize_task, shared, jobs):
                results[path] = record | {"timestamp": stamps[path]}
                parts.write(path, results[path])  # atomic, per image: a killed batch resumes here
                progress.update(1, f"{Path(path).name}: {'ok' if record['success'] else 'failed'}")
        except BrokenProcessPool:  # a worker died (out of memory, a crash)
            raise LineregError(
                f"a worker process died ({len(results)} results saved beside {args.out}); "
                "see the messages above, then run again with --resume"
            ) from None
    order = {path: k for k, path in enumerate(stamps)}
    results = dict(sorted(results.items(), key=lambda item: order.get(item[0], len(order))))
    io.write_json_atomic(args.out, results)
    if args.tum:
        ok = [r for r in results.values() if r["success"] and r.get("timestamp") is not None]
        io.write_tum(args.tum, [r["timestamp"] for r in ok], [r["cam_from_world"] for r in ok])
    parts.clear()  # everything is in --out now
    done = sum(r["success"] for r in results.values())
    print(f"localized {done}/{len(results)} images -> {args.out}", file=sys.stderr)
    bad = {p: r["reason"] for p, r in results.items() if r.get("input_error")}
    for reason in bad.values():
        print(f"linereg localize: error: {reason}", file=sys.stderr)
    return 2 if bad else 0


def tum_timestamps(images: Sequence[Path]) -> list[float]:
    """Returns one TUM timestamp (s) per image: the file stems when all are distinct numbers, else 0, 1, 2...

    One rule for the whole batch: stems and positions mixed could collide or interleave meaninglessly.
    """
    stems = [p.stem for p in images]
    if all(_NUMBER.fullmatch(s) for s in stems) and len({float(s) for s in stems}) == len(stems):
        return [float(s) for s in stems]
    return [float(k) for k in range(len(images))]


class ResultParts:
    """One JSON file per localized image, written atomically, in ``.<out name>.parts/`` beside ``out``."""

    def __init__(self, out: Path) -> None:
        self.folder = out.parent / f".{out.name}.parts"

    def write(self, image: str, record: dict) -> None:
        from .. import io

        name = hashlib.sha1(image.encode("utf-8")).hexdigest()[:20] + ".json"
        io.write_json_atomic(self.folder / name, {"image": image, "record": record})

    def load(self) -> dict[str, dict]:
        """Returns image -> record of every saved part (a part that cannot be read is done again)."""
        from .. import io

        out = {}
        for path in sorted(self.folder.glob("*.json")) if self.folder.is_dir() else []:
            try:
                part = io.read_json(path)
                out[str(part["image"])] = dict(part["record"])
            except (LineregError, KeyError, TypeError, ValueError):
                log.warning("%s: unreadable saved result, the image is localized again", path)
        return out

    def clear(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def _init_worker(map_path: str, overlay_dir: str | None, config_path: str | None) -> None:
    from .. import io
    from ..config import RegisterConfig
    from ..map.linemap import LineMap

    _worker_state["map"] = LineMap.load(map_path)
    _worker_state["config"] = io.read_config(config_path) if config_path else RegisterConfig()
    _worker_state["overlay_dir"] = overlay_dir


def _localize_task(shared: tuple, job: tuple) -> tuple[str, dict]:
    """A batch task (``linereg.batch``): loads the map on a worker's first task, then localizes one image.

    A map that cannot be loaded raises here, and the runner hands the error to the command (one line).
    """
    with _worker_lock:
        if _worker_state.get("shared") != shared:
            _worker_state.clear()
            _init_worker(*shared)
            _worker_state["shared"] = shared
    return _localize_one(job)


def _localize_one(job: tuple) -> tuple[str, dict]:
    from .. import io
    from ..lines2d import detect
    from ..localization import localize
    from ..overlay import draw_overlay

    path, camera, prior = job
    line_map = _worker_state["map"]
    try:
        image = io.read_image(path)
        result = localize(image, line_map, camera, _worker_state["config"], prior=prior)
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
    if prior is not None:
        record["prior"] = prior.to_dict()  # what the pose was searched within
    return path, record
