"""3D line segments of an unorganised point cloud, in the spirit of Lu et al. 2019 ("Fast 3D line segment
detection from unorganized point cloud"), the extractor the paper uses (section IV-A).

Steps: shift to a local frame -> planar regions (``planes.segment_planes``) -> each region rasterised in its
own plane, its contours traced and cut into straight runs -> intersection lines where two planes meet at a
crease, clipped to where both regions reach it -> collinear pieces merged -> back to the input frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from .config import Lines3DConfig
from .contours import image_lines, plane_basis, region_image
from .creases import crease_segments
from .edge_refine import refine_edges
from .errors import InvalidInputError
from .planes import Planes, segment_planes, voxel_downsample

logger = logging.getLogger(__name__)

_CELL_SPACINGS = 1.5  # automatic raster cell, in point spacings: fewer empty cells inside a region
_LONE_FRACTION = 0.25  # a line off its region's dominant directions is kept if this long (of its size)
_DOMINANT_SHARE = 0.15  # a dominant direction holds this share of a region's line length


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
    if len(planes.counts) == 0:
        return np.zeros((0, 6))
    # raster cells follow each region's own density (a scanner's falls with range)
    cells = (
        np.full(len(planes.counts), config.cell_m) if config.cell_m > 0 else _CELL_SPACINGS * planes.spacing_m
    )
    cells = np.maximum(cells, 1e-3)
    order = np.argsort(planes.labels, kind="stable")
    bounds = np.searchsorted(planes.labels[order], np.arange(len(planes.counts) + 1))
    members = [order[bounds[r] : bounds[r + 1]] for r in range(len(planes.counts))]
    # small patches (clutter) give fragments, not edges: about count * spacing^2 of surface each
    large = planes.counts * planes.spacing_m**2 >= config.min_region_area_m2
    creases = crease_segments(points, planes, members, large, cells, config)
    contours, near_m = [np.zeros((0, 6))], [np.zeros(0)]
    for r in np.flatnonzero(large):
        found = contour_segments(points[members[r]], planes.normals[r], planes.centroids[r], cells[r], config)
        contours.append(found)
        near_m.append(np.full(len(found), 2.0 * cells[r]))
    contour = drop_near(np.concatenate(contours), creases, np.concatenate(near_m), 10.0)
    segments = np.concatenate([creases, contour])
    # creases are exact plane intersections: they win over the (rasterised) contour along the same line
    priority = np.r_[np.zeros(len(creases)), np.ones(len(contour))]
    merged = merge_collinear(segments, priority, config)
    logger.debug("%d crease + %d contour segments -> %d merged", len(creases), len(contour), len(merged))
    return merged


def check_points(points: object) -> np.ndarray:
    """Returns (P, 3) float64 finite points, or raises InvalidInputError naming the problem."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (P, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InvalidInputError("points must be finite (no NaN or inf)")
    return arr


def drop_near(
    segments: np.ndarray, reference: np.ndarray, distance: np.ndarray, angle_deg: float
) -> np.ndarray:
    """Returns the (k, 6) segments that do not run along a reference segment (within (k,) ``distance``
    and angle_deg): a region's contour along a crease is the crease's intersection line, only less exact."""
    if len(segments) == 0 or len(reference) == 0:
        return segments
    distance = np.asarray(distance)[:, None]
    r0, r1 = reference[:, :3], reference[:, 3:]
    rlen = np.linalg.norm(r1 - r0, axis=1)
    rdir = (r1 - r0) / rlen[:, None]
    near = np.ones((len(segments), len(reference)), dtype=bool)
    for end in (segments[:, :3], segments[:, 3:]):  # both endpoints within distance of the reference
        t = np.clip(np.einsum("srj,rj->sr", end[:, None] - r0[None], rdir), -distance, rlen + distance)
        near &= np.linalg.norm(end[:, None] - r0[None] - t[..., None] * rdir[None], axis=2) <= distance
    sdir = segments[:, 3:] - segments[:, :3]
    sdir /= np.linalg.norm(sdir, axis=1, keepdims=True)
    near &= np.abs(sdir @ rdir.T) >= np.cos(np.radians(angle_deg))
    return segments[~near.any(axis=1)]


def contour_segments(
    points: np.ndarray, normal: np.ndarray, centroid: np.ndarray, cell: float, config: Lines3DConfig
) -> np.ndarray:
    """Returns (K, 6) segments along the boundary of one planar region of (n, 3) local points."""
    basis = plane_basis(normal)
    uv = (points - centroid) @ basis.T
    image, lo, cell = region_image(uv, cell, config)
    lines2d = image_lines(image, config.min_length_m / cell, config)
    uv_lines = (lo + (lines2d.reshape(-1, 2) + 0.5) * cell).reshape(-1, 4)  # pixel centres -> plane
    uv_lines = refine_edges(uv, uv_lines, 2.0 * cell)
    size = float(np.ptp(uv, axis=0).max()) if len(uv) else 0.0
    uv_lines = snap_directions(uv_lines[_has_parallel(uv_lines, size, config)], config.snap_angle_deg)
    xyz = centroid + uv_lines.reshape(-1, 2) @ basis
    return xyz.reshape(-1, 6)


