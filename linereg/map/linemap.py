"""The line map: 3D segments of a point cloud, their kinds, parallel clusters, the surfaces they came from,
a tile index and metadata.

Built once from a cloud (``LineMap.build``) and saved as one ``.npz`` file whose ``metadata`` entry is
JSON (format version, units, frame, the cloud's profile, extraction parameters, ...). The tile index is a
uniform grid over the two largest extents of the map (``tiles``); a segment is listed in every tile it
passes through. Format version 2 added ``kinds`` and the surface mesh; version-1 files still load (kinds
unknown, no surfaces: visibility is the frustum test only). Version 3 changed nothing in the layout: a
version-2 map built from a cloud had its surfaces in the cloud's local frame (shifted by the cloud's
lowest corner), so such a file loads without its surfaces, and says so (rebuild it for occlusion).
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
from ..config import Lines3DConfig, MapBuildConfig, ParallelConfig, PlaneDirectionsConfig, VisibilityConfig
from ..directions import DirectionClusters
from ..errors import FileFormatError
from ..geometry import camera_center
from ..registration import check_segments
from . import kinds as segment_kinds
from .surfaces import Surfaces, make_surfaces
from .tiles import TILE_KEY_SPAN, bounds, flat, grid, point_segment_distance, tile_index
from .visibility import Visibility

__all__ = ["FORMAT_VERSION", "TILE_KEY_SPAN", "LineMap", "check_map_file"]

logger = logging.getLogger(__name__)

FORMAT_VERSION = 3
SUPPORTED_VERSIONS = (1, 2, 3)
_ARRAYS = ("segments", "directions", "labels", "support", "tile_keys", "tile_ptr", "tile_members")
_ARRAYS_V2 = ("kinds", "surface_vertices", "surface_triangles", "surface_origin")


class LineMap:
    """3D segments (M, 6) float64 metres with their (M,) int8 ``kinds`` (``map.kinds``), parallel
    ``clusters``, the ``surfaces`` they came from (a mesh, or None), a tile index and ``metadata``."""

    def __init__(
        self,
        segments: np.ndarray,
        clusters: DirectionClusters,
        metadata: dict[str, Any],
        index=None,
        kinds: np.ndarray | None = None,
        surfaces: Surfaces | None = None,
    ):
        self.segments = segments
        self.clusters = clusters
        self.metadata = metadata
        self.kinds = (
            np.zeros(len(segments), np.int8)
            if kinds is None
            else segment_kinds.check_kinds(kinds, len(segments))
        )
        self.surfaces = surfaces if surfaces is not None and len(surfaces) else None
        self.cache: dict[str, Any] = {}  # what queries derive from the map once (``localization.map_view``)
        tiles = metadata["grid"]
        self._axes = np.asarray(tiles["axes"], dtype=np.int64)
        self._origin = np.asarray(tiles["origin"], dtype=np.float64)
        self.tile_m = float(tiles["tile_m"])
        index = index if index is not None else tile_index(segments, tiles)
        self._keys, self._ptr, self._members = index
        # (T, 2) i, j of each tile
        self._cells = np.stack(np.divmod(self._keys, TILE_KEY_SPAN), axis=1) - TILE_KEY_SPAN // 2
        self._visibility: Visibility | None = None

    # ------------------------------------------------------------------------------------ construction

    @classmethod
    def build(
        cls,
        points: np.ndarray,
        config: MapBuildConfig | Lines3DConfig | None = None,
        name: str = "map",
        parallel_config: ParallelConfig | None = None,
        progress: Callable[[str], None] | None = None,
        sensor_origin: np.ndarray | None = None,
        intensity: np.ndarray | None = None,
        rings: np.ndarray | None = None,
        **metadata: Any,
    ) -> LineMap:
        """Returns the map of (P, 3) float64 points (``build.extract_map``: parameters from the cloud's
        profile, segments with their kinds, surfaces), then clusters. A ``Lines3DConfig`` is the base whose
        default-valued fields the profile chooses. ``sensor_origin`` (3,): where the scanner stood, if
        known. ``intensity`` (P,): each point's return intensity, for ``MapBuildConfig.intensity_edges``
        (``io.read_cloud_intensity`` reads it). ``rings`` (P,): each point's laser number where the file
        gives one (``io.read_cloud_fields``): a single sweep's rings, and its sensor found from them even in a
        vehicle's frame (``map.profile.rings_from_field``). ``progress(stage)`` is called as stages start (profile,
        normals, regions, lines, clusters). An empty map says why in ``metadata["empty_reason"]``; what was
        asked for and could not be done is in ``metadata["notes"]``; how many points were dropped as exact
        copies of earlier ones in ``metadata["repeated_points"]`` (when a tenth of them have a twin).
        """
        from .build import extract_map

        if isinstance(config, Lines3DConfig):
            config = MapBuildConfig(lines3d=config)
        config = config or MapBuildConfig()
        content = extract_map(points, config, sensor_origin, progress, intensity, rings)
        extra: dict[str, Any] = {
            "point_count": content.profile.num_points,
            "profile": content.profile.as_dict(),
            "extraction": asdict(content.config),
        }
        if content.reason:
            extra["empty_reason"] = content.reason
        if content.notes:
            extra["notes"] = list(content.notes)
        if content.repeated:  # exact copies of earlier points, dropped (``build.distinct_points``)
            extra["repeated_points"] = content.repeated
        planes = (content.plane_normals, content.plane_areas) if config.plane_directions else None
        return cls.from_segments(
            content.segments,
            name=name,
            parallel_config=parallel_config,
            progress=progress,
            kinds=content.kinds,
            surfaces=content.surfaces,
            planes=planes,
            plane_config=config.directions,
            **(extra | metadata),
        )

    @classmethod
    def from_segments(
        cls,
        lines3d: np.ndarray,
        name: str = "map",
        parallel_config: ParallelConfig | None = None,
        tile_m: float | None = None,
        progress: Callable[[str], None] | None = None,
        kinds: np.ndarray | None = None,
        surfaces: Surfaces | tuple[np.ndarray, np.ndarray] | None = None,
        planes: tuple[np.ndarray, np.ndarray] | None = None,
        plane_config: PlaneDirectionsConfig | None = None,
        **metadata: Any,
    ) -> LineMap:
        """Returns the map of given (M, 6) float64 segments; ``tile_m`` defaults to 1/32 of the extent;
        ``kinds`` (M,) int (default ``kinds.UNKNOWN``); ``surfaces``: a Surfaces or (vertices (V, 3),
        triangles (T, 3)) in the map frame that may hide segments (default none). ``planes``: (R, 3) unit
        normals and (R,) areas (m^2) of the cloud's planar regions: the direction clusters take the
        directions of the dominant ones (``plane_directions.map_clusters``, configured by ``plane_config``);
        None: clusters of the segments alone (``parallel_clusters``)."""
        # imported here: the map format does not depend on them
        from ..parallel import parallel_clusters
        from .plane_directions import map_clusters

        segments = check_segments(lines3d, "lines3d", 6)
        kinds = None if kinds is None else segment_kinds.check_kinds(kinds, len(segments))
        if isinstance(surfaces, tuple):
            surfaces = make_surfaces(*surfaces)
        if progress:
            progress("clusters")
        if not len(segments):
            clusters = _no_clusters()
        elif planes is not None:
            clusters = map_clusters(segments, *planes, parallel_config, plane_config)
        else:
            clusters = parallel_clusters(segments, parallel_config)
        meta = {
            "format_version": FORMAT_VERSION,
            "map_id": uuid.uuid4().hex,
            "name": name,
            "units": "m",
            "frame": "map",
            "point_count": None,
            "extraction": None,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "bounds": bounds(segments).tolist(),
            "num_segments": len(segments),
            "grid": grid(segments, tile_m),
        } | metadata
        return cls(segments, clusters, meta, kinds=kinds, surfaces=surfaces)

    # ------------------------------------------------------------------------------------ files

    def save(self, path: str | os.PathLike) -> None:
        """Writes the map to one .npz file (format version 3), atomically."""
        from ..io import write_bytes_atomic

        buffer = _bytes_io.BytesIO()
        c = self.clusters
        arrays = (self.segments, c.directions, c.labels, c.support, self._keys, self._ptr, self._members)
        s = self.surfaces
        mesh = (
            (s.vertices, s.triangles, s.origin)
            if s is not None
            else (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros(3))
        )
        named = dict(zip(_ARRAYS, arrays, strict=True)) | dict(
            zip(_ARRAYS_V2, (self.kinds, *mesh), strict=True)
        )
        metadata = self.metadata | {"format_version": FORMAT_VERSION}
        np.savez_compressed(buffer, metadata=np.array(json.dumps(metadata)), **named)
        write_bytes_atomic(path, buffer.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike) -> LineMap:
        """Returns the map stored at ``path``; FileFormatError if missing, corrupt or of another version.
        A version-1 file loads without kinds (all unknown) and without surfaces."""
        path = Path(path)
        check_map_file(path)
        try:
            with np.load(path, allow_pickle=False) as npz:
                missing = [k for k in ("metadata", *_ARRAYS) if k not in npz.files]
                if missing:
                    raise FileFormatError(f"{path}: not a linereg map file (an .npz without {missing[0]!r})")
                metadata = json.loads(str(npz["metadata"]))
                version = metadata.get("format_version") if isinstance(metadata, dict) else None
                if version not in SUPPORTED_VERSIONS:
                    raise FileFormatError(
                        f"{path}: line map format version {version!r} is not supported (supported: "
                        f"{', '.join(map(str, SUPPORTED_VERSIONS))})"
                    )
                names = _ARRAYS + (_ARRAYS_V2 if version >= 2 else ())
                missing = [k for k in names if k not in npz.files]
                if missing:
                    raise FileFormatError(f"{path}: corrupt line map file (no {missing[0]!r})")
                arrays = {k: npz[k] for k in names}
        except FileFormatError:
            raise
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, zlib.error) as e:
            raise FileFormatError(
                f"{path}: corrupt or truncated line map file ({type(e).__name__}: {e})"
            ) from None
        clusters = DirectionClusters(arrays["directions"], arrays["labels"], arrays["support"])
        index = (arrays["tile_keys"], arrays["tile_ptr"], arrays["tile_members"])
        surfaces, kinds = None, None
        if version >= 2:
            kinds = arrays["kinds"]
            mesh = (arrays["surface_vertices"], arrays["surface_triangles"], arrays["surface_origin"])
            surfaces = Surfaces(
                mesh[0].astype(np.float32), mesh[1].astype(np.int32), mesh[2].astype(np.float64)
            )
            if _misplaced_surfaces(metadata) and len(surfaces):
                logger.warning(
                    "%s: a format version 2 map built from a cloud holds misplaced surfaces: loaded without "
                    "them (visibility is the frustum test only); rebuild the map for occlusion",
                    path,
                )
                surfaces = None
        line_map = cls(arrays["segments"].astype(np.float64), clusters, metadata, index, kinds, surfaces)
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
        return int(flat(cell.astype(np.int64)[None])[0])

    def segments_near(self, position: np.ndarray, radius_m: float) -> np.ndarray:
        """Returns the (k,) int64 sorted indices of segments within ``radius_m`` (3D) of a (3,) position."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        lo = np.floor((position[self._axes] - radius_m - self._origin) / self.tile_m).astype(np.int64)
        hi = np.floor((position[self._axes] + radius_m - self._origin) / self.tile_m).astype(np.int64)
        # the non-empty tiles inside the query square: O(tiles), whatever the radius
        inside = np.flatnonzero(((self._cells >= lo) & (self._cells <= hi)).all(axis=1))
        parts = [self._members[self._ptr[p] : self._ptr[p + 1]] for p in inside]
        cand = np.unique(np.concatenate([np.zeros(0, np.int64), *parts]))
        return cand[point_segment_distance(position, self.segments[cand]) <= radius_m]

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
        cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
        center = camera_center(cam_from_world) if prior_position is None else prior_position
        cand = np.arange(len(self.segments)) if radius_m is None else self.segments_near(center, radius_m)
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        a, b = self.segments[cand, :3] @ R.T + t, self.segments[cand, 3:] @ R.T + t
        in_front = (a[:, 2] > min_depth_m) & (b[:, 2] > min_depth_m)
        z = np.maximum(np.stack([a[:, 2], b[:, 2]], axis=1), min_depth_m)
        x = camera.fx * np.stack([a[:, 0], b[:, 0]], axis=1) / z + camera.cx
        y = camera.fy * np.stack([a[:, 1], b[:, 1]], axis=1) / z + camera.cy
        # a conservative box test: the segment's bounding box meets the image
        inside = (x.max(1) >= -0.5) & (x.min(1) <= camera.width - 0.5)
        inside &= (y.max(1) >= -0.5) & (y.min(1) <= camera.height - 0.5)
        return cand[in_front & inside]

    def visibility(self, config: VisibilityConfig | None = None) -> Visibility:
        """Returns the map's visibility queries (built on first use; a ``config`` replaces the cached one)."""
        if self._visibility is None or (config is not None and config != self._visibility.config):
            self._visibility = Visibility(self.segments, self.surfaces, config)
        return self._visibility

    def visible_parts(
        self, camera: Camera, cam_from_world: np.ndarray, index: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((K, 6) float64 world sub-segments visible from the camera: in front of it, inside its
        image, not hidden by the map's surfaces; (K,) int64 the row of ``segments`` each came from).

        A segment partly hidden gives its visible runs; ``index`` restricts to those rows (None: all).
        Without surfaces: the frustum test only. See ``map.visibility``.
        """
        return self.visibility().visible_parts(camera, cam_from_world, index)

    def surface_footprint(
        self, camera: Camera, cam_from_world: np.ndarray, cell_px: float
    ) -> np.ndarray | None:
        """Returns (h, w) bool cells of ``cell_px`` pixels whose ray from the camera meets the map's
        surfaces (``Visibility.footprint``), None for a map without surfaces."""
        return self.visibility().footprint(camera, cam_from_world, cell_px)

    @property
    def accuracy_m(self) -> float:
        """How well the map places its lines (m): the point spacing of the cloud it was built from (an edge
        is placed to within about one spacing of where the scan's points end), 0 for a map of given segments
        (its lines are taken as exact)."""
        profile = self.metadata.get("profile") or {}
        spacing = profile.get("spacing_m") if isinstance(profile, dict) else None
        return float(spacing) if spacing is not None and np.isfinite(spacing) and spacing > 0 else 0.0

    def potentially_visible(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Returns (k,) int64 sorted rows of the segments that may be visible from some camera centre in
        the axis-aligned box [lo, hi] ((3,) each); conservative (never leaves out a segment visible from a
        point of the box). Sets per cell are computed on first use and cached."""
        return self.visibility().potentially_visible(lo, hi)

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
        if self.surfaces is not None:
            surfaces: dict[str, Any] = {"triangles": len(self.surfaces), "area_m2": self.surfaces.area_m2()}
        elif self.metadata.get("format_version") == 1:
            surfaces = {"triangles": 0, "note": "format version 1 map: no surfaces (frustum-only visibility)"}
        elif _misplaced_surfaces(self.metadata):
            surfaces = {
                "triangles": 0,
                "note": "format version 2 map: its surfaces were misplaced and are left out (frustum-only "
                "visibility); rebuild it from the cloud",
            }
        else:
            surfaces = {"triangles": 0, "note": "no surfaces (frustum-only visibility)"}
        return meta | {
            "num_segments": len(self.segments),
            "total_length_m": float(lengths.sum()),
            "kinds": segment_kinds.kind_counts(self.kinds),
            "surfaces": surfaces,
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


def _misplaced_surfaces(metadata: dict[str, Any]) -> bool:
    """Returns True for a map file whose surfaces ``LineMap.build`` wrote in the cloud's local frame: a
    format version 2 map built from a cloud (``extraction`` set)."""
    return metadata.get("format_version") == 2 and metadata.get("extraction") is not None


def _no_clusters() -> DirectionClusters:
    return DirectionClusters(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0))
