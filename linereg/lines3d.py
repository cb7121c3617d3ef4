"""3D line segments of an unorganised point cloud, in the spirit of Lu et al. 2019 ("Fast 3D line segment
detection from unorganized point cloud"), the extractor the paper uses (section IV-A).

Steps: shift to a local frame -> planar regions (``planes.segment_planes``) -> each region rasterised in its
own plane, its contours traced and cut into straight runs -> intersection lines where two planes meet at a
crease, clipped to where both regions reach it -> collinear pieces merged -> back to the input frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .config import Lines3DConfig
from .creases import crease_segments
from .errors import InvalidInputError
from .planes import Planes, segment_planes, voxel_downsample

logger = logging.getLogger(__name__)

_MAX_TILT = np.tan(np.radians(10.0))  # the most a boundary line's angle is corrected from the points
_CELL_SPACINGS = 1.5  # automatic raster cell, in point spacings: fewer empty cells inside a region
_LONE_FRACTION = 0.25  # a line off its region's dominant directions is kept if this long (of its size)
_DOMINANT_SHARE = 0.15  # a dominant direction holds this share of a region's line length
_MAX_RASTER_PIXELS = 40_000_000  # a region's raster is coarsened beyond this (a 6 km^2 plane at 1 cm...)


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


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Returns (2, 3) in-plane unit axes; the first follows the world axis most parallel to the plane, so
    facades and floors are rasterised axis-aligned (straight edges become straight pixel rows)."""
    axis = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = axis - normal * (axis @ normal)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(normal, e1)])


