"""Visibility from the cloud itself: a depth buffer per photo made of point splats, then a depth test.

A point covers a square splat as wide as the gap to its neighbours (``diameter_px``, from its local
spacing and range), so a sparse occluder still hides what lies behind it. Splats are written with one
``np.minimum.at`` per chunk: up to ``EXACT_MAX_PX`` wide as squares of ``ceil(d)`` pixels; wider ones (near
points, few) into a pyramid, at level ``L = ceil(log2 d)`` (cells of ``c = 2^L`` px) in the cell whose 2 x 2
block covers ``[u - c/2, u + c/2]``. ``finish`` spreads every cell over its 2 x 2 block and takes the minimum
over levels; ``fill_gaps`` then closes the holes irregular sampling leaves. The pixel image has a margin
round the photo where points just outside it splat too, so an occluder crossing the image border hides
what lies behind it up to the border. Square splats lie in their point's tangent plane
(``depth_slope``), so a slanted surface does not hide itself. The depth test (``behind_m``) evaluates a
point's own tangent plane at the pixels within half its splat diameter of its pixel (an occluder's outline
lies up to half a spacing beyond its splats): a nearer surface anywhere there hides it, and the tolerance
stays small. Every step of the buffer is a
minimum, so buffers of different chunks combine by ``np.minimum`` before or after ``finish`` alike
(chunks may be splatted on different machines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from . import kernels
from .config import VisibilityConfig

EXACT_MAX_PX = 5  # splats up to this wide are exact squares of pixels; wider ones go to the pyramid
# the pixel image has this many pixels of margin round the photo: a square splat of a point just outside
# the photo lands there partly, and whatever is clipped to its outer edge is cropped by ``finish``
PAD_PX = EXACT_MAX_PX // 2 + 1
GAP_DIRECTIONS = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1))  # (dy, dx)


@dataclass(frozen=True)
class SplatLayout:
    """Where the levels of one photo's splat pyramid lie in a flat float32 buffer.

    Level -1 (single pixels) is the (H + 2 PAD_PX, W + 2 PAD_PX) image with its margin at offset 0;
    level L >= 0 is a (ceil(H/c) + 1, ceil(W/c) + 1) grid of cells of ``c = 2^L`` px (one more row and
    column: blocks starting at -1).
    """

    width: int
    height: int
    max_level: int

    @classmethod
    def for_camera(cls, camera: Camera, config: VisibilityConfig) -> SplatLayout:
        max_level = max(math.ceil(math.log2(max(config.max_splat_px, 1))), 0)
        return cls(camera.width, camera.height, max_level)

    @property
    def margin_px(self) -> float:
        """How far (px) outside the photo a point may lie and still splat into it: half the widest splat.

        Points of an occluder just beyond the image border cover its first pixels; without them a farther
        surface would show through there.
        """
        return 0.5 * max(float(1 << self.max_level), EXACT_MAX_PX) + 0.5

    def shape(self, level: int) -> tuple[int, int]:
        if level < 0:
            return self.height + 2 * PAD_PX, self.width + 2 * PAD_PX
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
    slope: np.ndarray | None = None,
) -> None:
    """Writes the minimum depth of every splat into ``buffer`` (from ``layout.empty()``), in place.

    u, v: (n,) float32 pixels, inside the image or up to ``layout.margin_px`` outside it; z: (n,) float32
    depth m; diameter_px: (n,) float32;
    slope: (n, 2) float32 dz/du, dz/dv (m per pixel, ``depth_slope``): square splats then write the depth
    of the point's tangent plane at each pixel rather than its own, pyramid splats stay flat.
    """
    side = np.maximum(np.ceil(diameter_px), 1.0).astype(np.int64)
    square = side <= EXACT_MAX_PX
    sel = np.flatnonzero(square)
    tilt = np.zeros((len(sel), 2), np.float32) if slope is None else slope[sel]
    kernels.splat_squares(
        buffer, layout.width + 2 * PAD_PX, PAD_PX, layout.width, layout.height,
        u[sel], v[sel], z[sel], side[sel], tilt, slope is not None,
    )  # fmt: skip
    sel = np.flatnonzero(~square)
    if len(sel):
        level = np.minimum(np.ceil(np.log2(diameter_px[sel])), layout.max_level).astype(np.int64)
        kernels.splat_blocks(buffer, _block_indices(layout, u[sel], v[sel], level), z[sel])


def depth_slope(
    normals_cam: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray, camera: Camera, max_slope: float
) -> np.ndarray:
    """Returns (n, 2) float32 dz/du, dz/dv (m per pixel) of the tangent planes of n points; 0 where the
    normal is unknown.

    The plane n . X = n . P (camera frame) meets the ray of pixel (u, v) at ``z = n . P / (n . ray)``,
    ``ray = ((u - cx) / fx, (v - cy) / fy, 1)``; its derivative at the point is
    ``dz/du = -z n_x / (fx n . ray)`` (same for v). The slope is clipped to ``max_slope`` x the size of a
    pixel at depth z (a tan of incidence): a grazing plane's extrapolation is not trusted further.
    normals_cam: (n, 3) float32 in the camera frame (NaN: unknown); u, v, z: (n,) float32.
    """
    x, y = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    facing = normals_cam[:, 0] * x + normals_cam[:, 1] * y + normals_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = -z[:, None] * normals_cam[:, :2] / (np.array([camera.fx, camera.fy]) * facing[:, None])
    limit = (max_slope / max(camera.fx, camera.fy)) * z[:, None]
    return np.nan_to_num(np.clip(g, -limit, limit), nan=0.0).astype(np.float32)


def _block_indices(layout: SplatLayout, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Returns (n,) flat indices of the cells (c = 2^level px) whose 2 x 2 block covers [u - c/2, u + c/2];
    -1 for a point so far outside the image that its block would lie wholly beyond the grid."""
    index = np.empty(len(u), dtype=np.int64)
    offsets = layout.offsets
    for lev in np.unique(level):
        sel = np.flatnonzero(level == lev)
        c = float(1 << lev)
        col = np.floor((u[sel] + 0.5) / c - 0.5).astype(np.int64) + 1  # +1: blocks start at cell -1
        row = np.floor((v[sel] + 0.5) / c - 0.5).astype(np.int64) + 1
        rows, cols = layout.shape(lev)
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        index[sel] = np.where(inside, offsets[lev + 1] + row * cols + col, -1)
    return index


