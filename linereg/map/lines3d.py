"""3D line segments of an unorganised point cloud, in the spirit of Lu et al. 2019 ("Fast 3D line segment
detection from unorganized point cloud"), the extractor the paper uses (section IV-A).

Steps: shift to a local frame -> planar regions (``planes.segment_planes``) -> each region rasterised in its
own plane, its contours traced and cut into straight runs (``contours``) -> the runs of every region turned
onto the scene's dominant directions (``line_families``) and moved onto where the region's points end,
bounded by the points of no region beyond (``edge_refine``) -> intersection lines where two planes meet at a
crease, clipped to where both regions reach it (``creases``) -> collinear pieces merged (``collinear``) ->
back to the input frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig
from ..errors import MAX_COORDINATE, InvalidInputError, beyond_bound
from ..threads import thread_count
from . import kinds
from .collinear import drop_near, merge_collinear
from .contours import image_contours, plane_basis, region_image, regions_lines
from .creases import crease_segments
from .edge_refine import refine_regions
from .line_families import box_lines, dominant_directions, has_parallel, snap_directions, snap_to_families
from .neighbours import flat_lists
from .planes import Planes, segment_planes, voxel_downsample
from .surfaces import Surfaces, concat_surfaces, empty_surfaces, raster_mesh

__all__ = ["check_points", "extract", "lines_and_surfaces", "lines_from_planes", "merge_collinear"]

logger = logging.getLogger(__name__)


def extract(
    points: np.ndarray, config: Lines3DConfig | None = None, progress: Callable[[str], None] | None = None
) -> np.ndarray:
    """Returns (M, 6) float64 3D segments ``X1, Y1, Z1, X2, Y2, Z2`` of (P, 3) points, in their frame.

    ``progress(stage)`` is called as the stages normals, regions, lines start.
    """
    config = config or Lines3DConfig()
    points = check_points(points)
    if len(points) == 0:
        return np.zeros((0, 6))
    # georeferenced coordinates (5e6 m) keep their precision only after a shift; min() is exact
    offset = points.min(axis=0)
    local = points - offset
    if config.downsample_m > 0:
        local = voxel_downsample(local, config.downsample_m)
    planes = segment_planes(local, config, progress)
    if progress:
        progress("lines")
    return lines_from_planes(local, planes, config) + np.tile(offset, 2)


def lines_from_planes(points: np.ndarray, planes: Planes, config: Lines3DConfig) -> np.ndarray:
    """Returns (M, 6) float64 merged contour and crease segments of the regions of (P, 3) local points."""
    return lines_and_surfaces(points, planes, config)[0]


def lines_and_surfaces(
    points: np.ndarray,
    planes: Planes,
    config: Lines3DConfig,
    mesh_cell_m: float = 0.0,
    sensor: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, Surfaces]:
    """Returns ((M, 6) float64 merged contour and crease segments of the regions of (P, 3) local points,
    (M,) int8 their kinds (``kinds.CREASE``, ``kinds.BOUNDARY``), the regions' surface rectangles in cells
    of at least ``mesh_cell_m`` (local frame; inf: none)); ``sensor`` (3,): the scanner's local position,
    for ``config.ring_cell_deg``."""
    none = (np.zeros((0, 6)), np.zeros(0, np.int8), empty_surfaces())
    if len(planes.counts) == 0:
        return none
    # raster cells follow each region's own density (a scanner's falls with range)
    cells = (
        np.full(len(planes.counts), config.cell_m)
        if config.cell_m > 0
        else config.cell_spacings * planes.spacing_m
    )
    if sensor is not None and config.ring_cell_deg > 0:
        # a sweep's rings lie range x gap apart: a finer raster falls apart between them
        reach = np.linalg.norm(planes.centroids - sensor, axis=1)
        cells = np.maximum(cells, reach * np.radians(config.ring_cell_deg))
    cells = np.maximum(cells, 1e-3)
    order = np.argsort(planes.labels, kind="stable")
    bounds = np.searchsorted(planes.labels[order], np.arange(len(planes.counts) + 1))
    members = [order[bounds[r] : bounds[r + 1]] for r in range(len(planes.counts))]
    # small patches (clutter) give fragments, not edges: about count * spacing^2 of surface each
    large = planes.counts * planes.spacing_m**2 >= config.min_region_area_m2
    creases = crease_segments(points, planes, members, large, cells, config)
    # points of no large region: a reveal, a ledge's underside, too narrow to be regions themselves
    loose = planes.labels < 0
    loose[~loose] = ~large[planes.labels[~loose]]
    loose_points = cKDTree(points[loose])
    kept = np.flatnonzero(large)
    regions = [Region(planes.normals[r], planes.centroids[r], cells[r]) for r in kept]
    frames = candidates([points[members[r]] for r in kept], regions, config)
    # directions from every region's candidates: a window pane's short sides take the facade's
    raw = [to_world(f.lines, reg, f.basis) for f, reg in zip(frames, regions, strict=True)]
    families = dominant_directions(np.concatenate([np.zeros((0, 6)), *raw]), config)
    beside = _beside_points(loose_points, regions, frames, config.beside_depth_m)
    contours = contour_segments(frames, regions, families, beside, config)
    near_m = [np.full(len(found), 2.0 * frame.cell) for frame, found in zip(frames, contours, strict=True)]
    contours, near_m = [np.zeros((0, 6)), *contours], [np.zeros(0), *near_m]
    contour = drop_near(np.concatenate(contours), creases, np.concatenate(near_m), 10.0)
    segments = np.concatenate([creases, contour])
    kind = np.r_[np.full(len(creases), kinds.CREASE), np.full(len(contour), kinds.BOUNDARY)].astype(np.int8)
    # creases are exact plane intersections: they win over the (rasterised) contour along the same line
    priority = np.r_[np.zeros(len(creases)), np.ones(len(contour))]
    merged, seeds = merge_collinear(segments, priority, config, return_seeds=True)
    logger.debug("%d crease + %d contour segments -> %d merged", len(creases), len(contour), len(merged))
    meshes = [
        raster_mesh(f.image, f.lo, f.cell, (reg.centroid, f.basis), mesh_cell_m)
        for f, reg in zip(frames, regions, strict=True)
        if np.isfinite(mesh_cell_m)
    ]
    return merged, kind[seeds], concat_surfaces(meshes, np.zeros(3))


def check_points(points: object) -> np.ndarray:
    """Returns (P, 3) float64 finite points, or raises InvalidInputError naming the problem."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (P, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InvalidInputError("points must be finite (no NaN or inf)")
    if (row := beyond_bound(arr)) is not None:
        raise InvalidInputError(f"points have a coordinate beyond +-{MAX_COORDINATE:g} m (point {row})")
    return arr


