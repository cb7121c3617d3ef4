"""Real scenes with ground truth: build each scene's line map, localize its images, say what failed and why.

``linereg bench real [--data DIR] [--out DIR] [--overlay] [--prior ROT_DEG POS_M [--guesses N]]``.

The data folder (``--data``, else ``$LINEREG_DATA``, else ``shared/data`` beside the repository) holds one
folder per scene with ``cameras.json`` and ``cloud.ply`` (format: that folder's README.md). Every image
``file`` has intrinsics, ``distortion`` and ``T_cam_from_world``; when it names a ``cloud_without_this_view``,
that cloud is the map, so an RGB-D frame's own depth is not in it. Library defaults throughout: these scenes
check the pipeline, they are not a tuning set.

Success here is a pose within ``--max-rot-deg`` and ``--max-pos-m`` of the ground truth (defaults 5 deg /
0.3 m: the ground truth itself is only good to ~1-2 deg / ~5 cm, and the paper's relative criterion
``|t_e| / |t_GT| < 0.1`` is meaningless when the camera sits near the world origin). Per image the table
also gives ``gt_inliers``: how many detected 2D lines match a map segment at the ground-truth pose (the
pipeline's own inlier test) -- few means the map and the image share too little for any pose search.
With ``--overlay``, each image gets the overlay of its estimate and one of the map at the true pose (``_gt``).
With ``--stages``, a second table runs every stage at the true pose (``real_stages``): which one fails first.
With ``--plane-directions``, the maps' direction clusters also hold the directions of their dominant planes
(``plane_directions.map_clusters``; the planes are segmented a second time here, which costs seconds).
``--map-config auto`` builds each map with ``map_profile.lines3d_config_for`` (limits from the point spacing),
``--map-config '{"min_length_m": 0.15}'`` with those ``Lines3DConfig`` fields overridden.
With ``--prior ROT_DEG POS_M`` every search gets a rough guess of the pose (at most that far from the truth,
seeded by scene and image name) as a ``Prior``: the camera-LiDAR calibration case of issues 9 and 10; with
``--guesses N`` each image is localized from N such guesses (the first the one above): one guess per photo
showed none of the wrong claims that other guesses lead to (session 55).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import honesty, report, search_check

DATA_ENV = "LINEREG_DATA"


def default_data_dir() -> Path:
    """Returns ``$LINEREG_DATA`` if set, else ``shared/data`` next to the repository holding this file."""
    if os.environ.get(DATA_ENV):
        return Path(os.environ[DATA_ENV])
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


@dataclass(frozen=True)
class RealImage:
    """One posed image of a scene: its file, camera, ground truth and the cloud that is its map."""

    scene: str
    image_path: Path
    camera: Any  # linereg.Camera
    cam_from_world: np.ndarray  # (4, 4) ground truth
    cloud_path: Path


def scene_folders(data_dir: Path) -> list[Path]:
    """Returns the sub-folders of ``data_dir`` holding both ``cameras.json`` and ``cloud.ply``, sorted
    (``[data_dir]`` itself when it is such a scene folder)."""
    if not data_dir.is_dir():
        return []
    if (data_dir / "cameras.json").is_file() and (data_dir / "cloud.ply").is_file():
        return [data_dir]
    return sorted(
        d for d in data_dir.iterdir() if (d / "cameras.json").is_file() and (d / "cloud.ply").is_file()
    )


def read_scene(folder: Path) -> list[RealImage]:
    """Returns the posed images of one scene folder (raises FileFormatError naming the file if malformed)."""
    from ..camera import Camera
    from ..errors import FileFormatError

    source = folder / "cameras.json"
    try:
        meta = json.loads(source.read_text())
        entries = meta["images"]
        images = []
        for entry in entries:
            pose = np.asarray(entry["T_cam_from_world"], dtype=np.float64)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise ValueError(f"{entry['file']}: T_cam_from_world must be a finite 4x4 matrix")
            cloud = folder / entry.get("cloud_without_this_view", meta.get("cloud", "cloud.ply"))
            camera = Camera.from_dict(entry, source=str(source))
            images.append(RealImage(folder.name, folder / entry["file"], camera, pose, cloud))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise FileFormatError(f"{source}: {type(e).__name__}: {e}") from None
    return images


def gt_matches(lines2d: np.ndarray, line_map: Any, camera: Any, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (K, 2) int64 ``(i2d, j3d)``: the (N, 4) undistorted 2D segments' matched map segments at the
    true pose (the score's pair test, as ``Registration.matches``)."""
    from ..config import RegisterConfig
    from ..score import image_lines, score_pose

    if not len(lines2d) or not len(line_map.segments):
        return np.zeros((0, 2), dtype=np.int64)
    config = RegisterConfig()
    image = image_lines(lines2d, camera, config.score)
    score = score_pose(image, line_map.segments, camera, cam_from_world, config.score)
    return score.matches(config.decide.min_cover)


