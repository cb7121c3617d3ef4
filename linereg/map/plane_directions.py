"""Map directions from planes: the dominant plane normals and their crease directions join the 3D clusters.

Line segments of a real cloud (RGB-D, sparse LiDAR) are short and ragged: their directions are off by
degrees, and a room's horizontal directions may have no cluster at all (docs/measurements.md).
The planes they come from are fitted to thousands of points each and are far more exact. A line lies in a
plane, so every direction a structured scene's lines take is either where two dominant planes meet (a
crease: ``n_a x n_b``) or, for a plane perpendicular to others, its normal (the floor's normal is the
direction of every vertical wall edge). Such a direction is only a line direction if some dominant plane
contains it; its plane support is the boundary length those planes would give along it, ``2 sqrt(area)``
each (a W x H rectangle has 2W of edge along one side).

``map_clusters`` merges these directions with ``parallel_clusters`` of the segments: a plane direction
near a segment cluster is the same direction (the segments keep theirs), the others are added, segments
join the direction they are parallel to within their tolerance, and all are ranked by segment length plus
plane support.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..config import ParallelConfig, PlaneDirectionsConfig
from ..directions import DirectionClusters
from ..parallel import (
    as_segments,
    canonical_sign,
    parallel_clusters,
    principal_direction,
    tolerance_rad,
)

logger = logging.getLogger(__name__)


def dominant_normals(
    normals: np.ndarray, areas: np.ndarray, config: PlaneDirectionsConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 3) unit normals, (K,) areas m^2) of the dominant plane orientations, largest first.

    normals: (R, 3) unit normals of planar regions; areas: (R,) their areas (m^2). Greedy: the normal whose
    ``normal_angle_deg`` neighbourhood holds the most area, refitted (area-weighted), its members removed.
    """
    config = config or PlaneDirectionsConfig()
    normals, areas = np.asarray(normals, float).reshape(-1, 3), np.asarray(areas, float).reshape(-1)
    if len(areas) > config.max_regions:  # the largest regions hold the area; the (R, R) test stays small
        keep = np.argsort(-areas, kind="stable")[: config.max_regions]
        normals, areas = normals[keep], areas[keep]
    cos_thr = np.cos(np.radians(config.normal_angle_deg))
    left = areas > 0
    total = float(areas[left].sum())
    found: list[np.ndarray] = []
    found_area: list[float] = []
    near = np.abs(normals @ normals.T) >= cos_thr  # (R, R): regions are few (hundreds to a few thousand)
    while left.any() and len(found) < config.max_planes:
        score = near[:, left] @ areas[left]
        best = int(np.argmax(np.where(left, score, -1.0)))
        members = left & near[best]
        if areas[members].sum() < config.min_area_share * total:
            break
        found.append(principal_direction(normals[members], areas[members], largest=True))
        found_area.append(float(areas[members].sum()))
        left &= ~members
    return canonical_sign(np.array(found).reshape(-1, 3)), np.array(found_area)


