"""``linereg track``: a camera's trajectory through a line map, from a folder of frames or a video.

Examples:
  linereg track --map site.linemap --camera camera.json frames/ --tum track.tum
  linereg track --map site.linemap --camera camera.json walk.mp4 --odometry odo.tum --tum track.tum --smooth

Frames are the images given (or every image of a folder given alone), in name order, or the frames of a
video read with OpenCV. Timestamps: the file stems when they are all numbers (TUM datasets), else the
frame's position (a video's: its time from the frame rate). ``--odometry`` is a TUM file of the camera's
poses in the odometry's own frame; each frame takes the nearest odometry pose in time, and consecutive
ones give the relative motion. Live tracking (``linereg.Tracker``) by default, one frame at a time;
``--smooth`` localizes the whole sequence in one graph (``linereg.localize_sequence``) instead.

``--start FILE``: where the camera starts, a JSON pose prior (``{"cam_from_world": 4 x 4, "sigma_rot_deg":
1, "radius_m": 0.1}`` or ``world_from_cam``; a robot leaving its dock, the last run's end): the first frame
is tracked from it instead of localized over the whole map.

``--tum`` gets every posed frame (its own fix, or placed by its neighbours); ``--out`` a JSON record per
frame (success, reason, the tracker's event, pose, covariance).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from . import check_output_file, description

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="track a camera through a line map (frames or a video)",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("frames", nargs="+", type=Path, metavar="FRAMES", help="image files, a folder or a video")
    p.add_argument("--map", required=True, type=Path, help="line map from `linereg map build`")
    p.add_argument(
        "--camera", required=True, type=Path, help="camera JSON or COLMAP cameras.txt (one camera)"
    )
    p.add_argument("--odometry", type=Path, help="TUM file of the camera's odometry poses")
    p.add_argument("--tum", type=Path, required=True, help="write the posed frames as a TUM trajectory")
    p.add_argument("--out", type=Path, help="also write one JSON record per frame")
    p.add_argument("--smooth", action="store_true", help="one graph over all frames instead of live tracking")
    p.add_argument(
        "--max-speed",
        type=float,
        metavar="M_S",
        help="the camera's top speed (m/s): after a long loss without odometry, relocalize within its reach "
        "since the last fix instead of over the whole map",
    )
    p.add_argument(
        "--start",
        type=Path,
        metavar="FILE",
        help="JSON pose prior of the first frame (cam_from_world or world_from_cam, sigma_rot_deg, radius_m)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io
    from ..map.linemap import LineMap, check_map_file

    check_output_file("--tum", args.tum)
    if args.max_speed is not None and not (np.isfinite(args.max_speed) and args.max_speed > 0):
        raise InvalidInputError(f"--max-speed must be a positive number of m/s, got {args.max_speed}")
    if args.out:
        check_output_file("--out", args.out)
    check_map_file(args.map)
    cameras = io.read_cameras(args.camera)
    if not hasattr(cameras, "fx"):
        raise InvalidInputError(f"--camera {args.camera}: holds several cameras; track needs one")
    start = start_prior(args.start) if args.start else None
    stamps, frames = frame_source(args.frames)
    relative = None
    if args.odometry:
        relative = odometry_steps(*io.read_tum(args.odometry), stamps)
    line_map = LineMap.load(args.map)
    if args.smooth:
        results, events = _smooth(list(frames), line_map, cameras, relative, start), None
    else:
        results, events = _track(frames, line_map, cameras, relative, stamps, args.max_speed, start)
    return _write(args, stamps, results, events)


def start_prior(path: Path):
    """Returns the Prior of a ``--start`` file: one JSON pose prior (``prior_files``), which must hold a pose."""
    from ..prior_files import read_priors

    table = read_priors(path)
    if table.shared is None or table.shared.cam_from_world is None:
        raise InvalidInputError(
            f"--start {path}: needs one pose prior (cam_from_world or world_from_cam, with sigma_rot_deg and "
            "radius_m), not a position alone or priors per image"
        )
    return table.shared


def frame_source(paths: list[Path]) -> tuple[list[float], Iterable[np.ndarray]]:
    """Returns (timestamps s, an iterable of images) of image files, a folder of them, or one video."""
    from .. import io
    from .localize import tum_timestamps

    if len(paths) == 1 and paths[0].is_dir():
        paths = sorted(p for p in paths[0].iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not paths:
            raise InvalidInputError("the folder holds no images")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise InvalidInputError(f"frame file(s) not found: {', '.join(missing[:5])}")
    if len(paths) == 1 and paths[0].suffix.lower() not in IMAGE_SUFFIXES:
        return _video(paths[0])
    return tum_timestamps(paths), (io.read_image(p) for p in paths)


def _video(path: Path) -> tuple[list[float], list[np.ndarray]]:
    import cv2

    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InvalidInputError(f"{path}: OpenCV cannot read this video")
    fps = capture.get(cv2.CAP_PROP_FPS) or 0.0
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    if not frames:
        raise InvalidInputError(f"{path}: no frames")
    step = 1.0 / fps if fps > 0 else 1.0
    return [k * step for k in range(len(frames))], frames


def odometry_steps(times: np.ndarray, cam_from_odom: np.ndarray, stamps: list[float]) -> list[np.ndarray]:
    """Returns the K - 1 measured cam_k_from_cam_k+1 between frames at ``stamps``: the odometry poses
    (M, 4, 4) cam_from_odom at the nearest of ``times`` (M,) to each frame."""
    index = [int(np.argmin(np.abs(times - s))) for s in stamps]
    poses = cam_from_odom[index]
    return [a @ np.linalg.inv(b) for a, b in itertools.pairwise(poses)]


def _track(frames, line_map, camera, relative, stamps, max_speed=None, start=None):
    from ..tracking import Tracker, TrackingConfig
    from .progress import Progress

    tracker = Tracker(line_map, camera, TrackingConfig(max_speed_m_s=max_speed))
    if start is not None:  # the radius holds 3 sigma of the position
        tracker.start_at(start.cam_from_world, start.sigma_rot_deg, start.radius_m / 3.0)
    results, events = [], []
    with Progress(len(stamps), "frames") as progress:
        for k, frame in enumerate(frames):
            results.append(tracker.step(frame, relative[k - 1] if relative and k else None, stamps[k]))
            events.append(tracker.event)
            progress.update(1)
    return results, events


def _smooth(frames, line_map, camera, relative, start=None):
    from ..sequence import localize_sequence

    return localize_sequence(frames, line_map, camera, relative, prior=start)


def _write(args: argparse.Namespace, stamps: list[float], results: list, events: list[str] | None) -> int:
    from .. import io
    from ..sequence import FROM_NEIGHBOURS

    posed = [k for k, r in enumerate(results) if r.success or r.reason.startswith(FROM_NEIGHBOURS)]
    io.write_tum(args.tum, [stamps[k] for k in posed], [results[k].cam_from_world for k in posed])
    if args.out:
        records = [
            {"timestamp": stamps[k], "event": events[k] if events else None} | r.to_dict()
            for k, r in enumerate(results)
        ]
        io.write_json_atomic(args.out, records)
    fixed = sum(r.success for r in results)
    print(
        f"{len(results)} frames: {fixed} fixed, {len(posed) - fixed} from neighbours, {len(results) - len(posed)} lost; wrote {args.tum}",
        file=sys.stderr,
    )
    return 0
