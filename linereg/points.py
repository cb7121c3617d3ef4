"""Corner points of line drawings: where two lines of different directions meet, and free segment ends.

A corner is a point with one or two *arms*: unit directions along which its segments leave it. In the
image, two segments of different directions whose lines cross within a small gap of an end of each form a
corner at the crossing (a window corner, the foot of a facade); the crossing does not move when LSD breaks
or shortens a segment, only when a segment misses the corner altogether. A segment end that is no corner is
a one-armed point. The map has the same points in 3D. Under a rotation R, a map point's arms project at an
image point to directions that do not depend on the camera centre (they point at vanishing points), so an
image point and a map point can correspond only if their arms agree: that is what makes the search's votes
few and sharp (``search.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .config import PointsConfig


@dataclass(frozen=True)
class Points:
    """Corners and free ends: positions (K, d), arms (K, 2, d) unit (the second NaN for one-armed points),
    arm_lengths (K, 2) (px or m; 0 for a missing arm), arm_segments (K, 2) int64 the segment of each arm
    (-1 for a missing arm), weight (K,): how much a match of the point counts."""

    positions: np.ndarray
    arms: np.ndarray
    arm_lengths: np.ndarray
    arm_segments: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def two_armed(self) -> np.ndarray:
        return ~np.isnan(self.arms[:, 1, 0])


def image_points(lines2d: np.ndarray, config: PointsConfig) -> Points:
    """Returns the corners and free ends of (N, 4) undistorted pixel segments."""
    return _points(np.asarray(lines2d, dtype=np.float64).reshape(-1, 2, 2), config.gap_px, config)


def map_points(lines3d: np.ndarray, config: PointsConfig, gap_m: float) -> Points:
    """Returns the corners and free ends of (M, 6) world segments; ``gap_m``: the largest gap between a
    segment's end and the corner it belongs to (the map's own scale: ``map_gap_m``)."""
    return _points(np.asarray(lines3d, dtype=np.float64).reshape(-1, 2, 3), gap_m, config)


def subset_points(points: Points, index: np.ndarray, num_segments: int) -> Points:
    """Returns the points of a map's (M = ``num_segments``) segments restricted to the rows ``index`` (k,),
    renumbered to those rows' order: the points whose every arm lies on a kept segment (a corner that loses
    an arm is left out, where ``map_points`` of the subset would make its other segment's end a free end:
    the subset is a view's, and the lost arm is one no camera in it sees)."""
    local = np.full(num_segments + 1, -1, dtype=np.int64)  # the last entry maps a missing arm (-1) to -1
    local[np.asarray(index, dtype=np.int64)] = np.arange(len(index))
    segments = local[points.arm_segments]
    keep = (segments[:, 0] >= 0) & ((segments[:, 1] >= 0) | (points.arm_segments[:, 1] < 0))
    return Points(
        points.positions[keep], points.arms[keep], points.arm_lengths[keep], segments[keep],
        points.weight[keep],
    )  # fmt: skip


def map_gap_m(lines3d: np.ndarray, config: PointsConfig) -> float:
    """Returns the corner gap for a map: ``config.gap_fraction`` of its median segment length."""
    lengths = np.linalg.norm(lines3d[:, 3:6] - lines3d[:, 0:3], axis=1)
    return float(config.gap_fraction * np.median(lengths)) if len(lengths) else 0.0


def _points(ends: np.ndarray, gap: float, config: PointsConfig) -> Points:
    """Returns the Points of (N, 2, d) segment ends (d = 2: pixels, 3: metres)."""
    n, _, dim = ends.shape
    if n == 0:
        empty = np.zeros((0, 2), np.int64)
        return Points(np.zeros((0, dim)), np.zeros((0, 2, dim)), np.zeros((0, 2)), empty, np.zeros(0))
    direction = ends[:, 1] - ends[:, 0]
    length = np.linalg.norm(direction, axis=1)
    unit = direction / np.maximum(length, 1e-300)[:, None]
    a, b = _near_end_pairs(ends, gap + config.gap_fraction * length, config.line_gap)
    corner, end_a, end_b, where = _corners(ends, unit, length, a, b, gap, config)
    a, b, end_a, end_b, where = a[corner], b[corner], end_a[corner], end_b[corner], where[corner]
    arms = np.stack([_arm(unit[a], end_a), _arm(unit[b], end_b)], axis=1)
    arm_lengths = np.stack([length[a], length[b]], axis=1)
    # a segment end that joins a corner is not also a free end
    used = np.zeros((n, 2), bool)
    used[a, end_a] = True
    used[b, end_b] = True
    seg, end = np.nonzero(~used)
    free_arms = np.full((len(seg), 2, dim), np.nan)
    free_arms[:, 0] = _arm(unit[seg], end)
    positions = np.r_[where, ends[seg, end]]
    weight = np.r_[np.full(len(where), config.corner_weight), np.full(len(seg), 1.0)]
    return Points(
        positions,
        np.r_[arms, free_arms],
        np.r_[arm_lengths, np.c_[length[seg], np.zeros(len(seg))]],
        np.r_[np.c_[a, b], np.c_[seg, np.full(len(seg), -1)]].astype(np.int64),
        weight,
    )