def _has_parallel(lines: np.ndarray, size: float, config: Lines3DConfig) -> np.ndarray:
    """Returns (k,) bool: lines of one region that follow one of its dominant directions, i.e. whose
    direction (within snap_angle_deg) other lines share with at least their own length and with
    _DOMINANT_SHARE of the region's whole line length, or that are long (_LONE_FRACTION of the region's
    ``size``, its longer side).

    Man-made boundaries come in a few parallel families (both sides of a window, ledge, facade), while a
    ragged boundary (clutter, a scanner's occlusion shadow, the edge of its sampling pattern on the
    ground) is cut into chords in every direction, each family holding a small share.
    """
    if len(lines) == 0:
        return np.zeros(0, dtype=bool)
    d = lines[:, 2:] - lines[:, :2]
    length = np.linalg.norm(d, axis=1)
    theta = np.arctan2(d[:, 1], d[:, 0])
    diff = np.abs((theta[:, None] - theta[None, :] + 0.5 * np.pi) % np.pi - 0.5 * np.pi)
    family = (diff <= np.radians(max(config.snap_angle_deg, 1.0))) @ length  # includes the line itself
    dominant = (family >= 2.0 * length) & (family >= _DOMINANT_SHARE * length.sum())
    return dominant | (length >= _LONE_FRACTION * size)


def snap_directions(lines: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """Returns (k, 4) 2D lines of one region turned about their midpoints onto the region's dominant
    directions: lines within max_angle_deg of the longest free line share its direction, averaged with
    weights length^2 (a facade's long outline fixes the direction of its short window edges)."""
    if max_angle_deg <= 0 or len(lines) < 2:
        return lines
    d = lines[:, 2:] - lines[:, :2]
    length = np.linalg.norm(d, axis=1)
    theta = np.arctan2(d[:, 1], d[:, 0])
    free = np.ones(len(lines), dtype=bool)
    out = lines.copy()
    for seed in np.argsort(-length, kind="stable"):
        if not free[seed]:
            continue
        diff = np.abs((theta - theta[seed] + 0.5 * np.pi) % np.pi - 0.5 * np.pi)  # undirected angle
        members = np.flatnonzero(free & (diff <= np.radians(max_angle_deg)))
        free[members] = False
        # mean of undirected angles: average the doubled angles
        w = length[members] ** 2
        mean = 0.5 * np.arctan2(
            (w * np.sin(2 * theta[members])).sum(), (w * np.cos(2 * theta[members])).sum()
        )
        direction = np.array([np.cos(mean), np.sin(mean)])
        sign = np.sign(d[members] @ direction)[:, None]
        mid = 0.5 * (lines[members, :2] + lines[members, 2:])
        half = 0.5 * length[members, None] * sign * direction
        out[members] = np.concatenate([mid - half, mid + half], axis=1)
    return out


def merge_collinear(segments: np.ndarray, priority: np.ndarray, config: Lines3DConfig) -> np.ndarray:
    """Returns (K, 6) segments with collinear, overlapping or nearly touching pieces merged into one.

    Seeds go by (priority, longest first); a seed keeps its own line and grows to cover the extent of
    every segment within collinear_angle_deg, collinear_distance_m of it and collinear_gap_m along it.
    """
    if len(segments) == 0:
        return np.zeros((0, 6))
    p, q = segments[:, :3], segments[:, 3:]
    lengths = np.linalg.norm(q - p, axis=1)
    keep = lengths > 1e-9
    p, q, lengths, priority = p[keep], q[keep], lengths[keep], priority[keep]
    dirs = (q - p) / lengths[:, None]
    cos_thr = np.cos(np.radians(config.collinear_angle_deg))
    free = np.ones(len(p), dtype=bool)
    out = []
    for i in np.lexsort((-lengths, priority)):
        if not free[i]:
            continue
        free[i] = False
        t0, t1 = 0.0, lengths[i]
        cand = np.flatnonzero(free & (np.abs(dirs @ dirs[i]) >= cos_thr))
        tp, tq = (p[cand] - p[i]) @ dirs[i], (q[cand] - p[i]) @ dirs[i]
        dp = np.linalg.norm(p[cand] - p[i] - np.outer(tp, dirs[i]), axis=1)
        dq = np.linalg.norm(q[cand] - p[i] - np.outer(tq, dirs[i]), axis=1)
        close = (dp <= config.collinear_distance_m) & (dq <= config.collinear_distance_m)
        cand, lo, hi = cand[close], np.minimum(tp, tq)[close], np.maximum(tp, tq)[close]
        grew = True
        while grew:  # absorbing a piece may bring the next one within the gap
            take = free[cand] & (lo <= t1 + config.collinear_gap_m) & (hi >= t0 - config.collinear_gap_m)
            grew = bool(take.any())
            if grew:
                t0, t1 = min(t0, lo[take].min()), max(t1, hi[take].max())
                free[cand[take]] = False
        if t1 - t0 >= config.min_length_m:
            out.append(np.r_[p[i] + t0 * dirs[i], p[i] + t1 * dirs[i]])
    return np.array(out).reshape(-1, 6)