def plane_directions(
    normals: np.ndarray, areas: np.ndarray, config: PlaneDirectionsConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((D, 3) unit line directions, (D,) plane support m) implied by dominant planes.

    Candidates are the dominant normals and the creases of every pair meeting at more than
    ``crease_min_angle_deg``; near-duplicates (``normal_angle_deg``) are one, and a candidate that lies
    within ``in_plane_deg`` of no dominant plane (support 0) is dropped.
    """
    config = config or PlaneDirectionsConfig()
    n, a = dominant_normals(normals, areas, config)
    if len(n) < 2:
        return np.zeros((0, 3)), np.zeros(0)
    i, j = np.triu_indices(len(n), 1)
    cross = np.cross(n[i], n[j])
    sine = np.linalg.norm(cross, axis=1)
    creases = cross[sine > np.sin(np.radians(config.crease_min_angle_deg))]
    creases /= np.linalg.norm(creases, axis=1, keepdims=True)
    candidates = np.concatenate([n, creases])
    in_plane = np.abs(candidates @ n.T) <= np.sin(np.radians(config.in_plane_deg))  # (C, K)
    support = in_plane @ (2.0 * np.sqrt(a))
    kept: list[int] = []
    cos_same = np.cos(np.radians(config.normal_angle_deg))
    for c in np.argsort(-support, kind="stable"):
        if support[c] > 0 and not any(abs(candidates[c] @ candidates[k]) >= cos_same for k in kept):
            kept.append(int(c))
    return canonical_sign(candidates[kept].reshape(-1, 3)), support[kept]


def map_clusters(
    lines3d: np.ndarray,
    normals: np.ndarray,
    areas: np.ndarray,
    config: ParallelConfig | None = None,
    planes: PlaneDirectionsConfig | None = None,
) -> DirectionClusters:
    """Returns the 3D direction clusters of (M, 6) segments with the directions of their planes added.

    normals: (R, 3) unit normals of the map's planar regions; areas: (R,) m^2. Segment clusters come from
    ``parallel_clusters`` (all of them, not only ``top_k``); a plane direction within ``merge_angle_deg``
    of one is that cluster, the others are added as directions of their own. Segments are labelled with
    the direction they are most parallel to within their tolerance; ``support`` is the members' length
    plus the plane support; at most ``config.top_k`` directions, strongest first. ``planes`` configures
    ``plane_directions``.
    """
    config = config or ParallelConfig()
    lines3d = as_segments(lines3d, "lines3d", 6)
    seg = parallel_clusters(lines3d, _all_clusters(config))
    extra, extra_support = plane_directions(normals, areas, planes)
    cos_merge = np.cos(np.radians(config.merge_angle_deg))
    plane_support = np.zeros(len(seg))
    added: list[np.ndarray] = []
    added_support: list[float] = []
    for d, s in zip(extra, extra_support, strict=True):
        close = np.abs(seg.directions @ d) >= cos_merge if len(seg) else np.zeros(0, dtype=bool)
        if close.any():
            plane_support[int(np.argmax(np.abs(seg.directions @ d)))] += s
        else:
            added.append(d)
            added_support.append(s)
    directions = np.concatenate([seg.directions, np.array(added).reshape(-1, 3)])
    bonus = np.concatenate([plane_support, added_support])
    d = lines3d[:, 3:6] - lines3d[:, 0:3]
    lengths = np.linalg.norm(d, axis=1)
    labels = _label(d / np.maximum(lengths, 1e-300)[:, None], lengths, directions, seg.labels, config)
    logger.debug("%d segment clusters, %d plane directions added", len(seg), len(added))
    return _ranked(directions, labels, lengths, bonus, config)


def _all_clusters(config: ParallelConfig) -> ParallelConfig:
    """Returns the config with ``top_k`` raised so that ``parallel_clusters`` keeps every cluster found."""
    return replace(config, top_k=max(config.num_clusters, config.top_k))


def _label(
    d: np.ndarray, lengths: np.ndarray, directions: np.ndarray, labels: np.ndarray, config: ParallelConfig
) -> np.ndarray:
    """Returns (M,) int64: the segment cluster's label if it had one, else the most parallel plane
    direction within the segment's tolerance, else -1."""
    if len(directions) == 0:
        return np.full(len(d), -1, dtype=np.int64)
    cos = np.abs(d @ directions.T)
    best = np.argmax(cos, axis=1)
    ok = (cos[np.arange(len(d)), best] >= np.cos(tolerance_rad(lengths, config))) & (lengths > 0)
    return np.where(labels >= 0, labels, np.where(ok, best, -1)).astype(np.int64)


def _ranked(
    directions: np.ndarray, labels: np.ndarray, lengths: np.ndarray, bonus: np.ndarray, config: ParallelConfig
) -> DirectionClusters:
    """Returns the clusters ordered by member length plus plane support, at most ``top_k``; a plane
    direction needs no members (its planes vouch for it), a segment cluster keeps ``min_lines``."""
    k = len(directions)
    assigned = labels >= 0
    support = np.bincount(labels[assigned], weights=lengths[assigned], minlength=k) + bonus
    order = np.argsort(-support, kind="stable")[: config.top_k]
    remap = np.full(k + 1, -1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    # support as ``parallel_clusters`` reports it (member length): localize recomputes it on the visible part
    member_length = np.bincount(labels[assigned], weights=lengths[assigned], minlength=k)
    return DirectionClusters(canonical_sign(directions[order]), remap[labels], member_length[order])