def contour_segments(
    points: np.ndarray, normal: np.ndarray, centroid: np.ndarray, cell: float, config: Lines3DConfig
) -> np.ndarray:
    """Returns (K, 6) segments along the boundary of one planar region of (n, 3) local points."""
    basis = plane_basis(normal)
    uv = (points - centroid) @ basis.T
    extent = np.ptp(uv, axis=0) if len(uv) else np.zeros(2)
    cell = max(cell, float(np.sqrt(np.prod(extent + 4 * cell) / _MAX_RASTER_PIXELS)))
    lo = uv.min(axis=0) - 2 * cell  # a 2-cell empty border: contours never touch the image edge
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    image: np.ndarray = np.zeros((int(ij[:, 1].max()) + 3, int(ij[:, 0].max()) + 3), np.uint8)
    image[ij[:, 1], ij[:, 0]] = 255
    image = cv2.morphologyEx(image, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))  # sampling gaps
    # holes and islands smaller than a square of half the shortest edge cannot hold an edge: sampling
    min_area = max((0.5 * config.min_length_m / cell) ** 2, 4.0)
    image = _remove_small(255 - _remove_small(255 - image, min_area), min_area)
    contours, _ = cv2.findContours(image, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    min_cells = config.min_length_m / cell
    lines2d = [
        _straight_runs(c.reshape(-1, 2).astype(np.float64), image, min_cells, config) for c in contours
    ]
    lines2d_all = np.concatenate([np.zeros((0, 4)), *lines2d])
    uv_lines = (lo + (lines2d_all.reshape(-1, 2) + 0.5) * cell).reshape(-1, 4)  # pixel centres -> plane
    uv_lines = refine_edges(uv, uv_lines, 2.0 * cell)
    uv_lines = snap_directions(
        uv_lines[_has_parallel(uv_lines, float(extent.max()), config)], config.snap_angle_deg
    )
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


def refine_edges(uv: np.ndarray, lines: np.ndarray, band: float) -> np.ndarray:
    """Returns (k', 4) boundary lines moved from the raster (cell-quantised) to where the points end.

    Along the line, bins of ``band`` length: the outermost of n points spread uniformly over
    [-band, e] lies on average (e + band) / (n + 1) inside the edge e, so e = o_max + (o_max + band) / n
    per bin; a least-squares line through the bins' e gives offset and angle. Lines this would tilt by
    more than 10 degrees, or with most bins off the fitted edge, are dropped. uv: (n, 2) region points in plane coordinates; lines: (k, 4).
    """
    if len(lines) == 0:
        return lines
    tree = cKDTree(uv)
    out = lines.copy()
    keep_line = np.ones(len(lines), dtype=bool)
    for k, (a, b) in enumerate(lines.reshape(-1, 2, 2)):
        length = np.linalg.norm(b - a)
        d = (b - a) / length
        m = np.array([-d[1], d[0]])
        samples = a + np.outer(np.arange(0.0, length + band, band), d)
        near = tree.query_ball_point(samples, 1.5 * band)
        idx = np.unique(np.concatenate([np.zeros(0, np.int64), *near]).astype(np.int64))
        t, s = (uv[idx] - a) @ d, (uv[idx] - a) @ m
        keep = (np.abs(s) <= band) & (t >= 0.5 * band) & (t <= length - 0.5 * band)
        t, s = t[keep], s[keep]
        # no points along most of it: the raster's closing bridged a gap, no boundary of the surface
        if len(s) < 10 or np.ptp(t) < 0.5 * length:
            keep_line[k] = False
            continue
        outward = -np.sign(s.mean())  # the points lie on the inner side
        fit = _edge_line(t, outward * s, band)
        if fit is None:
            keep_line[k] = False
            continue
        if fit[2] < 0.5 * (length - band) / band:  # most of the line has no straight edge behind it
            keep_line[k] = False
            continue
        e_a, e_b = np.clip(fit[1] + fit[0] * np.array([0.0, length]), -band, band)
        if abs(e_b - e_a) > length * _MAX_TILT:  # not one straight edge
            keep_line[k] = False
            continue
        out[k] = np.r_[a + outward * e_a * m, b + outward * e_b * m]
    return out[keep_line]


def _remove_small(image: np.ndarray, min_area: float) -> np.ndarray:
    """Returns the (H, W) uint8 binary image without its 8-connected foreground parts below min_area px."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(image, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False  # background
    return np.where(keep[labels], 255, 0).astype(np.uint8)


def _edge_line(t: np.ndarray, o: np.ndarray, band: float) -> tuple[float, float, int] | None:
    """Returns (slope, intercept, bins on it) of the edge e(t) behind points at (t, outward offset o):
    bins on it are the band-long stretches whose edge estimate lies within band / 2 of the line."""
    bins = np.floor((t - t.min()) / band).astype(np.int64)
    count = np.bincount(bins)
    top = np.full(len(count), -np.inf)
    np.maximum.at(top, bins, o)
    ok = count >= 6  # the maximum of fewer points says little
    if ok.sum() < 2:
        return None
    centre = np.bincount(bins, t)[ok] / count[ok]
    edge = top[ok] + (top[ok] + band) / count[ok]
    weight = np.sqrt(count[ok])
    slope, intercept = np.polyfit(centre, edge, 1, w=weight)
    residual = np.abs(edge - (slope * centre + intercept))
    inliers = residual <= max(2.5 * np.median(residual), 1e-9)
    if 2 <= inliers.sum() < len(edge):  # a bin reaching into a neighbouring structure
        slope, intercept = np.polyfit(centre[inliers], edge[inliers], 1, w=weight[inliers])
    on_line = int((np.abs(edge - (slope * centre + intercept)) <= 0.5 * band).sum())
    return float(slope), float(intercept), on_line


def _straight_runs(
    contour: np.ndarray, image: np.ndarray, min_cells: float, config: Lines3DConfig
) -> np.ndarray:
    """Returns (k, 4) pixel segments fitted to the straight runs of one closed (n, 2) pixel contour."""
    if len(contour) < max(min_cells, 4):
        return np.zeros((0, 4))
    poly = cv2.approxPolyDP(contour.astype(np.int32)[:, None, :], config.approx_cells, True).reshape(-1, 2)
    vertex_idx = _vertex_indices(contour, poly)
    out = []
    n = len(contour)
    for a, b in zip(vertex_idx, np.roll(vertex_idx, -1), strict=True):
        run = contour[np.arange(a, a + (b - a) % n + 1) % n]
        chord = np.linalg.norm(run[-1] - run[0])
        # a run much longer than its chord turns a corner: the polygon cut it, it is no edge
        if chord < min_cells or len(run) > 1.2 * chord + 2:
            continue
        trim = max(2, len(run) // 10)
        core = run[trim:-trim] if len(run) > 2 * trim + 4 else run  # corners round off: fit on the middle
        centre, direction = _fit_line(core)
        ends = centre + np.outer((run[[0, -1]] - centre) @ direction, direction)
        if _is_step(image, ends[0], ends[1]):
            out.append(ends.ravel())
    return np.array(out).reshape(-1, 4)


def _fit_line(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (centre (2,), unit direction (2,)) of the line through (n, 2) pixels; pixels more than a
    pixel off the first fit (the start of the next side, when a polygon vertex misses a corner) are
    left out of the second."""
    keep = np.ones(len(xy), dtype=bool)
    for _ in range(2):
        centre = xy[keep].mean(axis=0)
        d = xy[keep] - centre
        sxx, syy, sxy = (d[:, 0] ** 2).sum(), (d[:, 1] ** 2).sum(), (d[:, 0] * d[:, 1]).sum()
        angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # principal axis of the 2 x 2 scatter
        direction = np.array([np.cos(angle), np.sin(angle)])
        residual = np.abs((xy - centre) @ np.array([-direction[1], direction[0]]))
        if (residual <= 1.0).sum() < 3:
            break
        keep = residual <= 1.0
    return centre, direction


def _is_step(image: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Returns whether the raster is filled on one side of pixel segment a-b and empty on the other, all
    along it (a polygon side cutting a rounded corner or crossing a ragged patch is not an edge)."""
    d = (b - a) / np.linalg.norm(b - a)
    m = np.array([-d[1], d[0]])
    along = a + np.outer(np.arange(1.0, np.linalg.norm(b - a) - 1.0), d)
    filled = []
    for side in (-1.5, 1.5):
        xy = np.rint(along + side * m).astype(np.int64)
        xy = np.clip(xy, 0, [image.shape[1] - 1, image.shape[0] - 1])
        filled.append(np.mean(image[xy[:, 1], xy[:, 0]] > 0) if len(xy) else 0.0)
    return bool(max(filled) >= 0.75 and min(filled) <= 0.25)


def _vertex_indices(contour: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Returns (k,) int64 positions in the contour of the polygon's vertices, in contour order."""
    match = (contour[:, None, :] == poly[None, :, :]).all(axis=2)  # (n, k)
    idx = [int(np.argmax(match[:, j])) for j in range(len(poly))]
    return np.unique(idx)


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
