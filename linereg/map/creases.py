"""Crease lines: where two large planar regions meet, a 3D edge exists that has no boundary in the cloud.

Part of the 3D line extraction (``lines3d.extract``): the plane-plane intersection line is kept only
over the stretch where both regions have points near it, reaching it from one side each.
"""

from __future__ import annotations

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
    box_lo, box_hi = np.zeros((len(planes.counts), 3)), np.zeros((len(planes.counts), 3))
    for r in np.unique(pairs):
        box_lo[r], box_hi[r] = points[members[r]].min(axis=0), points[members[r]].max(axis=0)
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
    # every region's points one after another (members[r] is that region's slice)
    sizes = np.array([len(members[r]) for r in range(len(members))], dtype=np.int64)
    first = np.r_[0, np.cumsum(sizes)]
    flat = np.concatenate([np.zeros(0, np.int64), *members]).astype(np.int64)
    gap_half = np.maximum((config.collinear_gap_m / cell[keep] / 2).astype(np.int64), 1)
    found = _crease_runs(
        points, flat, first, a[keep], b[keep], origin[keep], directions[keep], enter[keep], leave[keep],
        cell[keep], gap_half, config.min_length_m, share,
    )  # fmt: skip
    return found.reshape(-1, 6)


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
    flat: np.ndarray,
    first: np.ndarray,
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
    points are flat[first[r]:first[r + 1]] of ``points``), the runs of raster cells ``cell[k]`` long where
    both regions have points within 3 cells of the line, gaps of up to 2 gap_half[k] cells closed, at
    least ``min_length`` long, kept where ``share`` of either region's points near the run lie on one side.

    A region's points near a line are those within 3 cells of it and within 4.5 cells of one of its
    samples spaced 3 cells from ``enter`` to past ``leave`` (the span inside both regions' boxes)."""
    out = np.empty((16, 6))
    found = 0
    for k in range(len(a)):
        r = 3.0 * cell[k]
        count = int(np.ceil((leave[k] + r - enter[k]) / r))
        size_a, size_b = first[a[k] + 1] - first[a[k]], first[b[k] + 1] - first[b[k]]
        ta, perp_a = np.empty(size_a), np.empty((size_a, 3))
        tb, perp_b = np.empty(size_b), np.empty((size_b, 3))
        na = _near_side(points, flat, first[a[k]], first[a[k] + 1], origin[k], direction[k], enter[k], r,
                        count, ta, perp_a)  # fmt: skip
        nb = _near_side(points, flat, first[b[k]], first[b[k] + 1], origin[k], direction[k], enter[k], r,
                        count, tb, perp_b)  # fmt: skip
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
    flat: np.ndarray,
    lo: int,
    hi: int,
    origin: np.ndarray,
    direction: np.ndarray,
    enter: float,
    r: float,
    count: int,
    t_out: np.ndarray,
    perp_out: np.ndarray,
) -> int:  # pragma: no cover - numba
    """Writes the line parameter and offset from the line (origin + t direction) of each point
    points[flat[lo:hi]] within ``r`` of it and within 1.5 r of its nearest of the ``count`` samples
    enter + i r, in their order; returns how many."""
    n = 0
    for m in range(lo, hi):
        q = flat[m]
        p0, p1, p2 = points[q, 0] - origin[0], points[q, 1] - origin[1], points[q, 2] - origin[2]
        t = p0 * direction[0] + p1 * direction[1] + p2 * direction[2]
        e0, e1, e2 = p0 - t * direction[0], p1 - t * direction[1], p2 - t * direction[2]
        if e0 * e0 + e1 * e1 + e2 * e2 > r * r:
            continue
        # the nearest sample along the line is the nearest in space: the offset across is the same
        s = enter + min(max(np.floor((t - enter) / r + 0.5), 0.0), count - 1.0) * r
        f0 = points[q, 0] - (origin[0] + s * direction[0])
        f1 = points[q, 1] - (origin[1] + s * direction[1])
        f2 = points[q, 2] - (origin[2] + s * direction[2])
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