def rough_guess(truth: np.ndarray, rot_deg: float, pos_m: float, seed: str) -> np.ndarray:
    """Returns a (4, 4) cam_from_world guess: the true pose turned about a random axis by up to ``rot_deg``
    and its centre moved in a random direction by up to ``pos_m`` (uniform; the same for the same ``seed``,
    e.g. the image's name, on any machine)."""
    from ..geometry import camera_center, rotation_from_vector

    rng = np.random.default_rng(int.from_bytes(hashlib.sha256(seed.encode()).digest()[:8], "little"))
    axis, move = rng.normal(size=3), rng.normal(size=3)
    turn = rotation_from_vector(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.0, rot_deg)))
    centre = camera_center(truth) + move / np.linalg.norm(move) * rng.uniform(0.0, pos_m)
    guess = np.eye(4)
    guess[:3, :3] = turn @ truth[:3, :3]
    guess[:3, 3] = -guess[:3, :3] @ centre
    return guess


def localize_one(
    item: RealImage,
    line_map: Any,
    bounds: tuple[float, float],
    stages: bool = False,
    prior: tuple[float, float] | None = None,
    draw: int = 0,
) -> tuple[dict[str, Any], Any]:
    """Returns (record, (lines2d, Registration)) of one image: errors, success within ``bounds``, times;
    with ``stages``, ``record["stages"]`` holds ``real_stages.stage_record`` at the true pose; with
    ``prior`` (rotation deg, position m), the search is given a rough guess that far from the truth at most
    (``rough_guess``, the ``draw``-th of the image) as a ``Prior`` of those bounds (the camera-LiDAR
    calibration case)."""
    from .. import io
    from ..geometry import pose_errors
    from ..lines2d import detect
    from ..localization import localize_segments
    from ..priors import Prior

    guess = None
    if prior is not None:
        guess = Prior(
            cam_from_world=rough_guess(item.cam_from_world, prior[0], prior[1], guess_seed(item, draw)),
            sigma_rot_deg=prior[0],
            radius_m=prior[1],
        )
    image = io.read_image(item.image_path)
    start = time.perf_counter()
    lines2d = detect(image, item.camera)
    detect_s = time.perf_counter() - start
    result = localize_segments(lines2d, line_map, item.camera.undistorted(), prior=guess)
    seconds = time.perf_counter() - start
    errors = pose_errors(result.cam_from_world, item.cam_from_world) if result.success else None
    record = report.trial_record("vp", 0, result.success, errors, seconds, result.num_inliers, result.reason)
    rot, pos = record["rotation_deg"], record["position_m"]
    record |= {
        "paper_success": record["success"],
        "success": bool(result.success and rot <= bounds[0] and pos <= bounds[1]),
        "scene": item.scene,
        "image": item.image_path.name,
        "guess": draw if prior is not None else None,
        "map": item.cloud_path.name,
        "num_lines2d": len(lines2d),
        "gt_inliers": len(gt_matches(lines2d, line_map, item.camera.undistorted(), item.cam_from_world)),
        "ambiguity": result.ambiguity,
        "stages_ms": {"lines2d": 1e3 * detect_s} | {k: 1e3 * v for k, v in result.timings.items()},
    }
    if result.success and not record["success"]:
        record["reason"] = f"pose off by {rot:.1f} deg / {pos:.2f} m"
    if result.success:  # how many of its own sigmas the claim is off (``honesty``)
        record["nees"] = honesty.nees(result.cam_from_world, item.cam_from_world, result.covariance)
    if result.cam_from_world is not None:
        from ..config import RegisterConfig
        from ..localization import map_view

        camera = item.camera.undistorted()
        rot_all, pos_all, _ = pose_errors(result.cam_from_world, item.cam_from_world)
        right = bool(rot_all <= bounds[0] and pos_all <= bounds[1])
        view = map_view(line_map, None, RegisterConfig())
        record["search_check"] = search_check.check(lines2d, view, camera, item.cam_from_world, result, right)
    if stages:
        from .real_stages import stage_record

        camera = item.camera.undistorted()
        record["stages"] = stage_record(lines2d, line_map, camera, item.cam_from_world)
    return record, (image, lines2d, result)


