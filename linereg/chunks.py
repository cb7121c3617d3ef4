"""Map segments grouped into chunks of nearby ones, each with the box of its segments' ends: the first cut
of every test of what a camera sees, so that a query's work follows what its view reaches, not the map's
size (on a city of tiled blocks a view's pyramid reaches an eighth of the chunks).

``Chunks.rows_in_view``: the rows whose chunk a view's pyramid reaches (``map.visibility`` starts its
occlusion test from them); ``kept_chunks``, compiled: the same per chunk, for the compiled projection of
the score and the local solves (``score._project_clipped``), which then pass over the segments of the
chunks left out.
"""

from __future__ import annotations

import numba
import numpy as np

from .camera import Camera

CHUNK_SEGMENTS = 64  # segments per chunk, on average
# maps with fewer segments are not cut into chunks by ``Chunks.of_map``: a projection of all of them costs
# microseconds
CHUNKED_FROM = 4096


class Chunks:
    """(M, 6) segments grouped by the cell of their midpoints (cells sized for ``CHUNK_SEGMENTS`` a cell on
    average), each group with the box of its segments' ends: a group whose box lies wholly outside a face
    of a view's pyramid (the image widened by a pixel, ``inward_normals``) or nearer than the near plane
    holds no segment that projects into the image. ``of``: (M,) int64 each segment's group; ``centre``,
    ``half``: (C, 3) each group's box."""

    def __init__(self, of: np.ndarray, centre: np.ndarray, half: np.ndarray):
        self.of, self.centre, self.half = of, centre, half

    @classmethod
    def build(cls, segments: np.ndarray) -> Chunks:
        """Returns the Chunks of (M, 6) segments."""
        ends = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 3)
        if len(ends) == 0:
            return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
        mid = ends.mean(axis=1)
        cell = _cell_size(np.ptp(mid, axis=0), max(len(ends) // CHUNK_SEGMENTS, 1))
        key = np.floor((mid - mid.min(axis=0)) / cell).astype(np.int64)
        dims = key.max(axis=0) + 1
        # (M,) each segment's chunk: its cell's rank among the occupied cells
        _, of = np.unique((key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2], return_inverse=True)
        count = int(of.max()) + 1
        low, high = np.full((count, 3), np.inf), np.full((count, 3), -np.inf)
        np.minimum.at(low, of, ends.min(axis=1))
        np.maximum.at(high, of, ends.max(axis=1))
        return cls(of.astype(np.int64), 0.5 * (low + high), 0.5 * (high - low))

    @classmethod
    def of_map(cls, segments: np.ndarray) -> Chunks | None:
        """Returns the Chunks of (M, 6) segments, or None for a map too small to gain from them
        (``CHUNKED_FROM``)."""
        return cls.build(segments) if len(segments) >= CHUNKED_FROM else None

    def subset(self, index: np.ndarray) -> Chunks:
        """Returns the Chunks of the segments ``index`` (rows of these): the same boxes, which hold them."""
        return Chunks(self.of[np.asarray(index, dtype=np.int64)], self.centre, self.half)

    def rows_in_view(
        self, camera: Camera, cam_from_world: np.ndarray, near: float, index: np.ndarray | None
    ) -> np.ndarray:
        """Returns the (k,) int64 rows of ``index`` (None: all, in order) whose chunk's box is not wholly
        outside a face of the view's pyramid nor wholly nearer than ``near``."""
        T = np.ascontiguousarray(cam_from_world, dtype=np.float64)
        intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64)
        kept = kept_chunks(
            self.centre, self.half, T, intrinsics, float(camera.width), float(camera.height), near
        )
        if index is None:
            return np.flatnonzero(kept[self.of])
        index = np.asarray(index, dtype=np.int64)
        return index[kept[self.of[index]]]


NO_CHUNKS = Chunks(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))  # the compiled kernels' "none"


def inward_normals(camera: Camera) -> np.ndarray:
    """Returns (3, 4) the camera-frame inward normals of the side faces of the pyramid through the camera
    centre and the image border widened by a pixel (the exact clipping's border lies half a pixel out):
    ``side_normals`` as columns."""
    return side_normals(
        camera.fx, camera.fy, camera.cx, camera.cy, float(camera.width), float(camera.height)
    ).T


@numba.njit(cache=True, nogil=True)
def side_normals(fx: float, fy: float, cx: float, cy: float, width: float, height: float) -> np.ndarray:
    """Returns (4, 3) rows: the camera-frame inward normals of the pyramid's side faces through the image
    border widened by a pixel (u >= -1.5, u <= width + 0.5, v >= -1.5, v <= height + 0.5)."""
    return np.array(
        [
            [1.0, 0.0, (cx + 1.5) / fx],
            [-1.0, 0.0, (width + 0.5 - cx) / fx],
            [0.0, 1.0, (cy + 1.5) / fy],
            [0.0, -1.0, (height + 0.5 - cy) / fy],
        ]
    )


@numba.njit(cache=True, nogil=True)
def kept_chunks(
    centre: np.ndarray,
    half: np.ndarray,
    T: np.ndarray,
    intrinsics: np.ndarray,
    width: float,
    height: float,
    near: float,
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (C,) bool: the chunks (boxes ``centre`` +- ``half``) not wholly outside a face of the
    pyramid of (4, 4) ``T`` (cam_from_world), ``intrinsics`` (fx, fy, cx, cy) and the image ``width`` x
    ``height`` widened by a pixel (``side_normals``), nor wholly nearer than ``near``: for each face, the
    largest value of its function over a box (its centre's, plus the half-sizes along |w|, w = R^T n); a
    face the whole box lies outside of by more than rounding rules the box out."""
    normals = np.empty((5, 3))  # the side faces, then the depth axis
    normals[:4] = side_normals(intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], width, height)
    normals[4, 0], normals[4, 1], normals[4, 2] = 0.0, 0.0, 1.0
    w, offset = np.empty((5, 3)), np.empty(5)
    largest = 0.0
    for f in range(5):
        for i in range(3):  # w = R^T n
            w[f, i] = T[0, i] * normals[f, 0] + T[1, i] * normals[f, 1] + T[2, i] * normals[f, 2]
        offset[f] = normals[f, 0] * T[0, 3] + normals[f, 1] * T[1, 3] + normals[f, 2] * T[2, 3]
        largest = max(largest, abs(offset[f]))
    offset[4] -= near
    largest = max(largest, abs(offset[4]))
    kept = np.empty(len(centre), np.bool_)
    for c in range(len(centre)):
        keep = True
        for f in range(5):
            mid = w[f, 0] * centre[c, 0] + w[f, 1] * centre[c, 1] + w[f, 2] * centre[c, 2]
            spread = abs(w[f, 0]) * half[c, 0] + abs(w[f, 1]) * half[c, 1] + abs(w[f, 2]) * half[c, 2]
            # a face the whole box lies outside of by more than rounding rules the box out
            if mid + spread + offset[f] < -1e-9 * (1.0 + abs(mid) + largest):
                keep = False
                break
        kept[c] = keep
    return kept


def _cell_size(extent: np.ndarray, cells: int) -> float:
    """Returns the edge of cubic cells that cut a box of (3,) ``extent`` into about ``cells`` cells, an axis
    thinner than a cell counting as one cell thick."""
    extent = np.sort(np.maximum(extent, 1e-9))[::-1]
    for used in (3, 2, 1):
        size = float((np.prod(extent[:used]) / cells) ** (1.0 / used))
        if used == 1 or extent[used - 1] >= size:
            return max(size, 1e-9)
    return 1.0  # not reached
