"""The tile index of a line map: a uniform grid over the two largest extents of the map; a segment is
listed in every tile it passes through (``LineMap.segments_near``, ``tile_segments``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInputError

TILE_KEY_SPAN = 1 << 31  # tile (i, j) -> one int64 id (i + span/2) * span + j + span/2, |i|, |j| < 2**30


def bounds(segments: np.ndarray) -> np.ndarray:
    """Returns (2, 3) min / max corner of all endpoints of (M, 6) segments (zeros for none)."""
    if len(segments) == 0:
        return np.zeros((2, 3))
    ends = segments.reshape(-1, 3)
    return np.stack([ends.min(axis=0), ends.max(axis=0)])


def grid(segments: np.ndarray, tile_m: float | None) -> dict[str, Any]:
    """Returns the tile grid: the two axes of largest extent, their origin and the tile size (m)."""
    box = bounds(segments)
    extent = box[1] - box[0]
    axes = np.sort(np.argsort(-extent, kind="stable")[:2])
    if tile_m is None:
        tile_m = max(float(extent.max()) / 32.0, 1.0)
    if not tile_m > 0:
        raise InvalidInputError(f"tile_m must be positive, got {tile_m}")
    return {"axes": axes.tolist(), "origin": box[0][axes].tolist(), "tile_m": float(tile_m)}


def flat(cells: np.ndarray) -> np.ndarray:
    """Returns (N,) int64 tile ids of (N, 2) int64 tile cells."""
    return (cells[:, 0] + TILE_KEY_SPAN // 2) * TILE_KEY_SPAN + (cells[:, 1] + TILE_KEY_SPAN // 2)


def tile_index(segments: np.ndarray, grid: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (keys (T,), ptr (T + 1,), members (K,)): segments of tile keys[t] = members[ptr[t]:ptr[t+1]]."""
    axes, origin, tile = np.asarray(grid["axes"]), np.asarray(grid["origin"]), float(grid["tile_m"])
    a, b = segments[:, 0:3][:, axes], segments[:, 3:6][:, axes]
    # sample every segment at a quarter tile: it then visits every tile it passes through
    steps = np.ceil(np.linalg.norm(b - a, axis=1) / (0.25 * tile)).astype(np.int64) + 1
    seg = np.repeat(np.arange(len(segments)), steps)
    frac = (np.arange(len(seg)) - np.repeat(np.cumsum(steps) - steps, steps)) / np.repeat(
        np.maximum(steps - 1, 1), steps
    )
    xy = a[seg] + frac[:, None] * (b[seg] - a[seg])
    keys = flat(np.floor((xy - origin) / tile).astype(np.int64))
    pairs = np.unique(np.stack([keys, seg], axis=1), axis=0) if len(seg) else np.zeros((0, 2), np.int64)
    tile_keys, starts = np.unique(pairs[:, 0], return_index=True)
    ptr = np.r_[starts, len(pairs)].astype(np.int64)
    return tile_keys.astype(np.int64), ptr, pairs[:, 1].astype(np.int64)


def point_segment_distance(point: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Returns (k,) distances of a (3,) point to (k, 6) finite segments."""
    a, b = segments[:, :3], segments[:, 3:]
    ab = b - a
    t = np.clip(
        np.einsum("ij,ij->i", point - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1
    )
    return np.linalg.norm(a + t[:, None] * ab - point, axis=1)