def guess_seed(item: RealImage, draw: int) -> str:
    """Returns the seed of an image's ``draw``-th rough guess: the first is seeded by the scene and image
    name alone (the bench's guesses before there were several), the others by their number too."""
    name = f"{item.scene}/{item.image_path.name}"
    return name if draw == 0 else f"{name}/{draw}"


def build_map(
    cloud_path: Path,
    plane_directions: bool = False,
    map_config: str | None = None,
    intensity_edges: bool = False,
) -> tuple[Any, dict[str, Any]]:
    """Returns (LineMap, record with points, segments and build seconds) of one cloud file; ``map_config``:
    None (defaults), ``"auto"`` or a JSON object of ``Lines3DConfig`` fields; ``intensity_edges``: also the
    steps of the cloud's intensity (``MapBuildConfig.intensity_edges``)."""
    from .. import io
    from ..config import MapBuildConfig
    from ..map.linemap import LineMap

    start = time.perf_counter()
    points, intensity, rings = io.read_cloud_fields(cloud_path, intensity=intensity_edges)
    config = MapBuildConfig(lines3d=lines3d_config(map_config, points), intensity_edges=intensity_edges)
    line_map = LineMap.build(points, config, intensity=intensity, rings=rings)
    if plane_directions:
        line_map = with_plane_directions(line_map, points)
    record = {
        "cloud": str(cloud_path),
        "num_points": len(points),
        "num_segments": len(line_map.segments),
        "build_s": time.perf_counter() - start,
    }
    return line_map, record


def lines3d_config(map_config: str | None, points: np.ndarray) -> Any:
    """Returns the Lines3DConfig a ``--map-config`` value asks for (InvalidInputError if malformed)."""
    from ..config import Lines3DConfig
    from ..errors import InvalidInputError
    from ..map.profile import lines3d_config_for

    if map_config is None:
        return Lines3DConfig()
    if map_config == "auto":
        return lines3d_config_for(points)
    try:
        return Lines3DConfig(**json.loads(map_config))
    except (ValueError, TypeError) as e:
        raise InvalidInputError(
            f"--map-config: 'auto' or a JSON object of Lines3DConfig fields ({e})"
        ) from None


def with_plane_directions(line_map: Any, points: np.ndarray) -> Any:
    """Returns the LineMap with clusters from its segments and the dominant planes of (P, 3) ``points``."""
    from ..config import Lines3DConfig
    from ..map.linemap import LineMap
    from ..map.plane_directions import map_clusters
    from ..map.planes import segment_planes

    planes = segment_planes(points - points.min(axis=0), Lines3DConfig())
    areas = planes.counts * planes.spacing_m**2  # a region's points times the area each stands for
    clusters = map_clusters(line_map.segments, planes.normals, areas)
    return LineMap(line_map.segments, clusters, line_map.metadata | {"plane_directions": True})


