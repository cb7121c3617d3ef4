"""The two passes of colorization as tasks over chunks of a cloud, for any runner (``linereg.batch``).

Pass 1, per chunk x group of photos: local spacing and normals, splats into each photo's depth buffer;
the buffers of all chunks are combined by their minimum (``depth``). A strided sample of the points comes
back too, for the exposure gains. Pass 2, per chunk: every photo's weighted colour of the points it sees,
blended. Tasks read their chunk themselves (an array slice, or rows of a file on a shared file system), so
only depth buffers and colours travel.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import batch
from ..camera import Camera
from .blend import Observation, Photo, accumulate, blended, focus_measure, observe, sharpness_weights
from .config import ColorizeConfig
from .cull import CELL_VOXELS, Cells, make_cells, rows_in_view
from .depth import SplatLayout, crop, fill_gaps, finish, splat
from .gains import clear_observations, estimate_gains
from .project import view_points
from .surface import default_voxel_m, local_surface

log = logging.getLogger(__name__)
Progress = Callable[[str, int, int], None]  # (pass, tasks done, tasks in the pass)
_readers: dict[tuple[str, int], Any] = {}  # FileSource: one open reader per file and process


@dataclass(frozen=True)
class ArraySource:
    """Points in memory: (P, 3) float64."""

    points: np.ndarray

    @property
    def num_points(self) -> int:
        return len(self.points)

    def read(self, start: int, stop: int) -> np.ndarray:
        return np.asarray(self.points[start:stop], dtype=np.float64)


@dataclass(frozen=True)
class FileSource:
    """Points of a cloud file (``linereg.io.open_cloud``), read by each task that needs them."""

    path: str
    num_points: int

    def read(self, start: int, stop: int) -> np.ndarray:
        from .. import io

        # keyed by process too: a forked worker must not share its parent's reader (one file offset)
        key = (self.path, os.getpid())
        if key not in _readers:
            _readers[key] = io.open_cloud(self.path)
        return _readers[key].read(start, stop)


@dataclass(frozen=True)
class Plan:
    """What every task is told: the configuration, the voxel of the surface statistics, the sample stride."""

    config: ColorizeConfig
    voxel_m: float
    sample_stride: int


@dataclass(frozen=True)
class View:
    """A photo's camera and pose: what pass 1 needs of it."""

    camera: Camera
    cam_from_world: np.ndarray


