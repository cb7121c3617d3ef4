"""Collinear 3D segments: pieces along one line merged, pieces along a better line dropped (part of
``lines3d.extract``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig
from .neighbours import flat_lists


def drop_near(
    segments: np.ndarray, reference: np.ndarray, distance: np.ndarray, angle_deg: float
) -> np.ndarray:
    """Returns the (k, 6) segments that do not run along a reference segment (within (k,) ``distance``
    and angle_deg): a region's contour along a crease is the crease's intersection line, only less exact."""
    return segments[~along(segments, reference, distance, angle_deg)]


def along(segments: np.ndarray, reference: np.ndarray, distance: np.ndarray, angle_deg: float) -> np.ndarray:
    """Returns (k,) bool: does each (k, 6) segment run along one of the (r, 6) reference segments (both its
    ends within (k,) ``distance`` of it, its direction within angle_deg)?

    Only the pairs whose first end lies near a reference (``_near_references``) are measured: a dense
    (k, r, 3) test of every pair took a second for a room's thousands of point edges. The measured pairs
    give the same answers, their numbers computed the same way.
    """
    if len(segments) == 0 or len(reference) == 0:
        return np.zeros(len(segments), dtype=bool)
    distance = np.broadcast_to(np.asarray(distance, dtype=np.float64), (len(segments),))
    r0, r1 = reference[:, :3], reference[:, 3:]
    rlen = np.linalg.norm(r1 - r0, axis=1)
    rdir = (r1 - r0) / rlen[:, None]
    sdir = segments[:, 3:] - segments[:, :3]
    sdir /= np.linalg.norm(sdir, axis=1, keepdims=True)
    parallel = np.abs(sdir @ rdir.T) >= np.cos(np.radians(angle_deg))
    s, r = _near_references(segments[:, :3], r0, rdir, rlen, distance)
    keep = parallel[s, r]
    s, r = s[keep], r[keep]
    near = np.ones(len(s), dtype=bool)
    for end in (segments[:, :3], segments[:, 3:]):  # both endpoints within distance of the reference
        rel = end[s] - r0[r]
        t = np.clip(np.einsum("pj,pj->p", rel, rdir[r]), -distance[s], rlen[r] + distance[s])
        near &= np.linalg.norm(rel - t[:, None] * rdir[r], axis=1) <= distance[s]
    out = np.zeros(len(segments), dtype=bool)
    out[s[near]] = True
    return out


def _near_references(
    ends: np.ndarray, r0: np.ndarray, rdir: np.ndarray, rlen: np.ndarray, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((q,) segment, (q,) reference) distinct pairs, a superset of those whose (k, 3) ``ends`` lie
    within (k,) ``distance`` of the reference's line clipped to [-distance, length + distance].

    References are sampled every ``step``: such an end lies within distance + step / 2 of a sample.
    """
    reach = float(distance.max())
    step = max(4.0 * reach, 1e-3)
    count = np.ceil((rlen + 2.0 * reach) / step).astype(np.int64) + 1
    ref = np.repeat(np.arange(len(r0)), count)
    pos = np.arange(len(ref)) - np.repeat(np.cumsum(count) - count, count)
    samples = r0[ref] + (np.minimum(pos * step, rlen[ref] + 2.0 * reach) - reach)[:, None] * rdir[ref]
    # a hair wider: rounding must not decide whether a pair is measured
    radius = (distance + 0.5 * step) * (1.0 + 1e-9) + 1e-9
    found = cKDTree(samples).query_ball_point(ends, radius, return_sorted=False)
    sizes, hits = flat_lists(found)
    key = np.unique(np.repeat(np.arange(len(ends)), sizes) * len(r0) + ref[hits])
    return key // len(r0), key % len(r0)


