"""2D line detection time (LSD + merging) at 640x480 and 1920x1080 on rendered and real photos.

``linereg bench lines2d [--images 5] [--repeats 5] [--data DIR] [--out DIR]``.

Images: the demo scene's rendered photos at 640x480 and the same views re-rendered at 1920x1080 (same
horizontal field of view), plus the photos of the real data folder (``bench real``'s ``--data``) at their
own size and upscaled to 1920x1080 (bicubic). Each image is detected
``--repeats`` times after one warm-up; the time is ``lines2d.detect`` (grey conversion, LSD, undistortion,
merging, short-segment removal), split into LSD alone (``lines2d.lsd_segments`` on the grey image) and the
rest, and the process CPU time of ``detect`` (all threads: LSD may run on bands in parallel).
Targets (issue 3): <= 30 ms at 640x480, <= 150 ms at 1920x1080.

Quality, so that speed is not bought with lines: on the demo photos, ``recall`` is the fraction of the
length of the building's visible edges (as long as ``detect`` keeps) that detected segments cover, and
``precision`` the fraction of the detected length lying on a visible edge; on every image, ``ref recall``
is the fraction of the length found by a slow reference detection (LSD at full resolution, one thread,
same merging) that ``detect`` covers. Covered: within ``COVER_PX`` (scaled with the image diagonal from
800 px) and ``COVER_DEG`` of a segment, inside its extent.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import report

HD = (1920, 1080)
TARGETS_MS = {(640, 480): 30.0, HD: 150.0}
COVER_PX, COVER_DEG = 2.0, 2.0  # at a 800 px diagonal (640x480); distances scale with the diagonal


def camera_for(image: np.ndarray) -> Any:
    """Returns a pinhole camera matching an image's size (intrinsics do not change detection time)."""
    from ..camera import Camera

    h, w = image.shape[:2]
    return Camera(fx=0.9 * w, fy=0.9 * w, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)


def upscale(image: np.ndarray, size: tuple[int, int] = HD) -> np.ndarray:
    """Returns ``image`` resized to ``size`` (width, height) with bicubic interpolation."""
    import cv2

    return cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)


def hd_camera(camera: Any) -> Any:
    """Returns the 1920x1080 camera with the horizontal field of view of ``camera`` (same optical axis)."""
    from ..camera import Camera

    scale = HD[0] / camera.width
    return Camera(camera.fx * scale, camera.fy * scale, (HD[0] - 1) / 2, (HD[1] - 1) / 2, *HD)


def demo_images(num_images: int, seed: int) -> Iterator[tuple[str, np.ndarray, np.ndarray | None]]:
    """Yields (source, image, (K, 4) true visible edges): the demo photos, then the same views at 1920x1080."""
    from ..sim.demo_scene import make_demo_scene
    from ..sim.render import render_image
    from ..sim.views import project_building

    scene = make_demo_scene(seed=seed, num_images=num_images)
    for image, cam_from_world in zip(scene.images, scene.cam_from_world, strict=True):
        yield "demo", image, project_building(scene.building, scene.camera, cam_from_world, 1.0)[0]
    camera, rng = hd_camera(scene.camera), np.random.default_rng(seed)
    for cam_from_world in scene.cam_from_world:
        image = render_image(scene.building, cam_from_world, camera, rng)
        yield "demo", image, project_building(scene.building, camera, cam_from_world, 1.0)[0]


def real_images(data_dir: Path) -> Iterator[tuple[str, np.ndarray, None]]:
    """Yields (source, image) for every photo of the real data folder, native size and 1920x1080."""
    from .. import io
    from .real import read_scene, scene_folders

    for folder in scene_folders(data_dir):
        for item in read_scene(folder):
            image = io.read_image(item.image_path)
            yield folder.name, image, None
            yield f"{folder.name} upscaled", upscale(image), None


