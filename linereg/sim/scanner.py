"""Terrestrial laser scans of a procedural building (``linereg.sim.building``): what a static scanner records.

Each scanner fires rays on a regular (azimuth, elevation) grid, so point density falls with range as on
a real instrument. Visibility comes from a spherical z-buffer: the building is rasterised into the six
90-degree views of a cube round the scanner (``render.rasterize``), the faces found in the 2 x 2 cube
pixels round each ray are intersected exactly and the nearest hit inside its face is kept (occlusion).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import InvalidInputError
from ..geometry import make_cam_from_world
from .building import Building
from .render import rasterize, rotate

log = logging.getLogger(__name__)

# the six 90-degree views of a cube round a scanner (+x, -x, +y, -y, +z, -z forward); rows: the view's
# camera x, y, z axes in world coordinates
CUBE_VIEWS = np.array(
    [
        [[0, -1, 0], [0, 0, -1], [1, 0, 0]],
        [[0, 1, 0], [0, 0, -1], [-1, 0, 0]],
        [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[-1, 0, 0], [0, 0, -1], [0, -1, 0]],
        [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
    ],
    dtype=np.float64,
)


@dataclass(frozen=True)
class ScanConfig:
    """A terrestrial laser scanner: angular grid, range limits and noise, optional subsampling."""

    angular_step_deg: float = 0.2  # between neighbouring rays, in azimuth and in elevation
    min_elevation_deg: float = -60.0  # the tripod hides the cone below
    max_elevation_deg: float = 85.0
    min_range_m: float = 0.5
    max_range_m: float = 80.0
    range_noise_m: float = 0.01  # std along the ray
    # > 0: thin the cloud to at most this many points, densest places first (``thin``)
    target_points: int = 0
    thin_voxel_m: float = 0.1  # cells of that thinning; 0 = uniform random subsample instead
    chunk_rays: int = 200_000  # rays processed at once (memory)


def scan(
    building: Building,
    scanner_positions: np.ndarray,
    rng: np.random.Generator,
    config: ScanConfig | None = None,
) -> np.ndarray:
    """Returns (P, 3) float64 world points that scanners at (S, 3) ``scanner_positions`` record."""
    cfg = config or ScanConfig()
    positions = np.asarray(scanner_positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or not np.isfinite(positions).all():
        raise InvalidInputError(
            f"scanner_positions must be a finite (S, 3) array, got shape {positions.shape}"
        )
    clouds = [scan_one(building, p, rng, cfg) for p in positions]
    cloud = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    if 0 < cfg.target_points < len(cloud):
        cloud = thin(cloud, cfg.target_points, rng, cfg.thin_voxel_m)
    log.debug("scan: %d scanners, %d points", len(positions), len(cloud))
    return cloud


def thin(cloud: np.ndarray, target: int, rng: np.random.Generator, voxel_m: float) -> np.ndarray:
    """Returns at most ``target`` of the (P, 3) points, in their order: at most k random points per voxel_m
    cell, k as large as the target allows (then a uniform subsample for the remainder).

    A scanner oversamples the ground round its tripod and near walls while far facades get few points;
    capping the density, as survey software's spatial subsampling does, spends the budget where it
    is thin instead of thinning everything alike.
    """
    if voxel_m <= 0 or len(cloud) <= target:
        keep = np.sort(rng.choice(len(cloud), min(target, len(cloud)), replace=False))
        return cloud[keep]
    order = rng.permutation(len(cloud))
    ijk = np.floor(cloud[order] / voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=0)
    key = (ijk[:, 0] * (ijk[:, 1].max() + 1) + ijk[:, 1]) * (ijk[:, 2].max() + 1) + ijk[:, 2]
    by_cell = np.argsort(key, kind="stable")  # random order within each cell
    _, start, counts = np.unique(key[by_cell], return_index=True, return_counts=True)
    rank = np.empty(len(key), dtype=np.int64)
    rank[by_cell] = np.arange(len(key)) - np.repeat(start, counts)
    # the smallest cap k with sum(min(count, k)) >= target; its surplus goes in a uniform subsample
    c = np.sort(counts)
    caps = np.arange(1, int(c[-1]) + 1)
    below = np.searchsorted(c, caps)  # cells with fewer points than the cap keep them all
    kept = np.r_[0, np.cumsum(c)][below] + caps * (len(c) - below)
    k = int(caps[min(int(np.searchsorted(kept, target)), len(caps) - 1)])
    chosen = order[rank < k]
    if len(chosen) > target:
        chosen = rng.choice(chosen, target, replace=False)
    return cloud[np.sort(chosen)]


def scan_one(
    building: Building, position: np.ndarray, rng: np.random.Generator, cfg: ScanConfig
) -> np.ndarray:
    """Returns (P, 3) float64 world points of one scanner at (3,) ``position`` (nearest hits, range noise)."""
    step = math.radians(cfg.angular_step_deg)
    azimuth = rng.uniform(0.0, step) + np.arange(0.0, 2.0 * math.pi, step)  # the head starts anywhere
    elevation = np.arange(math.radians(cfg.min_elevation_deg), math.radians(cfg.max_elevation_deg), step)
    az, el = np.meshgrid(azimuth, elevation)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    # cube pixels about one ray step wide: the exact test over 2 x 2 pixels then misses only thinner faces
    size = math.ceil(2.0 / step)
    cube = Camera(size / 2.0, size / 2.0, (size - 1) / 2.0, (size - 1) / 2.0, size, size)
    side = _cube_side(dirs)
    tables = _face_tables(building, position)
    points = []
    for k in np.unique(side):
        view_from_world = make_cam_from_world(CUBE_VIEWS[k], -CUBE_VIEWS[k] @ position)
        face_id, _ = rasterize(building, view_from_world, cube, near_m=1e-3)
        for chunk in np.array_split(
            np.flatnonzero(side == k), max(1, int(np.sum(side == k)) // cfg.chunk_rays)
        ):
            rng_m = _nearest_hits(tables, dirs[chunk], face_id, cube, CUBE_VIEWS[k])
            ok = (rng_m >= cfg.min_range_m) & (rng_m <= cfg.max_range_m)
            r = rng_m[ok] + rng.normal(0.0, cfg.range_noise_m, size=int(ok.sum()))
            points.append(position + r[:, None] * dirs[chunk][ok])
    return np.concatenate(points) if points else np.zeros((0, 3))


def _cube_side(dirs: np.ndarray) -> np.ndarray:
    """Returns (R,) int cube view index (+x, -x, +y, -y, +z, -z) whose 90-degree frustum holds each ray."""
    axis = np.argmax(np.abs(dirs), axis=1)
    negative = dirs[np.arange(len(dirs)), axis] < 0
    return 2 * axis + negative


def _face_tables(building: Building, position: np.ndarray) -> dict[str, np.ndarray]:
    """Returns per-face (F,) / (F, 3) arrays for exact ray tests from ``position``: plane and edge axes.

    A ray ``position + t d`` meets face f at ``t = num / (d . n)``; the hit's coordinates along the two
    (unit) edge axes from corner 0 are ``q + t (d . axis)``, inside if within ``[0, length]``.
    """
    quads = building.faces
    n = building.normals
    e1, e2 = quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]
    l1, l2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
    rel = position - quads[:, 0]
    u1, u2 = e1 / l1[:, None], e2 / l2[:, None]
    return {
        "n": n,
        "num": -np.einsum("fk,fk->f", rel, n),
        "u1": u1,
        "u2": u2,
        "q1": np.einsum("fk,fk->f", rel, u1),
        "q2": np.einsum("fk,fk->f", rel, u2),
        "l1": l1,
        "l2": l2,
    }


def _nearest_hits(
    tables: dict[str, np.ndarray], dirs: np.ndarray, face_id: np.ndarray, cube: Camera, rot: np.ndarray
) -> np.ndarray:
    """Returns (R,) range (inf: no hit) along unit rays (R, 3) to the nearest face among the 2 x 2 cube
    pixels round each ray's image point (cube view rotation ``rot``); hits must lie inside their face.
    """
    c = rotate(dirs, rot)
    u0 = np.clip(np.floor(cube.fx * c[:, 0] / c[:, 2] + cube.cx).astype(np.int64), 0, cube.width - 2)
    v0 = np.clip(np.floor(cube.fy * c[:, 1] / c[:, 2] + cube.cy).astype(np.int64), 0, cube.height - 2)
    flat_ids = face_id.ravel()
    corner = v0 * cube.width + u0
    best = np.full(len(dirs), np.inf)
    tried: list[np.ndarray] = []
    for offset in (0, 1, cube.width, cube.width + 1):
        f = np.take(flat_ids, corner + offset)
        todo = f >= 0
        for g in tried:  # a face already tested for this ray gives the same answer
            todo &= f != g
        tried.append(f)
        rows = np.flatnonzero(todo)
        t = _hit_range(tables, dirs[rows], f[rows])
        better = t < best[rows]
        best[rows[better]] = t[better]
    return best


def _hit_range(tables: dict[str, np.ndarray], dirs: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Returns (R,) range along unit rays (R, 3) to faces (R,) int, inf where the ray misses the face."""
    tol = 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        t = tables["num"][faces] / np.einsum("rk,rk->r", dirs, tables["n"][faces])
    a = tables["q1"][faces] + t * np.einsum("rk,rk->r", dirs, tables["u1"][faces])
    b = tables["q2"][faces] + t * np.einsum("rk,rk->r", dirs, tables["u2"][faces])
    ok = (t > 0) & (a >= -tol) & (a <= tables["l1"][faces] + tol)
    ok &= (b >= -tol) & (b <= tables["l2"][faces] + tol)
    return np.where(ok, t, np.inf)
