"""Planar regions of a point cloud by region growing over voxel plane fits (Lu et al. 2019, section 3.1).

Normals come from local PCA, one fit per occupied voxel (a cubic neighbourhood: as fast as a voxel hash,
no per-point neighbour search). Planar voxels whose normals and offsets agree are grown into regions
(connected components), near-coplanar adjacent regions are merged, then every point, including those in
voxels straddling a crease, joins the adjacent region whose plane it lies on.
All coordinates are local (the caller subtracts a georeferenced offset first).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .config import Lines3DConfig

logger = logging.getLogger(__name__)

# the 13 "forward" offsets of the 26-neighbourhood; each adjacent pair is visited once
_OFFSETS = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)], dtype=np.int64)


@dataclass(frozen=True)
class Voxels:
    """Occupied voxels: ``keys`` (V, 3) int64 sorted, ``of_point`` (P,) voxel of each point,
    ``neighbors`` (V, 13) int64 index of the forward neighbour voxel or -1, plane fits of each voxel."""

    keys: np.ndarray
    of_point: np.ndarray
    neighbors: np.ndarray
    counts: np.ndarray  # (V,) int64
    centroids: np.ndarray  # (V, 3)
    normals: np.ndarray  # (V, 3) unit
    curvature: np.ndarray  # (V,) lambda_min / sum(lambda), inf for too few points
    size_m: float


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


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Returns (P', 3) float64 centroids of the points in each occupied voxel of size ``voxel_m``."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    counts = np.bincount(inverse).astype(np.float64)
    return np.stack([np.bincount(inverse, points[:, i]) for i in range(3)], axis=1) / counts[:, None]


def fit_planes(points: np.ndarray, group: np.ndarray, num_groups: int) -> tuple[np.ndarray, ...]:
    """Returns (counts (G,), centroids (G, 3), normals (G, 3), curvature (G,)) of points grouped by (P,) ids.

    Groups with fewer than 3 points get curvature inf. Curvature is the surface variation
    lambda_0 / (lambda_0 + lambda_1 + lambda_2) of the group's covariance (0 on a perfect plane).
    """
    counts = np.bincount(group, minlength=num_groups).astype(np.float64)
    safe = np.maximum(counts, 1.0)[:, None]
    centroids = np.stack([np.bincount(group, points[:, i], num_groups) for i in range(3)], axis=1) / safe
    d = points - centroids[group]  # centred first: sums of squares stay exact far from the origin
    cov = np.empty((num_groups, 3, 3))
    for i, j in itertools.combinations_with_replacement(range(3), 2):
        cov[:, i, j] = cov[:, j, i] = np.bincount(group, d[:, i] * d[:, j], num_groups) / safe[:, 0]
    normals = np.zeros((num_groups, 3))
    curvature = np.full(num_groups, np.inf)
    fit = counts >= 3  # most voxels of a sparse scan hold one or two points: no eigen-solve for those
    eigval, eigvec = np.linalg.eigh(cov[fit])
    normals[fit] = eigvec[:, :, 0]
    curvature[fit] = eigval[:, 0] / np.maximum(eigval.sum(axis=1), 1e-300)
    return counts.astype(np.int64), centroids, normals, curvature


def build_voxels(points: np.ndarray, voxel_m: float) -> Voxels:
    """Returns the occupied voxels of (P, 3) local points with their plane fits and forward neighbours."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 3  # room for the +1 offsets
    flat = np.ravel_multi_index((keys + 1).T, dims)
    uniq, of_point = np.unique(flat, return_inverse=True)
    of_point = of_point.ravel()
    neighbors = np.full((len(uniq), len(_OFFSETS)), -1, dtype=np.int64)
    vox = np.stack(np.unravel_index(uniq, dims), axis=1)
    for k, offset in enumerate(_OFFSETS):
        target = np.ravel_multi_index((vox + offset).T, dims)
        pos = np.minimum(np.searchsorted(uniq, target), len(uniq) - 1)
        neighbors[:, k] = np.where(uniq[pos] == target, pos, -1)
    counts, centroids, normals, curvature = fit_planes(points, of_point, len(uniq))
    return Voxels(vox - 1, of_point, neighbors, counts, centroids, normals, curvature, voxel_m)


def _edges(voxels: Voxels) -> tuple[np.ndarray, np.ndarray]:
    """Returns the (E,) index pairs of 26-adjacent voxels."""
    a = np.repeat(np.arange(len(voxels.keys)), voxels.neighbors.shape[1])
    b = voxels.neighbors.ravel()
    keep = b >= 0
    return a[keep], b[keep]


def _components(num: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(num, num))
    return connected_components(graph, directed=False)[1]


