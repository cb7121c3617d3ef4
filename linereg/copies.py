"""Copies of what a pose sees elsewhere in the map: the rivals a symmetric or repeated map makes.

A pose explains an image through the map corners it matched. Wherever the map repeats those corners (a
building's 180-degree twin, the next window bay, a courtyard turned by 90 degrees), a camera placed and
turned accordingly sees the same corners in the same places and explains the same image lines. Such a copy
is the one rival a significance test cannot see (the repetition is the map's, not chance), and the search
need not have solved it. It is found from the map alone: under each rotation candidate R' the matched
corners q of the pose (R, c), turned by ``S = R'^T R``, must land on map corners X of the same arm
directions, so the copy's camera centre is ``X - S (q - c)`` for some pairing; where many corners agree on
it, the copy is. Every pairing votes, so no copy sharing that many corners is missed (within the voxel
the votes are counted in), whatever the search did.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
from scipy.spatial import cKDTree

from .camera import Camera
from .config import DecideConfig
from .geometry import camera_center, make_cam_from_world, project_points, rotation_error_deg
from .points import Points
from .search import MapSignatures
from .significance import depth_of


def copy_starts(
    cam_from_world: np.ndarray,
    matched: np.ndarray,
    map_pts: Points,
    signatures: MapSignatures,
    lines3d: np.ndarray,
    camera: Camera,
    rotations: list[np.ndarray],
    arm_angle_deg: float,
    config: DecideConfig,
    regions: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[tuple[np.ndarray, float, float]]:
    """Returns (start cam_from_world, size_m, share) of the copies of a pose's matched corners: under each
    (3, 3) rotation in ``rotations`` (and the pose's own), every camera centre on which corners holding at
    least ``copy_share`` of the matched corners' weight agree, best first, each known to within ``size_m``;
    the pose itself (closer than ``distinct_fraction`` of its depth at its own rotation) is left out. A
    window lattice gives many (each bay's shift shares nearly all corners): which of them are rivals is the
    score's to say (``pipeline.copy_rivals``), not the share's.

    matched: (M,) bool map segments the pose matched; map_pts, signatures: the map's corners and their arm
    codes (``search.map_signatures``); arm_angle_deg: how far a turned arm may be from a map direction;
    regions: boxes ((3,) low, (3,) high) the copies' centres must lie in (None: anywhere): a prior's, so that
    the copies counted are those it admits, and a large map's pairings elsewhere cost nothing.
    """
    R, c = cam_from_world[:3, :3], camera_center(cam_from_world)
    codes = signatures.codes
    q = _seen_corners(cam_from_world, matched, map_pts, codes, camera)
    if len(q) < 3:
        return []
    weight = map_pts.weight[q]
    total = float(weight.sum())
    depth = depth_of(lines3d[matched], cam_from_world)
    # voxels of the distinctness radius: a copy closer than that to the pose is the pose
    voxel = config.distinct_fraction * depth
    cos_arm = np.cos(np.radians(arm_angle_deg))
    order, sorted_keys = signatures.order, signatures.keys
    if (
        regions is not None
    ):  # a copy's corner X = centre + S (q - c) lies within the corners' reach of a region
        reach = float(np.linalg.norm(map_pts.positions[q] - c, axis=1).max())
        near = np.zeros(len(map_pts), dtype=bool)
        for lo, hi in regions:
            near |= np.all((map_pts.positions >= lo - reach) & (map_pts.positions <= hi + reach), axis=1)
        kept = near[order]
        order, sorted_keys = order[kept], sorted_keys[kept]
    turns: list[np.ndarray] = []
    out: list[tuple[np.ndarray, float, float]] = []
    for R_copy in [R, *rotations]:
        S = R_copy.T @ R
        if any(rotation_error_deg(S, T) < arm_angle_deg for T in turns):
            continue
        turns.append(S)
        keys = _turned_keys(codes[q], S, signatures.directions, cos_arm)
        k, m = _compatible(keys, order, sorted_keys)
        if len(k) == 0:
            continue
        centres = map_pts.positions[m] - (map_pts.positions[q[k]] - c) @ S.T
        if regions is not None:
            inside = np.zeros(len(centres), dtype=bool)
            for lo, hi in regions:
                inside |= np.all((centres >= lo) & (centres <= hi), axis=1)
            centres, k = centres[inside], k[inside]
            if len(k) == 0:
                continue
        own = rotation_error_deg(S, np.eye(3)) < config.distinct_angle_deg
        for centre, share in _agreements(
            centres, k, weight, total, voxel, config.copy_share, c if own else None
        ):
            out.append((make_cam_from_world(R_copy, -R_copy @ centre), voxel, share))
    out.sort(key=lambda s: -s[2])
    return out


def _seen_corners(
    cam_from_world: np.ndarray, matched: np.ndarray, map_pts: Points, codes: np.ndarray, camera: Camera
) -> np.ndarray:
    """Returns the indices of the map points in front of the camera and inside the image with every arm on
    a matched segment and in a cluster."""
    seg = map_pts.arm_segments
    on = (seg[:, 0] >= 0) & matched[np.maximum(seg[:, 0], 0)]
    on &= (seg[:, 1] < 0) | matched[np.maximum(seg[:, 1], 0)]
    on &= (codes[:, 0] >= 0) & ((codes[:, 1] >= 0) | (seg[:, 1] < 0))
    x = map_pts.positions @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    on &= x[:, 2] > 1e-6
    uv = project_points(camera, x[on])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    return np.flatnonzero(on)[inside]


def _turned_keys(codes: np.ndarray, S: np.ndarray, directions: np.ndarray, cos_arm: float) -> np.ndarray:
    """Returns (Q,) the signature keys (``search.MapSignatures``) of points with arm ``codes`` (Q, 2) once
    turned by S: each cluster goes to the cluster its turned direction falls on (sign kept in the code);
    -1 where an arm's cluster falls on none."""
    nc = 2 * len(directions)
    dots = (directions @ S.T) @ directions.T  # [c, c']: turned cluster c against cluster c'
    target = np.argmax(np.abs(dots), axis=1)
    sign = dots[np.arange(len(directions)), target]
    code_map = np.full(nc, -1, np.int64)
    ok = np.abs(sign) >= cos_arm
    for a in range(2):  # arm along (0) or against (1) its cluster's direction
        code_map[2 * np.arange(len(directions)) + a] = np.where(ok, 2 * target + (a ^ (sign < 0)), -1)
    first = code_map[np.maximum(codes[:, 0], 0)]
    two = codes[:, 1] >= 0
    second = np.where(two, code_map[np.maximum(codes[:, 1], 0)], 0)
    lo, hi = np.minimum(first, second), np.maximum(first, second)
    keys = np.where(two, lo * nc + hi, nc * nc + first)
    return np.where((first < 0) | (two & (second < 0)), -1, keys)


def _compatible(
    keys: np.ndarray, order: np.ndarray, sorted_keys: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P,) k, (P,) m): every pair of a turned point k and a map point m of the same key, among the
    map points ``order`` whose keys are ``sorted_keys`` (``MapSignatures.order``, ``.keys`` or part of them)."""
    lo = np.searchsorted(sorted_keys, keys, "left")
    hi = np.searchsorted(sorted_keys, keys, "right")
    counts = np.where(keys >= 0, hi - lo, 0)
    k = np.repeat(np.arange(len(keys)), counts)
    start = np.repeat(lo - np.cumsum(counts) + counts, counts)
    return k, order[start + np.arange(len(k))]


@numba.njit(cache=True, nogil=True)
def _bound_kept(
    cell: np.ndarray, offsets: np.ndarray, weight: np.ndarray, bins: int, threshold: float
) -> np.ndarray:  # pragma: no cover - numba
    """Returns the sorted indices ``8 p + o`` of the votes (pair p of weight ``weight[p]`` in voxel
    ``cell[p] + offsets[o]``) whose bin (voxel modulo ``bins``) gathers at least ``threshold``: the bound
    ``_agreements`` cuts with, summed in vote order as ``np.bincount`` sums (the same floats), in three
    passes over the votes and no (8 P,) arrays (docs/measurements.md, session 47)."""
    bound = np.zeros(bins)
    for p in range(len(cell)):
        for o in range(8):
            bound[(cell[p] + offsets[o]) % bins] += weight[p]
    count = 0
    for p in range(len(cell)):
        for o in range(8):
            if bound[(cell[p] + offsets[o]) % bins] >= threshold:
                count += 1
    kept = np.empty(count, np.int64)
    count = 0
    for p in range(len(cell)):
        for o in range(8):
            if bound[(cell[p] + offsets[o]) % bins] >= threshold:
                kept[count] = 8 * p + o
                count += 1
    return kept


def _first_of_each(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((U,) the distinct values sorted, (U,) the index of each one's first occurrence) of (P,)
    int64 ``values``: what ``np.unique(values, return_index=True)`` returns, in a quarter of its time (an
    unstable sort, each run's smallest index, where it sorts stably)."""
    order = np.argsort(values)
    ordered = values[order]
    start = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    return ordered[start], np.minimum.reduceat(order, start)


def _agreements(
    centres: np.ndarray,
    k: np.ndarray,
    weight: np.ndarray,
    total: float,
    voxel: float,
    min_share: float,
    exclude: np.ndarray | None,
) -> list[tuple[np.ndarray, float]]:
    """Returns every (centre, share) where the (P, 3) ``centres`` of distinct points ``k`` agree within a
    voxel, holding at least ``min_share`` of the ``total`` weight, best first and each at least two voxels
    from a better one (and from ``exclude``): every centre votes in the 8 voxels nearest to it, so any two
    closer than a voxel on each axis share one; a point counts once per voxel."""
    base = np.floor(centres / voxel - 0.5).astype(np.int64)
    base -= base.min(axis=0)
    side = base.max(axis=0) + 2
    cell = (base[:, 0] * side[1] + base[:, 1]) * side[2] + base[:, 2]
    # the 8 voxels nearest each centre: offsets (0/1 on each axis) in the flattened index
    offsets = ((np.indices((2, 2, 2)).reshape(3, 8).T) * [side[1] * side[2], side[2], 1]).sum(axis=1)
    # only the voxels that can reach the share are counted exactly: a bound of each voxel's vote sums every
    # pair's weight (a point as often as it votes there, hashed voxels sharing a bin), and the exact count
    # below sorts the votes of the bins it keeps alone (the same result; on the demo photos 16 of 72 turns
    # keep none)
    bins = max(min(int(np.prod(side)), 16 * len(cell)), 1)
    kept = _bound_kept(cell, offsets, weight[k], bins, min_share * total * (1.0 - 1e-9))
    if len(kept) == 0:
        return []
    n = int(k.max()) + 1
    cells = cell[kept // 8] + offsets[kept % 8]  # the kept votes' voxels
    once, first = _first_of_each(cells * n + k[kept // 8])  # once per voxel
    first = kept[first]
    voxel_of = once // n  # sorted, as ``once`` is
    new = np.r_[True, voxel_of[1:] != voxel_of[:-1]]
    ids, inverse = voxel_of[new], np.cumsum(new) - 1
    votes = np.bincount(inverse, weights=weight[once % n], minlength=len(ids))
    pair = first // 8  # the pair (row of ``centres``) behind each (voxel, point) vote
    ranked = np.argsort(-votes, kind="stable")
    ranked = ranked[votes[ranked] / total >= min_share]
    if len(ranked) == 0:
        return []
    # each voxel's centre: the median of the centres of its votes' pairs, all voxels at once
    by_voxel = np.argsort(inverse, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(inverse, minlength=len(ids)))]
    counts = bounds[ranked + 1] - bounds[ranked]
    offsets = np.r_[0, np.cumsum(counts)[:-1]]
    rows = pair[by_voxel[np.repeat(bounds[ranked] - offsets, counts) + np.arange(counts.sum())]]
    group = np.repeat(np.arange(len(ranked)), counts)
    medians = np.empty((len(ranked), 3))
    for axis in range(3):
        values = centres[rows, axis][np.lexsort((centres[rows, axis], group))]
        low, high = values[offsets + (counts - 1) // 2], values[offsets + counts // 2]
        medians[:, axis] = np.where(counts % 2 == 1, low, 0.5 * (low + high))
    # best first, each kept unless closer than two voxels to one kept before it (or to ``exclude``)
    radius = np.nextafter(2.0 * voxel, 0.0)
    near = cKDTree(medians).query_ball_point(medians, radius)
    dropped = np.zeros(len(ranked), dtype=bool)
    if exclude is not None:
        dropped |= np.linalg.norm(medians - exclude, axis=1) < 2 * voxel
    out: list[tuple[np.ndarray, float]] = []
    for i in range(len(ranked)):
        if dropped[i]:
            continue
        dropped[near[i]] = True
        out.append((medians[i], float(votes[ranked[i]]) / total))
    return out
