"""``bench lines3d --real DIR``: maps of real clouds judged against real photos at their true poses.

Per scene folder (``bench.real.read_scene``: ``cameras.json``, the cloud each image's map is built from --
for an RGB-D frame the cloud without its own depth) the map is built in a child process (seconds, peak
memory), and per image: LSD segments (``lines2d.detect``), the map's visible parts at the true pose
(``LineMap.visible_parts``: occlusion by the map's surfaces), recall and precision (``lines3d_judge``),
per line kind, and the geometric ceiling (the cloud's depth discontinuities and creases). Overlays
(``--overlay``): the photo, its segments in grey, map parts that agree in green, the others in red.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from . import lines3d_judge as judge_mod
from . import report


def run_scene(folder: Path, overrides: dict[str, Any], overlay_dir: Path | None) -> dict[str, Any]:
    """Returns the record of one scene folder: per cloud its build cost, per image the judge's numbers."""
    from .. import io
    from ..config import LineDetectConfig
    from ..lines2d import detect
    from ..map import kinds as map_kinds
    from .lines3d import build_in_child
    from .real import read_scene

    images = read_scene(folder)
    maps: dict[Path, tuple[Any, dict[str, Any], np.ndarray]] = {}
    records = []
    for item in images:
        if item.cloud_path not in maps:
            print(
                f"{folder.name}: building the map of {item.cloud_path.name} ...", file=sys.stderr, flush=True
            )
            fields = io.read_cloud_fields(item.cloud_path, intensity=bool(overrides.get("intensity_edges")))
            cloud = fields.points
            line_map, cost = build_in_child(cloud, overrides, fields.intensity, fields.rings)
            maps[item.cloud_path] = (line_map, cost | {"points": len(cloud)}, cloud)
        line_map, cost, cloud = maps[item.cloud_path]
        camera = item.camera.undistorted()
        photo = io.read_image(item.image_path)
        lines2d = detect(photo, item.camera)
        min_px = LineDetectConfig().min_length_frac * math.hypot(camera.width, camera.height)
        parts, rows = line_map.visible_parts(camera, item.cam_from_world)
        result = judge_mod.judge(lines2d, parts, rows, line_map.kinds, camera, item.cam_from_world, min_px)
        top = judge_mod.ceiling(lines2d, cloud, camera, item.cam_from_world, line_map.metadata.get("profile"))
        record = {k: v for k, v in result.items() if not k.startswith("_")}
        record["by_kind"] = {map_kinds.NAMES[k]: v for k, v in record["by_kind"].items()}
        record |= {"image": item.image_path.name, "map": item.cloud_path.name}
        record |= {"ceiling": top["ceiling"], "covered": top["covered"]}
        records.append(record)
        if overlay_dir is not None:
            png = draw(
                photo, lines2d, judge_mod.project(parts, camera, item.cam_from_world), result["_pairs"][1]
            )
            edges = np.where(top["edge_mask"][:, :, None], np.array([255, 0, 255], np.uint8), 0)
            png = np.where(top["edge_mask"][:, :, None], (0.5 * png + 0.5 * edges).astype(np.uint8), png)
            io.write_image_atomic(overlay_dir / f"{folder.name}_{item.image_path.stem}.png", png)
    builds = [
        {"cloud": p.name, "segments": len(m), "profile": m.metadata.get("profile", {}).get("kind")}
        | c
        | {"kinds": map_kinds.kind_counts(m.kinds), "triangles": len(m.surfaces) if m.surfaces else 0}
        for p, (m, c, _) in maps.items()
    ]
    return {"scene": folder.name, "builds": builds, "images": records}


