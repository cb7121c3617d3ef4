"""Edges of an evenly sampled cloud found per point: where the surface bends or ends, grouped into lines
along the scene's directions (part of ``build.extract_map``; kind ``kinds.POINT_EDGE``).

The planar regions of ``lines3d`` need a face of some 0.03-0.1 m^2 before it gives an edge. A dense RGB-D
room holds most of what a photo shows in smaller structure (a chair's rail, a shelf's lip, a cabinet's
door): no region, no line. Here every point is judged on its own neighbourhood instead:

1. Its normal (PCA of its ``neighbours``) is compared with those of its ``compare_neighbours``: when
   ``bend_share`` of them are ``crease_deg`` away, the surface bends there (a band of points either side
   of a crease; one turned neighbour is noise); the neighbours' centroid shifted ``boundary_shift`` of
   their radius to one side in the tangent plane marks an end (a boundary).
2. For each direction given (``build`` gives the scene's frame: a room's floor and walls), the edge
   points are projected along it: a line of that direction is a pile in the 2D projection (its points
   fall on one spot), found as a peak of the smoothed 2D histogram. Points within ``width_spacings`` of
   a pile's centre belong to it and split into runs where ``gap_spacings`` hold no point; a run of
   ``min_length_m`` holding ``fill`` points per spacing is a segment through the pile's centre.
3. A run whose cross-section is one flat sheet centred on it (noise, or a fused cloud's layers a few cm
   apart, piled up inside a wall or a floor) lies inside a surface and is dropped: a crease's
   cross-section is an L, a boundary's a half sheet.

Measured on the shared RGB-D rooms (``linereg bench lines3d --real``, docs/measurements.md, session 21).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numba
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..config import PointEdgesConfig
from ..kernels import jacobi_rotation
from ..threads import thread_count
from .neighbours import flat_lists

__all__ = ["EdgePoints", "edge_points", "find_edge_points", "point_edges"]

MIN_SECTION_POINTS = 10  # a cross-section of fewer points has no shape to judge
BLOCK_POINTS = 4096  # the fewest points of a block of neighbour fits (one thread's share of the work)


class EdgePoints(NamedTuple):
    """A cloud's points where the surface bends or ends (``find_edge_points``): the (E, 3) ``edge`` points
    and the KD-tree of all the points (None: too few points to judge)."""

    edge: np.ndarray
    tree: cKDTree | None


def find_edge_points(points: np.ndarray, config: PointEdgesConfig | None = None) -> EdgePoints:
    """Returns the EdgePoints of (P, 3) points (``edge_points``): the first step of ``point_edges``, which
    needs no directions (map building starts it before the planes that give them)."""
    config = config or PointEdgesConfig()
    if len(points) < config.neighbours + 1:
        return EdgePoints(np.zeros((0, 3)), None)
    tree = cKDTree(points)
    return EdgePoints(points[edge_points(points, tree, config)], tree)


def point_edges(
    points: np.ndarray,
    directions: np.ndarray,
    spacing_m: float,
    noise_m: float,
    min_length_m: float,
    config: PointEdgesConfig | None = None,
    found: EdgePoints | None = None,
) -> np.ndarray:
    """Returns (K, 6) float64 segments along the (D, 3) unit ``directions`` where the surface of the
    (P, 3) ``points`` (evenly sampled ``spacing_m`` apart, ``noise_m`` noise) bends or ends, at least
    ``min_length_m`` long; ``found``: their ``find_edge_points``, if already known."""
    config = config or PointEdgesConfig()
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(points) < config.neighbours + 1 or len(directions) == 0 or spacing_m <= 0:
        return np.zeros((0, 6))
    edge, tree = found if found is not None else find_edge_points(points, config)
    if len(edge) == 0 or tree is None:
        return np.zeros((0, 6))
    runs = [_runs_along(edge, d, spacing_m, min_length_m, config) for d in _distinct(directions, config)]
    segments = np.concatenate(runs) if runs else np.zeros((0, 6))
    if len(segments):
        segments = segments[~_flat(segments, points, tree, spacing_m, noise_m, config)]
    return segments


def edge_points(points: np.ndarray, tree: cKDTree, config: PointEdgesConfig) -> np.ndarray:
    """Returns (P,) bool: does the surface bend (``bend_share`` of the compared neighbours' normals
    ``crease_deg`` away) or end (the neighbours' centroid ``boundary_shift`` of their radius to one side)
    at each point?"""
    normal = np.zeros_like(points)
    shift = np.zeros(len(points))
    k = config.neighbours
    compare = min(config.compare_neighbours, k)
    near = np.zeros((len(points), compare), dtype=np.int64)
    threads = thread_count(8)
    # blocks of at most config.chunk points on the threads: the neighbour searches and the compiled fits
    # release the GIL, and every point's numbers are the same in any block. Four blocks a thread: a
    # thread held up (another process on the core) leaves its work to the others
    size = max(1, min(config.chunk, max(BLOCK_POINTS, -(-len(points) // (4 * threads)))))
    blocks = [slice(lo, lo + size) for lo in range(0, len(points), size)]

    def fit(block: slice) -> None:
        dist, nb = tree.query(points[block], k=k)
        _fit_normals(points, block.start, nb, dist[:, -1], normal, shift)
        near[block] = nb[:, :compare]

    bends = np.zeros(len(points), dtype=bool)
    least = int(np.ceil(config.bend_share * compare - 1e-9))  # of the compared normals turned

    def bend(block: slice) -> None:
        _bends(normal, near, block.start, min(block.stop, len(points)), np.cos(np.radians(config.crease_deg)),
               least, bends)  # fmt: skip

    with ThreadPoolExecutor(max_workers=threads) as pool:
        list(pool.map(fit, blocks))
        list(pool.map(bend, blocks))
    return bends | (shift > config.boundary_shift)


@numba.njit(cache=True, nogil=True)
def _fit_normals(
    points: np.ndarray, start: int, nb: np.ndarray, radius: np.ndarray, normal: np.ndarray, shift: np.ndarray
) -> None:  # pragma: no cover - numba
    """Fills ``normal[start + i]`` (the unit normal: the least-spread axis of the (n, k) neighbours ``nb[i]``
    of point start + i) and ``shift[start + i]`` (their centroid's offset from the point in its tangent
    plane, as a share of ``radius[i]``, the farthest neighbour's distance)."""
    k = nb.shape[1]
    cov = np.empty((3, 3))
    for i in range(nb.shape[0]):
        c0 = c1 = c2 = 0.0
        for j in range(k):
            q = nb[i, j]
            c0 += points[q, 0]
            c1 += points[q, 1]
            c2 += points[q, 2]
        c0 /= k
        c1 /= k
        c2 /= k
        for e in range(9):
            cov[e // 3, e % 3] = 0.0
        for j in range(k):
            q = nb[i, j]
            d0, d1, d2 = points[q, 0] - c0, points[q, 1] - c1, points[q, 2] - c2
            cov[0, 0] += d0 * d0
            cov[0, 1] += d0 * d1
            cov[0, 2] += d0 * d2
            cov[1, 1] += d1 * d1
            cov[1, 2] += d1 * d2
            cov[2, 2] += d2 * d2
        n0, n1, n2 = _least_axis(cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2])
        p = start + i
        o0, o1, o2 = c0 - points[p, 0], c1 - points[p, 1], c2 - points[p, 2]
        along = o0 * n0 + o1 * n1 + o2 * n2
        o0, o1, o2 = o0 - along * n0, o1 - along * n1, o2 - along * n2
        normal[p, 0], normal[p, 1], normal[p, 2] = n0, n1, n2
        shift[p] = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2) / max(radius[i], 1e-12)


@numba.njit(cache=True, nogil=True)
def _least_axis(
    a00: float, a01: float, a02: float, a11: float, a12: float, a22: float
) -> tuple[float, float, float]:  # pragma: no cover - numba
    """Returns the unit eigenvector of the smallest eigenvalue of the symmetric 3 x 3 matrix (cyclic Jacobi
    rotations until the off-diagonal is below 1e-15 of the trace: a few sweeps)."""
    a = np.empty((3, 3))
    a[0, 0], a[0, 1], a[0, 2] = a00, a01, a02
    a[1, 0], a[1, 1], a[1, 2] = a01, a11, a12
    a[2, 0], a[2, 1], a[2, 2] = a02, a12, a22
    v = np.zeros((3, 3))
    v[0, 0] = v[1, 1] = v[2, 2] = 1.0
    scale = abs(a00) + abs(a11) + abs(a22) + 1e-300
    for _ in range(32):
        if abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2]) <= 1e-15 * scale:
            break
        for pair in range(3):
            p = 0 if pair < 2 else 1
            q = 1 if pair == 0 else 2
            jacobi_rotation(a, v, p, q)
    m = 0
    if a[1, 1] < a[m, m]:
        m = 1
    if a[2, 2] < a[m, m]:
        m = 2
    return v[0, m], v[1, m], v[2, m]


