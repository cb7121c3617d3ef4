"""Planar regions grown at one voxel size: voxel plane fits -> planar voxels grown into regions over
26-adjacency (connected components) -> each point joins the nearest plane among the regions around it.

Part of ``planes.segment_planes`` (Lu et al. 2019, section 3.1), which runs it at several voxel sizes.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..config import Lines3DConfig
from .voxels import (
    AROUND,
    Moments,
    Voxels,
    adjacent_pairs,
    build_voxels,
    combine_moments,
    moments,
    neighbors,
    plane_distances,
    plane_fits,
)


def regions_at(points: np.ndarray, config: Lines3DConfig) -> np.ndarray:
    """Returns (P,) int64 labels of the regions grown with voxels of config.voxel_m (-1: none)."""
    voxels = build_voxels(points, config.voxel_m)
    fits = moments(points, voxels.of_point, len(voxels.flat), config.min_voxel_points)
    # growing compares |n_a . n_b|: the normals' signs do not matter, so the faster closed form does
    nrm, curv = plane_fits(fits, closed_form=True)
    voxel_labels = relabel(grow_regions(voxels, fits.centroids, nrm, curv, config), 1)
    if (voxel_labels < 0).all():
        return np.full(len(points), -1, dtype=np.int64)
    labels = _assign_points(points, voxels, fits, voxel_labels, config)
    # regions too small at this scale leave their points to the next, coarser one
    return relabel(labels, config.min_region_points)


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
    out[index] = components(len(index), local[a[ok]], local[b[ok]])
    return out


def components(num: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (num,) int64 connected component of each node of the undirected graph of edges (a, b)."""
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(num, num))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def relabel(labels: np.ndarray, min_count: int) -> np.ndarray:
    """Returns labels renumbered 0.. by decreasing size, groups smaller than ``min_count`` set to -1."""
    valid = labels >= 0
    counts = np.bincount(labels[valid]) if valid.any() else np.zeros(0, dtype=np.int64)
    out = np.full_like(labels, -1)
    out[valid] = renumber(counts, min_count)[labels[valid]]
    return out


def renumber(counts: np.ndarray, min_count: int) -> np.ndarray:
    """Returns (G,) int64 new number of each group of (G,) ``counts``: 0.. by decreasing count (ties keep
    their order), -1 for groups smaller than ``min_count``."""
    order = np.argsort(-counts, kind="stable")
    new_of_old = np.full(len(counts), -1, dtype=np.int64)
    kept = order[counts[order] >= min_count]
    new_of_old[kept] = np.arange(len(kept))
    return new_of_old


def _assign_points(
    points: np.ndarray, voxels: Voxels, voxel_fits: Moments, voxel_labels: np.ndarray, config: Lines3DConfig
) -> np.ndarray:
    """Returns (P,) labels: each point joins the nearest plane (within distance_m) among the regions of its
    own and its 26 neighbouring voxels; planes are fitted on the points of each region's planar voxels
    (from the voxels' ``moments``). Ties go to the lower label."""
    regions = combine_moments(voxel_fits, voxel_labels, int(voxel_labels.max()) + 1)
    # distances are |(x - c) . n|: the normals' signs do not matter, so the faster closed form does
    cen, (nrm, _) = regions.centroids, plane_fits(regions, closed_form=True)
    table, count = _candidates(voxels, voxel_labels)
    per_point = count[voxels.of_point]
    labels = np.full(len(points), -1, dtype=np.int64)
    # most points have one candidate region: its distance decides
    one = np.flatnonzero(per_point == 1)
    c = table[0, voxels.of_point[one]]
    near = plane_distances(points, one, cen, nrm, c) <= config.distance_m
    labels[one[near]] = c[near]
    # points in crease voxels: one row per (point, candidate region), the nearest plane wins
    many = np.flatnonzero(per_point > 1)
    per_point = per_point[many]
    point = np.repeat(np.arange(len(many)), per_point)
    first = np.cumsum(per_point) - per_point  # row of each point's first candidate
    c = table[np.arange(len(point)) - first[point], voxels.of_point[many][point]]
    dist = plane_distances(points, many[point], cen, nrm, c)
    dist[dist > config.distance_m] = np.inf
    labels[many] = _nearest(point, c, dist, len(many))
    return labels


def _candidates(voxels: Voxels, voxel_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, V) int64 the distinct regions among each voxel's 27 (itself and its 26 neighbours),
    first rows first, padded with -1; (V,) int64 how many each voxel has)."""
    region_voxels = np.flatnonzero(voxel_labels >= 0)
    around = neighbors(voxels, region_voxels, AROUND).T.ravel()  # offset-major: no transposing copy
    label = np.tile(voxel_labels[region_voxels], len(AROUND))
    found = around >= 0
    target, label = around[found], label[found]
    # each pass writes one of the regions a voxel receives (the last write wins) and keeps the others:
    # as many passes as regions meet in a voxel (a few), no sort of the 27 x (region voxels) pairs
    columns = []
    count = np.zeros(len(voxels.flat), dtype=np.int64)
    while len(target):
        column = np.full(len(voxels.flat), -1, dtype=np.int64)
        column[target] = label
        columns.append(column)
        rest = column[target] != label
        count[target[~rest]] = len(columns)  # the voxels written to hold this many so far
        target, label = target[rest], label[rest]
    if not columns:
        return np.full((1, len(voxels.flat)), -1, dtype=np.int64), count
    return np.stack(columns), count


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


def group_order(labels: np.ndarray, num: int) -> np.ndarray:
    """Returns (P,) int64 the stable order sorting (P,) int64 labels in [-1, num)."""
    # 16-bit keys sort by radix sort, in linear time
    small = labels.astype(np.int16) if num < 2**15 else labels
    return np.argsort(small, kind="stable")