def run_scene(
    folder: Path,
    bounds: tuple[float, float],
    overlay_dir: Path | None,
    stages: bool = False,
    plane_directions: bool = False,
    map_config: str | None = None,
    prior: tuple[float, float] | None = None,
    intensity_edges: bool = False,
    guesses: int = 1,
) -> dict[str, Any]:
    """Returns a scene's map records and image records (with a ``prior``, ``guesses`` records per image,
    one per rough guess); maps are built once per distinct cloud file."""
    items = read_scene(folder)
    maps: dict[Path, Any] = {}
    map_records, records = [], []
    for item in items:
        if item.cloud_path not in maps:
            maps[item.cloud_path], record = build_map(
                item.cloud_path, plane_directions, map_config, intensity_edges
            )
            map_records.append(record)
            print(
                f"{folder.name}/{item.cloud_path.name}: {record['num_points']:,} points -> "
                f"{record['num_segments']:,} segments in {record['build_s']:.1f} s",
                file=sys.stderr,
            )
        for draw in range(guesses if prior is not None else 1):
            try:
                record, (image, lines2d, result) = localize_one(
                    item, maps[item.cloud_path], bounds, stages, prior, draw
                )
            except Exception as e:  # an image that crashes the pipeline is a finding, recorded with its cause
                records.append(
                    {
                        "scene": item.scene,
                        "image": item.image_path.name,
                        "guess": draw if prior is not None else None,
                        "success": False,
                        "reason": f"{type(e).__name__}: {e}",
                    }
                )
                continue
            records.append(record)
            if overlay_dir is not None:
                suffix = f"_guess{draw}" if draw else ""
                _write_overlay(
                    overlay_dir / f"{item.scene}_{item.image_path.stem}{suffix}.png",
                    image,
                    item,
                    lines2d,
                    maps[item.cloud_path],
                    result,
                )
    return {"scene": folder.name, "maps": map_records, "images": records}


def _write_overlay(path: Path, image, item: RealImage, lines2d, line_map, result) -> None:
    """Writes the overlay of the estimate and, beside it (``*_gt.png``), the map seen from the true pose."""
    from .. import io
    from ..overlay import draw_overlay
    from ..registration import Registration

    camera = item.camera.undistorted()
    io.write_image_atomic(path, draw_overlay(image, camera, lines2d, line_map.segments, result))
    matches = gt_matches(lines2d, line_map, camera, item.cam_from_world)
    truth = Registration(True, cam_from_world=item.cam_from_world, matches=matches, num_inliers=len(matches))
    picture = draw_overlay(image, camera, lines2d, line_map.segments, truth)
    io.write_image_atomic(path.with_name(path.stem + "_gt.png"), picture)


IMAGE_COLUMNS = (
    ("scene", "scene", ""),
    ("image", "image", ""),
    ("guess", "guess", "d"),
    ("success", "ok", ""),
    ("rotation_deg", "R_e deg", ".2f"),
    ("position_m", "pos m", ".3f"),
    ("num_lines2d", "2D lines", "d"),
    ("gt_inliers", "GT inl", "d"),
    ("num_inliers", "inliers", "d"),
    ("nees", "NEES", ".1f"),  # a claim's error in its own sigmas (``honesty``)
    ("time_ms", "ms", ".0f"),
    ("reason", "reason", ""),
)
MAP_COLUMNS = (
    ("cloud", "cloud", ""),
    ("num_points", "points", ",d"),
    ("num_segments", "segments", ",d"),
    ("build_s", "build s", ".1f"),
)