def make_plan(source: Any, config: ColorizeConfig) -> Plan:
    """Returns the Plan of a source: ``voxel_m`` from its first chunk unless configured."""
    voxel_m = config.surface.voxel_m
    if voxel_m <= 0:
        first = source.read(0, min(config.chunk_points, source.num_points))
        first = first[np.isfinite(first).all(axis=1)]
        voxel_m = default_voxel_m(first) if len(first) >= 2 else 1.0
    stride = max(source.num_points // max(config.gains.sample_points, 1), 1)
    return Plan(config, float(voxel_m), stride)


def chunk_ranges(num_points: int, chunk_points: int) -> list[tuple[int, int]]:
    """Returns [(start, stop)) row ranges of at most ``chunk_points`` covering ``num_points``."""
    return [(s, min(s + chunk_points, num_points)) for s in range(0, num_points, max(chunk_points, 1))]


def chunk_geometry(points: np.ndarray, plan: Plan, shifted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((n,) float32 spacing, (n, 3) float32 normals) of a chunk; NaN rows for non-finite points.

    shifted: from the voxel grid shifted by half a voxel (``local_surface``; the normals ``observe`` checks).
    """
    spacing = np.full(len(points), np.nan, dtype=np.float32)
    normals = np.full((len(points), 3), np.nan, dtype=np.float32)
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    if len(finite):
        spacing[finite], normals[finite] = local_surface(
            points[finite], plan.voxel_m, plan.config.surface, shifted
        )
    return spacing, normals


def chunk_cells(points: np.ndarray, plan: Plan) -> Cells:
    """Returns the chunk's points grouped in cells for frustum culling (``linereg.color.cull``)."""
    return make_cells(points, CELL_VOXELS * plan.voxel_m)


def depth_task(shared: tuple, item: tuple[int, int, tuple[int, ...]]) -> tuple:
    """Pass 1 on rows [start, stop) for photos ``ids``: returns (ids, [float32 depth maps with their
    margin, ``depth.finish``], sample).

    sample: (points (m, 3) float64, spacing (m,), normals (m, 3)) of the rows that are multiples of the
    sample stride, or None (the sample comes with the first photo group only).
    """
    source, views, plan = shared
    start, stop, ids = item
    points = source.read(start, stop)
    spacing, normals = chunk_geometry(points, plan)
    cells = chunk_cells(points, plan)
    vis = plan.config.visibility
    maps = []
    for k in ids:
        view = views[k]
        layout = SplatLayout.for_camera(view.camera, vis)
        buffer = layout.empty()
        # points just outside the photo splat into it too (an occluder across the image border)
        rows = rows_in_view(cells, view.camera, view.cam_from_world, vis.near_m, layout.margin_px)
        seen = view_points(
            points, normals, spacing, view.camera, view.cam_from_world, vis, rows, layout.margin_px
        )
        splat(buffer, layout, seen.u, seen.v, seen.z, seen.diameter, seen.slope)
        maps.append(finish(buffer, layout))
    sample = None
    if ids and ids[0] == 0:
        rows = np.arange((-start) % plan.sample_stride, stop - start, plan.sample_stride)
        sample = (points[rows], spacing[rows], normals[rows])
    return ids, maps, sample


def colour_task(shared: tuple, item: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pass 2 on rows [start, stop): returns ((n, 3) uint8 RGB, (n,) uint16 photos that coloured each)."""
    source, photos, maps, plan = shared
    start, stop = item
    points = source.read(start, stop)
    spacing, normals = chunk_geometry(points, plan)
    _, check = chunk_geometry(points, plan, shifted=True)
    cells = chunk_cells(points, plan)
    total, weights = np.zeros((len(points), 3)), np.zeros(len(points))
    count = np.zeros(len(points), dtype=np.uint16)
    for photo, depth in zip(photos, maps, strict=True):
        rows = rows_in_view(cells, photo.camera, photo.cam_from_world, plan.config.visibility.near_m)
        seen = observe(photo, depth, points, spacing, normals, plan.config, rows, check_normals=check)
        accumulate(total, weights, count, seen)
    return blended(total, weights), count


def depth_pass(
    source: Any, views: list[View], plan: Plan, run: batch.InlineRunner, progress: Progress | None = None
) -> tuple[list[np.ndarray], tuple]:
    """Returns every photo's (H, W) float32 depth map (gaps closed) and the strided sample (points, spacing,
    normals)."""
    ranges = chunk_ranges(source.num_points, plan.config.chunk_points)
    # enough tasks to keep every worker busy: split the photos into groups when chunks are few
    groups = min(max(math.ceil(2 * run.workers / len(ranges)), 1), len(views))
    ids = [tuple(int(k) for k in g) for g in np.array_split(np.arange(len(views)), groups)]
    items = [(s, e, g) for s, e in ranges for g in ids]
    maps: list[np.ndarray | None] = [None] * len(views)
    samples = []
    for done, (_, (got, parts, sample)) in enumerate(
        run.unordered(depth_task, (source, views, plan), items), 1
    ):
        for k, part in zip(got, parts, strict=True):
            current = maps[k]
            maps[k] = part if current is None else np.minimum(current, part)
        if sample is not None:
            samples.append(sample)
        if progress:
            progress("depth", done, len(items))
    merged = tuple(np.concatenate(column) for column in zip(*samples, strict=True))
    return [crop(fill_gaps(m, plan.config.visibility)) for m in maps if m is not None], merged


def prepare_photos(photos: list[Photo], maps: list[np.ndarray], sample: tuple, plan: Plan) -> list[Photo]:
    """Returns the photos with their sharpness weights and exposure gains (from the sample)."""
    sharp = sharpness_weights(
        np.array([focus_measure(p.image) for p in photos]), plan.config.weights.blur_power
    )
    photos = [replace(p, sharpness=float(s), gain=None) for p, s in zip(photos, sharp, strict=True)]
    points, spacing, normals = sample
    observations: list[Observation] = [
        clear_observations(
            p, m, points, normals, observe(p, m, points, spacing, normals, plan.config), plan.config
        )
        for p, m in zip(photos, maps, strict=True)
    ]
    gains = estimate_gains(observations, len(points), plan.config.gains)
    return [replace(p, gain=g) for p, g in zip(photos, gains, strict=True)]


def colorize_source(
    source: Any,
    photos: list[Photo],
    config: ColorizeConfig,
    run: batch.InlineRunner | None = None,
    progress: Progress | None = None,
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """Yields (start, stop, (n, 3) uint8 RGB, (n,) uint16 photo counts) chunk by chunk, in row order."""
    run = run or batch.InlineRunner()
    plan = make_plan(source, config)
    log.info("colorize: %d points, %d photos, voxel %.3f m", source.num_points, len(photos), plan.voxel_m)
    views = [View(p.camera, p.cam_from_world) for p in photos]
    maps, sample = depth_pass(source, views, plan, run, progress)
    photos = prepare_photos(photos, maps, sample, plan)
    ranges = chunk_ranges(source.num_points, config.chunk_points)
    results = run.ordered(colour_task, (source, photos, maps, plan), ranges)
    for done, ((start, stop), (rgb, count)) in enumerate(zip(ranges, results, strict=True), 1):
        if progress:
            progress("colour", done, len(ranges))
        yield start, stop, rgb, count
