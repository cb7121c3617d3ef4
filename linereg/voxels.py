"""Voxel grids of a point cloud: occupied voxels, their neighbours and per-group plane fits (numpy only).

A voxel is found by binary search in the sorted linear indices of the occupied voxels: a scan fills a
tiny share of its bounding box (1 M points, 0.1 m voxels: 0.5 M of 136 M cells), too few for a dense table.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

# the 13 "forward" offsets of the 26-neighbourhood: each adjacent pair is visited once
FORWARD = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)], dtype=np.int64)
# the voxel itself and its 26 neighbours
AROUND = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)


@dataclass(frozen=True)
class Voxels:
    """Occupied voxels of size ``size_m``: ``keys`` (V, 3) int64 integer coordinates (from 0), ``flat``
    (V,) int64 sorted linear index of each in a grid padded by one voxel on every side, ``strides`` (3,)
    int64 of that grid, ``of_point`` (P,) int64 voxel of each point, ``counts`` (V,) int64 points."""

    keys: np.ndarray
    flat: np.ndarray
    strides: np.ndarray
    of_point: np.ndarray
    counts: np.ndarray
    size_m: float


def build_voxels(points: np.ndarray, voxel_m: float) -> Voxels:
    """Returns the occupied voxels of size ``voxel_m`` of (P, 3) float64 local points."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 3  # room for the -1 and +1 offsets
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    flat, of_point, counts = np.unique((keys + 1) @ strides, return_inverse=True, return_counts=True)
    vox = np.stack(np.unravel_index(flat, tuple(dims)), axis=1) - 1
    return Voxels(vox, flat, strides, of_point.ravel(), counts, voxel_m)


def neighbors(voxels: Voxels, index: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Returns (N, K) int64 index of the voxel at each (K, 3) offset from each voxel of ``index`` (N,),
    -1 where that voxel is empty. Offsets are -1, 0 or 1 per axis (the padding keeps them in the grid)."""
    target = voxels.flat[index][:, None] + offsets @ voxels.strides
    pos = np.searchsorted(voxels.flat, target.ravel()).reshape(target.shape)
    pos = np.minimum(pos, len(voxels.flat) - 1)
    return np.where(voxels.flat[pos] == target, pos, -1)


def adjacent_pairs(voxels: Voxels, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (E,) int64 index pairs (a, b) of 26-adjacent occupied voxels, both among ``index`` (N,) int64
    (a bool mask of the voxels also works: it is turned into indices), each pair once."""
    index = np.flatnonzero(index) if index.dtype == bool else index
    member = np.zeros(len(voxels.flat), dtype=bool)
    member[index] = True
    nb = neighbors(voxels, index, FORWARD)
    keep = nb >= 0
    keep[keep] = member[nb[keep]]
    return np.repeat(index, keep.sum(axis=1)), nb[keep]


def fit_planes(
    points: np.ndarray, group: np.ndarray, num_groups: int, min_points: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns (counts (G,) int64, centroids (G, 3), normals (G, 3), curvature (G,)) of (P, 3) points grouped
    by (P,) int64 ids in [0, G).

    Curvature is the surface variation lambda_0 / (lambda_0 + lambda_1 + lambda_2) of the group's covariance
    (0 on a perfect plane). Groups with fewer than ``min_points`` (at least 3) points are not fitted: zero
    normal, curvature inf.
    """
    counts = np.bincount(group, minlength=num_groups)
    normals = np.zeros((num_groups, 3))
    curvature = np.full(num_groups, np.inf)
    safe = np.maximum(counts, 1).astype(np.float64)
    sums = np.stack([np.bincount(group, points[:, i], num_groups) for i in range(3)], axis=1)
    centroids = sums / safe[:, None]
    # a sparse scan's voxels mostly hold one or two points: neither moments nor eigen-solves for those
    keep = counts[group] >= max(min_points, 3)
    points, group = points[keep], group[keep]
    d = points - centroids[group]  # centred first: sums of squares stay exact far from the origin
    cov = np.empty((num_groups, 3, 3))
    for i, j in itertools.combinations_with_replacement(range(3), 2):
        cov[:, i, j] = cov[:, j, i] = np.bincount(group, d[:, i] * d[:, j], num_groups) / safe
    fit = counts >= max(min_points, 3)
    eigval, eigvec = np.linalg.eigh(cov[fit])
    normals[fit] = eigvec[:, :, 0]
    curvature[fit] = eigval[:, 0] / np.maximum(eigval.sum(axis=1), 1e-300)
    return counts, centroids, normals, curvature


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Returns (P', 3) float64 centroids of the points in each occupied voxel of size ``voxel_m``."""
    voxels = build_voxels(points, voxel_m)
    sums = np.stack([np.bincount(voxels.of_point, points[:, i]) for i in range(3)], axis=1)
    return sums / voxels.counts[:, None]
