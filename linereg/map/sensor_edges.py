"""Edges of a single sweep seen from its sensor: occluding contours and sharp bends along the scan rings.

A spinning LiDAR samples each ring densely in azimuth but leaves a range-proportional gap between rings,
too wide for small structure (a pole, a car's side, a door frame) to form planar regions. Along each ring
(points sorted by azimuth about the sensor):

- an *occluding contour* point is the near side of a range jump: its neighbour along the ring lies
  farther by more than ``jump_fraction`` of the range plus ``jump_m`` (the far side is background seen
  past the silhouette: no edge of it is where the point is);
- a *bend* point has a high LOAM smoothness ``|sum_j (p_j - p_i)| / (2 w r_i)`` over the w neighbours on
  each side (Zhang & Singh 2014), a local maximum, with no range jump in its window.

Edge points of neighbouring rings lying within ``link_gaps`` ring gaps of each other are linked; each
linked group is cut into straight lines (sequential RANSAC, tolerance a fraction of the range); lines of
``min_points`` points and ``min_length_m`` are kept, tagged occluding or ring edge by their points.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..config import SensorEdgesConfig
from . import kinds


def sensor_edges(
    points: np.ndarray, ring: np.ndarray, sensor: np.ndarray, config: SensorEdgesConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((E, 6) float64 edge segments, (E,) int8 kinds) of (P, 3) points with (P,) int64 ring ids
    (-1: none) scanned from (3,) ``sensor``."""
    config = config or SensorEdgesConfig()
    index, kind = edge_points(points, ring, sensor, config)
    segments, segment_kinds = [], []
    for line, members in lines_across_rings(points[index], ring[index], sensor, config):
        segments.append(line)
        occluding = (kind[members] == kinds.OCCLUDING).mean() >= 0.5
        segment_kinds.append(kinds.OCCLUDING if occluding else kinds.RING_EDGE)
    return np.array(segments).reshape(-1, 6), np.array(segment_kinds, dtype=np.int8)