def configure(parser: argparse.ArgumentParser) -> None:
    """Adds the ``bench real`` arguments and sets ``func=run``."""
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help=f"data folder or one scene folder (default ${DATA_ENV} or shared/data beside the repository)",
    )
    parser.add_argument("--out", type=Path, default=Path("bench-results/real"), help="output directory")
    parser.add_argument(
        "--overlay", action="store_true", help="also write one overlay PNG per image to --out"
    )
    parser.add_argument(
        "--stages", action="store_true", help="also run every stage at the true pose (which fails first)"
    )
    parser.add_argument(
        "--plane-directions",
        action="store_true",
        help="add the directions of the maps' dominant planes to their direction clusters",
    )
    parser.add_argument(
        "--map-config",
        default=None,
        help="'auto' (limits from the point spacing) or a JSON object of Lines3DConfig fields",
    )
    parser.add_argument(
        "--prior",
        nargs=2,
        type=float,
        metavar=("ROT_DEG", "POS_M"),
        default=None,
        help="give each search a rough guess of the pose, at most ROT_DEG / POS_M from the truth "
        "(seeded by the image name), as a Prior of those bounds: the camera-LiDAR calibration case",
    )
    parser.add_argument(
        "--guesses",
        type=int,
        default=1,
        help="with --prior: localize each image from this many rough guesses (default 1): a photo's "
        "wrong claim may need a guess that leads to it",
    )
    parser.add_argument(
        "--intensity-edges",
        action="store_true",
        help="build the maps with the steps of the clouds' intensity too (single sweeps with an intensity)",
    )
    parser.add_argument("--max-rot-deg", type=float, default=5.0, help="success bound on R_e (default 5)")
    parser.add_argument(
        "--max-pos-m", type=float, default=0.3, help="success bound on position (default 0.3)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Runs every scene, prints the tables, writes results.json; returns the exit code."""
    from ..errors import InvalidInputError

    if args.prior is not None and (args.prior[0] <= 0 or args.prior[1] <= 0):
        raise InvalidInputError(f"--prior: ROT_DEG and POS_M must be positive, got {args.prior}")
    prior = None if args.prior is None else (float(args.prior[0]), float(args.prior[1]))
    if args.guesses < 1 or (args.guesses > 1 and prior is None):
        raise InvalidInputError(f"--guesses must be >= 1 and needs --prior above 1, got {args.guesses}")
    data = args.data if args.data is not None else default_data_dir()
    folders = scene_folders(data)
    if not folders:
        raise InvalidInputError(f"{data}: no scene folder with cameras.json and cloud.ply")
    bounds = (args.max_rot_deg, args.max_pos_m)
    overlay_dir = args.out if args.overlay else None
    edges = args.intensity_edges
    report.warm_up()
    scenes = [
        run_scene(
            folder,
            bounds,
            overlay_dir,
            args.stages,
            args.plane_directions,
            args.map_config,
            prior,
            edges,
            args.guesses,
        )
        for folder in folders
    ]
    records = [r for s in scenes for r in s["images"]]
    print(report.format_table([m for s in scenes for m in s["maps"]], MAP_COLUMNS))
    print()
    print(report.format_table(records, IMAGE_COLUMNS))
    if args.stages:
        from .real_stages import STAGE_COLUMNS

        rows = [{"scene": r["scene"], "image": r["image"]} | r.get("stages", {}) for r in records]
        print("\nat the true pose:")
        print(report.format_table(rows, STAGE_COLUMNS))
    done = sum(r["success"] for r in records)
    wrong = sum(bool(r.get("reported")) and not r["success"] for r in records)
    runs = "" if args.guesses == 1 else f" localizations ({args.guesses} rough guesses per image)"
    print(
        f"localized {done}/{len(records)}{runs} within {bounds[0]:g} deg / {bounds[1]:g} m of the ground truth"
    )
    print(f"wrong but claimed: {wrong}/{len(records)} (reported as success, outside those bounds)")
    if args.guesses > 1:
        print(_per_image(records))
    print(search_check.summary_line(search_check.tally(records)))
    covariance = honesty.summary(r["nees"] for r in records if "nees" in r)
    print(honesty.summary_line(covariance))
    results = {
        "benchmark": "real",
        "data": str(data),
        "bounds": {"rotation_deg": bounds[0], "position_m": bounds[1]},
        "plane_directions": args.plane_directions,
        "map_config": args.map_config,
        "intensity_edges": args.intensity_edges,
        "prior": None if prior is None else {"rotation_deg": prior[0], "position_m": prior[1]},
        "guesses": args.guesses,
        "covariance": covariance,
        "scenes": scenes,
    }
    path = report.write_json_atomic(args.out / "results.json", results)
    print(f"wrote {path}", file=sys.stderr)
    return 0


def _per_image(records: list[dict[str, Any]]) -> str:
    """Returns the line saying how many images were right, and claimed wrong, from at least one guess."""
    right: set[tuple[str, str]] = set()
    wrong: set[tuple[str, str]] = set()
    images = {(r["scene"], r["image"]) for r in records}
    for r in records:
        key = (r["scene"], r["image"])
        if r["success"]:
            right.add(key)
        elif r.get("reported"):
            wrong.add(key)
    return (
        f"per image: {len(right)}/{len(images)} right from at least one guess, "
        f"{len(wrong)}/{len(images)} claimed wrong from at least one"
    )
