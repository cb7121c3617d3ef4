"""Candidate boundary lines of one planar region: its raster image, the image's contours and their straight
runs (part of ``lines3d.extract``; ``edge_refine`` then moves them onto the points).

Every contour of a region is processed at once: the runs between the vertices of each contour's polygon
(``cv2.approxPolyDP``) are gathered into flat arrays, and their lines are fitted with grouped sums.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..config import Lines3DConfig


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Returns (2, 3) in-plane unit axes; the first follows the world axis most parallel to the plane, so
    facades and floors are rasterised axis-aligned (straight edges become straight pixel rows)."""
    axis = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = axis - normal * (axis @ normal)
    e1 /= np.linalg.norm(e1)
    # normal x e1 written out: np.cross costs more than the rest for one pair (the same products)
    n, e = normal, e1
    return np.array([e1, [n[1] * e[2] - n[2] * e[1], n[2] * e[0] - n[0] * e[2], n[0] * e[1] - n[1] * e[0]]])


def region_image(uv: np.ndarray, cell: float, config: Lines3DConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """Returns ((H, W) uint8 occupancy image, (2,) plane coordinates of pixel (0, 0)'s corner, cell) of
    (n, 2) in-plane points; sampling gaps closed, holes and islands too small to hold an edge removed."""
    extent = np.ptp(uv, axis=0) if len(uv) else np.zeros(2)
    cell = max(cell, float(np.sqrt(np.prod(extent + 4 * cell) / config.max_raster_pixels)))
    lo = uv.min(axis=0) - 2 * cell  # a 2-cell empty border: contours never touch the image edge
    # the extreme points lie on a cell border by construction: a hair inside keeps rounding from deciding
    ij = np.floor((uv - lo) / cell + 1e-6).astype(np.int64)
    image: np.ndarray = np.zeros((int(ij[:, 1].max()) + 3, int(ij[:, 0].max()) + 3), np.uint8)
    image[ij[:, 1], ij[:, 0]] = 255
    image = cv2.morphologyEx(image, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))  # sampling gaps
    # holes and islands smaller than a square of half the shortest edge cannot hold an edge: sampling
    min_area = max((0.5 * config.min_length_m / cell) ** 2, 4.0)
    image = _remove_small(255 - _remove_small(255 - image, min_area), min_area)
    return image, lo, cell


