"""Visibility from the cloud itself: a depth buffer per photo made of point splats, then a depth test.

A point covers a square splat as wide as the gap to its neighbours (``diameter_px``, from its local
spacing and range), so a sparse occluder still hides what lies behind it. Splats are written with one
``np.minimum.at`` per chunk: up to ``EXACT_MAX_PX`` wide as squares of ``ceil(d)`` pixels; wider ones (near
points, few) into a pyramid, at level ``L = ceil(log2 d)`` (cells of ``c = 2^L`` px) in the cell whose 2 x 2
block covers ``[u - c/2, u + c/2]``. ``finish`` spreads every cell over its 2 x 2 block and takes the minimum
over levels; ``fill_gaps`` then closes the holes irregular sampling leaves. Every step is a minimum, so buffers of different chunks combine by ``np.minimum`` before or
after ``finish`` alike (chunks may be splatted on different machines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from .config import VisibilityConfig

EXACT_MAX_PX = 5  # splats up to this wide are exact squares of pixels; wider ones go to the pyramid


@dataclass(frozen=True)
class SplatLayout:
    """Where the levels of one photo's splat pyramid lie in a flat float32 buffer.

    Level -1 (single pixels) is the (H, W) image at offset 0; level L >= 0 is a (ceil(H/c) + 1,
    ceil(W/c) + 1) grid of cells of ``c = 2^L`` px (one more row and column: blocks starting at -1).
    """

    width: int
    height: int
    max_level: int

    @classmethod
    def for_camera(cls, camera: Camera, config: VisibilityConfig) -> SplatLayout:
        max_level = max(math.ceil(math.log2(max(config.max_splat_px, 1))), 0)
        return cls(camera.width, camera.height, max_level)

    def shape(self, level: int) -> tuple[int, int]:
        if level < 0:
            return self.height, self.width
        c = 1 << level
        return -(-self.height // c) + 1, -(-self.width // c) + 1

    @property
    def offsets(self) -> np.ndarray:
        """(max_level + 3,) int64 start of levels -1, 0, ..., max_level and the total size."""
        sizes = [math.prod(self.shape(level)) for level in range(-1, self.max_level + 1)]
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def empty(self) -> np.ndarray:
        """Returns the flat float32 buffer with nothing splatted (+inf everywhere)."""
        return np.full(int(self.offsets[-1]), np.inf, dtype=np.float32)


def splat(
    buffer: np.ndarray,
    layout: SplatLayout,
    u: np.ndarray,
    v: np.ndarray,
    z: np.ndarray,
    diameter_px: np.ndarray,
) -> None:
    """Writes the minimum depth of every splat into ``buffer`` (from ``layout.empty()``), in place.

    u, v: (n,) float32 pixels inside the image; z: (n,) float32 depth m; diameter_px: (n,) float32.
    """
    side = np.maximum(np.ceil(diameter_px), 1.0).astype(np.int64)
    index, depth = [], []
    for s in np.unique(np.minimum(side, EXACT_MAX_PX + 1)):
        sel = np.flatnonzero(side == s) if s <= EXACT_MAX_PX else np.flatnonzero(side > EXACT_MAX_PX)
        if s <= EXACT_MAX_PX:
            index.append(_square_indices(layout, u[sel], v[sel], int(s)))
            depth.append(np.repeat(z[sel], s * s))
        else:
            level = np.minimum(np.ceil(np.log2(diameter_px[sel])), layout.max_level).astype(np.int64)
            index.append(_block_indices(layout, u[sel], v[sel], level))
            depth.append(z[sel])
    if index:
        np.minimum.at(buffer, np.concatenate(index), np.concatenate(depth))


def _square_indices(layout: SplatLayout, u: np.ndarray, v: np.ndarray, side: int) -> np.ndarray:
    """Returns (n * side^2,) flat indices of the ``side`` x ``side`` pixels centred on each point (clipped)."""
    first_col = np.floor(u - 0.5 * side + 1.0).astype(np.int64)  # side 1: the pixel holding the point
    first_row = np.floor(v - 0.5 * side + 1.0).astype(np.int64)
    steps = np.arange(side)
    cols = np.clip(first_col[:, None] + steps, 0, layout.width - 1)  # (n, side)
    rows = np.clip(first_row[:, None] + steps, 0, layout.height - 1)
    return (rows[:, :, None] * layout.width + cols[:, None, :]).ravel()


def _block_indices(layout: SplatLayout, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Returns (n,) flat indices of the cells (c = 2^level px) whose 2 x 2 block covers [u - c/2, u + c/2]."""
    index = np.empty(len(u), dtype=np.int64)
    offsets = layout.offsets
    for lev in np.unique(level):
        sel = np.flatnonzero(level == lev)
        c = float(1 << lev)
        col = np.floor((u[sel] + 0.5) / c - 0.5).astype(np.int64) + 1  # +1: blocks start at cell -1
        row = np.floor((v[sel] + 0.5) / c - 0.5).astype(np.int64) + 1
        index[sel] = offsets[lev + 1] + row * layout.shape(lev)[1] + col
    return index


