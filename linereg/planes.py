"""Planar regions of a point cloud by region growing over voxel plane fits (Lu et al. 2019, section 3.1).

Normals come from local PCA, one fit per occupied voxel (a cubic neighbourhood: as fast as a voxel hash,
no per-point neighbour search). Planar voxels whose normals and offsets agree are grown into regions
(connected components), near-coplanar adjacent regions are merged, then every point, including those in
voxels straddling a crease, joins the adjacent region whose plane it lies on.
All coordinates are local (the caller subtracts a georeferenced offset first).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .config import Lines3DConfig
from .voxels import (
    AROUND,
    Moments,
    Voxels,
    adjacent_pairs,
    build_voxels,
    combine_moments,
    fit_planes,
    moments,
    neighbors,
    plane_distances,
    plane_fits,
    voxel_downsample,
)

__all__ = ["Planes", "fit_planes", "grow_regions", "segment_planes", "voxel_downsample"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Planes:
    """Planar regions: ``labels`` (P,) int64 region of each point (-1: none), per region ``normals`` (R, 3),
    ``centroids`` (R, 3), ``counts`` (R,), ``pairs`` (Q, 2) int64 regions that touch, and the estimated
    point spacing of each region ``spacing_m`` (R,) float64."""

    labels: np.ndarray
    normals: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray
    pairs: np.ndarray
    spacing_m: np.ndarray


def grow_regions(
    voxels: Voxels, centroids: np.ndarray, normals: np.ndarray, curvature: np.ndarray, config: Lines3DConfig
) -> np.ndarray:
    """Returns (V,) int64 region label of each voxel (-1: not planar), by growing over similar neighbours.

    ``centroids`` (V, 3), ``normals`` (V, 3), ``curvature`` (V,) are the voxels' plane fits (``fit_planes``).
    """
    planar = (voxels.counts >= config.min_voxel_points) & (curvature <= config.max_curvature)
    a, b = adjacent_pairs(voxels, planar)
    n, c = normals, centroids
    cos_thr = np.cos(np.radians(config.angle_deg))
    delta = c[b] - c[a]
    ok = np.abs(np.einsum("ij,ij->i", n[a], n[b])) >= cos_thr
    ok &= np.abs(np.einsum("ij,ij->i", n[a], delta)) <= config.distance_m
    ok &= np.abs(np.einsum("ij,ij->i", n[b], delta)) <= config.distance_m
    # components of the planar voxels only (a sparse scan's voxels are mostly not planar)
    index = np.flatnonzero(planar)
    local = np.full(len(planar), -1, dtype=np.int64)
    local[index] = np.arange(len(index))
    out = np.full(len(planar), -1, dtype=np.int64)
    out[index] = _components(len(index), local[a[ok]], local[b[ok]])
    return out


def _components(num: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (num,) int64 connected component of each node of the undirected graph of edges (a, b)."""
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(num, num))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _relabel(labels: np.ndarray, min_count: int) -> np.ndarray:
    """Returns labels renumbered 0.. by decreasing size, groups smaller than ``min_count`` set to -1."""
    valid = labels >= 0
    counts = np.bincount(labels[valid]) if valid.any() else np.zeros(0, dtype=np.int64)
    out = np.full_like(labels, -1)
    out[valid] = _renumber(counts, min_count)[labels[valid]]
    return out


def _renumber(counts: np.ndarray, min_count: int) -> np.ndarray:
    """Returns (G,) int64 new number of each group of (G,) ``counts``: 0.. by decreasing count (ties keep
    their order), -1 for groups smaller than ``min_count``."""
    order = np.argsort(-counts, kind="stable")
    new_of_old = np.full(len(counts), -1, dtype=np.int64)
    kept = order[counts[order] >= min_count]
    new_of_old[kept] = np.arange(len(kept))
    return new_of_old