class Region(NamedTuple):
    """One planar region: unit normal (3,), centroid (3,), raster cell (m)."""

    normal: np.ndarray
    centroid: np.ndarray
    cell: float


class Frame(NamedTuple):
    """A region in its plane: (2, 3) in-plane axes, (n, 2) points, (k, 4) candidate lines, raster cell,
    the raster's contours as (m, 2) in-plane pixel centres, the (H, W) uint8 raster and (2,) the plane
    coordinates of its pixel (0, 0)'s corner."""

    basis: np.ndarray
    uv: np.ndarray
    lines: np.ndarray
    cell: float
    outlines: list[np.ndarray]
    image: np.ndarray
    lo: np.ndarray

    @property
    def band(self) -> float:
        """The width (m) within which points belong to a boundary line: two raster cells."""
        return 2.0 * self.cell


def candidates(points: list[np.ndarray], regions: list[Region], config: Lines3DConfig) -> list[Frame]:
    """Returns each region of (n, 3) local points in its plane with the straight runs of its raster's
    contours as candidate boundary lines (the runs of all regions fitted together: ``regions_lines``)."""
    bases = [plane_basis(region.normal) for region in regions]
    uvs = [(p - region.centroid) @ basis.T for p, region, basis in zip(points, regions, bases, strict=True)]
    rasters = [region_image(uv, region.cell, config) for uv, region in zip(uvs, regions, strict=True)]
    contours = [image_contours(image)[0] for image, _, _ in rasters]
    least = [config.min_length_m / cell for _, _, cell in rasters]
    found = regions_lines([image for image, _, _ in rasters], contours, least, config)
    frames = []
    for basis, uv, (image, lo, cell), lines2d, outline in zip(
        bases, uvs, rasters, found, contours, strict=True
    ):
        uv_lines = (lo + (lines2d.reshape(-1, 2) + 0.5) * cell).reshape(-1, 4)  # pixel centres -> plane
        # the contours (outer and hole) that could hold two parallel edges of the shortest length
        outlines = [
            lo + (c.reshape(-1, 2) + 0.5) * cell for c in outline if len(c) * cell >= 4 * config.min_length_m
        ]
        frames.append(Frame(basis, uv, uv_lines, cell, outlines, image, lo))
    return frames


def to_world(lines: np.ndarray, region: Region, basis: np.ndarray) -> np.ndarray:
    """Returns (k, 6) local 3D segments of (k, 4) lines in a region's plane."""
    return (region.centroid + lines.reshape(-1, 2) @ basis).reshape(-1, 6)