def merge_collinear(
    segments: np.ndarray, priority: np.ndarray, config: Lines3DConfig, return_seeds: bool = False
) -> Any:
    """Returns (K, 6) segments with collinear, overlapping or nearly touching pieces merged into one
    (with ``return_seeds``: and the (K,) int64 input row each merged segment grew from).

    Seeds go by (priority, longest first); a seed keeps its own line and grows to cover the extent of
    every segment within collinear_angle_deg, collinear_distance_m of it and collinear_gap_m along it.
    """
    if len(segments) == 0:
        return (np.zeros((0, 6)), np.zeros(0, np.int64)) if return_seeds else np.zeros((0, 6))
    rows = np.arange(len(segments))
    p, q = segments[:, :3], segments[:, 3:]
    lengths = np.linalg.norm(q - p, axis=1)
    keep = lengths > 1e-9
    p, q, lengths, priority, rows = p[keep], q[keep], lengths[keep], priority[keep], rows[keep]
    dirs = (q - p) / lengths[:, None]
    seed_of, member, lo, hi = _collinear_pairs(p, q, dirs, config)
    starts = np.searchsorted(seed_of, np.arange(len(p) + 1))
    gap = config.collinear_gap_m
    free = np.ones(len(p), dtype=bool)
    out, seeds = [], []
    for i in np.lexsort((-lengths, priority)):
        if not free[i]:
            continue
        free[i] = False
        t0, t1 = 0.0, lengths[i]
        cand, c_lo, c_hi = (x[starts[i] : starts[i + 1]] for x in (member, lo, hi))
        grew = len(cand) > 0
        while grew:  # absorbing a piece may bring the next one within the gap
            take = free[cand] & (c_lo <= t1 + gap) & (c_hi >= t0 - gap)
            grew = bool(take.any())
            if grew:
                t0, t1 = min(t0, c_lo[take].min()), max(t1, c_hi[take].max())
                free[cand[take]] = False
        if t1 - t0 >= config.min_length_m:
            out.append(np.r_[p[i] + t0 * dirs[i], p[i] + t1 * dirs[i]])
            seeds.append(rows[i])
    merged = np.array(out).reshape(-1, 6)
    return (merged, np.array(seeds, dtype=np.int64)) if return_seeds else merged


def _collinear_pairs(p: np.ndarray, q: np.ndarray, dirs: np.ndarray, config: Lines3DConfig):
    """Returns ((c,) seed, (c,) member, (c,) lo, (c,) hi) sorted by seed: the pairs of distinct (N,)
    segments p-q (unit ``dirs``) where the member is parallel to the seed within collinear_angle_deg and
    both its ends lie within collinear_distance_m of the seed's line, with the member's extent [lo, hi]
    along the seed's line (from the seed's start).

    Candidates are the segments of one direction group whose midpoints, seen along the group's
    direction, lie within 2 collinear_distance_m + collinear_slack_m of each other: all pairs but those of
    long lines both tilted within the angle, far apart along them.
    """
    mid = 0.5 * (p + q)
    seeds, members = [], []
    for group in _direction_groups(dirs, np.linalg.norm(q - p, axis=1), config.collinear_angle_deg):
        if len(group) < 2:
            continue
        axis = dirs[group[0]]
        across = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]  # two axes normal to it
        pairs = cKDTree(mid[group] @ across).query_pairs(
            2.0 * config.collinear_distance_m + config.collinear_slack_m, output_type="ndarray"
        )
        seeds.append(group[np.r_[pairs[:, 0], pairs[:, 1]]])
        members.append(group[np.r_[pairs[:, 1], pairs[:, 0]]])
    seed, c = (
        np.concatenate([np.zeros(0, np.int64), *seeds]),
        np.concatenate([np.zeros(0, np.int64), *members]),
    )
    parallel = np.abs(np.einsum("ck,ck->c", dirs[c], dirs[seed])) >= np.cos(
        np.radians(config.collinear_angle_deg)
    )
    seed, c = seed[parallel], c[parallel]
    tp = np.einsum("ck,ck->c", p[c] - p[seed], dirs[seed])
    tq = np.einsum("ck,ck->c", q[c] - p[seed], dirs[seed])
    dp = np.linalg.norm(p[c] - p[seed] - tp[:, None] * dirs[seed], axis=1)
    dq = np.linalg.norm(q[c] - p[seed] - tq[:, None] * dirs[seed], axis=1)
    close = (dp <= config.collinear_distance_m) & (dq <= config.collinear_distance_m)
    order = np.argsort(seed[close], kind="stable")
    return (
        seed[close][order],
        c[close][order],
        np.minimum(tp, tq)[close][order],
        np.maximum(tp, tq)[close][order],
    )


def _direction_groups(dirs: np.ndarray, lengths: np.ndarray, angle_deg: float) -> list[np.ndarray]:
    """Returns index arrays of the (N, 3) unit directions grouped greedily, longest first: a seed takes every
    free direction within 2 angle_deg (so that two within angle_deg of each other mostly share a group)."""
    cos_thr = np.cos(np.radians(2.0 * angle_deg))
    free = np.ones(len(dirs), dtype=bool)
    groups = []
    for seed in np.argsort(-lengths, kind="stable"):
        if free[seed]:
            idx = np.flatnonzero(free)
            group = idx[np.abs(dirs[idx] @ dirs[seed]) >= cos_thr]
            free[group] = False
            groups.append(np.r_[seed, group[group != seed]])  # the seed first: its direction is the axis
    return groups
