"""``linereg calibrate``: a camera-LiDAR extrinsic from several photos and sweeps and a rough guess of it.

Example:
  linereg calibrate --camera camera.json --guess guess.json \\
      --frame 000002.png 000002.pcd --frame 000007.png 000007.pcd --frame 000008.png 000008.pcd \\
      --out extrinsic.json --overlay overlays/

Each ``--frame PHOTO MAP`` is one stop of the rig: its photo and its LiDAR's sweep, as a line map file
(``linereg map build SWEEP -o SWEEP.linemap``) or a point cloud (built here with the library's defaults).
The guess is a JSON prior whose pose is the guessed cam_from_lidar ("x_cam = R x_lidar + t"), with how far
off it may be (else ``--guess-sigma DEG M``, default 5 deg / 0.5 m):
  {"cam_from_lidar": [[...], [...], [...], [0, 0, 0, 1]], "sigma_rot_deg": 5, "radius_m": 0.5}

Every photo is localized alone near the guess, then the one pose that explains all of them together is
found and refined in one GTSAM graph (``linereg.calibrate``). The JSON result holds the extrinsic, its
covariance, each frame's score, matches and its own localization; it is claimed (``success``) only when
at least two photos are explained, no distinct pose scores within the decision's margin and the pose is
pinned closer than distinct poses lie. Exit status 0 when claimed, 1 when not (the reason is printed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import InvalidInputError
from . import check_output_dir, check_output_file, description
from .progress import Progress

MAP_SUFFIXES = (".linemap", ".npz")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="camera-LiDAR extrinsic from several photos and sweeps",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--frame",
        nargs=2,
        action="append",
        required=True,
        type=Path,
        metavar=("PHOTO", "MAP"),
        help="a photo and its sweep (a line map file or a point cloud); give two or more",
    )
    p.add_argument("--camera", required=True, type=Path, help="camera JSON (shared or per photo file name)")
    p.add_argument("--guess", required=True, type=Path, help="JSON prior: the guessed cam_from_lidar")
    p.add_argument(
        "--guess-sigma",
        type=float,
        nargs=2,
        default=(5.0, 0.5),
        metavar=("DEG", "M"),
        help="how far the guess may be off, where its file does not say (default 5 0.5)",
    )
    p.add_argument("--out", type=Path, default=Path("calibration.json"), help="JSON result")
    p.add_argument("--overlay", type=Path, metavar="DIR", help="write one overlay PNG per photo here")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io
    from ..calibration import calibrate_segments
    from ..lines2d import detect
    from ..map.linemap import LineMap

    check_output_file("--out", args.out)
    if args.overlay is not None:
        check_output_dir("--overlay", args.overlay)
    if len(args.frame) < 2:
        raise InvalidInputError(
            f"--frame: a calibration needs two or more photos with their sweeps, got {len(args.frame)}"
        )
    for photo, source in args.frame:
        for path in (photo, source):
            if not path.is_file():
                raise InvalidInputError(f"--frame {photo} {source}: no such file {path}")
    guess = _read_guess(args.guess, args.guess_sigma)
    cameras = io.read_cameras(args.camera)
    progress = Progress(2 * len(args.frame) + 1, "calibrate")
    images, lines, maps, cams = [], [], [], []
    for photo, source in args.frame:
        camera = io.camera_for_image(cameras, photo, f"--camera {args.camera}")
        image = io.read_image(photo)
        if image.shape[:2] != (camera.height, camera.width):
            raise InvalidInputError(
                f"--frame {photo}: {image.shape[1]}x{image.shape[0]} pixels, its camera is "
                f"{camera.width}x{camera.height}"
            )
        images.append(image)
        lines.append(detect(image, camera))  # undistorted pixels: the overlays draw them too
        cams.append(camera.undistorted())
        progress.update(1, f"read {photo.name}")
        if source.suffix.lower() in MAP_SUFFIXES:
            maps.append(LineMap.load(source))
        else:
            cloud = io.read_cloud_fields(source)  # a sweep's ring field, if it has one
            origin = io.read_sensor_origin(source)
            maps.append(LineMap.build(cloud.points, sensor_origin=origin, rings=cloud.rings))
        progress.update(1, f"map of {source.name}")
    result = calibrate_segments(lines, maps, cams, guess)
    progress.update(1, "done")
    progress.close()
    record = result.to_dict() | {"frames": [[str(p), str(m)] for p, m in args.frame]}
    io.write_json_atomic(args.out, record)
    if args.overlay is not None:
        _overlays(args, images, lines, maps, cams, result)
    verdict = "calibrated" if result.success else f"not claimed: {result.reason}"
    print(f"{verdict}; {len(images)} photos; wrote {args.out}")
    print(_frame_table(args.frame, result))
    print(json.dumps({"cam_from_lidar": result.cam_from_lidar.round(6).tolist()}), file=sys.stdout)
    return 0 if result.success else 1


def _frame_table(frames: list, result) -> str:
    """Returns one line per photo: its matches and score at the answer, where it settles alone."""
    from ..bench.report import format_table

    rows = []
    for k, (photo, _) in enumerate(frames):
        rotation, shift = result.frame_offsets[k] if k < len(result.frame_offsets) else (None, None)
        rows.append({
            "photo": photo.name,
            "inliers": int(result.frame_inliers[k]) if k < len(result.frame_inliers) else None,
            "score": float(result.frame_scores[k]) if k < len(result.frame_scores) else None,
            "rotation": rotation, "shift": shift,
        })  # fmt: skip
    columns = (
        ("photo", "photo", ""), ("inliers", "inliers", "d"), ("score", "score px", ".0f"),
        ("rotation", "alone: deg off", ".2f"), ("shift", "m off", ".3f"),
    )  # fmt: skip
    return format_table(rows, columns)


def _read_guess(path: Path, sigma: tuple[float, float]):
    """Returns the guess's Prior: its file, with ``sigma`` (deg, m) where the file gives none."""
    from ..priors import Prior

    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InvalidInputError(f"--guess {path}: {e}") from None
    if isinstance(data, dict) and "cam_from_lidar" in data and "cam_from_world" not in data:
        data["cam_from_world"] = data.pop("cam_from_lidar")  # the same pose, named for what it is here
    if not isinstance(data, dict) or ("cam_from_world" not in data and "world_from_cam" not in data):
        raise InvalidInputError(f"--guess {path}: needs a pose: cam_from_lidar (or cam_from_world)")
    data = {"sigma_rot_deg": sigma[0], "radius_m": sigma[1]} | data
    return Prior.from_dict(data, source=f"--guess {path}")


def _overlays(args: argparse.Namespace, images, lines, maps, cams, result) -> None:
    """Writes each photo's overlay at the calibrated pose (or the best one found when not claimed): its
    (undistorted) ``lines`` and its map, ``cams`` undistorted."""
    import numpy as np

    from .. import io
    from ..overlay import draw_overlay
    from ..registration import Registration

    args.overlay.mkdir(parents=True, exist_ok=True)
    frames = zip(args.frame, images, lines, maps, cams, strict=True)
    for k, ((photo, _), image, lines2d, line_map, cam) in enumerate(frames):
        matched = result.frame_matches[k] if k < len(result.frame_matches) else np.zeros((0, 2), np.int64)
        at = Registration(success=True, cam_from_world=result.cam_from_lidar, matches=matched)
        caption = ("calibrated" if result.success else "not claimed (best pose shown)") + f", photo {k}"
        picture = draw_overlay(image, cam, lines2d, line_map.segments, at, caption)
        io.write_image_atomic(args.overlay / f"{photo.stem}.png", picture)