def grow_regions(voxels: Voxels, config: Lines3DConfig) -> np.ndarray:
    """Returns (V,) int64 region label of each voxel (-1: not planar), by growing over similar neighbours."""
    planar = (voxels.counts >= config.min_voxel_points) & (voxels.curvature <= config.max_curvature)
    a, b = _edges(voxels)
    a, b = a[planar[a] & planar[b]], b[planar[a] & planar[b]]
    n, c = voxels.normals, voxels.centroids
    cos_thr = np.cos(np.radians(config.angle_deg))
    delta = c[b] - c[a]
    ok = np.abs(np.einsum("ij,ij->i", n[a], n[b])) >= cos_thr
    ok &= np.abs(np.einsum("ij,ij->i", n[a], delta)) <= config.distance_m
    ok &= np.abs(np.einsum("ij,ij->i", n[b], delta)) <= config.distance_m
    comp = _components(len(voxels.keys), a[ok], b[ok])
    comp[~planar] = -1
    return comp


def _relabel(labels: np.ndarray, min_count: int) -> np.ndarray:
    """Returns labels renumbered 0.. by decreasing size, groups smaller than ``min_count`` set to -1."""
    valid = labels >= 0
    counts = np.bincount(labels[valid]) if valid.any() else np.zeros(0, dtype=np.int64)
    order = np.argsort(-counts, kind="stable")
    new_of_old = np.full(len(counts), -1, dtype=np.int64)
    kept = order[counts[order] >= min_count]
    new_of_old[kept] = np.arange(len(kept))
    out = np.full_like(labels, -1)
    out[valid] = new_of_old[labels[valid]]
    return out


