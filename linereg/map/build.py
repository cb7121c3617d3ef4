"""A line map's content from a point cloud: what ``LineMap.build`` runs.

1. Profile the cloud (``profile``: spacing, noise, scan rings) and choose the extraction parameters from it.
2. Planar regions (``planes``), their boundaries and creases, their surfaces as a mesh (``lines3d``).
3. Where the sensor origin is known and the cloud is a single sweep with rings: occluding contours and
   ring-curvature edges (``sensor_edges``), those not already along a plane's edge.
   With ``MapBuildConfig.intensity_edges`` and an intensity per point, also the steps of the intensity
   along the rings (``intensity_edges``: road markings, paint).
4. In a dense RGB-D fusion: edges found per point where the surface bends or ends, along the directions
   of the scene's frame of dominant planes (``point_edges``: small structure no planar region holds),
   those not already along a plane's edge. A cloud without such a frame gets none.
Each segment is tagged with its kind (``kinds``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

import numpy as np

from ..config import Lines3DConfig, MapBuildConfig
from ..errors import InvalidInputError
from ..threads import thread_count
from . import kinds
from .collinear import along
from .lines3d import check_points, lines_and_surfaces
from .planes import Planes, segment_planes, voxel_downsample
from .profile import CloudProfile, adapted_config, profile_and_rings
from .surfaces import Surfaces, empty_surfaces, shift_surfaces

if TYPE_CHECKING:
    from .point_edges import EdgePoints

logger = logging.getLogger(__name__)
T = TypeVar("T")

# dense, evenly sampled clouds (``profile.kind``): every point's neighbourhood is a round patch of surface
# a few cm across. Coarser even clouds ("map", the demo's scan) are not measured with point edges yet
POINT_EDGE_KINDS = ("rgbd",)


class MapContent(NamedTuple):
    """What map building found: (M, 6) float64 ``segments``, (M,) int8 ``kinds``, the ``surfaces`` mesh, the
    cloud's ``profile``, the ``config`` used, for an empty map the ``reason``, and the planar regions'
    (R, 3) unit ``plane_normals`` and (R,) ``plane_areas`` (m^2: points x spacing^2) for the directions."""

    segments: np.ndarray
    kinds: np.ndarray
    surfaces: Surfaces
    profile: CloudProfile
    config: Lines3DConfig
    reason: str
    plane_normals: np.ndarray = np.zeros((0, 3))
    plane_areas: np.ndarray = np.zeros(0)
    notes: tuple[str, ...] = ()  # what was asked for and could not be done (e.g. intensity edges, no rings)
    repeated: int = 0  # points dropped as exact copies of earlier ones (``distinct_points``)


def extract_map(
    points: np.ndarray,
    config: MapBuildConfig | None = None,
    sensor_origin: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    intensity: np.ndarray | None = None,
    rings: np.ndarray | None = None,
) -> MapContent:
    """Returns the MapContent of (P, 3) float64 points (their frame); ``sensor_origin`` (3,): where the
    scanner stood, if known (a single sweep in its sensor's frame has it at the origin: found by its
    rings); ``intensity`` (P,): each point's return intensity, if the cloud has one (used only with
    ``config.intensity_edges``; NaN: none); ``rings`` (P,): each point's laser number, if the file says
    (a driver's ``ring`` field; negative or NaN: none; ``profile.rings_from_field``). ``progress(stage)`` is
    called as the stages profile, normals, regions, lines start."""
    config = config or MapBuildConfig()
    points = check_points(points)
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=np.float64).reshape(-1)
        if len(intensity) != len(points):
            raise InvalidInputError(
                f"intensity must hold one value per point: {len(intensity)} for {len(points)} points"
            )
    if rings is not None:
        rings = laser_numbers(rings, len(points))
    if sensor_origin is not None:
        sensor_origin = np.asarray(sensor_origin, dtype=np.float64).reshape(3)
        if not np.isfinite(sensor_origin).all():
            raise InvalidInputError(f"sensor_origin must be finite, got {sensor_origin}")
    if progress:
        progress("profile")
    profile, ring = profile_and_rings(points, sensor_origin, config.profile, rings)
    repeated = 0
    if len(points) > 1 and profile.spacing_p10_m == 0.0:
        # a tenth of the points sampled have an exact twin (an export repeating its points, a merge of
        # overlapping copies): copies add no geometry, but every density the build is tuned by counts them,
        # and a spacing of 0 is no scale (a plane repeated 10x gave no line); the first of each is kept, in
        # the cloud's order (a sweep's rings follow it)
        keep = distinct_points(points)
        repeated = len(points) - len(keep)
        points = points[keep]
        intensity = None if intensity is None else intensity[keep]
        rings = None if rings is None else rings[keep]
        logger.info("%d repeated points dropped (exact copies of earlier ones)", repeated)
        profile, ring = profile_and_rings(points, sensor_origin, config.profile, rings)
    lines_config = adapted_config(profile, config.lines3d, config.profile) if config.adapt else config.lines3d
    if len(points) == 0:
        return _empty(profile, lines_config, "the cloud holds no points")
    # georeferenced coordinates (5e6 m) keep their precision only after a shift; min() is exact
    offset = points.min(axis=0)
    local = points - offset
    if lines_config.downsample_m > 0:
        local = voxel_downsample(local, lines_config.downsample_m)
    sensor = None if profile.sensor_origin is None else np.asarray(profile.sensor_origin) - offset
    # the sensor's edges need only the points, the point edges only the planes: their KD-tree searches
    # and array sums (which release the GIL) run in a thread of their own while this one grows the
    # regions and traces their outlines (Python-bound)
    with ThreadPoolExecutor(max_workers=1) as pool:
        run = pool.submit if thread_count(2) > 1 else _now
        sensed = None
        notes: tuple[str, ...] = ()
        if rings is not None and profile.ring_source != "field":
            notes += (
                "ring field: its lasers are not one spinning sensor's cones about one axis "
                + (f"(rings found by {profile.ring_source} instead)" if profile.rings else "(no rings used)"),
            )
        with_intensity = config.intensity_edges and intensity is not None
        if config.intensity_edges and not with_intensity:
            notes += ("intensity edges: the cloud has no intensity",)
        elif with_intensity and (sensor is None or not profile.rings):
            notes += ("intensity edges: found only along a single sweep's rings, and this cloud has none",)
        if (config.sensor_edges or with_intensity) and sensor is not None and profile.rings:
            sensed = run(
                _sensor_edges, points, ring, intensity if with_intensity else None, offset, sensor, config
            )
        edges, at_points = None, None
        if config.point_edges or (config.point_edges is None and profile.kind in POINT_EDGE_KINDS):
            from .point_edges import find_edge_points

            # the edge points need no planes: found while this thread grows them; the lines along the
            # planes' directions after (the same one-thread pool: in that order)
            at_points = run(find_edge_points, local, config.point)
        planes = segment_planes(local, lines_config, progress)
        if at_points is not None:
            edges = run(_point_edges, local, planes, profile, lines_config, config, at_points)
        if progress:
            progress("lines")
        mesh_cell = config.mesh_cell_m if config.surfaces else np.inf
        segments, kind, surfaces = lines_and_surfaces(local, planes, lines_config, mesh_cell, sensor)
        if sensed is not None:
            found, found_kind = sensed.result()
            # an edge along a plane's boundary or crease is that line (exactly fitted to its plane)
            segments, kind = _add_edges(segments, kind, found, found_kind, config.sensor.along_plane_m)
        if edges is not None:
            if progress:
                progress("point edges")
            found = edges.result()
            found_kind = np.full(len(found), kinds.POINT_EDGE, np.int8)
            segments, kind = _add_edges(segments, kind, found, found_kind, config.point.along_m)
    if not config.surfaces:
        surfaces = empty_surfaces()
    reason = "" if len(segments) else _why_empty(len(planes.counts), lines_config)
    logger.info("%s cloud: %d segments (%s)", profile.kind, len(segments), kinds.kind_counts(kind))
    # the mesh was made in the local frame: the map frame is local + offset
    surfaces = shift_surfaces(surfaces, offset) if len(surfaces) else empty_surfaces()
    areas = planes.counts * planes.spacing_m**2
    for note in notes:
        logger.warning(note)
    return MapContent(
        segments + np.tile(offset, 2), kind, surfaces, profile, lines_config, reason, planes.normals, areas,
        notes, repeated,
    )  # fmt: skip


def laser_numbers(rings: object, count: int) -> np.ndarray:
    """Returns (count,) int64 laser numbers of a ring field (NaN and negative values -1: none), or raises
    InvalidInputError naming ``rings`` (a value per point, whole numbers)."""
    values = np.asarray(rings)
    if values.ndim != 1 or len(values) != count:
        raise InvalidInputError(
            f"rings must hold one laser number per point: shape {values.shape} for {count} points"
        )
    if not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
        raise InvalidInputError(f"rings must be laser numbers, got values of type {values.dtype}")
    values = values.astype(np.float64)
    finite = np.isfinite(values)
    if (values[finite] != np.round(values[finite])).any():
        raise InvalidInputError("rings must be whole laser numbers, got fractions")
    out = np.full(count, -1, dtype=np.int64)
    laser = finite & (np.where(finite, values, -1.0) >= 0)
    out[laser] = values[laser].astype(np.int64)
    return out


def distinct_points(points: np.ndarray) -> np.ndarray:
    """Returns (K,) the sorted indices of the first occurrence of each distinct row of (P, 3) float64
    points (-0.0 and 0.0 alike): the cloud without its exact repeats, in its own order."""
    rows = np.ascontiguousarray(points + 0.0)  # -0.0 + 0.0 is 0.0: equal values, equal bytes
    _, first = np.unique(rows.view(np.dtype((np.void, rows.dtype.itemsize * 3))).ravel(), return_index=True)
    return np.sort(first)


def _sensor_edges(
    points: np.ndarray,
    ring: np.ndarray,
    intensity: np.ndarray | None,
    offset: np.ndarray,
    sensor: np.ndarray,
    config: MapBuildConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 6) local segments, (K,) int8 kinds) of a sweep's occluding contours and ring-curvature
    edges (``sensor_edges``, if ``config.sensor_edges``) and of its (P,) ``intensity``'s steps
    (``intensity_edges``, when given) of its (P, 3) points in the map frame with their (P,) rings (the
    profile's), ``offset`` their local origin."""
    from .intensity_edges import intensity_edges
    from .sensor_edges import sensor_edges

    local = points - offset
    found, found_kind = np.zeros((0, 6)), np.zeros(0, np.int8)
    if config.sensor_edges:
        found, found_kind = sensor_edges(local, ring, sensor, config.sensor)
    if intensity is not None:
        steps = intensity_edges(local, intensity, ring, sensor, config.intensity, config.sensor)
        # a step along a geometric edge is that edge (the paint ends where the kerb does)
        steps = steps[~along(steps, found, np.full(len(steps), config.sensor.along_plane_m), 10.0)]
        found = np.concatenate([found, steps])
        found_kind = np.r_[found_kind, np.full(len(steps), kinds.INTENSITY, np.int8)]
    return found, found_kind


def _point_edges(
    local: np.ndarray,
    planes: Planes,
    profile: CloudProfile,
    lines_config: Lines3DConfig,
    config: MapBuildConfig,
    found: Future[EdgePoints],
) -> np.ndarray:
    """Returns (K, 6) point edges (``point_edges``) of (P, 3) local points along the scene's frame, from
    the edge points ``found`` (done before this runs: the same one-thread pool ran it first)."""
    from .plane_directions import frame_directions
    from .point_edges import point_edges

    # only along the scene's frame (a room's floor and walls): edge points of noise pile up along any
    # direction, and a tilted plane's creases or a ragged segment's direction would collect them
    frame, _ = frame_directions(planes.normals, planes.counts * planes.spacing_m**2, config.directions)
    spacing = max(profile.spacing_m, lines_config.downsample_m)
    min_length = lines_config.min_length_m
    return point_edges(local, frame, spacing, profile.noise_m, min_length, config.point, found.result())


def _now(run: Callable[..., T], *args: Any) -> Future[T]:
    """Returns a finished Future of ``run(*args)``: the work done in this thread (one thread allowed)."""
    done: Future[T] = Future()
    done.set_result(run(*args))
    return done


def _add_edges(
    segments: np.ndarray, kind: np.ndarray, found: np.ndarray, found_kind: np.ndarray, along_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (segments, kinds) with the (F, 6) ``found`` edges of ``found_kind`` appended, those running
    within ``along_m`` along a segment already there left out (a plane's line is fitted exactly)."""
    keep = ~along(found, segments, np.full(len(found), along_m), 10.0)
    return np.concatenate([segments, found[keep]]), np.r_[kind, found_kind[keep]].astype(np.int8)


def _why_empty(num_regions: int, config: Lines3DConfig) -> str:
    if num_regions == 0:
        return (
            f"no planar region of at least {config.min_region_points} points within {config.distance_m} m of "
            "a plane (a line of points, scattered points or clutter give no plane edges)"
        )
    return (
        f"{num_regions} planar regions, but none has a straight edge of at least {config.min_length_m} m "
        f"or covers {config.min_region_area_m2} m^2"
    )


def _empty(profile: CloudProfile, config: Lines3DConfig, reason: str) -> MapContent:
    return MapContent(np.zeros((0, 6)), np.zeros(0, np.int8), empty_surfaces(), profile, config, reason)
