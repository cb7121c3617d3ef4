"""Map directions from planes: the direction clusters of a line map take the directions of its dominant planes.

Line segments of a real cloud (RGB-D, sparse LiDAR) are short and ragged: their directions are off by
degrees, and a room's horizontal directions may have no cluster at all (docs/measurements.md).
The planes they come from are fitted to thousands of points each and are far more exact. A line lies in a
plane, so every direction a structured scene's lines take is either where two dominant planes meet (a
crease: ``n_a x n_b``) or, for a plane perpendicular to others, its normal (the floor's normal is the
direction of every vertical wall edge). Such a direction is only a line direction if some dominant plane
contains it; its plane support is the boundary length those planes would give along it, ``2 sqrt(area)``
each (a W x H rectangle has 2W of edge along one side).

``frame_directions`` keeps those of the scene's frame: a reference plane (a room's floor, a street's
ground) with the dominant planes perpendicular to it; tilted planes (a sofa's back, a misregistered wall)
give directions few lines take. ``map_clusters``, what ``LineMap.build`` clusters with by default, takes the
frame's directions as they are (a Kinect room's vertical segments lean 6-25 degrees, its segment clusters
are 5-16 degrees off the walls' frame, and its far-range clutter holds most of the segment length);
segments join the direction they are parallel to within their tolerance, and clusters of the other
segments follow the frame's directions. Maps whose segment clusters already lie within 1 degree of the
frame (an exact scan), and clouds without a frame (one dominant plane), keep the segments' own clusters.
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
    diverse_order,
    nearest_direction,
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
    weight = near.astype(np.float32)  # one conversion: a boolean product converts on every round
    while left.any() and len(found) < config.max_planes:
        score = weight @ np.where(left, areas, 0.0).astype(np.float32)
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


def frame_directions(
    normals: np.ndarray, areas: np.ndarray, config: PlaneDirectionsConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((D, 3) unit line directions, (D,) plane support m) of the scene's frame of dominant planes.

    A built scene stands on a floor or the ground: its walls are perpendicular to it, and so are its
    vertical edges to every horizontal one. The reference ``u`` is the dominant normal (``dominant_normals``)
    whose own area plus that of the dominant planes within ``perpendicular_deg`` of perpendicular to it
    (one per orientation: planes within twice that of a larger one count no more) is largest (the floor of a room, the ground of a street; in a box-like scene any axis gives the same
    frame). The directions are ``u`` (where two walls meet) and, for each such wall, its crease with the
    reference plane ``u x w`` and the horizontal across it ``(u x w) x u``; near-duplicates
    (``normal_angle_deg``) are one. Tilted dominant planes (a sofa's back, a misregistered wall) give
    none: their creases with the rest are directions few lines take. Support: ``2 sqrt(area)`` of each of
    the frame's planes a direction lies in (within ``in_plane_deg``). No wall perpendicular to any dominant
    plane: no directions.
    """
    config = config or PlaneDirectionsConfig()
    n, a = dominant_normals(normals, areas, config)
    if len(n) < 2:
        return np.zeros((0, 3)), np.zeros(0)
    cos = np.abs(n @ n.T)  # (K, K)
    perp = cos <= np.sin(np.radians(config.perpendicular_deg))
    # a wall counts once per orientation: a road and its sloped sidewalk, 5 degrees apart, are one ground,
    # not two walls that would make a facade the reference
    alike = cos >= np.cos(np.radians(2.0 * config.perpendicular_deg))
    walls_of = [_distinct(np.flatnonzero(perp[k]), alike) for k in range(len(n))]
    score = np.array([a[k] + a[w].sum() if len(w) else -1.0 for k, w in enumerate(walls_of)])
    u = int(np.argmax(score))
    if score[u] < 0:
        return np.zeros((0, 3)), np.zeros(0)
    walls = np.flatnonzero(perp[u])
    crease = np.cross(n[u], n[walls])
    crease /= np.linalg.norm(crease, axis=1, keepdims=True)
    across = np.cross(crease, n[u])
    candidates = np.concatenate([n[u][None], crease, across])
    frame = np.r_[u, walls]
    in_plane = np.abs(candidates @ n[frame].T) <= np.sin(np.radians(config.in_plane_deg))
    support = in_plane @ (2.0 * np.sqrt(a[frame]))
    kept: list[int] = []
    cos_same = np.cos(np.radians(config.normal_angle_deg))
    for c in np.argsort(-support, kind="stable"):
        if not any(abs(candidates[c] @ candidates[k]) >= cos_same for k in kept):
            kept.append(int(c))
    return canonical_sign(candidates[kept].reshape(-1, 3)), support[kept]


def _distinct(members: np.ndarray, alike: np.ndarray) -> np.ndarray:
    """Returns the (k,) ``members`` (dominant planes, largest first) not alike (``alike``: (K, K) bool) an
    earlier kept one."""
    kept: list[int] = []
    for m in members:
        if not alike[m, kept].any():
            kept.append(int(m))
    return np.array(kept, dtype=np.int64)