@numba.njit(cache=True, nogil=True)
def _bends(
    normal: np.ndarray, near: np.ndarray, lo: int, hi: int, cos: float, least: int, out: np.ndarray
) -> None:  # pragma: no cover - numba
    """Sets ``out[p]`` for p in [lo, hi): are at least ``least`` of the normals of p's ``near`` points more
    than arccos(``cos``) from p's own (either sign)?"""
    for p in range(lo, hi):
        turned = 0
        for j in range(near.shape[1]):
            q = near[p, j]
            dot = normal[p, 0] * normal[q, 0] + normal[p, 1] * normal[q, 1] + normal[p, 2] * normal[q, 2]
            if abs(dot) < cos:
                turned += 1
        out[p] = turned >= least


def _distinct(directions: np.ndarray, config: PointEdgesConfig) -> list[np.ndarray]:
    """Returns the unit directions with near-duplicates (``direction_deg``) left out."""
    kept: list[np.ndarray] = []
    cos = np.cos(np.radians(config.direction_deg))
    for d in directions / np.linalg.norm(directions, axis=1, keepdims=True):
        if all(abs(d @ k) < cos for k in kept):
            kept.append(d)
    return kept


def _runs_along(
    edge: np.ndarray, d: np.ndarray, spacing: float, min_length: float, config: PointEdgesConfig
) -> np.ndarray:
    """Returns (k, 6) segments along unit ``d`` where the (E, 3) edge points pile up in projection."""
    a = np.cross(d, np.eye(3)[np.argmin(np.abs(d))])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    uv = np.c_[edge @ a, edge @ b]
    t = edge @ d
    lo = uv.min(axis=0) - 2 * spacing
    ij = np.floor((uv - lo) / spacing).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 3)
    # counts of whole points: a bincount adds the same ones as np.add.at, many times faster
    hist = np.bincount(ij[:, 0] * shape[1] + ij[:, 1], minlength=shape[0] * shape[1]).reshape(shape)
    hist = hist.astype(np.float64)
    sigma = config.smooth_cells
    smooth = ndimage.gaussian_filter(hist, sigma)
    # a pile of a segment min_length long: fill x min_length / spacing points, 1 / (2 pi sigma^2) of them
    # in the smoothed peak cell
    least = config.fill * min_length / spacing / (2 * np.pi * sigma**2)
    peaks = np.argwhere(
        (smooth == ndimage.maximum_filter(smooth, size=2 * config.peak_cells + 1)) & (smooth >= least)
    )
    if len(peaks) == 0:
        return np.zeros((0, 6))
    centres = lo + (peaks + 0.5) * spacing
    label = np.full(shape, -1, dtype=np.int64)
    label[peaks[:, 0], peaks[:, 1]] = np.arange(len(peaks))
    pile = _nearest_pile(uv, ij, label, lo, spacing, config.width_spacings * spacing)
    on = pile >= 0
    uv, t, pile = uv[on], t[on], pile[on]
    if len(t) == 0:
        return np.zeros((0, 6))
    count = np.bincount(pile, minlength=len(centres)).astype(np.float64)
    sums = np.stack([np.bincount(pile, uv[:, k], len(centres)) for k in range(2)], axis=1)
    centre = sums / np.maximum(count, 1.0)[:, None]
    order = np.lexsort((t, pile))
    pile, t = pile[order], t[order]
    new_run = np.r_[True, (pile[1:] != pile[:-1]) | (np.diff(t) > config.gap_spacings * spacing)]
    starts = np.flatnonzero(new_run)
    ends = np.r_[starts[1:], len(t)] - 1
    length = t[ends] - t[starts]
    keep = (length >= min_length) & (ends - starts + 1 >= config.fill * length / spacing)
    starts, ends = starts[keep], ends[keep]
    base = centre[pile[starts]] @ np.stack([a, b])
    return np.concatenate([base + t[starts, None] * d, base + t[ends, None] * d], axis=1)


