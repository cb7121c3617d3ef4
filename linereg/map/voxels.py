"""Voxel grids of a point cloud: occupied voxels, their neighbours and per-group plane fits (numpy only).

A voxel is found in a dense table of the grid's cells when the grid is small enough (``MAX_TABLE_CELLS``,
``TABLE_CELLS_PER_POINT``), else by binary search in the sorted linear indices of the occupied voxels: a scan
fills a tiny share of its bounding box (docs/measurements.md), and a table of a large box would be mostly
empty.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

# the 13 "forward" offsets of the 26-neighbourhood: each adjacent pair is visited once
FORWARD = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)], dtype=np.int64)
# the voxel itself and its 26 neighbours
AROUND = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)
# the largest grid (cells) tabulated, 128 MB of int32: a table finds a voxel faster than a binary search
# and gives the occupied cells without sorting the points; both give the same voxels (speed only)
MAX_TABLE_CELLS = 2**25
# ... and at most this many cells a point: filling and scanning a table costs its cells, sorting the points
# their count; a sparse sweep of 17k points spanning 30 M cells spent 0.2 s on its table alone
TABLE_CELLS_PER_POINT = 64


@dataclass(frozen=True)
class Voxels:
    """Occupied voxels of size ``size_m``: ``keys`` (V, 3) int64 integer coordinates (from 0), ``flat``
    (V,) int64 sorted linear index of each in a grid padded by one voxel on every side, ``strides`` (3,)
    int64 of that grid, ``of_point`` (P,) int64 voxel of each point, ``counts`` (V,) int64 points, and
    ``lookup`` (cells,) int32 the voxel of every grid cell (-1: empty), None for grids too large for a table.
    """

    keys: np.ndarray
    flat: np.ndarray
    strides: np.ndarray
    of_point: np.ndarray
    counts: np.ndarray
    size_m: float
    lookup: np.ndarray | None


def build_voxels(points: np.ndarray, voxel_m: float) -> Voxels:
    """Returns the occupied voxels of size ``voxel_m`` of (P, 3) float64 local points."""
    # per coordinate (contiguous columns are several times faster than (P, 3) reductions); floor is
    # monotonic, so the extremes of the keys are the keys of the extremes
    if len(points) == 0:
        none = np.zeros(0, dtype=np.int64)
        return Voxels(np.zeros((0, 3), np.int64), none, np.ones(3, np.int64), none, none, voxel_m, None)
    cols = [points[:, i] for i in range(3)]
    lo = np.array([np.floor(c.min() / voxel_m) for c in cols], dtype=np.int64)
    dims = np.array([np.floor(c.max() / voxel_m) for c in cols], dtype=np.int64) - lo + 3  # -1, +1 room
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    cell = np.zeros(len(points), dtype=np.int64)
    for c, low, stride in zip(cols, lo, strides, strict=True):
        cell += (np.floor(c / voxel_m).astype(np.int64) - (low - 1)) * stride
    lookup = None
    if int(dims.prod()) <= min(MAX_TABLE_CELLS, TABLE_CELLS_PER_POINT * len(points)):
        # a table of every cell: the occupied ones in order without sorting the points
        lookup = np.full(int(dims.prod()), -1, dtype=np.int32)
        lookup[cell] = 0
        flat = np.flatnonzero(lookup == 0)
        lookup[flat] = np.arange(len(flat), dtype=np.int32)
        of_point = lookup[cell].astype(np.int64)
        counts = np.bincount(of_point, minlength=len(flat))
    else:
        flat, of_point, counts = _unique(cell, int(dims.prod()))
    vox = np.stack(np.unravel_index(flat, tuple(dims)), axis=1) - 1
    return Voxels(vox, flat, strides, of_point.ravel(), counts, voxel_m, lookup)


def _unique(values: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ``np.unique(values, return_inverse=True, return_counts=True)`` of (N,) int64 in [0, bound)."""
    n = len(values)
    shift = max(n - 1, 1).bit_length()
    if (max(bound - 1, 1).bit_length() + shift > 63) or n == 0:
        return np.unique(values, return_inverse=True, return_counts=True)
    # sorting values with their index packed in the low bits is several times faster than an argsort
    packed = np.sort((values << shift) | np.arange(n, dtype=np.int64))
    order = packed & ((1 << shift) - 1)
    packed >>= shift
    first = np.empty(n, dtype=bool)
    first[0] = True
    np.not_equal(packed[1:], packed[:-1], out=first[1:])
    inverse = np.empty(n, dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    starts = np.flatnonzero(first)
    return packed[starts], inverse, np.diff(np.append(starts, n))


def neighbors(voxels: Voxels, index: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Returns (N, K) int64 index of the voxel at each (K, 3) offset from each voxel of ``index`` (N,),
    -1 where that voxel is empty. Offsets are -1, 0 or 1 per axis (the padding keeps them in the grid)."""
    # one row per offset: sorted targets make look-ups and binary searches cache-friendly
    target = (offsets @ voxels.strides)[:, None] + voxels.flat[index][None, :]
    if voxels.lookup is not None:
        return voxels.lookup[target].T.astype(np.int64)
    pos = np.minimum(np.searchsorted(voxels.flat, target), len(voxels.flat) - 1)
    return np.where(voxels.flat[pos] == target, pos, -1).T


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


@dataclass(frozen=True)
class Moments:
    """Point groups summarised: ``counts`` (G,) int64, ``centroids`` (G, 3), ``fitted`` (G,) bool the groups
    whose covariance was computed and their ``covariance`` (F, 3, 3), in group order."""

    counts: np.ndarray
    centroids: np.ndarray
    covariance: np.ndarray
    fitted: np.ndarray


def moments(points: np.ndarray, group: np.ndarray, num_groups: int, min_points: int = 3) -> Moments:
    """Returns the moments of (P, 3) points grouped by (P,) int64 ids in [0, G) (negative: left out); groups
    with fewer than ``min_points`` (at least 3) points get a centroid but no covariance."""
    # contiguous columns: bincount copies strided weights
    if len(group) and group.min() < 0:
        valid = group >= 0
        group, cols = group[valid], [points[:, i][valid] for i in range(3)]
    else:
        cols = [np.ascontiguousarray(points[:, i]) for i in range(3)]
    counts = np.bincount(group, minlength=num_groups)
    safe = np.maximum(counts, 1).astype(np.float64)
    centroids = np.stack([np.bincount(group, c, num_groups) for c in cols], axis=1) / safe[:, None]
    # a sparse scan's voxels mostly hold one or two points: no moments for those
    fit = counts >= max(min_points, 3)
    if not fit.all():
        keep = fit[group]
        group, cols = group[keep], [c[keep] for c in cols]
    # centred first: sums of squares stay exact far from the origin
    d = [c - centroids[:, i][group] for i, c in enumerate(cols)]
    fitted = (np.cumsum(fit) - 1)[group]  # compact index of the fitted groups
    cov = np.empty((int(fit.sum()), 3, 3))
    for i, j in itertools.combinations_with_replacement(range(3), 2):
        cov[:, i, j] = cov[:, j, i] = np.bincount(fitted, d[i] * d[j], len(cov)) / safe[fit]
    return Moments(counts, centroids, cov, fit)


def combine_moments(parts: Moments, into: np.ndarray, num_groups: int) -> Moments:
    """Returns the moments of groups made of fitted ``parts`` (G,): part g joins group into[g] (negative: none).

    Parallel-axis theorem: S = sum_g n_g (C_g + (c_g - c)(c_g - c)^T) about the joint centroid c; a group
    holds all the points of its parts, so it equals ``moments`` of those points up to rounding.
    """
    index = np.flatnonzero((into >= 0) & parts.fitted)
    row = (np.cumsum(parts.fitted) - 1)[index]  # of the parts' covariance
    to, n = into[index], parts.counts[index].astype(np.float64)
    counts = np.bincount(to, parts.counts[index], num_groups).astype(np.int64)
    safe = np.maximum(counts, 1).astype(np.float64)
    part_c = parts.centroids[index]
    sums = np.stack([np.bincount(to, n * part_c[:, i], num_groups) for i in range(3)], axis=1)
    centroids = sums / safe[:, None]
    d = part_c - centroids[to]
    scatter = n[:, None, None] * (parts.covariance[row] + d[:, :, None] * d[:, None, :])
    flat = [np.bincount(to, scatter[:, i, j], num_groups) for i in range(3) for j in range(3)]
    cov = np.stack(flat, axis=1).reshape(num_groups, 3, 3) / safe[:, None, None]
    fitted = counts >= 3
    return Moments(counts, centroids, cov[fitted], fitted)


def plane_fits(m: Moments, closed_form: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Returns (normals (G, 3), curvature (G,)) of moments: the covariance's smallest eigenvector and the
    surface variation lambda_0 / (lambda_0 + lambda_1 + lambda_2) (0 on a perfect plane); zero normal and
    curvature inf where not fitted. ``closed_form`` solves the 3 x 3 eigenproblems in closed form (several
    times faster for many groups, the same normals up to rounding, but of arbitrary sign)."""
    normals = np.zeros((len(m.counts), 3))
    curvature = np.full(len(m.counts), np.inf)
    cov = m.covariance
    smallest, normals[m.fitted], total = _smallest_eigen(cov) if closed_form else _smallest_eigh(cov)
    curvature[m.fitted] = smallest / np.maximum(total, 1e-300)
    return normals, curvature


def fit_planes(
    points: np.ndarray, group: np.ndarray, num_groups: int, min_points: int = 3, closed_form: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns (counts (G,) int64, centroids (G, 3), normals (G, 3), curvature (G,)) of (P, 3) points grouped
    by (P,) int64 ids in [0, G); points of negative id are left out. See ``moments`` and ``plane_fits``."""
    m = moments(points, group, num_groups, min_points)
    normals, curvature = plane_fits(m, closed_form)
    return m.counts, m.centroids, normals, curvature


def _smallest_eigh(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (smallest eigenvalue (N,), its unit eigenvector (N, 3), eigenvalue sum (N,)) of (N, 3, 3)."""
    eigval, eigvec = np.linalg.eigh(cov)
    return eigval[:, 0], eigvec[:, :, 0], eigval.sum(axis=1)


def _smallest_eigen(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ``_smallest_eigh(cov)`` of symmetric (N, 3, 3) in closed form: the trigonometric solution of
    the characteristic cubic (Smith 1961), the eigenvector as the largest cross product of two rows of
    cov - lambda I. Near-repeated smallest eigenvalues (no stable cross product) go to ``eigh``."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00**2 + b11**2 + b22**2 + 2.0 * (a01**2 + a02**2 + a12**2)) / 6.0)
    det = b00 * (b11 * b22 - a12**2) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = np.clip(det / np.maximum(2.0 * p**3, 1e-300), -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    m = cov - smallest[:, None, None] * np.eye(3)
    rows = [(0, 1), (0, 2), (1, 2)]
    cross = np.stack([np.cross(m[:, i], m[:, j]) for i, j in rows], axis=1)  # (N, 3 pairs, 3)
    norm2 = np.einsum("nki,nki->nk", cross, cross)
    pick = norm2.argmax(axis=1)
    vec = cross[np.arange(len(cov)), pick]
    big = np.sqrt(norm2[np.arange(len(cov)), pick])
    # |cross| / |m|^2 ~ (lambda_1 - lambda_0) / (lambda_2 - lambda_0): below 1e-4 the vector loses digits
    stable = big > 1e-4 * np.einsum("nij,nij->n", m, m)
    vec[stable] /= big[stable, None]
    total = 3.0 * q
    if not stable.all():
        smallest[~stable], vec[~stable], total[~stable] = _smallest_eigh(cov[~stable])
    return smallest, vec, total


def plane_distances(
    points: np.ndarray, index: np.ndarray, centroids: np.ndarray, normals: np.ndarray, plane: np.ndarray
) -> np.ndarray:
    """Returns (N,) float64 distances of points[index] ((P, 3), (N,) int64) to planes ``plane`` (N,) int64
    through (R, 3) centroids with (R, 3) unit normals: |(x - c) . n|."""
    out = np.zeros(len(index))
    for i in range(3):  # per coordinate: 1-D gathers are faster than (N, 3) ones
        out += (points[:, i][index] - centroids[:, i][plane]) * normals[:, i][plane]
    return np.abs(out, out=out)


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Returns (P', 3) float64 centroids of the points in each occupied voxel of size ``voxel_m``."""
    voxels = build_voxels(points, voxel_m)
    sums = np.stack([np.bincount(voxels.of_point, points[:, i]) for i in range(3)], axis=1)
    return sums / voxels.counts[:, None]