def time_image(image: np.ndarray, repeats: int) -> dict[str, Any]:
    """Returns median milliseconds (wall and CPU) of ``detect`` and of LSD alone over ``repeats`` runs."""
    from ..config import LineDetectConfig
    from ..lines2d import detect, lsd_segments, to_gray8

    camera, config = camera_for(image), LineDetectConfig()
    segments = detect(image, camera, config)  # warm-up (and the count)
    total, cpu, lsd = [], [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        detect(image, camera, config)
        total.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        gray = to_gray8(image)
        start = time.perf_counter()
        raw = lsd_segments(gray, config)
        lsd.append(time.perf_counter() - start)
    return {
        "detect_ms": 1e3 * float(np.median(total)),
        "detect_ms_best": 1e3 * float(np.min(total)),  # least disturbed by other processes on the machine
        "detect_cpu_ms": 1e3 * float(np.median(cpu)),
        "lsd_ms": 1e3 * float(np.median(lsd)),
        "num_lsd": len(raw),
        "num_segments": len(segments),
        "segments": segments,
    }


def coverage(lines: np.ndarray, by: np.ndarray, dist_px: float, angle_deg: float) -> float:
    """Returns the fraction of the length of (N, 4) ``lines`` covered by (M, 4) segments ``by``.

    The lines are sampled every ``dist_px``; a sample is covered by a segment of ``by`` within
    ``angle_deg`` of its line's direction, ``dist_px`` of its line and inside its extent (+ dist_px).
    """
    from ..geometry import segment_directions, segment_lengths

    length = segment_lengths(lines)
    if len(lines) == 0 or length.sum() == 0:
        return float("nan")
    if len(by) == 0:
        return 0.0
    counts = np.maximum(np.ceil(length / dist_px).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(lines)), counts)
    t = (np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts) + 0.5) / counts[owner]
    samples = lines[owner, 0:2] + t[:, None] * (lines[owner, 2:4] - lines[owner, 0:2])
    weight = length[owner] / counts[owner]
    u, origin, extent = segment_directions(by), by[:, 0:2], segment_lengths(by)
    cos_min = np.cos(np.radians(angle_deg))
    covered = np.zeros(len(samples), dtype=bool)
    for rows in np.array_split(np.arange(len(samples)), max(1, len(samples) * len(by) // 2_000_000)):
        rel = samples[rows, None, :] - origin[None, :, :]  # (S, M, 2)
        along = rel[..., 0] * u[:, 0] + rel[..., 1] * u[:, 1]
        across = np.abs(rel[..., 0] * u[:, 1] - rel[..., 1] * u[:, 0])
        parallel = np.abs(segment_directions(lines[owner[rows]]) @ u.T) >= cos_min
        inside = (along >= -dist_px) & (along <= extent + dist_px)
        covered[rows] = (parallel & inside & (across <= dist_px)).any(axis=1)
    return float(weight[covered].sum() / weight.sum())


def quality(image: np.ndarray, segments: np.ndarray, truth: np.ndarray | None) -> dict[str, float]:
    """Returns recall and precision against true edges (NaN without them) and recall of the reference."""
    from dataclasses import replace

    from ..config import LineDetectConfig
    from ..geometry import segment_lengths
    from ..lines2d import detect

    h, w = image.shape[:2]
    config = LineDetectConfig()
    reference = replace(config, lsd_scale=1.0, max_work_pixels=w * h, lsd_bands=1)
    diagonal = float(np.hypot(w, h))
    dist_px = COVER_PX * diagonal / 800.0
    out = {"ref_recall": coverage(detect(image, camera_for(image), reference), segments, dist_px, COVER_DEG)}
    out["recall"] = out["precision"] = float("nan")
    if truth is not None:
        long = truth[segment_lengths(truth) >= config.min_length_frac * diagonal]
        out["recall"] = coverage(long, segments, dist_px, COVER_DEG)
        out["precision"] = coverage(segments, truth, dist_px, COVER_DEG)
    return out


def summarize(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Returns one row per (source, size): image count, median / p95 / max detect ms, LSD ms, segments."""
    rows = []
    for (source, size), group in report.by_key(records, "key").items():
        ms = np.array([r["detect_ms"] for r in group])
        target = TARGETS_MS.get(tuple(size), float("nan"))
        rows.append(
            {
                "source": source,
                "size": f"{size[0]}x{size[1]}",
                "n": len(group),
                "detect_ms_median": float(np.median(ms)),
                "detect_ms_p95": float(np.percentile(ms, 95)),
                "detect_ms_max": float(ms.max()),
                "detect_ms_best": float(np.median([r["detect_ms_best"] for r in group])),
                "detect_cpu_ms": float(np.median([r["detect_cpu_ms"] for r in group])),
                "lsd_ms_median": float(np.median([r["lsd_ms"] for r in group])),
                "segments_median": float(np.median([r["num_segments"] for r in group])),
                "recall": float(np.mean([r["recall"] for r in group])),
                "precision": float(np.mean([r["precision"] for r in group])),
                "ref_recall": float(np.mean([r["ref_recall"] for r in group])),
                "target_ms": target,
                "met": "-" if np.isnan(target) else ("yes" if np.median(ms) <= target else "no"),
            }
        )
    return rows


COLUMNS = (
    ("source", "source", ""),
    ("size", "size", ""),
    ("n", "n", "d"),
    ("detect_ms_median", "detect ms med", ".1f"),
    ("detect_ms_p95", "p95", ".1f"),
    ("detect_ms_max", "max", ".1f"),
    ("detect_ms_best", "best-of ms", ".1f"),
    ("detect_cpu_ms", "CPU ms", ".1f"),
    ("lsd_ms_median", "LSD ms med", ".1f"),
    ("segments_median", "segments", ".0f"),
    ("recall", "recall", ".1%"),
    ("precision", "precision", ".1%"),
    ("ref_recall", "ref recall", ".1%"),
    ("target_ms", "target ms", ".0f"),
    ("met", "met (med)", ""),
)


def configure(parser: argparse.ArgumentParser) -> None:
    """Adds the ``bench lines2d`` arguments and sets ``func=run``."""
    from .real import DATA_ENV

    parser.add_argument("--images", type=int, default=5, help="demo photos (default 5)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per image (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="demo scene seed (default 0)")
    parser.add_argument(
        "--data", type=Path, default=None, help=f"real data folder (default ${DATA_ENV} or ../shared/data)"
    )
    parser.add_argument("--out", type=Path, default=Path("bench-results/lines2d"), help="output directory")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Times detection on every image, prints the table, writes results.json; returns the exit code."""
    from ..config import LineDetectConfig
    from ..errors import InvalidInputError
    from ..lines2d import lsd_bands
    from .real import default_data_dir

    if args.images < 1 or args.repeats < 1:
        raise InvalidInputError("--images and --repeats must be >= 1")
    data = args.data if args.data is not None else default_data_dir()
    records = []
    for source, image, truth in [*demo_images(args.images, args.seed), *real_images(data)]:
        size = (image.shape[1], image.shape[0])
        timed = time_image(image, args.repeats)
        segments = timed.pop("segments")
        record = {"source": source, "key": (source, size), "size": size} | timed
        records.append(record | quality(image, segments, truth))
    rows = summarize(records)
    print(report.format_table(rows, COLUMNS))
    threads = lsd_bands(LineDetectConfig())
    print(
        "detect = grey + LSD + undistort + merge + filter; median over repeats per image, then over images;"
        " best-of: fastest repeat per image (median over images); CPU: process time of detect (all threads);"
        " recall / precision vs the demo's true edges, ref recall vs full-resolution LSD (means over images);"
        f" LSD on {threads} band(s) in parallel"
    )
    results = {
        "benchmark": "lines2d",
        "options": {"images": args.images, "repeats": args.repeats, "seed": args.seed, "data": str(data)}
        | {"lsd_bands": threads},
        "targets_ms": {f"{w}x{h}": t for (w, h), t in TARGETS_MS.items()},
        "rows": rows,
        "images": [{k: v for k, v in r.items() if k != "key"} for r in records],
    }
    path = report.write_json_atomic(args.out / "results.json", results)
    print(f"wrote {path}", file=sys.stderr)
    return 0
