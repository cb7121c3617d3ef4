"""``localize``: pixels and a line map in, a Registration out (2D lines, the map's view, ``register``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from .camera import Camera
from .chunks import Chunks
from .config import LineDetectConfig, RegisterConfig
from .directions import subset_clusters
from .geometry import segment_lengths
from .lines2d import detect
from .map.linemap import LineMap
from .map.reach import seen_from
from .pipeline import MapView, register_undistorted
from .points import map_gap_m, map_points, subset_points
from .priors import Prior
from .registration import Registration, check_segments
from .search import map_signatures
from .timing import StageTimer

__all__ = ["Prior", "localize", "localize_segments", "map_view", "prepare_map"]


def localize(
    image: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None = None,
    prior: Prior | None = None,
    detect_config: LineDetectConfig | None = None,
) -> Registration:
    """Returns the Registration of an image (H, W[, C], uint8/uint16/float) in a line map.

    Matches index ``line_map.segments``; timings include ``lines2d`` (detection).
    """
    timer = StageTimer()
    with timer("lines2d"):
        lines2d = detect(image, camera, detect_config)  # undistorted pixels
    return _localize_undistorted(lines2d, line_map, camera.undistorted(), config, prior, timer)


def localize_segments(
    lines2d: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None = None,
    prior: Prior | None = None,
) -> Registration:
    """Returns the Registration of precomputed (N, 4) 2D segments (distorted pixels if camera.dist) in a map."""
    lines2d = check_segments(lines2d, "lines2d", 4)
    if camera.has_distortion:
        lines2d = camera.undistort_points(lines2d.reshape(-1, 2)).reshape(-1, 4)
    return _localize_undistorted(lines2d, line_map, camera.undistorted(), config, prior, StageTimer())


def map_view(line_map: LineMap, index: np.ndarray | None, config: RegisterConfig) -> MapView:
    """Returns the MapView of the map's segments ``index`` (None: all): clusters restricted to them, their
    corner points and chunks (the whole map's, computed once and kept by the map, restricted to them:
    ``points.subset_points``, ``Chunks.subset``) and signatures."""
    if index is None:
        cached = line_map.cache.get("view")
        if cached is None or cached[0] != config.points:
            segments = line_map.segments
            points = map_points(segments, config.points, map_gap_m(segments, config.points))
            signatures = map_signatures(points, line_map.clusters.labels, line_map.clusters.directions)
            parts = line_map.visible_parts if _has_surfaces(line_map) else None
            footprint = line_map.surface_footprint if _has_surfaces(line_map) else None
            view = MapView(
                segments, line_map.clusters, points, signatures, parts=parts, accuracy_m=line_map.accuracy_m,
                footprint=footprint, chunks=Chunks.of_map(segments),
            )  # fmt: skip
            cached = (config.points, view)
            line_map.cache["view"] = cached
        return cached[1]
    segments = line_map.segments[index]
    clusters = subset_clusters(line_map.clusters, index, segment_lengths(segments))
    whole = map_view(line_map, None, config)
    points = subset_points(whole.points, index, len(line_map.segments))
    signatures = map_signatures(points, clusters.labels, clusters.directions)
    return MapView(
        segments,
        clusters,
        points,
        signatures,
        parts=_subset_parts(line_map, index),
        accuracy_m=line_map.accuracy_m,
        footprint=line_map.surface_footprint if _has_surfaces(line_map) else None,
        chunks=None if whole.chunks is None else whole.chunks.subset(index),
    )


def prepare_map(line_map: LineMap, config: RegisterConfig | None = None) -> None:
    """Derives what every query of a map needs once, so that no query waits for it: the whole map's view
    (corner points, signatures, chunks: ``map_view``) and its occlusion test's ray-casting scene and chunks
    (``Visibility.prepare``)."""
    map_view(line_map, None, config or RegisterConfig())
    if _has_surfaces(line_map):
        line_map.visibility().prepare()


def _has_surfaces(line_map: LineMap) -> bool:
    return line_map.surfaces is not None and len(line_map.surfaces) > 0


def _subset_parts(
    line_map: LineMap, index: np.ndarray
) -> Callable[[Camera, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """Returns the occlusion test of the map's rows ``index``, naming the rows of the subset (None: the map
    has no surfaces)."""
    if not _has_surfaces(line_map):
        return None
    index = np.asarray(index, dtype=np.int64)
    local = np.full(len(line_map.segments), -1, dtype=np.int64)
    local[index] = np.arange(len(index))

    def parts(camera: Camera, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pieces, rows = line_map.visible_parts(camera, cam_from_world, index)
        return pieces, local[rows]

    return parts


def _localize_undistorted(
    lines2d: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None,
    prior: Prior | None,
    timer: StageTimer,
) -> Registration:
    config = config or RegisterConfig()
    if len(lines2d) < config.min_lines2d:
        reason = f"only {len(lines2d)} line segments in the image; at least {config.min_lines2d} are needed"
        return Registration(success=False, reason=reason, timings=timer.finish())
    if prior is None and line_map.metadata.get("down") is not None:
        pass  # the map's down only matters with a gravity prior
    elif prior is not None and prior.world_down is None and line_map.metadata.get("down") is not None:
        prior = dataclasses.replace(prior, world_down=np.asarray(line_map.metadata["down"], dtype=np.float64))
    with timer("culling"):
        index = None
        if prior is not None and prior.position is not None and prior.radius_m is not None:
            index = seen_from_prior(line_map, camera, prior, config)
        view = map_view(line_map, index, config)
    if len(view.segments) < config.min_lines3d:
        where = "the map has" if index is None else "the prior leaves"
        reason = f"{where} only {len(view.segments)} segments; at least {config.min_lines3d} are needed"
        return Registration(success=False, reason=reason, timings=timer.finish())
    result = register_undistorted(lines2d, view, camera, config, timer, prior)
    if index is None:
        return result
    matches = np.c_[result.matches[:, 0], index[result.matches[:, 1]]].astype(np.int64)
    return dataclasses.replace(result, matches=matches)


def seen_from_prior(line_map: LineMap, camera: Camera, prior: Prior, config: RegisterConfig) -> np.ndarray:
    """Returns the (k,) int64 rows of the map segments that may project at least ``min_projected_px`` into
    the image from a pose the prior allows: its centre within the prior's ball and, with a prior rotation,
    turned at most 3 sigma from it (``map.reach``; the prior's rotation test, ``priors.admits``, is 3 sigma)."""
    assert prior.position is not None and prior.radius_m is not None
    turn = None
    if prior.cam_from_world is not None and prior.sigma_rot_deg is not None:
        turn = np.radians(3.0 * prior.sigma_rot_deg + config.search.rotation_slack_deg)
    keep = seen_from(
        line_map.segments, camera, prior.position, prior.radius_m, config.search.min_projected_px,
        prior.cam_from_world, turn,
    )  # fmt: skip
    return np.flatnonzero(keep)