def draw(photo: np.ndarray, lines2d: np.ndarray, projected: np.ndarray, agreeing: np.ndarray) -> np.ndarray:
    """Returns a BGR uint8 overlay: the darkened photo, image segments grey, map parts green (agreeing)
    or red."""
    from ..lines2d import to_gray8

    grey = to_gray8(photo)
    canvas = cv2.cvtColor((0.6 * grey).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    ok = np.zeros(len(projected), dtype=bool)
    ok[agreeing] = True
    for segs, colour, width in (
        (lines2d, (200, 200, 200), 1),
        (projected[~ok], (0, 0, 255), 1),
        (projected[ok], (0, 255, 0), 2),
    ):
        for x1, y1, x2, y2 in np.nan_to_num(segs).clip(-1e5, 1e5).tolist():
            cv2.line(
                canvas,
                (round(x1), round(y1)),
                (round(x2), round(y2)),
                colour,
                width,
                cv2.LINE_AA,
            )
    return canvas


def summarise(scene: dict[str, Any]) -> dict[str, Any]:
    """Returns one table row of a scene: means over its images, build cost per 10^6 points."""
    imgs = scene["images"]
    builds = scene["builds"]
    points = sum(b["points"] for b in builds)
    mean = lambda key: float(np.nanmean([r[key] for r in imgs])) if imgs else float("nan")  # noqa: E731
    recall, ceiling = mean("recall"), mean("ceiling")
    return {
        "set": scene["scene"],
        "kind": builds[0]["profile"] if builds else "",
        "images": len(imgs),
        "segments": int(np.mean([b["segments"] for b in builds])) if builds else 0,
        "recall": recall,
        "precision": mean("precision"),
        "ceiling": ceiling,
        "of_ceiling": recall / ceiling if ceiling > 0 else float("nan"),
        "s_per_mpts": sum(b["seconds"] for b in builds) / max(points / 1e6, 1e-9),
        "peak_gb": max((b["peak_gb"] for b in builds), default=float("nan")),
    }


COLUMNS = (
    ("set", "set", ""),
    ("kind", "cloud", ""),
    ("images", "images", "d"),
    ("segments", "segments", "d"),
    ("recall", "recall", ".1%"),
    ("precision", "precision", ".1%"),
    ("ceiling", "ceiling", ".1%"),
    ("of_ceiling", "recall/ceiling", ".0%"),
    ("s_per_mpts", "s / 1e6 pts", ".1f"),
    ("peak_gb", "peak GB", ".2f"),
)


def kind_rows(scenes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Returns rows per (set, line kind): mean recall contribution, segments in view, precision."""
    rows = []
    for scene in scenes:
        names = sorted({k for r in scene["images"] for k in r["by_kind"]})
        for name in names:
            vals = [r["by_kind"].get(name) for r in scene["images"]]
            vals = [v for v in vals if v]
            rows.append(
                {
                    "set": scene["scene"],
                    "line kind": name,
                    "in_view": float(np.mean([v["in_view"] for v in vals])),
                    "recall": float(np.mean([v["recall"] for v in vals])),
                    "precision": float(np.nanmean([v["precision"] for v in vals])),
                }
            )
    return rows


KIND_COLUMNS = (
    ("set", "set", ""),
    ("line kind", "line kind", ""),
    ("in_view", "in view", ".1f"),
    ("recall", "recall", ".1%"),
    ("precision", "precision", ".1%"),
)


def run_real(data_dir: Path, overrides: dict[str, Any], out: Path, overlay: bool) -> dict[str, Any]:
    """Runs every scene folder of ``data_dir``; prints the tables; returns the results."""
    from .real import scene_folders

    folders = scene_folders(data_dir)
    if not folders:
        from ..errors import InvalidInputError

        raise InvalidInputError(f"--real {data_dir}: no scene folder (cameras.json + cloud.ply) there")
    scenes = [run_scene(f, overrides, out / "overlays" if overlay else None) for f in folders]
    rows = [summarise(s) for s in scenes]
    print(report.format_table(rows, COLUMNS))
    warm = [b["warm_seconds"] for scene in scenes for b in scene["builds"]]
    print(
        f"s / 1e6 pts: LineMap.build's wall time per 10^6 points, after the child's start (imports, compiled "
        f"kernels loaded once per process: {min(warm):.2f}-{max(warm):.2f} s, not counted)"
    )
    print()
    print(report.format_table(kind_rows(scenes), KIND_COLUMNS))
    return {"scenes": scenes, "table": rows}
