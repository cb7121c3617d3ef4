"""The line map: 3D segments of a point cloud, their parallel clusters, a tile index and metadata.

Built once from a cloud (``LineMap.build``) and saved as one ``.npz`` file whose ``metadata`` entry is
JSON (format version, units, frame, extraction parameters, ...). The tile index is a uniform grid over
the two largest extents of the map; a segment is listed in every tile it passes through.
"""

from __future__ import annotations

import io as _bytes_io
import json
import logging
import os
import uuid
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..config import Lines3DConfig, ParallelConfig
from ..directions import DirectionClusters
from ..errors import FileFormatError, InvalidInputError
from ..geometry import camera_center
from ..registration import check_segments

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
_ARRAYS = ("segments", "directions", "labels", "support", "tile_keys", "tile_ptr", "tile_members")


class LineMap:
    """3D segments (M, 6) float64 metres with parallel ``clusters``, a tile index and ``metadata``."""

    def __init__(
        self, segments: np.ndarray, clusters: DirectionClusters, metadata: dict[str, Any], index=None
    ):
        self.segments = segments
        self.clusters = clusters
        self.metadata = metadata
        grid = metadata["grid"]
        self._axes = np.asarray(grid["axes"], dtype=np.int64)
        self._origin = np.asarray(grid["origin"], dtype=np.float64)
        self.tile_m = float(grid["tile_m"])
        index = index if index is not None else _tile_index(segments, grid)
        self._keys, self._ptr, self._members = index
        # (T, 2) i, j of each tile
        self._cells = np.stack(np.divmod(self._keys, TILE_KEY_SPAN), axis=1) - TILE_KEY_SPAN // 2

    # ------------------------------------------------------------------------------------ construction

    @classmethod
    def build(
        cls,
        points: np.ndarray,
        config: Lines3DConfig | None = None,
        name: str = "map",
        parallel_config: ParallelConfig | None = None,
        progress: Callable[[str], None] | None = None,
        **metadata: Any,
    ) -> LineMap:
        """Returns the map of (P, 3) float64 points: segments by ``lines3d.extract``, then clusters.

        ``progress(stage)`` is called as stages start (normals, regions, lines, clusters).
        """
        from .lines3d import check_points, extract

        config = config or Lines3DConfig()
        points = check_points(points)
        segments = extract(points, config, progress=progress)
        extra: dict[str, Any] = {"point_count": len(points), "extraction": asdict(config)} | metadata
        return cls.from_segments(
            segments, name=name, parallel_config=parallel_config, progress=progress, **extra
        )

    @classmethod
    def from_segments(
        cls,
        lines3d: np.ndarray,
        name: str = "map",
        parallel_config: ParallelConfig | None = None,
        tile_m: float | None = None,
        progress: Callable[[str], None] | None = None,
        **metadata: Any,
    ) -> LineMap:
        """Returns the map of given (M, 6) float64 segments; ``tile_m`` defaults to 1/32 of the extent."""
        from ..parallel import parallel_clusters  # imported here: the map format does not depend on it

        segments = check_segments(lines3d, "lines3d", 6)
        if progress:
            progress("clusters")
        clusters = parallel_clusters(segments, parallel_config) if len(segments) else _no_clusters()
        meta = {
            "format_version": FORMAT_VERSION,
            "map_id": uuid.uuid4().hex,
            "name": name,
            "units": "m",
            "frame": "map",
            "point_count": None,
            "extraction": None,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "bounds": _bounds(segments).tolist(),
            "num_segments": len(segments),
            "grid": _grid(segments, tile_m),
        } | metadata
        return cls(segments, clusters, meta)

    # ------------------------------------------------------------------------------------ files

    def save(self, path: str | os.PathLike) -> None:
        """Writes the map to one .npz file, atomically."""
        from ..io import write_bytes_atomic

        buffer = _bytes_io.BytesIO()
        c = self.clusters
        arrays = (self.segments, c.directions, c.labels, c.support, self._keys, self._ptr, self._members)
        np.savez_compressed(
            buffer, metadata=np.array(json.dumps(self.metadata)), **dict(zip(_ARRAYS, arrays, strict=True))
        )
        write_bytes_atomic(path, buffer.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike) -> LineMap:
        """Returns the map stored at ``path``; FileFormatError if missing, corrupt or of another version."""
        path = Path(path)
        check_map_file(path)
        try:
            with np.load(path, allow_pickle=False) as npz:
                missing = [k for k in ("metadata", *_ARRAYS) if k not in npz.files]
                if missing:
                    raise FileFormatError(f"{path}: not a linereg map file (an .npz without {missing[0]!r})")
                metadata = json.loads(str(npz["metadata"]))
                version = metadata.get("format_version") if isinstance(metadata, dict) else None
                if version != FORMAT_VERSION:
                    raise FileFormatError(
                        f"{path}: line map format version {version!r} is not supported (supported: {FORMAT_VERSION})"
                    )
                arrays = {k: npz[k] for k in _ARRAYS}
        except FileFormatError:
            raise
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, zlib.error) as e:
            raise FileFormatError(
                f"{path}: corrupt or truncated line map file ({type(e).__name__}: {e})"
            ) from None
        clusters = DirectionClusters(arrays["directions"], arrays["labels"], arrays["support"])
        index = (arrays["tile_keys"], arrays["tile_ptr"], arrays["tile_members"])
        line_map = cls(arrays["segments"].astype(np.float64), clusters, metadata, index)
        logger.info("%s: %d segments, %d clusters", path, len(line_map), len(clusters))
        return line_map

    # ------------------------------------------------------------------------------------ queries

    def __len__(self) -> int:
        return len(self.segments)

    def tile_ids(self) -> np.ndarray:
        """Returns the (T,) int64 ids of the non-empty tiles."""
        return self._keys.copy()

    def tile_segments(self, tile_id: int) -> np.ndarray:
        """Returns the (k,) int64 indices of the segments passing through one tile (empty if none)."""
        pos = int(np.searchsorted(self._keys, tile_id))
        if pos >= len(self._keys) or self._keys[pos] != tile_id:
            return np.zeros(0, dtype=np.int64)
        return self._members[self._ptr[pos] : self._ptr[pos + 1]].copy()

    def tile_of(self, position: np.ndarray) -> int:
        """Returns the id of the tile holding a (3,) position (it may be empty)."""
        cell = np.floor((np.asarray(position, dtype=np.float64)[self._axes] - self._origin) / self.tile_m)
        return int(_flat(cell.astype(np.int64)[None])[0])

    def segments_near(self, position: np.ndarray, radius_m: float) -> np.ndarray:
        """Returns the (k,) int64 sorted indices of segments within ``radius_m`` (3D) of a (3,) position."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        lo = np.floor((position[self._axes] - radius_m - self._origin) / self.tile_m).astype(np.int64)
        hi = np.floor((position[self._axes] + radius_m - self._origin) / self.tile_m).astype(np.int64)
        # the non-empty tiles inside the query square: O(tiles), whatever the radius
        inside = np.flatnonzero(((self._cells >= lo) & (self._cells <= hi)).all(axis=1))
        parts = [self._members[self._ptr[p] : self._ptr[p + 1]] for p in inside]
        cand = np.unique(np.concatenate([np.zeros(0, np.int64), *parts]))
        return cand[_point_segment_distance(position, self.segments[cand]) <= radius_m]

    def visible(
        self,
        camera: Camera,
        cam_from_world: np.ndarray | None,
        prior_position: np.ndarray | None = None,
        radius_m: float | None = None,
        min_depth_m: float = 1e-3,
    ) -> np.ndarray:
        """Returns the (k,) int64 indices of the segments a camera may see.

        Without a pose: all segments, or those within ``radius_m`` of ``prior_position``. With a pose:
        those within ``radius_m`` of the camera centre (if given) that project into the image.
        """
        if cam_from_world is None:
            if prior_position is None or radius_m is None:
                return np.arange(len(self.segments))
            return self.segments_near(prior_position, radius_m)
        from ..matching import project_segments

        cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
        center = camera_center(cam_from_world) if prior_position is None else prior_position
        cand = np.arange(len(self.segments)) if radius_m is None else self.segments_near(center, radius_m)
        pixels, in_front = project_segments(self.segments[cand], camera, cam_from_world, min_depth_m)
        x, y = pixels[:, [0, 2]], pixels[:, [1, 3]]
        # a conservative box test: the segment's bounding box meets the image
        inside = (x.max(1) >= -0.5) & (x.min(1) <= camera.width - 0.5)
        inside &= (y.max(1) >= -0.5) & (y.min(1) <= camera.height - 0.5)
        return cand[in_front & inside]

    def info(self) -> dict[str, Any]:
        """Returns a JSON-ready summary: metadata, segment count, clusters (direction, size, support)."""
        c = self.clusters
        clusters = [
            {
                "direction": c.directions[k].round(6).tolist(),
                "size": int((c.labels == k).sum()),
                "support_m": float(c.support[k]),
            }
            for k in range(len(c))
        ]
        meta = {k: v for k, v in self.metadata.items() if k != "grid"}
        lengths = np.linalg.norm(self.segments[:, 3:] - self.segments[:, :3], axis=1)
        return meta | {
            "num_segments": len(self.segments),
            "total_length_m": float(lengths.sum()),
            "num_tiles": len(self._keys),
            "tile_m": self.tile_m,
            "clusters": clusters,
            "unclustered": int((c.labels < 0).sum()),
        }


# ---------------------------------------------------------------------------------------------- helpers


def check_map_file(path: str | os.PathLike) -> None:
    """Raises FileFormatError naming ``path`` unless it is a readable file that starts like a map (.npz).

    Reads only the first bytes: entry points check ``--map`` with it before any work.
    """
    path = Path(path)
    if path.is_dir():
        raise FileFormatError(f"{path}: is a directory, not a line map file")
    if not path.is_file():
        raise FileFormatError(f"{path}: no such map file")
    try:
        with open(path, "rb") as f:
            head = f.read(len(_NPZ_MAGIC))
    except OSError as e:
        raise FileFormatError(f"{path}: cannot read the map file ({e.strerror})") from None
    if not head:
        raise FileFormatError(f"{path}: empty file, not a line map")
    if head != _NPZ_MAGIC:
        raise FileFormatError(f"{path}: not a linereg map file (written by `linereg map build`)")


_NPZ_MAGIC = b"PK\x03\x04"  # a map is an .npz: a zip archive


def _no_clusters() -> DirectionClusters:
    return DirectionClusters(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0))


def _bounds(segments: np.ndarray) -> np.ndarray:
    """Returns (2, 3) min / max corner of all endpoints (zeros for an empty map)."""
    if len(segments) == 0:
        return np.zeros((2, 3))
    ends = segments.reshape(-1, 3)
    return np.stack([ends.min(axis=0), ends.max(axis=0)])


def _grid(segments: np.ndarray, tile_m: float | None) -> dict[str, Any]:
    """Returns the tile grid: the two axes of largest extent, their origin and the tile size (m)."""
    bounds = _bounds(segments)
    extent = bounds[1] - bounds[0]
    axes = np.sort(np.argsort(-extent, kind="stable")[:2])
    if tile_m is None:
        tile_m = max(float(extent.max()) / 32.0, 1.0)
    if not tile_m > 0:
        raise InvalidInputError(f"tile_m must be positive, got {tile_m}")
    return {"axes": axes.tolist(), "origin": bounds[0][axes].tolist(), "tile_m": float(tile_m)}


TILE_KEY_SPAN = 1 << 31  # tile (i, j) -> one int64 id (i + span/2) * span + j + span/2, |i|, |j| < 2**30


def _flat(cells: np.ndarray) -> np.ndarray:
    return (cells[:, 0] + TILE_KEY_SPAN // 2) * TILE_KEY_SPAN + (cells[:, 1] + TILE_KEY_SPAN // 2)


def _tile_index(segments: np.ndarray, grid: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    keys = _flat(np.floor((xy - origin) / tile).astype(np.int64))
    pairs = np.unique(np.stack([keys, seg], axis=1), axis=0) if len(seg) else np.zeros((0, 2), np.int64)
    tile_keys, starts = np.unique(pairs[:, 0], return_index=True)
    ptr = np.r_[starts, len(pairs)].astype(np.int64)
    return tile_keys.astype(np.int64), ptr, pairs[:, 1].astype(np.int64)


def _point_segment_distance(point: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Returns (k,) distances of a (3,) point to (k, 6) finite segments."""
    a, b = segments[:, :3], segments[:, 3:]
    ab = b - a
    t = np.clip(
        np.einsum("ij,ij->i", point - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1
    )
    return np.linalg.norm(a + t[:, None] * ab - point, axis=1)