def finish(buffer: np.ndarray, layout: SplatLayout) -> np.ndarray:
    """Returns the (H + 2 PAD_PX, W + 2 PAD_PX) float32 depth map (m, +inf where no point) of the photo
    and its margin: the minimum over all levels (``crop`` cuts the photo out of it).

    The margin holds the square splats of points just outside the photo, so ``fill_gaps`` sees an
    occluder that crosses the image border on both sides of it.
    """
    h, w = layout.height, layout.width
    offsets = layout.offsets
    depth = buffer[: offsets[1]].reshape(layout.shape(-1)).copy()
    inner = depth[PAD_PX : PAD_PX + h, PAD_PX : PAD_PX + w]  # a view: the photo's pixels
    for lev in range(layout.max_level + 1):
        grid = buffer[offsets[lev + 1] : offsets[lev + 2]].reshape(layout.shape(lev))
        # cell i is covered by the blocks stored at i (starting at cell i - 1) and at i + 1
        cells = np.minimum(np.minimum(grid[:-1, :-1], grid[1:, :-1]), np.minimum(grid[:-1, 1:], grid[1:, 1:]))
        c = 1 << lev
        np.minimum(inner, np.repeat(np.repeat(cells, c, axis=0), c, axis=1)[:h, :w], out=inner)
    return depth


def crop(depth: np.ndarray) -> np.ndarray:
    """Returns the (H, W) photo part of a depth map with its margin (``finish``)."""
    return depth[PAD_PX:-PAD_PX, PAD_PX:-PAD_PX]