def _flat(
    segments: np.ndarray,
    points: np.ndarray,
    tree: cKDTree,
    spacing: float,
    noise: float,
    config: PointEdgesConfig,
) -> np.ndarray:
    """Returns (K,) bool: is each segment's cross-section (the points within ``section_spacings`` of it)
    one flat sheet centred on it (thinner than ``flat_noises`` x noise, half a spacing or ``flat_aspect``
    x its width; its centroid within ``centred_share`` of the radius), or too sparse to judge (fewer than
    MIN_SECTION_POINTS)? A crease's cross-section is an L, a boundary's a half sheet: neither is centred."""
    radius = config.section_spacings * spacing
    p0, p1 = segments[:, :3], segments[:, 3:]
    length = np.linalg.norm(p1 - p0, axis=1)
    d = (p1 - p0) / length[:, None]
    # the segment's cylinder in slices at most a radius long, each inside the ball round its middle
    count = np.ceil(length / radius).astype(np.int64)
    seg = np.repeat(np.arange(len(segments)), count)
    step = length[seg] / count[seg]
    mid = (np.arange(len(seg)) - np.repeat(np.cumsum(count) - count, count) + 0.5) * step
    near = tree.query_ball_point(
        p0[seg] + mid[:, None] * d[seg], np.hypot(radius, 0.5 * step), workers=thread_count(8)
    )
    sizes, idx = flat_lists(near)
    # each point counts in its own slice only (the balls overlap)
    n, sums, second = _section_moments(points, idx, np.r_[0, np.cumsum(sizes)], seg, p0, d, mid, step, radius)
    mean = sums / np.maximum(n, 1.0)[:, None]
    cov = second / np.maximum(n, 1.0)[:, None, None] - np.einsum("ni,nj->nij", mean, mean)
    # the cross-section lies across d: its covariance has a zero eigenvalue along d, then thickness, width
    values = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0.0))
    thickness, width = values[:, 1], values[:, 2]
    # a fused cloud's layers (a few cm apart) make a sheet thicker than its noise, not than its width
    flat = (thickness < max(config.flat_noises * noise, 0.5 * spacing)) | (
        thickness < config.flat_aspect * width
    )
    centred = np.linalg.norm(mean, axis=1) < config.centred_share * radius
    return (n < MIN_SECTION_POINTS) | (flat & centred)


