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
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, replace

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig
from .regions import components, group_order, grow_regions, regions_at, relabel, renumber
from .voxels import (
    Moments,
    Voxels,
    adjacent_pairs,
    build_voxels,
    combine_moments,
    fit_planes,
    moments,
    plane_distances,
    plane_fits,
    voxel_downsample,
)

__all__ = ["Planes", "fit_planes", "grow_regions", "segment_planes", "voxel_downsample"]

logger = logging.getLogger(__name__)
BRUTE_POINTS = 200  # regions up to this many points find their spacing without a KD-tree (home_kinect's
# 1,302 regions, two threads: 0.16 s; 0.32 s at 1,000 points, 0.33 s all by KD-trees)


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
    comp = components(num, a[ok], b[ok])
    merged = renumber(np.bincount(comp, fits.counts, num).astype(np.int64), 1)[comp]
    out = np.full_like(labels, -1)
    out[labels >= 0] = merged[labels[labels >= 0]]
    return out, combine_moments(fits, merged, int(merged.max()) + 1)


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
        found = regions_at(points[todo], replace(config, voxel_m=voxel_m))
        labels[todo[found >= 0]] = found[found >= 0] + labels.max() + 1
        voxel_m *= 2.0
    if (labels < 0).all():
        return _empty_planes(len(points))
    # merge across scales on a grid coarse enough to join sparse neighbours, fine enough for details
    grid = build_voxels(points, min(0.5 * voxel_m, 4.0 * config.voxel_m))
    labels, regions = _merge_coplanar(labels, points, grid, config)
    labels = relabel(_drop_off_plane(points, labels, regions, config.distance_m), config.min_region_points)
    if (labels < 0).all():
        return _empty_planes(len(points))
    num = int(labels.max()) + 1
    # the spacing's tree builds release the GIL: two threads, while this one fits the planes
    with ThreadPoolExecutor(max_workers=2) as pool:
        spacing = _region_spacing(points, labels, num, pool)
        counts, cen, nrm, _ = fit_planes(points, labels, num)
        pairs = _touching(grid, labels)
        spacing_m = spacing()
    logger.debug("%d regions, %d touching pairs", num, len(pairs))
    return Planes(labels, nrm, cen, counts, pairs[:, :2], spacing_m)


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


def _region_spacing(
    points: np.ndarray, labels: np.ndarray, num: int, pool: Executor, neighbours: int = 8
) -> Callable[[], np.ndarray]:
    """Returns a call that returns the (R,) typical point spacings (m) of the regions, computed on
    ``pool``: k points within r of a point cover pi r^2 of the plane, so r_k sqrt(pi / k) (median over
    up to 500 of the region's points).

    Nearest neighbours, not points per voxel: a thin strip (a 25 cm ledge) or a region cut by voxel
    borders fills only part of its voxels, which made it look several times sparser than it is. A region
    of up to BRUTE_POINTS points compares its sample with all its points (one compiled loop for all of
    them: a room holds a thousand small regions), a larger one queries a KD-tree; the distances are the
    same bit for bit.
    """
    order = group_order(labels, num)
    bounds = np.searchsorted(labels[order], np.arange(num + 1))
    sizes = np.diff(bounds)
    small = np.flatnonzero(sizes <= BRUTE_POINTS)
    large = np.flatnonzero(sizes > BRUTE_POINTS)

    def spacing(r: int) -> float:
        member = points[order[bounds[r] : bounds[r + 1]]]
        k = min(neighbours, len(member) - 1)
        sample = member[:: max(1, len(member) // 500)]
        # sliding-midpoint trees build faster; the neighbours found are the same
        tree = cKDTree(member, balanced_tree=False, compact_nodes=False)
        dist, _ = tree.query(sample, k=k + 1)  # the first neighbour is the point itself
        return float(np.median(dist[:, -1]))

    brute = pool.submit(_small_region_medians, points, order, bounds.astype(np.int64), small, neighbours)
    found = pool.map(spacing, large)

    def result() -> np.ndarray:
        median = np.zeros(num)
        median[large] = np.fromiter(found, dtype=np.float64, count=len(large))
        median[small] = brute.result()
        k = np.minimum(neighbours, sizes - 1)
        out = np.zeros(num)
        ok = k >= 1
        out[ok] = median[ok] * np.sqrt(np.pi / k[ok])
        return out

    return result


@numba.njit(cache=True, nogil=True)
def _small_region_medians(
    points: np.ndarray, order: np.ndarray, bounds: np.ndarray, regions: np.ndarray, neighbours: int
) -> np.ndarray:  # pragma: no cover - numba
    """Returns per region r of ``regions`` (its points points[order[bounds[r]:bounds[r + 1]]]) the median
    over every max(1, n // 500)-th of its n points of the distance to its k-th nearest other point
    (k = min(neighbours, n - 1); 0.0 when k < 1), by comparing with all its points."""
    out = np.zeros(len(regions))
    for i in range(len(regions)):
        lo, hi = bounds[regions[i]], bounds[regions[i] + 1]
        n = hi - lo
        k = min(neighbours, n - 1)
        if k < 1:
            continue
        step = max(1, n // 500)
        kth = np.empty((n + step - 1) // step)
        best = np.empty(k + 1)  # the point itself is the first
        for s in range(len(kth)):
            p = order[lo + s * step]
            for j in range(k + 1):
                best[j] = np.inf
            for m in range(lo, hi):
                q = order[m]
                dx, dy, dz = (
                    points[q, 0] - points[p, 0],
                    points[q, 1] - points[p, 1],
                    points[q, 2] - points[p, 2],
                )
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best[k]:
                    j = k
                    while j > 0 and best[j - 1] > d2:
                        best[j] = best[j - 1]
                        j -= 1
                    best[j] = d2
            kth[s] = np.sqrt(best[k])
        out[i] = _median(kth)
    return out


@numba.njit(cache=True, nogil=True)
def _median(values: np.ndarray) -> float:  # pragma: no cover - numba
    """Returns the median of the (n >= 1,) ``values`` (reordered in place), as ``np.median`` gives it: the
    middle value, or the mean of the two middle ones. Quickselect (Hoare partitions round the middle)."""
    n = len(values)
    mid = n // 2
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = values[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if mid <= j:
            hi = j
        elif mid >= i:
            lo = i
        else:
            break
    if n % 2:
        return values[mid]
    below = values[0]
    for k in range(1, mid):
        below = max(below, values[k])
    return (below + values[mid]) / 2.0


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
