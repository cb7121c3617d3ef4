"""Camera-LiDAR calibration over several frames: the joint answer against each frame localized alone.

``linereg bench calibrate [--seeds 0 1 2] [--photos 4] [--data DIR ...] [--guesses 5] [--out DIR]``.

Synthetic rigs: the demo scene of each seed, its photos taken from a rig whose camera sits 3 deg / 0.37 m
off its LiDAR (``sim.rig``: each stop's map is the scan's map in that stop's LiDAR frame). Real rigs
(``--data``): the images of every scene folder under the DIRs grouped by their ground-truth pose, each group of
two or more one rig (KITTI's object frames of one day's drives share their Velodyne-to-camera calibration, and
each folder's map is its sweep in the Velodyne's frame). Every rig is calibrated from ``--guesses`` rough
guesses of its extrinsic (at most 5 deg / 0.5 m off, ``bench.real.rough_guess``) with ``linereg.calibrate``;
the table gives per guess the joint answer (claimed or not, its error, its NEES: the error in its own
sigmas) and how each photo localized alone near the same guess did (right / wrong claims within the
bounds of ``--max-rot-deg`` / ``--max-pos-m``: default 5 deg / 0.3 m, as ``bench real``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

EXTRINSIC_DEG = (1.0, -2.0, 2.0)  # the synthetic rig's camera turned off its LiDAR (rotation vector, deg)
EXTRINSIC_M = (0.1, -0.2, 0.3)  # ... and moved


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--seeds", type=int, nargs="*", default=[0, 1, 2], help="demo scene seeds (synthetic rigs)"
    )
    parser.add_argument("--photos", type=int, default=4, help="photos per synthetic rig (default 4)")
    parser.add_argument(
        "--data", type=Path, nargs="*", default=[], help="also the real rigs of these data folders, pooled"
    )
    parser.add_argument("--guesses", type=int, default=5, help="rough guesses per rig (default 5)")
    parser.add_argument("--max-rot-deg", type=float, default=5.0, help="right: within this rotation (deg)")
    parser.add_argument("--max-pos-m", type=float, default=0.3, help="... and this position (m)")
    parser.add_argument("--out", type=Path, default=Path("bench-results/calibrate"), help="output directory")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import check_output_dir
    from ..errors import InvalidInputError
    from . import report

    if args.guesses < 1 or args.photos < 2:
        raise InvalidInputError(
            f"--guesses must be >= 1 and --photos >= 2, got {args.guesses}, {args.photos}"
        )
    check_output_dir("--out", args.out)
    report.warm_up()
    rigs = [synthetic_rig(seed, args.photos) for seed in args.seeds]
    if args.data:
        rigs += real_rigs(args.data)
    rows = [row for rig in rigs for row in calibrate_rig(rig, args)]
    print(report.format_table(rows, COLUMNS))
    for kind in ("synthetic", "real"):
        mine = [r for r in rows if r["kind"] == kind]
        if mine:
            print(_summary(kind, mine))
    args.out.mkdir(parents=True, exist_ok=True)
    path = report.write_json_atomic(args.out / "results.json", {"benchmark": "calibrate", "rows": rows})
    print(f"wrote {path}")
    return 0


COLUMNS = (
    ("rig", "rig", ""),
    ("photos", "photos", "d"),
    ("guess", "guess", "d"),
    ("guess_deg", "guess deg", ".1f"),
    ("guess_m", "guess m", ".2f"),
    ("success", "claimed", ""),
    ("rotation_deg", "R_e deg", ".3f"),
    ("position_m", "pos m", ".3f"),
    ("nees", "NEES", ".1f"),
    ("alone", "alone right/wrong", ""),
    ("seconds", "s", ".1f"),
    ("reason", "reason", ""),
)


def synthetic_rig(seed: int, photos: int) -> dict[str, Any]:
    """Returns a rig of the demo scene of ``seed``: its first ``photos`` photos, the maps of each stop."""
    from scipy.spatial.transform import Rotation

    from ..geometry import make_cam_from_world
    from ..map.linemap import LineMap
    from ..sim.demo_scene import make_demo_scene
    from ..sim.rig import rig_maps

    scene = make_demo_scene(seed=seed, num_images=photos)
    extrinsic = make_cam_from_world(
        Rotation.from_rotvec(np.radians(EXTRINSIC_DEG)).as_matrix(), np.array(EXTRINSIC_M)
    )
    maps = rig_maps(LineMap.build(scene.cloud), list(scene.cam_from_world), extrinsic)
    return {
        "name": f"demo seed {seed}", "kind": "synthetic", "images": list(scene.images), "maps": maps,
        "cameras": [scene.camera] * photos, "truth": extrinsic,
    }  # fmt: skip


def real_rigs(folders: list[Path]) -> list[dict[str, Any]]:
    """Returns the rigs of data folders: images of every scene grouped by their identical ground truth."""
    from .. import io
    from .real import build_map, read_scene, scene_folders

    groups: dict[bytes, list[Any]] = {}
    for folder in [f for data in folders for f in scene_folders(data)]:
        for item in read_scene(folder):
            groups.setdefault(np.round(item.cam_from_world, 6).tobytes(), []).append(item)
    rigs = []
    for items in groups.values():
        if len(items) < 2:
            continue
        maps = {}
        for item in items:
            if item.cloud_path not in maps:
                maps[item.cloud_path] = build_map(item.cloud_path)[0]
        rigs.append({
            "name": _rig_name(sorted({item.scene for item in items})), "kind": "real",
            "images": [io.read_image(item.image_path) for item in items],
            "maps": [maps[item.cloud_path] for item in items],
            "cameras": [item.camera for item in items], "truth": items[0].cam_from_world,
        })  # fmt: skip
    return rigs


def calibrate_rig(rig: dict[str, Any], args: argparse.Namespace) -> list[dict[str, Any]]:
    """Returns one row per rough guess of the rig's extrinsic."""
    from ..calibration import calibrate
    from ..geometry import pose_errors
    from ..priors import Prior
    from .honesty import nees
    from .real import rough_guess

    rows = []
    truth = rig["truth"]
    for k in range(args.guesses):
        guess = rough_guess(truth, 5.0, 0.5, f"{rig['name']}/{k}")
        start = time.perf_counter()
        result = calibrate(
            rig["images"],
            rig["maps"],
            rig["cameras"],
            Prior(cam_from_world=guess, sigma_rot_deg=5.0, radius_m=0.5),
        )
        seconds = time.perf_counter() - start
        rot, pos, _ = pose_errors(result.cam_from_lidar, truth)
        right = rot <= args.max_rot_deg and pos <= args.max_pos_m
        alone = [(s.success, pose_errors(s.cam_from_world, truth)) for s in result.singles]
        alone_right = sum(ok and e[0] <= args.max_rot_deg and e[1] <= args.max_pos_m for ok, e in alone)
        alone_wrong = sum(ok and not (e[0] <= args.max_rot_deg and e[1] <= args.max_pos_m) for ok, e in alone)
        g_rot, g_pos, _ = pose_errors(guess, truth)
        rows.append({
            "rig": rig["name"], "kind": rig["kind"], "photos": len(rig["images"]), "guess": k,
            "guess_deg": g_rot, "guess_m": g_pos, "success": bool(result.success),
            "right": bool(result.success and right), "wrong": bool(result.success and not right),
            "rotation_deg": rot, "position_m": pos,
            "nees": nees(result.cam_from_lidar, truth, result.covariance) if result.success else None,
            "nees_any": nees(result.cam_from_lidar, truth, result.covariance),
            "alone": f"{alone_right}/{alone_wrong}", "alone_right": alone_right, "alone_wrong": alone_wrong,
            "alone_errors": [[float(e[0]), float(e[1])] for ok, e in alone if ok],
            "seconds": seconds, "reason": result.reason[:90], "frame_inliers": result.frame_inliers.tolist(),
        })  # fmt: skip
        print(f"  {rig['name']} guess {k}: {'claimed' if result.success else 'not claimed'}, {rot:.3f} deg / "
              f"{pos:.3f} m, {seconds:.1f} s {result.reason[:70]}", flush=True)  # fmt: skip
    return rows


