"""Which points of a chunk a photo may see at all: coarse cells of the chunk against the photo's frustum.

A chunk's points are grouped once into cubic cells (``make_cells``: one sort); each photo then projects
only the points of the cells whose bounding sphere meets its view frustum (``rows_in_view``). A photo
sees a small part of a large scan, so this is what keeps the cost of a chunk x photo task near the
number of points the photo sees rather than the chunk's size. The test is conservative: a cell that may
hold a visible point is always kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from .project import field_of_view

CELL_VOXELS = 16.0  # a cell is this many surface voxels wide (~5 m on the demo scan): ~10^3-10^4 points


@dataclass(frozen=True)
class Cells:
    """A chunk's finite points grouped by cell.

    rows: (n,) int64 chunk rows sorted by cell; starts: (C + 1,) int64 where each cell's rows begin in
    ``rows``; centre: (C, 3) float64 world; radius: (C,) float64 m, the bounding sphere of each cell's points.
    """

    rows: np.ndarray
    starts: np.ndarray
    centre: np.ndarray
    radius: np.ndarray


def make_cells(points: np.ndarray, cell_m: float) -> Cells:
    """Returns the Cells of (P, 3) float64 points (non-finite rows left out) for cubes of ``cell_m``."""
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    if len(finite) == 0:
        empty = np.zeros(0)
        return Cells(finite, np.zeros(1, dtype=np.int64), empty.reshape(0, 3), empty)
    cell = np.floor(points[finite] / cell_m)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1.0
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True]).astype(np.int64)
    rows = finite[order]
    sorted_points = points[rows]
    lo = np.minimum.reduceat(sorted_points, starts[:-1], axis=0)
    hi = np.maximum.reduceat(sorted_points, starts[:-1], axis=0)
    return Cells(rows, starts, 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1))


def rows_in_view(
    cells: Cells, camera: Camera, cam_from_world: np.ndarray, near_m: float, margin_px: float = 0.0
) -> np.ndarray:
    """Returns (n,) int64 the chunk rows of the cells whose bounding sphere meets the photo's frustum
    (widened by ``margin_px`` round the image)."""
    if len(cells.radius) == 0:
        return cells.rows
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    c = cells.centre @ R.T + t  # (C, 3) camera frame; cells are few
    r = cells.radius
    lo, hi = field_of_view(camera, margin_px)
    # the four side planes through the centre of projection: x = lo_x z, x = hi_x z, same for y; a sphere
    # meets the half-space inside when its centre lies less than r outside (distances along unit normals)
    keep = c[:, 2] + r > near_m
    for axis in (0, 1):
        for slope, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
            distance = sign * (c[:, axis] - slope * c[:, 2]) / np.sqrt(1.0 + slope * slope)
            keep &= distance < r
    chosen = np.flatnonzero(keep)
    if len(chosen) == len(r):
        return cells.rows
    first, last = cells.starts[chosen], cells.starts[chosen + 1]
    return cells.rows[_ranges(first, last)]


def _ranges(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Returns the concatenation of ``arange(first[i], last[i])`` over i, as one int64 array."""
    lengths = last - first
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    steps = np.ones(total, dtype=np.int64)
    heads = np.cumsum(lengths)[:-1]
    steps[0] = first[0]
    steps[heads] = first[1:] - last[:-1] + 1
    return np.cumsum(steps)