def contour_segments(
    frames: list[Frame],
    regions: list[Region],
    families: tuple[np.ndarray, np.ndarray],
    beside: list[np.ndarray],
    config: Lines3DConfig,
) -> list[np.ndarray]:
    """Returns per planar region (K, 6) segments along its boundary: candidates turned onto the global
    direction ``families`` (``dominant_directions``), moved onto the points; ``beside`` (q, 3) per region:
    the points of no large region beside it (``_beside_points``), which bound the edges of its plane or
    continue it. The regions' lines are moved onto their points together (``refine_regions``)."""
    raws, lines, fixed = [], [], []
    for frame in frames:
        snapped, known = snap_to_families(frame.lines, frame.basis, families, config)
        # the rectangles round the region's points and round its rectangular contours
        box = np.zeros((0, 4))
        if config.rectangles:
            box = np.concatenate(
                [
                    box_lines([frame.uv], frame.basis, families, config, min_fill=0.0),
                    box_lines(frame.outlines, frame.basis, families, config),
                ]
            )
        raws.append(np.concatenate([frame.lines, box]))
        lines.append(np.concatenate([snapped, box]))
        fixed.append(np.r_[known, np.ones(len(box), dtype=bool)])
    bands = [frame.band for frame in frames]
    refined = refine_regions([f.uv for f in frames], lines, bands, config, beside, fixed)
    out = []
    for frame, region, raw, (moved, kept) in zip(frames, regions, raws, refined, strict=True):
        size = float(np.ptp(frame.uv, axis=0).max()) if len(frame.uv) else 0.0
        # judged on the raster's own directions: snapping makes the chords of a ragged outline parallel too
        kept[kept] = has_parallel(raw[kept], size, config)
        out.append(to_world(snap_directions(moved[kept], config.snap_angle_deg), region, frame.basis))
    return out


def _beside_points(
    loose: cKDTree, regions: list[Region], frames: list[Frame], depth_m: float
) -> list[np.ndarray]:
    """Returns per region (q, 3) u, v, signed plane distance of the loose points (a KD-tree) within depth_m
    of the region's plane and a band (2 cells) of its points' bounding box in it.

    One KD-tree query for every region (each region's ball as a query of its own gave the same points,
    for a room's thousand regions at a thousand calls' cost).
    """
    out = [np.zeros((0, 3)) for _ in regions]
    todo = [k for k, f in enumerate(frames) if len(f.uv)] if loose.n else []
    if not todo:
        return out
    lo = np.array([frames[k].uv.min(axis=0) for k in todo])
    hi = np.array([frames[k].uv.max(axis=0) for k in todo])
    band = np.array([frames[k].band for k in todo])
    centres = np.array(
        [regions[k].centroid + 0.5 * (lo[i] + hi[i]) @ frames[k].basis for i, k in enumerate(todo)]
    )
    reaches = np.sqrt(np.sum((0.5 * (hi - lo) + band[:, None]) ** 2, axis=1) + depth_m**2)
    found = loose.query_ball_point(centres, reaches, return_sorted=False, workers=thread_count(8))
    sizes, index = flat_lists(found)
    first = np.r_[0, np.cumsum(sizes)]
    normals = np.array([regions[k].normal for k in todo]).reshape(-1, 3)
    origins = np.array([regions[k].centroid for k in todo]).reshape(-1, 3)
    bases = np.array([frames[k].basis for k in todo]).reshape(-1, 2, 3)
    rows, kept = _beside_rows(loose.data, index, first, origins, normals, bases, lo - band[:, None],
                              hi + band[:, None], depth_m)  # fmt: skip
    ends = np.r_[0, np.cumsum(kept)]
    for i, k in enumerate(todo):
        out[k] = rows[ends[i] : ends[i + 1]]
    return out


@numba.njit(cache=True, nogil=True)
def _beside_rows(
    data: np.ndarray,
    index: np.ndarray,
    first: np.ndarray,
    origin: np.ndarray,
    normal: np.ndarray,
    basis: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    depth_m: float,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((q, 3) u, v, signed plane distance of the points data[index[first[i]:first[i + 1]]]
    within ``depth_m`` of region i's plane (``origin``, ``normal``) whose plane coordinates (``basis``)
    lie in the box lo[i]-hi[i], region after region; (R,) how many of each region)."""
    rows = np.empty((len(index), 3))
    kept = np.zeros(len(first) - 1, dtype=np.int64)
    n = 0
    for i in range(len(first) - 1):
        for m in range(first[i], first[i + 1]):
            q = index[m]
            r0, r1, r2 = data[q, 0] - origin[i, 0], data[q, 1] - origin[i, 1], data[q, 2] - origin[i, 2]
            depth = r0 * normal[i, 0] + r1 * normal[i, 1] + r2 * normal[i, 2]
            if abs(depth) > depth_m:
                continue
            u = r0 * basis[i, 0, 0] + r1 * basis[i, 0, 1] + r2 * basis[i, 0, 2]
            v = r0 * basis[i, 1, 0] + r1 * basis[i, 1, 1] + r2 * basis[i, 1, 2]
            if u < lo[i, 0] or u > hi[i, 0] or v < lo[i, 1] or v > hi[i, 1]:
                continue
            rows[n, 0], rows[n, 1], rows[n, 2] = u, v, depth
            n += 1
            kept[i] += 1
    return rows[:n], kept