def _arm(unit: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Returns the direction in which a segment leaves its end ``end`` (0: first, 1: second)."""
    return np.where((end == 0)[:, None], unit, -unit)


def _near_end_pairs(ends: np.ndarray, reach: np.ndarray, line_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P,), (P,)) segment pairs a < b, in increasing order of ``a n + b``, that may make a corner
    (``_corners``): an end of each within ``R`` = max(``reach``) of each other (``reach``: (N,) each
    segment's, ``gap`` + ``gap_fraction`` of its length) and within ``(2 + line_gap)`` times the larger of
    the two segments' reaches.

    A corner's crossing lies within ``reach`` of an end of each segment along its line, the two lines
    within ``line_gap`` of the smaller reach of each other there: those two ends lie within
    reach_a + reach_b + line_gap min(reach_a, reach_b) of each other. The pairs within R that this bound
    leaves out make no corner, so the corners are those of every end pair within R (what this returned
    before), without the pairs of short segments R apart: on a city of window lattices and 26 m corner
    edges, R is ~4 m and a window edge's bound ~0.6 m."""
    n = len(ends)
    points = ends.reshape(2 * n, -1)
    longest = float(reach.max())
    bound = np.minimum((2.0 + line_gap) * reach * (1.0 + 1e-9), longest)  # each segment's, at most R
    tree = cKDTree(points)
    # every pair within the bound of most segments (the 90th percentile's), then the ends of the segments with
    # a larger bound against every end, each pair kept within the wider end's bound (the larger of a pair's)
    per_end = np.repeat(bound, 2)
    common = float(np.quantile(per_end, 0.9))
    pairs = [tree.query_pairs(common, output_type="ndarray")]
    wide = np.flatnonzero(per_end > common)
    if len(wide):
        found = cKDTree(points[wide]).sparse_distance_matrix(tree, longest, output_type="ndarray")
        found = found[found["v"] <= per_end[wide][found["i"]]]
        pairs.append(np.c_[wide[found["i"]], found["j"]].astype(np.int64))
    pairs_all = np.concatenate(pairs)
    a, b = pairs_all[:, 0] // 2, pairs_all[:, 1] // 2  # rows 2s, 2s + 1 are the ends of segment s
    keep = a != b
    key = np.unique(np.minimum(a, b)[keep] * n + np.maximum(a, b)[keep])
    return key // n, key % n


def _corners(
    ends: np.ndarray,
    unit: np.ndarray,
    length: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    gap: float,
    config: PointsConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns (corner (P,) bool, end of a (P,), end of b (P,), (P, d) corner position) of candidate pairs:
    directions apart by at least ``min_angle_deg``, lines passing within ``line_gap`` of each other, the
    crossing within ``gap`` (+ ``gap_fraction`` of the length) of one end of each segment."""
    ua, ub = unit[a], unit[b]
    cos = np.abs(np.einsum("pk,pk->p", ua, ub))
    # closest points of the two infinite lines: ends[a, 0] + sa ua and ends[b, 0] + sb ub
    w = ends[a, 0] - ends[b, 0]
    c = np.einsum("pk,pk->p", ua, ub)
    d, e = np.einsum("pk,pk->p", ua, w), np.einsum("pk,pk->p", ub, w)
    den = np.maximum(1.0 - c * c, 1e-12)
    sa, sb = (c * e - d) / den, (e - c * d) / den
    pa, pb = ends[a, 0] + sa[:, None] * ua, ends[b, 0] + sb[:, None] * ub
    ga, gb = gap + config.gap_fraction * length[a], gap + config.gap_fraction * length[b]
    end_a = np.where(np.abs(sa) <= np.abs(sa - length[a]), 0, 1)
    end_b = np.where(np.abs(sb) <= np.abs(sb - length[b]), 0, 1)
    near_a = np.minimum(np.abs(sa), np.abs(sa - length[a])) <= ga
    near_b = np.minimum(np.abs(sb), np.abs(sb - length[b])) <= gb
    crossing = np.linalg.norm(pa - pb, axis=1) <= config.line_gap * np.minimum(ga, gb)
    corner = (cos <= np.cos(np.radians(config.min_angle_deg))) & near_a & near_b & crossing
    return corner, end_a, end_b, 0.5 * (pa + pb)
