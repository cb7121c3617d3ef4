"""Negative evidence: how much of the map a pose predicts in image areas where the image shows no lines.

Repetitive and symmetric buildings let a wrong pose explain as many image segments as the truth (the far
side of a symmetric block, a view turned by 90 degrees in a courtyard). What tells them apart is what each
pose predicts *beyond* its matches: the wrong pose puts facade edges into the sky or onto the empty ground,
where the image has no segment at all. Map lines hidden behind a facade (the map has no surfaces to occlude
them) land on that facade, among its windows and ledges, so they are not counted: only predictions far from
every detected 2D segment are. The measure uses segments only (no pixels), so ``register`` has it too.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from .camera import Camera
from .matching import project_segments

CELLS_PER_RADIUS = 8  # raster of the 2D segments: coarse enough to be cheap, fine next to the radius


class EmptyAreas(NamedTuple):
    """Where an image shows no line: mask (h, w) bool over square cells of cell_px pixels (cell (r, c)
    covers pixels [c, c + 1) x [r, r + 1) times cell_px)."""

    mask: np.ndarray
    cell_px: float


def empty_areas(lines2d: np.ndarray, camera: Camera, radius_px: float) -> EmptyAreas:
    """Returns the cells of the image farther than radius_px from every (N, 4) undistorted 2D segment."""
    cell = max(radius_px / CELLS_PER_RADIUS, 1.0)
    h, w = int(np.ceil(camera.height / cell)), int(np.ceil(camera.width / cell))
    occupied = np.zeros((h, w), np.uint8)
    points = _samples(lines2d, 0.5 * cell)[0] / cell
    r, c = points[:, 1].astype(np.int64), points[:, 0].astype(np.int64)
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    occupied[r[inside], c[inside]] = 1
    if not occupied.any():
        return EmptyAreas(np.ones((h, w), bool), cell)
    distance = cv2.distanceTransform(1 - occupied, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return EmptyAreas(distance * cell > radius_px, cell)


def unexplained_length(
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    empty: EmptyAreas,
    min_depth_m: float = 0.1,
) -> float:
    """Returns the total length (px) of projected map segments that falls in the empty cells of ``empty``.

    lines3d: (M, 6) world; cam_from_world: (4, 4); empty: from ``empty_areas``. Segments are clipped to
    the image and to ``z >= min_depth_m`` (nearer, a segment's projection is unbounded); each is sampled
    every half cell.
    """
    projected, visible = project_segments(lines3d, camera, cam_from_world, min_depth_m)
    clipped = _clip(projected[visible], camera.width, camera.height)
    points, step = _samples(clipped, 0.5 * empty.cell_px)
    if len(points) == 0:
        return 0.0
    r = np.clip((points[:, 1] / empty.cell_px).astype(np.int64), 0, empty.mask.shape[0] - 1)
    c = np.clip((points[:, 0] / empty.cell_px).astype(np.int64), 0, empty.mask.shape[1] - 1)
    return float(step[empty.mask[r, c]].sum())


def _samples(segments: np.ndarray, spacing_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((S, 2) points every ~spacing_px along (N, 4) segments, (S,) the length each stands for)."""
    if len(segments) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    a, b = segments[:, 0:2], segments[:, 2:4]
    length = np.linalg.norm(b - a, axis=1)
    count = np.maximum(np.ceil(length / spacing_px).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(segments)), count)
    start = np.cumsum(count) - count
    s = (np.arange(count.sum()) - start[owner] + 0.5) / count[owner]  # cell centres along each segment
    points = a[owner] + s[:, None] * (b - a)[owner]
    return points, (length / count)[owner]


def _clip(segments: np.ndarray, width: int, height: int) -> np.ndarray:
    """Returns the (K, 4) parts of (N, 4) pixel segments inside the image (Liang-Barsky), empty ones dropped."""
    a, d = segments[:, 0:2], segments[:, 2:4] - segments[:, 0:2]
    lo, hi = np.array([-0.5, -0.5]), np.array([width - 0.5, height - 0.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - a) / d, (hi - a) / d
    enter = np.where(d != 0, np.minimum(t1, t2), np.where((a >= lo) & (a <= hi), -np.inf, np.inf))
    leave = np.where(d != 0, np.maximum(t1, t2), np.where((a >= lo) & (a <= hi), np.inf, -np.inf))
    t0 = np.maximum(enter.max(axis=1), 0.0)
    t1_ = np.minimum(leave.min(axis=1), 1.0)
    keep = t1_ > t0
    a, d, t0, t1_ = a[keep], d[keep], t0[keep], t1_[keep]
    return np.c_[a + t0[:, None] * d, a + t1_[:, None] * d]