def _touching(voxels: Voxels, point_labels: np.ndarray) -> np.ndarray:
    """Returns (Q, 3) int64 (region a < region b, count) of regions sharing a voxel or adjacent voxels."""
    labelled = point_labels >= 0
    num = int(point_labels.max()) + 1 if labelled.any() else 1
    vl = np.unique(voxels.of_point[labelled] * num + point_labels[labelled])  # sorted (voxel, label)
    voxel, label = vl // num, vl % num
    same = voxel[:-1] == voxel[1:]  # one voxel holding two regions: a crease voxel
    pairs = [np.stack([label[:-1][same], label[1:][same]], axis=1)]
    # the majority region of each voxel, then 26-adjacent voxels with different majorities
    major = _majority(voxels.of_point, point_labels, len(voxels.keys))
    a, b = _edges(voxels)
    pairs.append(np.stack([major[a], major[b]], axis=1))
    pairs_all = np.concatenate(pairs)
    pairs_all = pairs_all[(pairs_all >= 0).all(axis=1) & (pairs_all[:, 0] != pairs_all[:, 1])]
    pairs_all.sort(axis=1)
    uniq, count = np.unique(pairs_all[:, 0] * num + pairs_all[:, 1], return_counts=True)
    return np.stack([uniq // num, uniq % num, count], axis=1)


def _merge_coplanar(
    labels: np.ndarray, points: np.ndarray, voxels: Voxels, config: Lines3DConfig
) -> np.ndarray:
    """Returns point labels with adjacent near-coplanar regions merged (Lu et al.: region merging)."""
    num = int(labels.max()) + 1
    valid = labels >= 0
    _, cen, nrm, _ = fit_planes(points[valid], labels[valid], num)
    pairs = _touching(voxels, labels)[:, :2]
    if len(pairs) == 0:
        return labels
    a, b = pairs[:, 0], pairs[:, 1]
    ok = np.abs(np.einsum("ij,ij->i", nrm[a], nrm[b])) >= np.cos(np.radians(config.merge_angle_deg))
    ok &= np.abs(np.einsum("ij,ij->i", nrm[a], cen[b] - cen[a])) <= config.merge_distance_m
    ok &= np.abs(np.einsum("ij,ij->i", nrm[b], cen[a] - cen[b])) <= config.merge_distance_m
    comp = _components(num, a[ok], b[ok])
    out = labels.copy()
    out[valid] = comp[labels[valid]]
    return out


def _assign_points(points: np.ndarray, voxels: Voxels, voxel_labels: np.ndarray, config: Lines3DConfig):
    """Returns (P,) labels: each point joins the nearest plane (within distance_m) among the regions of its
    own and its 26 neighbouring voxels; planes are fitted on the points of each region's planar voxels."""
    num = int(voxel_labels.max()) + 1
    seed = voxel_labels[voxels.of_point]
    _, cen, nrm, _ = fit_planes(points[seed >= 0], seed[seed >= 0], num)
    # both directions of the 13 forward offsets give the full 26-neighbourhood
    back = np.full_like(voxels.neighbors, -1)
    rows, cols = np.nonzero(voxels.neighbors >= 0)
    back[voxels.neighbors[rows, cols], cols] = rows
    around = np.concatenate([np.arange(len(voxels.keys))[:, None], voxels.neighbors, back], axis=1)
    cand_of_voxel = np.where(around >= 0, voxel_labels[np.maximum(around, 0)], -1)
    # the distinct candidate regions of each voxel: most voxels have one, crease voxels a few
    cand = np.sort(cand_of_voxel, axis=1)
    first = cand >= 0
    first[:, 1:] &= cand[:, 1:] != cand[:, :-1]
    rank = np.cumsum(first, axis=1) - 1
    labels = np.full(len(points), -1, dtype=np.int64)
    best = np.full(len(points), np.inf)
    for j in range(int(first.sum(axis=1).max(initial=0))):
        row, col = np.nonzero(first & (rank == j))
        label_j = np.full(len(cand), -1, dtype=np.int64)
        label_j[row] = cand[row, col]
        c = label_j[voxels.of_point]
        idx = np.flatnonzero(c >= 0)
        c = c[idx]
        dist = np.abs(np.einsum("ij,ij->i", points[idx] - cen[c], nrm[c]))
        better = (dist < best[idx]) & (dist <= config.distance_m)
        labels[idx[better]], best[idx[better]] = c[better], dist[better]
    return labels


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
    labels = _relabel(_merge_coplanar(labels, points, grid, config), 1)
    labels = _relabel(_drop_off_plane(points, labels, config.distance_m), config.min_region_points)
    if (labels < 0).all():
        return _empty_planes(len(points))
    num = int(labels.max()) + 1
    counts, cen, nrm, _ = fit_planes(points[labels >= 0], labels[labels >= 0], num)
    pairs = _touching(grid, labels)
    logger.debug("%d regions, %d touching pairs", num, len(pairs))
    return Planes(labels, nrm, cen, counts, pairs[:, :2], _region_spacing(points, labels, num))


def _regions_at(points: np.ndarray, config: Lines3DConfig) -> np.ndarray:
    """Returns (P,) int64 labels of the regions grown with voxels of config.voxel_m (-1: none)."""
    voxels = build_voxels(points, config.voxel_m)
    voxel_labels = _relabel(grow_regions(voxels, config), 1)
    if (voxel_labels < 0).all():
        return np.full(len(points), -1, dtype=np.int64)
    labels = _assign_points(points, voxels, voxel_labels, config)
    # regions too small at this scale leave their points to the next, coarser one
    return _relabel(labels, config.min_region_points)


def _drop_off_plane(points: np.ndarray, labels: np.ndarray, distance_m: float) -> np.ndarray:
    """Returns labels with points farther than distance_m from their region's (refitted) plane set to -1."""
    ok = labels >= 0
    _, cen, nrm, _ = fit_planes(points[ok], labels[ok], int(labels.max()) + 1)
    out = labels.copy()
    idx = np.flatnonzero(ok)
    dist = np.abs(np.einsum("ij,ij->i", points[idx] - cen[labels[idx]], nrm[labels[idx]]))
    out[idx[dist > distance_m]] = -1
    return out


def _region_spacing(points: np.ndarray, labels: np.ndarray, num: int, neighbours: int = 8) -> np.ndarray:
    """Returns (R,) float64 typical point spacing (m) of each region: k points within r of a point cover
    pi r^2 of the plane, so r_k sqrt(pi / k) (median over up to 500 of the region's points).

    Nearest neighbours, not points per voxel: a thin strip (a 25 cm ledge) or a region cut by voxel
    borders fills only part of its voxels, which made it look several times sparser than it is.
    """
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(num + 1))
    out = np.zeros(num)
    for r in range(num):
        member = points[order[bounds[r] : bounds[r + 1]]]
        k = min(neighbours, len(member) - 1)
        if k < 1:
            continue
        sample = member[:: max(1, len(member) // 500)]
        dist, _ = cKDTree(member).query(sample, k=k + 1)  # the first neighbour is the point itself
        out[r] = float(np.median(dist[:, -1])) * np.sqrt(np.pi / k)
    return out


def _majority(of_point: np.ndarray, labels: np.ndarray, num_voxels: int) -> np.ndarray:
    """Returns (V,) int64 the most frequent label among each voxel's points (-1 for none)."""
    ok = labels >= 0
    out = np.full(num_voxels, -1, dtype=np.int64)
    if not ok.any():
        return out
    num = int(labels.max()) + 1
    keys, votes = np.unique(of_point[ok] * num + labels[ok], return_counts=True)
    voxel = keys // num
    order = np.lexsort((votes, voxel))  # per voxel ascending votes: the last of each run wins
    last = np.r_[voxel[order][1:] != voxel[order][:-1], True]
    out[voxel[order][last]] = keys[order][last] % num
    return out


def _empty_planes(num_points: int) -> Planes:
    empty = np.zeros((0, 3))
    no_pairs = np.zeros((0, 2), np.int64)
    return Planes(
        np.full(num_points, -1, dtype=np.int64), empty, empty, np.zeros(0, np.int64), no_pairs, np.zeros(0)
    )
