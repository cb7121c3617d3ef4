"""Colorization on the demo scene: leave-one-photo-out PSNR against naive colouring, occlusion, throughput.

``linereg bench colorize [--images 10] [--seed 0] [--points 10000000] [--photos 20] [--workers 2] [--out DIR]``.

1. Leave one photo out: the demo scan is coloured from every photo but one (ours, and a naive colouring:
   each point takes the nearest photo it projects into, no visibility test), re-projected into the photo
   left out (the points the renderer's z-buffer says it sees, averaged per pixel) and compared with it:
   PSNR over the pixels both colourings cover. The photos are rendered with one texture and tint per
   surface (a fresh generator of the same seed per photo), so a surface has one true colour.
2. Occlusion: every point a photo coloured that the renderer says it cannot see (more than 0.1 m behind
   the faces the photo shows at its pixel and the 8 round it, each met along the point's own ray).
3. Throughput and memory: ``--points`` points (jittered copies of the scan) x ``--photos`` photos of
   640 x 480 written as a binary PLY, then ``colorize_file`` on ``--workers`` local processes; wall time,
   points/s, peak RSS of the parent, of the largest worker and of the whole process tree at once
   (``linereg.bench.memory``: workers started by a fork server are not our children to wait for).

Writes results.json and PNG strips per held-out view (photo | naive | ours | untextured scan) to --out.
Targets (issue 12, 2 cores): PSNR >= 25 dB, 0 points coloured through an occluder, 10^7 x 20 in <= 60 s.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import report

NOISE_TOLERANCE_M = 0.05  # 5 sigma of the demo scanner's range noise
OCCLUDED_M = 0.1  # a point this far behind every face round its pixel is hidden from the photo
TARGETS = {"psnr_db": 25.0, "occluded": 0, "throughput_s": 60.0}


def configure(parser: argparse.ArgumentParser) -> None:
    """Adds the ``bench colorize`` arguments and sets ``func=run``."""
    parser.add_argument("--images", type=int, default=10, help="photos of the demo scene (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    parser.add_argument("--points", type=int, default=10_000_000, help="throughput cloud size (0: skip)")
    parser.add_argument("--photos", type=int, default=20, help="throughput photos (default 20)")
    parser.add_argument("--workers", type=int, default=2, help="throughput worker processes (default 2)")
    parser.add_argument("--out", type=Path, default=Path("bench-results/colorize"), help="output directory")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Runs the benchmark, prints the tables, writes results.json and the pictures; returns the exit code."""
    from ..errors import InvalidInputError

    if args.images < 2:
        raise InvalidInputError(f"--images must be >= 2 (one is left out), got {args.images}")
    args.out.mkdir(parents=True, exist_ok=True)
    scene = consistent_scene(args.seed, max(args.images, args.photos if args.points else 0))
    progress = report.Progress(args.images + 2, "colorize")
    try:
        views = leave_one_out(scene, args.images, args.out, progress)
        occlusion = occlusion_check(scene, args.images)
        progress.advance("occlusion")
        throughput = measure_throughput(scene, args.points, args.photos, args.workers) if args.points else {}
        progress.advance("throughput")
    finally:
        progress.close()
    psnr = {m: float(np.mean([v[f"psnr_{m}_db"] for v in views])) for m in ("ours", "naive")}
    results = {
        "benchmark": "colorize",
        "options": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k != "func"},
        "views": views,
        "psnr_mean_db": psnr,
        "occlusion": occlusion,
        "throughput": throughput,
        "targets": TARGETS,
    }
    report.write_json_atomic(args.out / "results.json", results)
    columns = [("photo", "photo", ""), ("psnr_ours_db", "ours dB", ".2f"), ("psnr_naive_db", "naive dB", ".2f"),
               ("pixels", "pixels", ""), ("coverage_ours", "ours cover", ".2f")]  # fmt: skip
    print(report.format_table(views, columns))
    print(f"mean PSNR: ours {psnr['ours']:.2f} dB, naive {psnr['naive']:.2f} dB (target >= 25)")
    print(
        f"coloured through an occluder: ours {occlusion['ours']} ({occlusion['ours_over_1m']} with it > 1 m in "
        f"front), naive {occlusion['naive']} (target 0); ours coloured {occlusion['pairs']:,} (point, photo) "
        f"pairs, {occlusion['points_coloured']:,} points; truly visible pairs coloured "
        f"{occlusion['visible_coloured']:,} of {occlusion['visible']:,}"
    )
    if throughput:
        print(
            f"throughput: {throughput['points']:,} points x {throughput['photos']} photos in "
            f"{throughput['seconds']:.1f} s ({throughput['points_per_s']:,.0f} points/s, "
            f"{throughput['workers']} workers; target <= 60 s); peak RSS parent "
            f"{throughput['peak_rss_parent_mb']:.0f} MB, largest worker {throughput['peak_rss_worker_mb']:.0f} MB, "
            f"process tree {throughput['peak_rss_tree_mb']:.0f} MB"
        )
    print(f"results and pictures in {args.out}", file=sys.stderr)
    return 0


