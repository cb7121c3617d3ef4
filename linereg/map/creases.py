"""Crease lines: where two large planar regions meet, a 3D edge exists that has no boundary in the cloud.

Part of the 3D line extraction (``lines3d.extract``): the plane-plane intersection line is kept only
over the stretch where both regions have points near it, reaching it from one side each.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig
from .neighbours import flat_lists
from .planes import Planes


class _Crease(NamedTuple):
    """The line where regions a and b meet: origin + t direction for t in [enter, leave] (inside both
    regions' boxes), searched with the larger region's raster ``cell``."""

    a: int
    b: int
    origin: np.ndarray
    direction: np.ndarray
    enter: float
    leave: float
    cell: float


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
    out = []
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
    lines = [
        _Crease(a[k], b[k], origin[k], directions[k], enter[k], leave[k], cell[k])
        for k in np.flatnonzero(inside)
    ]
    near = _near_lines(points, members, lines)
    for k, line in enumerate(lines):
        (ta, perp_a), (tb, perp_b) = near[k, 0], near[k, 1]
        for t0, t1 in _common_runs(ta, tb, line.cell, config):
            if _one_sided(ta, perp_a, t0, t1, share) and _one_sided(tb, perp_b, t0, t1, share):
                out.append(np.r_[line.origin + t0 * line.direction, line.origin + t1 * line.direction])
    return np.array(out).reshape(-1, 6)


def _one_sided(t: np.ndarray, perp: np.ndarray, t0: float, t1: float, share: float) -> bool:
    """Returns whether at least ``share`` of a region's points near a crease run lie on one side of it: a
    crease bounds both regions, while facets of a rough surface that cross mid-way have points on both sides."""
    inside = (t >= t0) & (t <= t1)
    if not inside.any():
        return False
    p = perp[inside]
    side = p @ (p.sum(axis=0) / max(np.linalg.norm(p.sum(axis=0)), 1e-12))
    return bool(max((side > 0).mean(), (side < 0).mean()) >= share)


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


def _near_lines(
    points: np.ndarray, members: list[np.ndarray], lines: list[_Crease]
) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Returns {(line k, side 0 / 1): ((n,) line parameters, (n, 3) offsets from the line)} of the points of
    region a (side 0) and b (side 1) of each of the ``lines`` within 3 cells of the line's span.

    A region's lines are looked up together, one KD-tree query of all their samples (a room's regions meet
    in thousands of pairs: one query each cost more than the search).
    """
    jobs: dict[int, list[tuple[int, int]]] = {}
    for k, line in enumerate(lines):
        for side, region in enumerate((line.a, line.b)):
            jobs.setdefault(int(region), []).append((k, side))
    out = {}
    for region, wanted in jobs.items():
        member = members[region]
        samples, radii, job_of = [], [], []
        for j, (k, _) in enumerate(wanted):
            line = lines[k]
            radius = 3 * line.cell
            at = line.origin + np.outer(np.arange(line.enter, line.leave + radius, radius), line.direction)
            samples.append(at)
            radii.append(np.full(len(at), 1.5 * radius))
            job_of.append(np.full(len(at), j))
        tree = cKDTree(points[member])
        found = tree.query_ball_point(np.concatenate(samples), np.concatenate(radii), return_sorted=False)
        sizes, hits = flat_lists(found)
        # distinct points of each line, in increasing order
        key = np.unique(np.repeat(np.concatenate(job_of), sizes) * len(member) + hits)
        bounds = np.searchsorted(key, np.arange(len(wanted) + 1) * len(member))
        for j, (k, side) in enumerate(wanted):
            line = lines[k]
            idx = key[bounds[j] : bounds[j + 1]] - j * len(member)
            out[k, side] = _near_line(points[member[idx]], line.origin, line.direction, 3 * line.cell)
    return out


def _near_line(
    near: np.ndarray, origin: np.ndarray, direction: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((k,) line parameters, (k, 3) offsets from the line) of the (n, 3) ``near`` points within
    ``radius`` of the line."""
    p = near - origin
    t = p @ direction
    perp = p - np.outer(t, direction)
    near_line = np.einsum("ij,ij->i", perp, perp) <= radius * radius
    return t[near_line], perp[near_line]


def _common_runs(
    ta: np.ndarray, tb: np.ndarray, cell: float, config: Lines3DConfig
) -> list[tuple[float, float]]:
    """Returns the (t0, t1) intervals, at least min_length_m long, covered by both parameter sets."""
    if len(ta) == 0 or len(tb) == 0:
        return []
    lo, hi = max(ta.min(), tb.min()), min(ta.max(), tb.max())
    if hi - lo < config.min_length_m:
        return []
    nbins = int((hi - lo) / cell) + 1
    occ_a = np.bincount(((ta[(ta >= lo) & (ta <= hi)] - lo) / cell).astype(np.int64), minlength=nbins) > 0
    occ_b = np.bincount(((tb[(tb >= lo) & (tb <= hi)] - lo) / cell).astype(np.int64), minlength=nbins) > 0
    both = _close_1d(occ_a & occ_b, max(int(config.collinear_gap_m / cell / 2), 1))
    edges = np.diff(np.r_[0, both.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = [(lo + s * cell, min(lo + e * cell, hi)) for s, e in zip(starts, stops, strict=True)]
    return [(t0, t1) for t0, t1 in runs if t1 - t0 >= config.min_length_m]


def _close_1d(mask: np.ndarray, half: int) -> np.ndarray:
    """Returns the (n,) boolean mask with gaps of up to 2 * half samples filled (1D morphological closing)."""
    kernel = np.ones(2 * half + 1)
    padded = np.r_[np.zeros(half), mask.astype(np.float64), np.zeros(half)]
    dilated = (np.convolve(padded, kernel, "same") > 0).astype(np.float64)
    eroded = (
        np.convolve(np.r_[np.ones(half), dilated[half:-half], np.ones(half)], kernel, "same")
        >= len(kernel) - 0.5
    )
    return eroded[half:-half]
