"""Crease lines: where two large planar regions meet, a 3D edge exists that has no boundary in the cloud.

Part of the 3D line extraction (``lines3d.extract``): the plane-plane intersection line is kept only
over the stretch where both regions have points near it, reaching it from one side each.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from ..config import Lines3DConfig
from .planes import Planes


def crease_segments(
    points: np.ndarray,
    planes: Planes,
    members: list[np.ndarray],
    large: np.ndarray,
    cells: np.ndarray,
    config: Lines3DConfig,
) -> np.ndarray:
    """Returns (K, 6) plane-plane intersection segments of touching ``large`` (R,) regions, clipped to
    where both have points within 3 cells of the line (a crease has no boundary in the cloud, only two
    planes meeting)."""
    pairs = planes.pairs[large[planes.pairs].all(axis=1)] if len(planes.pairs) else planes.pairs
    directions = np.cross(planes.normals[pairs[:, 0]], planes.normals[pairs[:, 1]])
    sines = np.linalg.norm(directions, axis=1)
    keep = sines >= np.sin(np.radians(config.crease_min_angle_deg))
    pairs, directions = pairs[keep], directions[keep] / sines[keep, None]
    # the regions of the pairs in grids (the others left empty), which also give their boxes
    used = np.zeros(len(members), dtype=bool)
    used[pairs.ravel()] = True
    empty = np.zeros(0, np.int64)
    grid = _region_grids(points, [m if u else empty for m, u in zip(members, used, strict=True)], 3.0 * cells)
    box_lo, box_hi = grid.low, grid.high
    share = config.crease_one_sided
    a, b = pairs[:, 0], pairs[:, 1]
    cell = np.maximum(cells[a], cells[b])
    # the point of the line nearest both centroids' planes: n_a.x = d_a, n_b.x = d_b, direction.x = mean
    na, nb, ca, cb = planes.normals[a], planes.normals[b], planes.centroids[a], planes.centroids[b]
    rhs = np.stack([np.vecdot(na, ca), np.vecdot(nb, cb), np.vecdot(0.5 * (ca + cb), directions)], axis=1)
    origin = np.linalg.solve(np.stack([na, nb, directions], axis=1), rhs[:, :, None])[:, :, 0]
    lo = np.maximum(box_lo[a], box_lo[b]) - 3 * cell[:, None]
    hi = np.minimum(box_hi[a], box_hi[b]) + 3 * cell[:, None]
    enter, leave, inside = _overlap(lo, hi, origin, directions)
    keep = np.flatnonzero(inside)
    gap_half = np.maximum((config.collinear_gap_m / cell[keep] / 2).astype(np.int64), 1)
    found = _crease_runs(
        points, grid, a[keep], b[keep], origin[keep], directions[keep], enter[keep], leave[keep],
        cell[keep], gap_half, config.min_length_m, share,
    )  # fmt: skip
    return found.reshape(-1, 6)


class _Grids(NamedTuple):
    """Every region's points in cubic cells of its own ``size`` (R,) from its ``low`` corner (R, 3) (its
    points' minimum; ``high``: their maximum), ``dims`` (R, 3) cells along each axis: region r's points are
    flat[first[r]:first[r + 1]] (indices into the cloud), sorted by their cell's ``keys``
    ((i dims[1] + j) dims[2] + k)."""

    flat: np.ndarray
    keys: np.ndarray
    first: np.ndarray
    low: np.ndarray
    high: np.ndarray
    size: np.ndarray
    dims: np.ndarray


def _region_grids(points: np.ndarray, members: list[np.ndarray], size: np.ndarray) -> _Grids:
    """Returns the _Grids of the regions' ``members`` (indices into the (P, 3) ``points``) with cells
    ``size`` (R,) wide: a line's near points are then looked up round its samples, not among all the
    region's points (a ground region meets hundreds of walls in a large scan)."""
    sizes = np.array([len(m) for m in members], dtype=np.int64)
    first = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    flat = np.concatenate([np.zeros(0, np.int64), *members]).astype(np.int64)
    region = np.repeat(np.arange(len(members)), sizes)
    low, high = np.zeros((len(members), 3)), np.zeros((len(members), 3))
    dims = np.ones((len(members), 3), dtype=np.int64)
    if len(flat) == 0:
        return _Grids(flat, np.zeros(0, np.int64), first, low, high, size.astype(np.float64), dims)
    has = sizes > 0
    p = points[flat]
    low[has] = np.minimum.reduceat(p, first[:-1][has], axis=0)
    high[has] = np.maximum.reduceat(p, first[:-1][has], axis=0)
    ijk = np.floor((p - low[region]) / size[region, None]).astype(np.int64)
    dims[has] = np.maximum.reduceat(ijk, first[:-1][has], axis=0) + 1
    key = (ijk[:, 0] * dims[region, 1] + ijk[:, 1]) * dims[region, 2] + ijk[:, 2]
    # one sort for all regions: each region's cells numbered after the previous regions' (the order of
    # points within a cell does not matter)
    cells = dims.prod(axis=1)
    order = np.argsort(key + (np.cumsum(cells) - cells)[region])
    return _Grids(flat[order], key[order], first, low, high, size.astype(np.float64), dims)