def _touching(voxels: Voxels, point_labels: np.ndarray) -> np.ndarray:
    """Returns (Q, 3) int64 (region a < region b, count) of regions sharing a voxel or adjacent voxels."""
    voxel, label, votes = _voxel_labels(voxels.of_point, point_labels)
    same = voxel[:-1] == voxel[1:]  # one voxel holding two regions: a crease voxel
    pairs = [np.stack([label[:-1][same], label[1:][same]], axis=1)]
    # the majority region of each voxel, then 26-adjacent voxels with different majorities
    major = _majority(voxel, label, votes, len(voxels.flat))
    a, b = adjacent_pairs(voxels, major >= 0)
    pairs.append(np.stack([major[a], major[b]], axis=1))
    pairs_all = np.concatenate(pairs)
    pairs_all = pairs_all[pairs_all[:, 0] != pairs_all[:, 1]]
    pairs_all.sort(axis=1)
    num = int(point_labels.max()) + 1 if len(pairs_all) else 1
    uniq, count = np.unique(pairs_all[:, 0] * num + pairs_all[:, 1], return_counts=True)
    return np.stack([uniq // num, uniq % num, count], axis=1)


def _merge_coplanar(
    labels: np.ndarray, points: np.ndarray, voxels: Voxels, config: Lines3DConfig
) -> tuple[np.ndarray, Moments]:
    """Returns ((P,) int64 point labels with adjacent near-coplanar regions merged (Lu et al.: region
    merging), numbered 0.. by decreasing size, and the merged regions' moments)."""
    num = int(labels.max()) + 1
    fits = moments(points, labels, num)
    cen, (nrm, _) = fits.centroids, plane_fits(fits)
    pairs = _touching(voxels, labels)[:, :2]
    a, b = pairs[:, 0], pairs[:, 1]
    ok = np.abs(np.einsum("ij,ij->i", nrm[a], nrm[b])) >= np.cos(np.radians(config.merge_angle_deg))
    ok &= np.abs(np.einsum("ij,ij->i", nrm[a], cen[b] - cen[a])) <= config.merge_distance_m
    ok &= np.abs(np.einsum("ij,ij->i", nrm[b], cen[a] - cen[b])) <= config.merge_distance_m
    comp = _components(num, a[ok], b[ok])
    merged = _renumber(np.bincount(comp, fits.counts, num).astype(np.int64), 1)[comp]
    out = np.full_like(labels, -1)
    out[labels >= 0] = merged[labels[labels >= 0]]
    return out, combine_moments(fits, merged, int(merged.max()) + 1)


def _assign_points(
    points: np.ndarray, voxels: Voxels, voxel_fits: Moments, voxel_labels: np.ndarray, config: Lines3DConfig
) -> np.ndarray:
    """Returns (P,) labels: each point joins the nearest plane (within distance_m) among the regions of its
    own and its 26 neighbouring voxels; planes are fitted on the points of each region's planar voxels
    (from the voxels' ``moments``). Ties go to the lower label."""
    regions = combine_moments(voxel_fits, voxel_labels, int(voxel_labels.max()) + 1)
    # distances are |(x - c) . n|: the normals' signs do not matter, so the faster closed form does
    cen, (nrm, _) = regions.centroids, plane_fits(regions, closed_form=True)
    table = _candidates(voxels, voxel_labels)
    per_point = (table >= 0).sum(axis=1)[voxels.of_point]
    labels = np.full(len(points), -1, dtype=np.int64)
    # most points have one candidate region: its distance decides
    one = np.flatnonzero(per_point == 1)
    c = table[voxels.of_point[one], 0]
    near = plane_distances(points, one, cen, nrm, c) <= config.distance_m
    labels[one[near]] = c[near]
    # points in crease voxels: one row per (point, candidate region), the nearest plane wins
    many = np.flatnonzero(per_point > 1)
    per_point = per_point[many]
    point = np.repeat(np.arange(len(many)), per_point)
    first = np.cumsum(per_point) - per_point  # row of each point's first candidate
    c = table[voxels.of_point[many][point], np.arange(len(point)) - first[point]]
    dist = plane_distances(points, many[point], cen, nrm, c)
    dist[dist > config.distance_m] = np.inf
    labels[many] = _nearest(point, c, dist, len(many))
    return labels


def _candidates(voxels: Voxels, voxel_labels: np.ndarray) -> np.ndarray:
    """Returns (V, K) int64 the distinct regions among each voxel's 27 (itself and its 26 neighbours),
    first columns first, padded with -1."""
    region_voxels = np.flatnonzero(voxel_labels >= 0)
    around = neighbors(voxels, region_voxels, AROUND)
    target = around.ravel()
    label = np.repeat(voxel_labels[region_voxels], around.shape[1])
    target, label = target[target >= 0], label[target >= 0]
    # each pass writes one of the regions a voxel receives (the last write wins) and keeps the others:
    # as many passes as regions meet in a voxel (a few), no sort of the 27 x (region voxels) pairs
    columns = []
    while len(target):
        column = np.full(len(voxels.flat), -1, dtype=np.int64)
        column[target] = label
        columns.append(column)
        rest = column[target] != label
        target, label = target[rest], label[rest]
    return np.stack(columns, axis=1) if columns else np.full((len(voxels.flat), 1), -1, dtype=np.int64)


def _nearest(group: np.ndarray, value: np.ndarray, key: np.ndarray, num: int) -> np.ndarray:
    """Returns (num,) int64 the ``value`` of smallest finite ``key`` in each group, the smallest value on
    ties (-1: none); rows (N,) are sorted by ``group``."""
    finite = np.isfinite(key)
    group, value, key = group[finite], value[finite], key[finite]
    out = np.full(num, -1, dtype=np.int64)
    if len(group) == 0:
        return out
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    best = np.minimum.reduceat(key, starts)
    rows = np.flatnonzero(key == np.repeat(best, np.diff(np.r_[starts, len(key)])))
    group, value = group[rows], value[rows]
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    out[group[starts]] = np.minimum.reduceat(value, starts)
    return out


def segment_planes(
    points: np.ndarray, config: Lines3DConfig | None = None, progress: Callable[[str], None] | None = None
) -> Planes:
    """Returns the planar regions of (P, 3) float64 local points (metres), largest region first.

    Scanner density falls with range, so regions grow at several voxel sizes (voxel_m x 1, 2, 4, ...):
    the points no finer region took are tried again with coarser voxels, which hold enough of them.
    """
    config = config or Lines3DConfig()
    if progress:
        progress("normals")
    labels = np.full(len(points), -1, dtype=np.int64)
    voxel_m = config.voxel_m
    for level in range(max(config.scales, 1)):
        todo = np.flatnonzero(labels < 0)
        if len(todo) < config.min_region_points:
            break
        if level == 0 and progress:
            progress("regions")
        found = _regions_at(points[todo], replace(config, voxel_m=voxel_m))
        labels[todo[found >= 0]] = found[found >= 0] + labels.max() + 1
        voxel_m *= 2.0
    if (labels < 0).all():
        return _empty_planes(len(points))
    # merge across scales on a grid coarse enough to join sparse neighbours, fine enough for details
    grid = build_voxels(points, min(0.5 * voxel_m, 4.0 * config.voxel_m))
    labels, regions = _merge_coplanar(labels, points, grid, config)
    labels = _relabel(_drop_off_plane(points, labels, regions, config.distance_m), config.min_region_points)
    if (labels < 0).all():
        return _empty_planes(len(points))
    num = int(labels.max()) + 1
    counts, cen, nrm, _ = fit_planes(points, labels, num)
    pairs = _touching(grid, labels)
    logger.debug("%d regions, %d touching pairs", num, len(pairs))
    return Planes(labels, nrm, cen, counts, pairs[:, :2], _region_spacing(points, labels, num))


def _regions_at(points: np.ndarray, config: Lines3DConfig) -> np.ndarray:
    """Returns (P,) int64 labels of the regions grown with voxels of config.voxel_m (-1: none)."""
    voxels = build_voxels(points, config.voxel_m)
    fits = moments(points, voxels.of_point, len(voxels.flat), config.min_voxel_points)
    # growing compares |n_a . n_b|: the normals' signs do not matter, so the faster closed form does
    nrm, curv = plane_fits(fits, closed_form=True)
    voxel_labels = _relabel(grow_regions(voxels, fits.centroids, nrm, curv, config), 1)
    if (voxel_labels < 0).all():
        return np.full(len(points), -1, dtype=np.int64)
    labels = _assign_points(points, voxels, fits, voxel_labels, config)
    # regions too small at this scale leave their points to the next, coarser one
    return _relabel(labels, config.min_region_points)


def _drop_off_plane(
    points: np.ndarray, labels: np.ndarray, regions: Moments, distance_m: float
) -> np.ndarray:
    """Returns (P,) labels with points farther than distance_m from their region's plane (fitted to all its
    points, from its ``regions`` moments) set to -1."""
    # distances are |(x - c) . n|: the normals' signs do not matter, so the faster closed form does
    normals, _ = plane_fits(regions, closed_form=True)
    out = labels.copy()
    idx = np.flatnonzero(labels >= 0)
    dist = plane_distances(points, idx, regions.centroids, normals, labels[idx])
    out[idx[dist > distance_m]] = -1
    return out


def _region_spacing(points: np.ndarray, labels: np.ndarray, num: int, neighbours: int = 8) -> np.ndarray:
    """Returns (R,) float64 typical point spacing (m) of each region: k points within r of a point cover
    pi r^2 of the plane, so r_k sqrt(pi / k) (median over up to 500 of the region's points).

    Nearest neighbours, not points per voxel: a thin strip (a 25 cm ledge) or a region cut by voxel
    borders fills only part of its voxels, which made it look several times sparser than it is.
    """
    order = _group_order(labels, num)
    bounds = np.searchsorted(labels[order], np.arange(num + 1))

    def spacing(r: int) -> float:
        member = points[order[bounds[r] : bounds[r + 1]]]
        k = min(neighbours, len(member) - 1)
        if k < 1:
            return 0.0
        sample = member[:: max(1, len(member) // 500)]
        # sliding-midpoint trees build about twice as fast; the neighbours found are the same
        tree = cKDTree(member, balanced_tree=False, compact_nodes=False)
        dist, _ = tree.query(sample, k=k + 1)  # the first neighbour is the point itself
        return float(np.median(dist[:, -1])) * np.sqrt(np.pi / k)

    # tree building and queries release the GIL: two threads use both cores of a small machine
    with ThreadPoolExecutor(max_workers=2) as pool:
        return np.array(list(pool.map(spacing, range(num))), dtype=np.float64)


def _group_order(labels: np.ndarray, num: int) -> np.ndarray:
    """Returns (P,) int64 the stable order sorting (P,) int64 labels in [-1, num)."""
    # 16-bit keys sort by radix sort, in linear time
    small = labels.astype(np.int16) if num < 2**15 else labels
    return np.argsort(small, kind="stable")


def _voxel_labels(of_point: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (voxel, label, votes), each (K,) int64: the distinct (voxel, label) pairs of the labelled
    points (sorted by voxel, then label) and how many points each holds."""
    ok = labels >= 0
    num = int(labels.max()) + 1 if ok.any() else 1
    keys, votes = np.unique(of_point[ok] * num + labels[ok], return_counts=True)
    return keys // num, keys % num, votes


def _majority(voxel: np.ndarray, label: np.ndarray, votes: np.ndarray, num_voxels: int) -> np.ndarray:
    """Returns (V,) int64 the most voted label of each voxel (-1 for none) from ``_voxel_labels``' pairs."""
    out = np.full(num_voxels, -1, dtype=np.int64)
    order = np.lexsort((votes, voxel))  # per voxel ascending votes: the last of each run wins
    last = np.r_[voxel[order][1:] != voxel[order][:-1], True] if len(order) else np.zeros(0, bool)
    out[voxel[order][last]] = label[order][last]
    return out


def _empty_planes(num_points: int) -> Planes:
    empty = np.zeros((0, 3))
    no_pairs = np.zeros((0, 2), np.int64)
    return Planes(
        np.full(num_points, -1, dtype=np.int64), empty, empty, np.zeros(0, np.int64), no_pairs, np.zeros(0)
    )