def map_clusters(
    lines3d: np.ndarray,
    normals: np.ndarray,
    areas: np.ndarray,
    config: ParallelConfig | None = None,
    planes: PlaneDirectionsConfig | None = None,
) -> DirectionClusters:
    """Returns the 3D direction clusters of (M, 6) segments, their directions taken from the planes.

    normals: (R, 3) unit normals of the map's planar regions; areas: (R,) m^2. The directions of
    ``frame_directions`` are exact (fitted to thousands of points): segments within their tolerance
    (``parallel.tolerance_rad``) of one are its members, and the direction stays the planes' (a real cloud's
    segments are biased: a Kinect room's vertical edges lean by degrees). The other segments form clusters of
    their own (``parallel_clusters``); one within ``merge_angle_deg`` of a plane direction joins it.
    Plane directions are ranked by plane support plus member length, and, with ``planes.planes_first``,
    precede the segment-only clusters (ranked by member length, at least ``min_lines`` members): a real
    map's far-range clutter holds more segment length than its structure. Within each group,
    ``diverse_order`` picks (a direction a few degrees from a stronger one adds nothing); at most
    ``config.top_k``. ``support`` is the members' length plus the plane support. Without plane directions,
    or when the segments' own clusters are the planes' directions already (each within the paper's
    ``parallel_angle_deg`` of one: an exact scan), this is ``parallel_clusters`` (the segments' clusters
    and members unchanged).
    """
    config = config or ParallelConfig()
    planes = planes or PlaneDirectionsConfig()
    lines3d = as_segments(lines3d, "lines3d", 6)
    fixed, bonus = frame_directions(normals, areas, planes)
    alone = parallel_clusters(lines3d, config)
    if len(fixed) == 0 or len(lines3d) == 0 or _agree(alone.directions, fixed, config):
        return alone
    d = lines3d[:, 3:6] - lines3d[:, 0:3]
    lengths = np.linalg.norm(d, axis=1)
    d /= np.maximum(lengths, 1e-300)[:, None]
    cos_thr = np.cos(tolerance_rad(lengths, config))
    on_plane = nearest_direction(d, fixed, cos_thr, lengths > 0)
    rest = np.flatnonzero(on_plane < 0)
    seg = parallel_clusters(lines3d[rest], _all_clusters(config))
    cos_merge = np.cos(np.radians(config.merge_angle_deg))
    apart = np.max(np.abs(seg.directions @ fixed.T), axis=1, initial=0.0) < cos_merge
    directions = np.concatenate([fixed, seg.directions[apart]])
    labels = nearest_direction(d, directions, cos_thr, lengths > 0)
    member = np.bincount(labels[labels >= 0], weights=lengths[labels >= 0], minlength=len(directions))
    count = np.bincount(labels[labels >= 0], minlength=len(directions))
    score = member + np.r_[bonus, np.zeros(int(apart.sum()))]
    is_plane = np.arange(len(directions)) < len(fixed)
    eligible = is_plane | (count >= config.min_lines)
    groups = [is_plane, eligible & ~is_plane] if planes.planes_first else [eligible]
    order: list[int] = []
    for group in groups:
        idx = np.flatnonzero(group)
        if len(order) < config.top_k:
            picked = idx[diverse_order(directions[idx], score[idx], config.top_k - len(order))]
            order += list(picked[np.argsort(-score[picked], kind="stable")])
    order_arr = np.array(order, dtype=np.int64)
    remap = np.full(len(directions) + 1, -1, dtype=np.int64)  # remap[-1] stays -1 for unassigned segments
    remap[order_arr] = np.arange(len(order_arr))
    logger.debug(
        "%d plane directions, %d segment-only clusters; kept %d plane, %d segment",
        len(fixed),
        int(apart.sum()),
        int(is_plane[order_arr].sum()),
        int((~is_plane[order_arr]).sum()),
    )
    return DirectionClusters(canonical_sign(directions[order_arr]), remap[labels], score[order_arr])


def _agree(clusters: np.ndarray, fixed: np.ndarray, config: ParallelConfig) -> bool:
    """Returns whether the (K, 3) directions of the segments' own clusters are as many as the map keeps
    (``top_k``, or all (F, 3) plane directions if fewer) and each is parallel (``parallel_angle_deg``) to a
    plane direction: the segments already show the planes' frame."""
    if len(clusters) < min(config.top_k, len(fixed)):
        return False
    cos = np.abs(clusters @ fixed.T).max(axis=1, initial=0.0)
    return bool(np.all(cos >= np.cos(np.radians(config.parallel_angle_deg))))


def _all_clusters(config: ParallelConfig) -> ParallelConfig:
    """Returns the config with ``top_k`` raised so that ``parallel_clusters`` keeps every cluster found."""
    return replace(config, top_k=max(config.num_clusters, config.top_k))