def fill_gaps(depth: np.ndarray, config: VisibilityConfig) -> np.ndarray:
    """Returns the float32 depth map (any shape: ``finish``'s, with its margin) with its gaps closed: a
    pixel that meets a surface nearer by more than ``depth_tol`` in at least ``gap_directions`` of 8
    directions (within ``gap_radius_px``) takes the farthest of those nearer depths; ``gap_passes`` times.

    Splats cover the mean spacing, but irregular and striped sampling (scan lines) leaves holes through
    which farther points show. A hole is enclosed by its occluder on (nearly) every side; a pixel beside
    an occluder's straight edge meets it in at most 3 to 5 directions and keeps its depth. Not a minimum
    like ``finish``: applied once, to the combined map.
    """
    h, w = depth.shape
    r = config.gap_radius_px
    nearest = np.empty((len(GAP_DIRECTIONS), h, w), dtype=np.float32)
    for _ in range(config.gap_passes):
        padded = np.pad(depth, r, constant_values=np.inf)
        for i, (dy, dx) in enumerate(GAP_DIRECTIONS):
            nearest[i] = np.inf
            for step in range(1, r + 1):
                y, x = r + dy * step, r + dx * step
                np.minimum(nearest[i], padded[y : y + h, x : x + w], out=nearest[i])
        enclosing = np.partition(nearest, config.gap_directions - 1, axis=0)[config.gap_directions - 1]
        with np.errstate(invalid="ignore"):  # inf * 0 where nothing encloses: no gap either way
            gap = depth > enclosing + config.depth_tol_m + config.depth_tol_rel * enclosing
        depth = np.where(gap, enclosing, depth)
    return depth


def diameter_px(spacing_m: np.ndarray, z: np.ndarray, camera: Camera, config: VisibilityConfig) -> np.ndarray:
    """Returns (n,) float32 splat diameters in pixels: the local spacing projected at depth z."""
    focal = max(camera.fx, camera.fy)
    return (config.splat_scale * focal) * spacing_m / z


def footprint_radius_px(diameter: np.ndarray, config: VisibilityConfig) -> np.ndarray:
    """Returns (n,) int64 the half-width (px) of the square of pixels a point's depth test covers: half its
    splat diameter (``EXACT_MAX_PX`` at most), rounded up, and at least ``silhouette_margin_px``.

    A surface's outline lies anywhere between its outermost sample and where the next one would be, a
    spacing further on, and its splats cover only the first half of that gap. A point just inside an
    occluder's true outline therefore lies up to half a spacing from the occluder's nearest splat, and its
    test reaches that far. The point's own spacing stands for the occluder's (surfaces side by side are
    scanned alike); it also covers the point's own splat, ``ceil(d)`` pixels wide.
    """
    reach = np.ceil(np.minimum(diameter, EXACT_MAX_PX) / 2.0).astype(np.int64)
    return np.maximum(reach, config.silhouette_margin_px)


def behind_m(
    depth: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray, slope: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """Returns (n,) float32 how far (m) each point's tangent plane lies behind the depth map, at worst over
    the pixels within ``radius`` (Chebyshev) of the pixel holding it.

    The plane is evaluated at each pixel's centre, ``z + slope . (pixel - (u, v))``, which is what the
    point's own splat (and its neighbours' on the same surface) wrote there: the point's surface stays
    level with the map, while a nearer surface anywhere in the footprint (an occluder's silhouette, the
    rim of a hole between its splats) shows as the point lying behind it. Beyond the image border the
    map's border pixels stand for what lies there.
    depth: (H, W) float32; u, v, z: (n,) float32; slope: (n, 2) float32 (``depth_slope``); radius: (n,) int64.
    """
    return kernels.behind(np.ascontiguousarray(depth), u, v, z, slope, radius)


def tolerance_m(
    z: np.ndarray, diameter: np.ndarray, tan_incidence: np.ndarray, camera: Camera, config: VisibilityConfig
) -> np.ndarray:
    """Returns (n,) float32 how far (m) a point's tangent plane may lie behind the depth map (``behind_m``)
    and the point still be visible.

    The floor (and the share of range, 0 by default), plus the depth change on a surface at
    ``tan_incidence`` to the viewing ray across what the depth map cannot follow. Square splats are
    tilted along their tangent planes and the test evaluates the point's own plane at each pixel's
    centre, so only the neighbours' tilts are left: each comes from its own voxel's normal and holds
    from its point, up to ``slope_slack_px`` from the centre (a flat test at the point's pixel needed a
    whole pixel, which let points 0.1-0.3 m behind a window reveal or a ledge through). Pyramid blocks
    are flat: there 1.5 cells of slope count (the nearest splat of the same surface at the point's
    pixel may come from a neighbour that far away).
    """
    cell = np.exp2(np.ceil(np.log2(np.maximum(diameter, 1.0))))
    reach_px = np.where(np.ceil(diameter) <= EXACT_MAX_PX, config.slope_slack_px, 1.5 * cell)
    footprint_m = reach_px * z / max(camera.fx, camera.fy)
    return config.depth_tol_m + config.depth_tol_rel * z + footprint_m * tan_incidence