def finish(buffer: np.ndarray, layout: SplatLayout) -> np.ndarray:
    """Returns the (H, W) float32 depth map (m, +inf where no point): the minimum over all levels."""
    h, w = layout.height, layout.width
    offsets = layout.offsets
    depth = buffer[: h * w].reshape(h, w).copy()
    for lev in range(layout.max_level + 1):
        grid = buffer[offsets[lev + 1] : offsets[lev + 2]].reshape(layout.shape(lev))
        # cell i is covered by the blocks stored at i (starting at cell i - 1) and at i + 1
        cells = np.minimum(np.minimum(grid[:-1, :-1], grid[1:, :-1]), np.minimum(grid[:-1, 1:], grid[1:, 1:]))
        c = 1 << lev
        np.minimum(depth, np.repeat(np.repeat(cells, c, axis=0), c, axis=1)[:h, :w], out=depth)
    return depth


def fill_gaps(depth: np.ndarray, config: VisibilityConfig) -> np.ndarray:
    """Returns the (H, W) float32 depth map with its gaps closed: a pixel at least ``depth_tol`` behind the
    5th nearest of its 8 neighbours takes that depth (``gap_passes`` times, each closes 1 px more).

    Splats cover the mean spacing, but irregular sampling leaves gaps through which farther points show;
    a gap has nearer neighbours on most sides, while a pixel beside an occluder's edge has at most 3 (a
    straight edge) and keeps its depth. Not a minimum like ``finish``: applied once, to the combined map.
    """
    for _ in range(config.gap_passes):
        padded = np.pad(depth, 1, mode="edge")
        h, w = depth.shape
        shifts = [padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        neighbours = np.stack([s for i, s in enumerate(shifts) if i != 4])
        fifth = np.partition(neighbours, 4, axis=0)[4]
        gap = depth > fifth + config.depth_tol_m + config.depth_tol_rel * fifth
        depth = np.where(gap, fifth, depth)
    return depth


def diameter_px(spacing_m: np.ndarray, z: np.ndarray, camera: Camera, config: VisibilityConfig) -> np.ndarray:
    """Returns (n,) float32 splat diameters in pixels: the local spacing projected at depth z."""
    focal = max(camera.fx, camera.fy)
    return (config.splat_scale * focal) * spacing_m / z


def tolerance_m(
    z: np.ndarray, diameter: np.ndarray, tan_incidence: np.ndarray, camera: Camera, config: VisibilityConfig
) -> np.ndarray:
    """Returns (n,) float32 how far (m) a point may lie behind the depth map and still be visible.

    The floor and the share of range, plus the depth change on a surface at ``tan_incidence`` to the
    viewing ray across the reach of a splat beyond its point (half a square and a pixel of rounding; 1.5
    cells of a pyramid block): the nearest splat of the same surface at its pixel may come from a
    neighbour that far away.
    """
    side = np.maximum(np.ceil(diameter), 1.0)
    cell = np.exp2(np.ceil(np.log2(np.maximum(diameter, 1.0))))
    reach_px = np.where(side <= EXACT_MAX_PX, 0.5 * side + 1.0, 1.5 * cell)
    footprint_m = reach_px * z / max(camera.fx, camera.fy)
    return config.depth_tol_m + config.depth_tol_rel * z + footprint_m * tan_incidence


def depth_at(depth: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Returns (n,) float32 the depth map at the pixels holding (u, v)."""
    return depth[np.floor(v + 0.5).astype(np.int64), np.floor(u + 0.5).astype(np.int64)]