def _summary(kind: str, rows: list[dict[str, Any]]) -> str:
    n = len(rows)
    right, wrong = sum(r["right"] for r in rows), sum(r["wrong"] for r in rows)
    photos = sum(r["photos"] for r in rows)
    alone_right, alone_wrong = sum(r["alone_right"] for r in rows), sum(r["alone_wrong"] for r in rows)
    beyond = sum(1 for r in rows if r["nees"] is not None and r["nees"] > 20.06)
    errors = [r for r in rows if r["right"]]
    median = ""
    if errors:
        median = (
            f"; median error of the right ones {np.median([r['rotation_deg'] for r in errors]):.3f} deg / "
            f"{np.median([r['position_m'] for r in errors]):.3f} m"
        )
    claimed = np.array([e for r in rows for e in r["alone_errors"]]).reshape(-1, 2)
    alone = ""
    if len(claimed):
        alone = f" (their claims' median error {np.median(claimed[:, 0]):.3f} deg / {np.median(claimed[:, 1]):.3f} m)"
    return (
        f"{kind}: {right}/{n} calibrations right, {wrong}/{n} claimed wrong, {beyond} claims beyond 3 sigma"
        f"{median}; the photos alone near the same guesses: {alone_right}/{photos} right, "
        f"{alone_wrong}/{photos} claimed wrong{alone}"
    )


def _rig_name(scenes: list[str]) -> str:
    """Returns a rig's name: its scenes joined, or for more than five the start they share and how many."""
    if len(scenes) <= 5:
        return "+".join(scenes)
    shared = scenes[0]
    for scene in scenes[1:]:
        while not scene.startswith(shared):
            shared = shared[:-1]
    return f"{shared.rstrip('_0') or scenes[0]}* ({len(scenes)} scenes)"