def _remove_small(image: np.ndarray, min_area: float) -> np.ndarray:
    """Returns the (H, W) uint8 binary image without its 8-connected foreground parts below min_area px."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(image, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False  # background
    return np.where(keep[labels], 255, 0).astype(np.uint8)


def image_contours(image: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Returns ((n, 1, 2) int32 pixel contours, outer and hole, of the (H, W) uint8 image, and a (C,) bool
    array telling the holes)."""
    contours, hierarchy = cv2.findContours(image, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    hole = hierarchy.reshape(-1, 4)[:, 3] >= 0 if len(contours) else np.zeros(0, dtype=bool)
    return list(contours), hole


def image_lines(
    image: np.ndarray, contours: list[np.ndarray], min_cells: float, config: Lines3DConfig
) -> np.ndarray:
    """Returns (k, 4) float64 pixel segments x1, y1, x2, y2 fitted to the straight runs of the contours
    of the (H, W) uint8 image; runs shorter than min_cells are dropped."""
    return regions_lines([image], [contours], [min_cells], config)[0]


def regions_lines(
    images: list[np.ndarray], contours: list[list[np.ndarray]], min_cells: list[float], config: Lines3DConfig
) -> list[np.ndarray]:
    """Returns ``image_lines`` of each region's image, contours and min_cells, fitted together: the polygon
    runs are found per contour, the fits and step tests as grouped sums over every region's runs (a room's
    thousand small regions cost more in calls than in sums; each run's sums are the same numbers)."""
    found = [_runs(c, m, config.approx_cells) for c, m in zip(contours, min_cells, strict=True)]
    counts = np.array([len(f[2]) for f in found], dtype=np.int64)
    if counts.sum() == 0:
        return [np.zeros((0, 4)) for _ in images]
    base = np.cumsum([0] + [len(f[0]) for f in found])[:-1]
    pixels = np.concatenate([f[0] for f in found])
    run_start = np.concatenate([f[1] + b for f, b in zip(found, base, strict=True)])
    run_len = np.concatenate([f[2] for f in found])
    region = np.repeat(np.arange(len(images)), counts)
    least = np.asarray(min_cells, dtype=np.float64)[region]
    run = np.repeat(np.arange(len(run_len)), run_len)
    pos = np.arange(len(run)) - np.repeat(np.cumsum(run_len) - run_len, run_len)
    xy = pixels[run_start[run] + pos]  # (sum of run lengths, 2): the runs' pixels one after the other
    first, last = xy[np.cumsum(run_len) - run_len], xy[np.cumsum(run_len) - 1]
    chord = np.linalg.norm(last - first, axis=1)
    # a run much longer than its chord turns a corner: the polygon cut it, it is no edge
    good = (chord >= least) & (run_len <= 1.2 * chord + 2)
    trim = np.maximum(2, run_len // 10)
    trimmed = run_len > 2 * trim + 4  # corners round off: fit on the middle
    core = ~trimmed[run] | ((pos >= trim[run]) & (pos < run_len[run] - trim[run]))
    centre, direction = _fit_lines(xy, run, core, len(run_len))
    ends = np.stack([first, last], axis=1)  # (R, 2, 2)
    along = np.einsum("rek,rk->re", ends - centre[:, None], direction)
    ends = centre[:, None] + along[..., None] * direction[:, None]
    lines, region = ends.reshape(-1, 4)[good], region[good]
    step = _is_step(images, region, lines)
    lines, region = lines[step], region[step]
    bounds = np.searchsorted(region, np.arange(len(images) + 1))
    return [lines[bounds[r] : bounds[r + 1]] for r in range(len(images))]


def _runs(contours, min_cells: float, approx_cells: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((N, 2) float64 pixels of the contours, each contour followed by its first pixels again so
    that a run wrapping round the start is contiguous, (R,) int64 start index of each run, (R,) its
    length in pixels): the runs between consecutive vertices of each contour's approximating polygon."""
    pieces, starts, lengths = [], [], []
    offset = 0
    for contour in contours:
        c = contour.reshape(-1, 2)
        n = len(c)
        if n < max(min_cells, 4):
            continue
        poly = cv2.approxPolyDP(contour, approx_cells, True).reshape(-1, 2)
        idx = _vertex_indices(c, poly)
        nxt = np.roll(idx, -1)
        span = (nxt - idx) % n + 1  # a polygon of one vertex gives one run round the whole contour
        pieces.append(np.concatenate([c, c]))
        starts.append(offset + idx)
        lengths.append(span)
        offset += 2 * n
    if not pieces:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return (
        np.concatenate(pieces).astype(np.float64),
        np.concatenate(starts).astype(np.int64),
        np.concatenate(lengths).astype(np.int64),
    )


def _vertex_indices(contour: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Returns (k,) int64 sorted positions in the (n, 2) contour of the first pixel equal to each vertex."""
    width = int(contour[:, 0].max()) + 1
    keys = contour[:, 1].astype(np.int64) * width + contour[:, 0]
    order = np.argsort(keys, kind="stable")
    pos = np.searchsorted(keys[order], poly[:, 1].astype(np.int64) * width + poly[:, 0])
    return np.unique(order[pos])


def _fit_lines(xy: np.ndarray, group: np.ndarray, use: np.ndarray, num: int) -> tuple[np.ndarray, ...]:
    """Returns ((G, 2) centres, (G, 2) unit directions) of the lines through the ``use`` pixels of each
    group; pixels more than a pixel off the first fit (the start of the next side, when a polygon vertex
    misses a corner) are left out of the second, unless fewer than 3 remain."""
    centre, direction = _principal_axes(xy, group, use, num)
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    close = use & (np.abs(np.einsum("nk,nk->n", xy - centre[group], normal[group])) <= 1.0)
    again = np.bincount(group[close], minlength=num) >= 3
    centre2, direction2 = _principal_axes(xy, group, close & again[group], num)
    return np.where(again[:, None], centre2, centre), np.where(again[:, None], direction2, direction)


def _principal_axes(xy: np.ndarray, group: np.ndarray, use: np.ndarray, num: int) -> tuple[np.ndarray, ...]:
    """Returns ((G, 2) mean, (G, 2) principal direction) of the ``use`` points of each group."""
    g, p = group[use], xy[use]
    count = np.maximum(np.bincount(g, minlength=num), 1)
    centre = np.stack([np.bincount(g, p[:, k], num) for k in range(2)], axis=1) / count[:, None]
    d = p - centre[g]
    sxx, syy, sxy = (np.bincount(g, w, num) for w in (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]))
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # principal axis of the 2 x 2 scatter
    return centre, np.stack([np.cos(angle), np.sin(angle)], axis=1)


def _is_step(images: list[np.ndarray], region: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Returns (k,) bool: is the raster of its ``region`` (k,) filled on one side of each pixel segment and
    empty on the other, all along it (a polygon side cutting a rounded corner or crossing a ragged patch
    is not an edge)?"""
    a, b = lines[:, :2], lines[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / np.maximum(length, 1e-12)[:, None]
    m = np.stack([-d[:, 1], d[:, 0]], axis=1)
    count = np.maximum(np.ceil(length - 2.0), 0).astype(np.int64)  # samples at 1, 2, ... < length - 1
    line = np.repeat(np.arange(len(lines)), count)
    step = np.arange(len(line)) - np.repeat(np.cumsum(count) - count, count) + 1.0
    along = a[line] + step[:, None] * d[line]
    # every region's raster in one flat array
    shape = np.array([im.shape for im in images], dtype=np.int64).reshape(-1, 2)
    start = np.r_[0, np.cumsum(shape[:, 0] * shape[:, 1])][:-1]
    flat = np.concatenate([im.ravel() for im in images]) if images else np.zeros(0, np.uint8)
    owner = region[line]
    top = np.stack([shape[owner, 1] - 1, shape[owner, 0] - 1], axis=1)
    filled = []
    for side in (-1.5, 1.5):
        xy = np.rint(along + side * m[line]).astype(np.int64)
        xy = np.clip(xy, 0, top)
        hits = np.bincount(line, flat[start[owner] + xy[:, 1] * shape[owner, 1] + xy[:, 0]] > 0, len(lines))
        filled.append(hits / np.maximum(count, 1))
    high, low = np.maximum(*filled), np.minimum(*filled)
    return (count > 0) & (high >= 0.75) & (low <= 0.25)