def lines_across_rings(
    p: np.ndarray, ring: np.ndarray, sensor: np.ndarray, config: SensorEdgesConfig
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Returns ((6,) segment, (k,) int64 indices of its points) of the straight lines through (n, 3) edge
    points of (n,) rings seen from (3,) ``sensor``: points of neighbouring rings linked (``_link``), each
    linked group cut into lines (``_lines``)."""
    if len(p) < config.min_points:
        return []
    out = []
    for members in _link(p, ring, sensor, config):
        for line, inliers in _lines(p[members], sensor, config):
            out.append((line, members[inliers]))
    return out


def along_rings(
    points: np.ndarray, ring: np.ndarray, sensor: np.ndarray, usable: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((n,) int64 indices of the ``usable`` (P,) bool points sorted by ring, then azimuth about
    (3,) ``sensor``; (n,) their ranges; (n - 1,) bool: is each one's successor its neighbour on the ring
    (consecutive and no wider apart than a few azimuth steps: no dropped returns)?)."""
    rel = points - sensor
    az = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.flatnonzero(usable)
    order = order[np.lexsort((az[order], ring[order]))]
    same = ring[order][1:] == ring[order][:-1]  # consecutive along one ring
    step = np.abs(np.diff(az[order]))
    typical = np.median(step[same]) if same.any() else 0.0
    return order, np.linalg.norm(rel[order], axis=1), same & (step <= 4.0 * typical + 1e-12)


def edge_points(
    points: np.ndarray, ring: np.ndarray, sensor: np.ndarray, config: SensorEdgesConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((n,) int64 indices of edge points, (n,) int8 their kind: OCCLUDING or RING_EDGE)."""
    counts = np.bincount(ring[ring >= 0]) if (ring >= 0).any() else np.zeros(0, np.int64)
    usable = (ring >= 0) & (counts[np.maximum(ring, 0)] >= config.min_ring_points if len(counts) else False)
    order, rr, linked = along_rings(points, ring, sensor, usable)
    farther_next = linked & (rr[1:] > rr[:-1] * (1 + config.jump_fraction) + config.jump_m)
    farther_prev = linked & (rr[:-1] > rr[1:] * (1 + config.jump_fraction) + config.jump_m)
    occluding = np.zeros(len(order), dtype=bool)
    occluding[:-1] |= farther_next
    occluding[1:] |= farther_prev
    jump = np.zeros(len(order), dtype=bool)
    jump[:-1] |= farther_next | farther_prev
    jump[1:] |= farther_next | farther_prev
    bend = _bends(points[order], rr, linked, jump, config)
    found = occluding | bend
    kind = np.where(occluding, kinds.OCCLUDING, kinds.RING_EDGE).astype(np.int8)
    return order[found], kind[found]


def _bends(
    p: np.ndarray, r: np.ndarray, linked: np.ndarray, jump: np.ndarray, config: SensorEdgesConfig
) -> np.ndarray:
    """Returns (n,) bool: LOAM smoothness above ``bend`` and a local maximum, over windows of w linked
    neighbours on each side without a range jump, of (n, 3) points sorted along their rings."""
    w = config.window
    n = len(p)
    # a run of linked points: windows must not leave it
    run = np.cumsum(np.r_[True, ~linked])
    total = np.zeros((n, 3))
    ok = np.ones(n, dtype=bool)
    jumps = np.cumsum(np.r_[0, jump.astype(np.int64)])
    for k in range(1, w + 1):
        for sign in (-1, 1):
            j = np.clip(np.arange(n) + sign * k, 0, n - 1)
            ok &= (run[j] == run) & (np.arange(n) + sign * k >= 0) & (np.arange(n) + sign * k < n)
            total += p[j] - p
    lo, hi = np.clip(np.arange(n) - w, 0, n), np.clip(np.arange(n) + w + 1, 0, n)
    ok &= (jumps[hi] - jumps[lo]) == 0
    smooth = np.linalg.norm(total, axis=1) / (2 * w * np.maximum(r, 1e-9))
    smooth[~ok] = 0.0
    peak = np.ones(n, dtype=bool)
    for k in range(1, w + 1):
        for sign in (-1, 1):
            j = np.clip(np.arange(n) + sign * k, 0, n - 1)
            peak &= smooth >= np.where(run[j] == run, smooth[j], 0.0)
    return ok & peak & (smooth > config.bend)


def _link(p: np.ndarray, ring: np.ndarray, sensor: np.ndarray, config: SensorEdgesConfig) -> list[np.ndarray]:
    """Returns index arrays of the groups of (n, 3) edge points linked across rings: pairs of different
    rings within ``link_gaps`` ring gaps (estimated as the median distance to the nearest edge point of
    another ring, per range) and ``max_link_m``."""
    r = np.linalg.norm(p - sensor, axis=1)
    tree = cKDTree(p)
    pairs = tree.query_pairs(config.max_link_m, output_type="ndarray")
    if len(pairs) == 0:
        return []
    a, b = pairs[:, 0], pairs[:, 1]
    d = np.linalg.norm(p[a] - p[b], axis=1)
    other = ring[a] != ring[b]
    # the angular gap between neighbouring rings: the smallest angle to an edge point of another ring
    ang = d / np.maximum(np.minimum(r[a], r[b]), 1e-9)
    nearest = np.full(len(p), np.inf)
    np.minimum.at(nearest, a[other], ang[other])
    np.minimum.at(nearest, b[other], ang[other])
    gap = float(np.median(nearest[np.isfinite(nearest)])) if np.isfinite(nearest).any() else 0.0
    ok = other & (ang <= config.link_gaps * gap)
    graph = coo_matrix((np.ones(int(ok.sum()), np.int8), (a[ok], b[ok])), shape=(len(p), len(p)))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    order = np.argsort(label, kind="stable")
    starts = np.r_[0, np.cumsum(size)]
    return [order[starts[g] : starts[g + 1]] for g in np.flatnonzero(size >= config.min_points)]


def _lines(p: np.ndarray, sensor: np.ndarray, config: SensorEdgesConfig, seed: int = 0):
    """Yields ((6,) segment, (n,) bool inliers) of the straight lines among (n, 3) linked edge points:
    sequential RANSAC over point pairs, inliers within line_tolerance_fraction of their range."""
    rng = np.random.default_rng(seed)
    left = np.ones(len(p), dtype=bool)
    tol = config.line_tolerance_fraction * np.linalg.norm(p - sensor, axis=1)
    while left.sum() >= config.min_points:
        idx = np.flatnonzero(left)
        hyp = rng.integers(0, len(idx), size=(min(64, len(idx) ** 2), 2))
        hyp = hyp[hyp[:, 0] != hyp[:, 1]]
        if len(hyp) == 0:
            return
        a, b = p[idx[hyp[:, 0]]], p[idx[hyp[:, 1]]]
        d = (b - a) / np.maximum(np.linalg.norm(b - a, axis=1), 1e-12)[:, None]
        rel = p[idx][None] - a[:, None]  # (H, n, 3)
        along = np.einsum("hnk,hk->hn", rel, d)
        dist = np.linalg.norm(rel - along[..., None] * d[:, None], axis=2)
        inl = dist <= tol[idx][None]
        best = int(np.argmax(inl.sum(axis=1)))
        members = idx[inl[best]]
        if len(members) < config.min_points:
            return
        centre = p[members].mean(axis=0)
        direction = np.linalg.svd(p[members] - centre, full_matrices=False)[2][0]
        t = (p[members] - centre) @ direction
        left[members] = False
        if np.ptp(t) >= config.min_length_m:
            mask = np.zeros(len(p), dtype=bool)
            mask[members] = True
            yield np.r_[centre + t.min() * direction, centre + t.max() * direction], mask