def consistent_scene(seed: int, num_images: int) -> Any:
    """Returns the demo scene with its photos re-rendered by one texture and tint per surface."""
    from dataclasses import replace

    from ..sim.demo_scene import make_demo_scene
    from ..sim.render import render_image

    scene = make_demo_scene(seed=seed, num_images=num_images)
    images = [
        render_image(scene.building, p, scene.camera, np.random.default_rng(seed + 1000))
        for p in scene.cam_from_world
    ]
    return replace(scene, images=np.array(images))


def truly_visible(scene: Any, k: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (rows, pixel index, state) of the points inside photo k, from the renderer's exact faces.

    Each point's own ray meets the planes of the faces the z-buffer shows at its pixel and the 8 round it:
    state 1 (visible) when one of them lies within ``NOISE_TOLERANCE_M`` of the point (scan noise is 1 cm),
    -1 (occluded) when every one is a face lying more than ``OCCLUDED_M`` in front of it and the point lies
    on none of their planes (within ``NOISE_TOLERANCE_M``, measured along the normal: a point 2 cm under
    the face the photo shows, seen at 80 degrees, lies 0.1 m behind it along the ray, but on it), 0
    otherwise (beside an edge, or next to the sky).
    """
    from ..color.project import project
    from ..sim.render import rasterize

    camera, cam_from_world = scene.camera, scene.cam_from_world[k]
    face, _ = rasterize(scene.building, cam_from_world, camera)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    normals = scene.building.normals @ R.T  # face planes in the camera frame: n . X = d
    offsets = np.einsum("fk,fk->f", normals, scene.building.faces[:, 0] @ R.T + t)
    pr = project(points, camera, cam_from_world, 0.1)
    ray = np.stack([(pr.u - camera.cx) / camera.fx, (pr.v - camera.cy) / camera.fy, np.ones(len(pr.u))], 1)
    row, col = np.floor(pr.v + 0.5).astype(np.int64), np.floor(pr.u + 0.5).astype(np.int64)
    padded = np.pad(face, 1, constant_values=-1)
    gap = np.full((9, len(row)), np.inf)  # point depth - face depth along the point's ray, per neighbour
    on_plane = np.zeros(len(row), bool)  # within the noise of a shown face's plane, along its normal
    cam_points = points[pr.index] @ R.T + t
    for i, (dy, dx) in enumerate((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)):
        f = padded[row + 1 + dy, col + 1 + dx]
        has = f >= 0
        denominator = np.einsum("nk,nk->n", normals[f[has]], ray[has])
        with np.errstate(divide="ignore"):
            gap[i, has] = pr.z[has] - offsets[f[has]] / denominator
        off_plane = np.einsum("nk,nk->n", normals[f[has]], cam_points[has]) - offsets[f[has]]
        on_plane[has] |= np.abs(off_plane) <= NOISE_TOLERANCE_M
    visible = (np.abs(gap) <= NOISE_TOLERANCE_M).any(axis=0)
    occluded = (gap > OCCLUDED_M).all(axis=0) & np.isfinite(gap).all(axis=0) & ~on_plane
    return pr.index, row * camera.width + col, np.where(visible, 1, np.where(occluded, -1, 0))


def naive_colours(scene: Any, photos: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P, 3) uint8 RGB, (P,) bool coloured): each point from the nearest photo it projects into."""
    from ..color.blend import sample_rgb
    from ..color.project import project
    from ..geometry import camera_center

    points = scene.cloud
    best = np.full(len(points), np.inf)
    colours = np.zeros((len(points), 3), dtype=np.uint8)
    for j in photos:
        pr = project(points, scene.camera, scene.cam_from_world[j], 0.1)
        distance = np.linalg.norm(points[pr.index] - camera_center(scene.cam_from_world[j]), axis=1)
        better = distance < best[pr.index]
        rows = pr.index[better]
        best[rows] = distance[better]
        colours[rows] = np.clip(np.rint(sample_rgb(scene.images[j], pr.u[better], pr.v[better])), 0, 255)
    return colours, np.isfinite(best)


def leave_one_out(scene: Any, num_images: int, out: Path, progress: Any) -> list[dict[str, Any]]:
    """Returns one record per held-out photo (PSNR ours / naive, pixels compared) and writes its strip."""
    from ..colorization import colorize

    views = []
    cam = scene.camera
    for k in range(num_images):
        others = [j for j in range(num_images) if j != k]
        ours, seen = colorize(
            scene.cloud, [scene.images[j] for j in others], cam, scene.cam_from_world[others]
        )
        naive, naive_seen = naive_colours(scene, others)
        rows, pixel, state = truly_visible(scene, k, scene.cloud)
        rows, pixel = rows[state == 1], pixel[state == 1]
        a, mask_a = splat_mean(ours, seen[rows] > 0, rows, pixel, cam.height * cam.width)
        b, mask_b = splat_mean(naive, naive_seen[rows], rows, pixel, cam.height * cam.width)
        truth = scene.images[k][:, :, ::-1].reshape(-1, 3).astype(np.float64)
        both = mask_a & mask_b
        views.append({
            "photo": k,
            "psnr_ours_db": psnr(a[both], truth[both]),
            "psnr_naive_db": psnr(b[both], truth[both]),
            "pixels": int(both.sum()),
            "coverage_ours": float(mask_a.sum() / max(np.count_nonzero(np.bincount(pixel)), 1)),
        })  # fmt: skip
        write_strip(out / f"view{k}.png", scene.images[k], a, mask_a, b, mask_b, scene, rows, pixel)
        progress.advance(f"photo {k}")
    return views


def splat_mean(colours: np.ndarray, keep: np.ndarray, rows: np.ndarray, pixel: np.ndarray, size: int):
    """Returns ((size, 3) float64 mean RGB per pixel of the kept points, (size,) bool pixels with one)."""
    rows, pixel = rows[keep], pixel[keep]
    total = np.stack([np.bincount(pixel, colours[rows, c].astype(np.float64), size) for c in range(3)], 1)
    count = np.bincount(pixel, minlength=size)
    return total / np.maximum(count, 1)[:, None], count > 0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Returns the PSNR (dB, peak 255) between two (n, 3) colour arrays."""
    mse = float(np.mean((a - b) ** 2)) if len(a) else float("nan")
    return 10.0 * np.log10(255.0**2 / max(mse, 1e-12))


def write_strip(path: Path, photo, ours, mask_a, naive, mask_b, scene, rows, pixel) -> None:
    """Writes photo | naive | ours | untextured scan (grey by range), each (H, W) of the held-out view."""
    from ..io import write_image_atomic

    h, w = photo.shape[:2]

    def picture(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        image = np.full((h * w, 3), 255, dtype=np.uint8)
        image[mask] = np.clip(np.rint(rgb[mask]), 0, 255).astype(np.uint8)[:, ::-1]
        return image.reshape(h, w, 3)

    grey = np.full((len(scene.cloud), 3), 150, dtype=np.uint8)
    before, mask_g = splat_mean(grey, np.ones(len(rows), bool), rows, pixel, h * w)
    write_image_atomic(
        path,
        np.concatenate([photo, picture(naive, mask_b), picture(ours, mask_a), picture(before, mask_g)], 1),
    )


def occlusion_check(scene: Any, num_images: int) -> dict[str, int]:
    """Returns how many (point, photo) pairs coloured a point the photo cannot see (ours, naive; ours
    split by how far in front the occluder is) and our coverage: (point, photo) pairs, points coloured,
    and of the pairs the renderer says are visible how many there are and how many we coloured."""
    from ..color.blend import observe
    from ..color.config import ColorizeConfig
    from ..color.engine import ArraySource, View, chunk_geometry, depth_pass, make_plan, prepare_photos
    from ..colorization import make_photos
    from ..geometry import camera_center

    config = ColorizeConfig()
    source = ArraySource(scene.cloud)
    plan = make_plan(source, config)
    views = [View(scene.camera, p) for p in scene.cam_from_world[:num_images]]
    photos = make_photos(list(scene.images[:num_images]), scene.camera, scene.cam_from_world[:num_images])
    maps, sample = depth_pass(source, views, plan, _inline())
    photos = prepare_photos(photos, maps, sample, plan)
    spacing, normals = chunk_geometry(scene.cloud, plan)
    _, check = chunk_geometry(scene.cloud, plan, shifted=True)
    truth = [truly_visible(scene, k, scene.cloud) for k in range(num_images)]
    distance = np.full((num_images, len(scene.cloud)), np.inf)
    for k, (rows, _, _) in enumerate(truth):  # naive: the nearest photo a point projects into colours it
        distance[k, rows] = np.linalg.norm(scene.cloud[rows] - camera_center(scene.cam_from_world[k]), axis=1)
    nearest = np.argmin(distance, axis=0)
    counts = dict.fromkeys(("ours", "ours_over_1m", "naive", "pairs", "visible", "visible_coloured"), 0)
    coloured = np.zeros(len(scene.cloud), bool)
    for k, (photo, depth) in enumerate(zip(photos, maps, strict=True)):
        used = observe(photo, depth, scene.cloud, spacing, normals, config, check_normals=check).index
        rows, _, state = truth[k]
        occluded = np.zeros(len(scene.cloud), bool)
        occluded[rows[state == -1]] = True
        counts["ours"] += int(occluded[used].sum())
        counts["ours_over_1m"] += int(occluded[used].sum() - _within_m(scene, k, used[occluded[used]], 1.0))
        counts["naive"] += int((occluded & (nearest == k)).sum())
        counts["pairs"] += len(used)
        counts["visible"] += int((state == 1).sum())  # what the photo shows of the scan, for scale
        counts["visible_coloured"] += int(np.isin(used, rows[state == 1]).sum())
        coloured[used] = True
    return {**counts, "points_coloured": int(coloured.sum())}


def _within_m(scene: Any, k: int, rows: np.ndarray, metres: float) -> int:
    """Returns how many of the points ``rows`` lie at most ``metres`` behind the face photo k shows at them."""
    from ..color.project import project
    from ..sim.render import rasterize

    _, inverse_depth = rasterize(scene.building, scene.cam_from_world[k], scene.camera)
    pr = project(scene.cloud, scene.camera, scene.cam_from_world[k], 0.1, rows)
    face_z = 1.0 / np.maximum(
        inverse_depth[np.floor(pr.v + 0.5).astype(int), np.floor(pr.u + 0.5).astype(int)], 1e-12
    )
    return int((pr.z - face_z <= metres).sum())


def _inline():
    from ..batch import InlineRunner

    return InlineRunner()


def measure_throughput(scene: Any, num_points: int, num_photos: int, workers: int) -> dict[str, Any]:
    """Returns wall time, points/s and peak RSS of ``colorize_file`` on a PLY of ``num_points``."""
    from .. import batch
    from ..colorization import colorize_file, make_photos
    from .memory import PeakMemory

    photos = make_photos(list(scene.images[:num_photos]), scene.camera, scene.cam_from_world[:num_photos])
    with tempfile.TemporaryDirectory(prefix="linereg-bench-colorize-") as folder:
        cloud = Path(folder) / "cloud.ply"
        write_jittered_ply(cloud, scene.cloud, num_points)
        start = time.perf_counter()
        with PeakMemory() as peak, batch.runner(workers, fork=False) as runner:
            histogram = colorize_file(cloud, Path(folder) / "out.ply", photos, run=runner)
        seconds = time.perf_counter() - start
    memory = peak.result()
    return {
        "points": num_points,
        "photos": len(photos),
        "workers": workers,
        "seconds": seconds,
        "points_per_s": num_points / seconds,
        "coloured": int(num_points - histogram[0]),
        "peak_rss_parent_mb": memory["parent_mb"],  # the whole bench run's, leave-one-out included
        "peak_rss_worker_mb": memory["largest_child_mb"],
        "peak_rss_tree_mb": memory["tree_mb"],  # parent and workers at once (sampled every 0.1 s)
        "worker_processes": memory["children"],
    }


def write_jittered_ply(path: Path, cloud: np.ndarray, num_points: int, chunk: int = 1_000_000) -> None:
    """Writes ``num_points`` points as a float32 binary PLY: copies of ``cloud`` jittered by 1 cm."""
    rng = np.random.default_rng(0)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {num_points}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for start in range(0, num_points, chunk):
            n = min(chunk, num_points - start)
            rows = np.arange(start, start + n) % len(cloud)
            f.write((cloud[rows] + rng.normal(0.0, 0.01, (n, 3))).astype("<f4").tobytes())