@numba.njit(cache=True, nogil=True)
def _nearest_pile(
    uv: np.ndarray, ij: np.ndarray, label: np.ndarray, lo: np.ndarray, spacing: float, width: float
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (E,) the pile (``label`` of its raster cell, -1: none) whose centre (the cell's centre) is
    nearest each point of (E, 2) ``uv`` in raster cell ``ij``, if within ``width``; -1 otherwise."""
    reach = int(np.ceil(width / spacing + 0.5))
    out = np.full(len(uv), -1, dtype=np.int64)
    for p in range(len(uv)):
        best = width * width
        for i in range(max(ij[p, 0] - reach, 0), min(ij[p, 0] + reach + 1, label.shape[0])):
            for j in range(max(ij[p, 1] - reach, 0), min(ij[p, 1] + reach + 1, label.shape[1])):
                if label[i, j] < 0:
                    continue
                du = uv[p, 0] - (lo[0] + (i + 0.5) * spacing)
                dv = uv[p, 1] - (lo[1] + (j + 0.5) * spacing)
                d2 = du * du + dv * dv
                if d2 < best or (d2 == best and out[p] < 0):
                    best = d2
                    out[p] = label[i, j]
    return out


@numba.njit(cache=True, nogil=True)
def _section_moments(
    points: np.ndarray,
    idx: np.ndarray,
    first: np.ndarray,
    seg: np.ndarray,
    p0: np.ndarray,
    d: np.ndarray,
    mid: np.ndarray,
    step: np.ndarray,
    radius: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns per segment (K,) the count, (K, 3) sum and (K, 3, 3) second moment of the offsets from it
    of the points idx[first[s]:first[s + 1]] found for slice s (of segment seg[s], from p0 along unit d,
    its middle ``mid[s]`` along and ``step[s]`` long) that lie in that slice, within ``radius`` of the
    segment."""
    k = len(p0)
    n = np.zeros(k)
    sums = np.zeros((k, 3))
    second = np.zeros((k, 3, 3))
    for s in range(len(seg)):
        g = seg[s]
        for m in range(first[s], first[s + 1]):
            q = idx[m]
            r0, r1, r2 = points[q, 0] - p0[g, 0], points[q, 1] - p0[g, 1], points[q, 2] - p0[g, 2]
            along = r0 * d[g, 0] + r1 * d[g, 1] + r2 * d[g, 2]
            e0, e1, e2 = r0 - along * d[g, 0], r1 - along * d[g, 1], r2 - along * d[g, 2]
            if abs(along - mid[s]) > 0.5 * step[s] or np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) > radius:
                continue
            n[g] += 1.0
            sums[g, 0] += e0
            sums[g, 1] += e1
            sums[g, 2] += e2
            second[g, 0, 0] += e0 * e0
            second[g, 0, 1] += e0 * e1
            second[g, 0, 2] += e0 * e2
            second[g, 1, 1] += e1 * e1
            second[g, 1, 2] += e1 * e2
            second[g, 2, 2] += e2 * e2
    for g in range(k):
        second[g, 1, 0] = second[g, 0, 1]
        second[g, 2, 0] = second[g, 0, 2]
        second[g, 2, 1] = second[g, 1, 2]
    return n, sums, second
