"""Merging of collinear 2D segment fragments (paper III: adjacent collinear segments are joined).

LSD breaks a line at every weak or occluded stretch; the pieces are joined here, pairs at a time,
best first, until nothing joins.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from .config import LineDetectConfig


def merge_collinear(lines2d: np.ndarray, gap_px: float, config: LineDetectConfig) -> np.ndarray:
    """Returns (K, 4) float64 segments, K <= N, with collinear fragments of (N, 4) ``lines2d`` joined.

    Two segments merge when their directions differ by less than ``merge_angle_deg``, all four endpoints
    lie within ``merge_offset_px`` of the joint line and the gap between them along it is below ``gap_px``
    (paper: merging step). Each round joins disjoint pairs, best (smallest gap) first, so chains of
    fragments collapse in a few rounds; it stops when a round merges nothing. A round leaves no
    mergeable pair of untouched segments behind, so later rounds only test pairs with a new segment.
    Candidate pairs are searched once: a joint segment's partners are its fragments' partners.
    """
    segments = np.asarray(lines2d, dtype=np.float64).reshape(-1, 4)
    graph = candidate_pairs(segments, gap_px, config)  # (C, 2) indices into lines2d
    row = np.arange(len(segments))  # row of segments holding each input segment
    pairs = graph
    for _ in range(config.max_merge_rounds):
        if len(pairs) == 0:
            break
        merged, ok, gap = _join(segments, pairs, config)
        ok &= gap <= gap_px
        pick = _disjoint_best(pairs[ok], gap[ok])
        if len(pick) == 0:
            break
        joined = pairs[ok][pick]
        used = np.zeros(len(segments), dtype=bool)
        used[joined.ravel()] = True
        kept = np.flatnonzero(~used)
        new_row = np.empty(len(segments), dtype=np.int64)
        new_row[kept] = np.arange(len(kept))
        new_row[joined] = len(kept) + np.arange(len(pick))[:, None]
        segments = np.concatenate([segments[kept], merged[ok][pick]])
        row = new_row[row]
        pairs = _unique_pairs(row[graph], len(segments), first_new=len(kept))
    return segments


def _unique_pairs(pairs: np.ndarray, n: int, first_new: int = 0) -> np.ndarray:
    """Returns (C', 2) int64 distinct pairs ``i < j`` of (C, 2) ``pairs`` (indices < n), dropping ``i == j``
    and pairs whose both indices are below ``first_new``."""
    lo, hi = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    code = np.sort((lo * n + hi)[(lo != hi) & (hi >= first_new)])
    first = np.ones(len(code), dtype=bool)  # np.unique is much slower here (numpy 2.4 hashes)
    first[1:] = code[1:] != code[:-1]
    code = code[first]
    return np.stack([code // n, code % n], axis=1).astype(np.int64, copy=False)


def candidate_pairs(lines2d: np.ndarray, gap_px: float, config: LineDetectConfig) -> np.ndarray:
    """Returns (C, 2) int64 index pairs ``i < j`` of segments that may be collinear and adjacent.

    Segments are cut into pieces no longer than ``2 gap_px``; a k-d tree over (angle, x, y of the piece's
    midpoint) finds pairs of similar direction whose pieces' extents may be within ``gap_px``: every pair
    with a gap along the joint line below ``gap_px``, and few others. ``_join`` decides. The angle
    tolerance is twice the merge angle so that a joint segment's partners are among its fragments'.
    """
    if len(lines2d) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    angle_rad = 2.0 * math.radians(config.merge_angle_deg)
    piece = 2.0 * max(gap_px, 1.0)
    # midpoints of two pieces (half-length <= piece / 2) at most gap_px apart (plus the offsets)
    reach = piece + gap_px + 2.0 * config.merge_offset_px
    x1, y1, x2, y2 = lines2d.T
    counts = np.ceil(np.hypot(x2 - x1, y2 - y1) / piece).astype(np.int64).clip(1, None)
    owner = np.repeat(np.arange(len(lines2d)), counts)
    t = (np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts) + 0.5) / counts[owner]
    keys = np.empty((len(owner), 3))
    keys[:, 0] = np.mod(np.arctan2(y2 - y1, x2 - x1), np.pi)[owner] / angle_rad
    keys[:, 1] = (x1[owner] + t * (x2 - x1)[owner]) / reach
    keys[:, 2] = (y1[owner] + t * (y2 - y1)[owner]) / reach
    # angles wrap at pi: mirrored copies of the pieces near it
    wrap = np.flatnonzero(keys[:, 0] > np.pi / angle_rad - 1.0)
    keys = np.concatenate([keys, keys[wrap] - np.array([np.pi / angle_rad, 0.0, 0.0])])
    owner = np.concatenate([owner, owner[wrap]])
    found = cKDTree(keys).query_pairs(1.0, p=np.inf, output_type="ndarray")
    i, j = _unique_pairs(owner[found], len(lines2d)).T  # also drops a segment's pairs with itself
    # whole segments: midpoints no farther apart than the half-lengths, the gap and the offsets
    half, mx, my = 0.5 * np.hypot(x2 - x1, y2 - y1), 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    close = (
        np.hypot(mx[i] - mx[j], my[i] - my[j]) <= half[i] + half[j] + gap_px + 2.0 * config.merge_offset_px
    )
    return np.stack([i[close], j[close]], axis=1)


def _join(
    lines2d: np.ndarray, pairs: np.ndarray, config: LineDetectConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((C, 4) joint segments, (C,) bool mergeable, (C,) gap px, negative for overlap) of pairs.

    The joint line passes through the length-weighted centroid of both midpoints along the
    length-weighted mean direction; it spans the extreme projections of the four endpoints.
    Written column by column: numpy reductions over a short last axis cost more than the arithmetic.
    """
    a, b = lines2d[pairs[:, 0]].T, lines2d[pairs[:, 1]].T  # (4, C) each
    ax, ay, bx, by = a[2] - a[0], a[3] - a[1], b[2] - b[0], b[3] - b[1]
    wa, wb = np.hypot(ax, ay), np.hypot(bx, by)
    dot = ax * bx + ay * by
    # length x unit direction is the segment's vector: their sum (polarities aligned) is the weighted mean
    sign = np.where(dot < 0, -1.0, 1.0)
    ux, uy = ax + sign * bx, ay + sign * by
    # keep the longer fragment's orientation (LSD's gradient polarity) for the joint segment
    longer = wa >= wb
    flip = np.where(ux * np.where(longer, ax, bx) + uy * np.where(longer, ay, by) < 0, -1.0, 1.0)
    norm = flip / np.maximum(np.hypot(ux, uy), 1e-300)
    ux, uy = ux * norm, uy * norm
    total = 2.0 * np.maximum(wa + wb, 1e-300)
    cx = (wa * (a[0] + a[2]) + wb * (b[0] + b[2])) / total
    cy = (wa * (a[1] + a[3]) + wb * (b[1] + b[3])) / total
    ends = [(a[0], a[1]), (a[2], a[3]), (b[0], b[1]), (b[2], b[3])]
    along = [(x - cx) * ux + (y - cy) * uy for x, y in ends]
    off = np.maximum.reduce([np.abs((x - cx) * uy - (y - cy) * ux) for x, y in ends])
    lo_a, hi_a = np.minimum(along[0], along[1]), np.maximum(along[0], along[1])
    lo_b, hi_b = np.minimum(along[2], along[3]), np.maximum(along[2], along[3])
    gap = np.maximum(lo_a, lo_b) - np.minimum(hi_a, hi_b)
    lo, hi = np.minimum(lo_a, lo_b), np.maximum(hi_a, hi_b)
    merged = np.stack([cx + lo * ux, cy + lo * uy, cx + hi * ux, cy + hi * uy], axis=1)
    cos_tol = math.cos(math.radians(config.merge_angle_deg))
    ok = (np.abs(dot) >= cos_tol * wa * wb) & (off <= config.merge_offset_px)
    return merged, ok, gap


def _disjoint_best(pairs: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Returns indices into ``pairs`` of a greedy set of disjoint pairs, lowest score first."""
    used: set[int] = set()
    pick = []
    for k in np.argsort(score, kind="stable"):
        i, j = int(pairs[k, 0]), int(pairs[k, 1])
        if i not in used and j not in used:
            used.update((i, j))
            pick.append(k)
    return np.asarray(pick, dtype=np.int64)