def _overlap(
    lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, direction: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (N,) t0, t1 and whether t1 > t0: the stretch of each (N, 3) line origin + t direction inside
    the (N, 3) box lo-hi (slab clipping; a line parallel to a slab outside it misses the box)."""
    flat = np.abs(direction) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - origin) / direction, (hi - origin) / direction
    enter = np.where(flat, -np.inf, np.minimum(ta, tb)).max(axis=1)
    leave = np.where(flat, np.inf, np.maximum(ta, tb)).min(axis=1)
    missed = (lo > hi).any(axis=1) | (flat & ~((lo <= origin) & (origin <= hi))).any(axis=1)
    return enter, leave, ~missed & (leave > enter)


@numba.njit(cache=True, nogil=True)
def _crease_runs(
    points: np.ndarray,
    grid: _Grids,
    a: np.ndarray,
    b: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    enter: np.ndarray,
    leave: np.ndarray,
    cell: np.ndarray,
    gap_half: np.ndarray,
    min_length: float,
    share: float,
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (K, 6) crease segments: per line k (origin[k] + t direction[k], regions a[k] and b[k], whose
    points are in ``grid``), the runs of raster cells ``cell[k]`` long where
    both regions have points within 3 cells of the line, gaps of up to 2 gap_half[k] cells closed, at
    least ``min_length`` long, kept where ``share`` of either region's points near the run lie on one side.

    A region's points near a line are those within 3 cells of it and within 4.5 cells of one of its
    samples spaced 3 cells from ``enter`` to past ``leave`` (the span inside both regions' boxes)."""
    out = np.empty((16, 6))
    found = 0
    largest = 0
    for g in range(len(grid.first) - 1):
        largest = max(largest, grid.first[g + 1] - grid.first[g])
    # buffers for the near points of a line's two regions, reused line after line
    ta, perp_a = np.empty(largest), np.empty((largest, 3))
    tb, perp_b = np.empty(largest), np.empty((largest, 3))
    for k in range(len(a)):
        r = 3.0 * cell[k]
        count = int(np.ceil((leave[k] + r - enter[k]) / r))
        na = _near_side(points, grid, a[k], origin[k], direction[k], enter[k], r, count, ta, perp_a)
        nb = _near_side(points, grid, b[k], origin[k], direction[k], enter[k], r, count, tb, perp_b)
        if na == 0 or nb == 0:
            continue
        lo_a = hi_a = ta[0]
        for i in range(na):
            lo_a, hi_a = min(lo_a, ta[i]), max(hi_a, ta[i])
        lo_b = hi_b = tb[0]
        for i in range(nb):
            lo_b, hi_b = min(lo_b, tb[i]), max(hi_b, tb[i])
        lo, hi = max(lo_a, lo_b), min(hi_a, hi_b)
        if hi - lo < min_length:
            continue
        c = cell[k]
        bins = int((hi - lo) / c) + 1
        in_a, both = np.zeros(bins, dtype=np.bool_), np.zeros(bins, dtype=np.bool_)
        for i in range(na):
            if ta[i] >= lo and ta[i] <= hi:
                in_a[int((ta[i] - lo) / c)] = True
        for i in range(nb):
            if tb[i] >= lo and tb[i] <= hi and in_a[int((tb[i] - lo) / c)]:
                both[int((tb[i] - lo) / c)] = True
        closed = _close_1d(both, gap_half[k])
        i = 0
        while i < bins:
            if not closed[i]:
                i += 1
                continue
            j = i
            while j < bins and closed[j]:
                j += 1
            t0, t1 = lo + i * c, min(lo + j * c, hi)
            i = j
            if t1 - t0 < min_length:
                continue
            if _one_sided(ta[:na], perp_a[:na], t0, t1, share) and _one_sided(
                tb[:nb], perp_b[:nb], t0, t1, share
            ):
                if found == len(out):
                    grown = np.empty((2 * len(out), 6))
                    for g in range(found):  # element by element: a slice copy costs seconds to compile
                        for e in range(6):
                            grown[g, e] = out[g, e]
                    out = grown
                for e in range(3):
                    out[found, e] = origin[k, e] + t0 * direction[k, e]
                    out[found, 3 + e] = origin[k, e] + t1 * direction[k, e]
                found += 1
    return out[:found]


@numba.njit(cache=True, nogil=True)
def _near_side(
    points: np.ndarray,
    grid: _Grids,
    region: int,
    origin: np.ndarray,
    direction: np.ndarray,
    enter: float,
    r: float,
    count: int,
    t_out: np.ndarray,
    perp_out: np.ndarray,
) -> int:  # pragma: no cover - numba
    """Writes the line parameter and offset from the line (origin + t direction) of each point of
    ``region`` within ``r`` of it and within 1.5 r of its nearest of the ``count`` samples enter + i r
    (the nearest along the line is the nearest in space: the offset across is the same); returns how
    many. Each sample looks at the region's cells within 1.5 r of it and keeps the points it is nearest."""
    lo, hi = grid.first[region], grid.first[region + 1]
    size = grid.size[region]
    reach = int(np.ceil(1.5 * r / size))
    d0, d1, d2 = grid.dims[region, 0], grid.dims[region, 1], grid.dims[region, 2]
    n = 0
    for s in range(count):
        at = enter + s * r
        x0, x1, x2 = (
            origin[0] + at * direction[0],
            origin[1] + at * direction[1],
            origin[2] + at * direction[2],
        )
        c0 = int(np.floor((x0 - grid.low[region, 0]) / size))
        c1 = int(np.floor((x1 - grid.low[region, 1]) / size))
        c2 = int(np.floor((x2 - grid.low[region, 2]) / size))
        for i in range(max(c0 - reach, 0), min(c0 + reach + 1, d0)):
            for j in range(max(c1 - reach, 0), min(c1 + reach + 1, d1)):
                row = (i * d1 + j) * d2
                k_lo, k_hi = max(c2 - reach, 0), min(c2 + reach + 1, d2)
                if k_lo >= k_hi:
                    continue
                m = lo + np.searchsorted(grid.keys[lo:hi], row + k_lo)
                while m < hi and grid.keys[m] < row + k_hi:
                    q = grid.flat[m]
                    m += 1
                    p0, p1, p2 = points[q, 0] - origin[0], points[q, 1] - origin[1], points[q, 2] - origin[2]
                    t = p0 * direction[0] + p1 * direction[1] + p2 * direction[2]
                    if min(max(np.floor((t - enter) / r + 0.5), 0.0), count - 1.0) != s:
                        continue  # another sample's point
                    e0, e1, e2 = p0 - t * direction[0], p1 - t * direction[1], p2 - t * direction[2]
                    if e0 * e0 + e1 * e1 + e2 * e2 > r * r:
                        continue
                    f0, f1, f2 = points[q, 0] - x0, points[q, 1] - x1, points[q, 2] - x2
                    if f0 * f0 + f1 * f1 + f2 * f2 > 2.25 * r * r:
                        continue
                    t_out[n] = t
                    perp_out[n, 0], perp_out[n, 1], perp_out[n, 2] = e0, e1, e2
                    n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _one_sided(
    t: np.ndarray, perp: np.ndarray, t0: float, t1: float, share: float
) -> bool:  # pragma: no cover - numba
    """Returns whether at least ``share`` of a region's points near a crease run (line parameter in
    [t0, t1]) lie on one side of it: a crease bounds both regions, while facets of a rough surface that
    cross mid-way have points on both sides."""
    s0 = s1 = s2 = 0.0
    n = 0
    for i in range(len(t)):
        if t[i] >= t0 and t[i] <= t1:
            s0 += perp[i, 0]
            s1 += perp[i, 1]
            s2 += perp[i, 2]
            n += 1
    if n == 0:
        return False
    norm = max(np.sqrt(s0 * s0 + s1 * s1 + s2 * s2), 1e-12)
    s0, s1, s2 = s0 / norm, s1 / norm, s2 / norm
    above = below = 0
    for i in range(len(t)):
        if t[i] >= t0 and t[i] <= t1:
            side = perp[i, 0] * s0 + perp[i, 1] * s1 + perp[i, 2] * s2
            above += side > 0
            below += side < 0
    return max(above / n, below / n) >= share


@numba.njit(cache=True, nogil=True)
def _close_1d(mask: np.ndarray, half: int) -> np.ndarray:  # pragma: no cover - numba
    """Returns the (n,) boolean mask with gaps of up to 2 * half samples filled (1D morphological closing;
    beyond the ends the dilation is taken as set, so a run reaching an end is not shortened)."""
    n = len(mask)
    dilated = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if mask[i]:
            for j in range(max(i - half, 0), min(i + half + 1, n)):  # loops: slices compile slowly
                dilated[j] = True
    closed = np.ones(n, dtype=np.bool_)
    for i in range(n):
        if not dilated[i]:
            for j in range(max(i - half, 0), min(i + half + 1, n)):
                closed[j] = False
    return closed
