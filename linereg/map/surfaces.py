"""The surfaces a map's segments came from, kept as one triangle mesh for occlusion tests (``visibility``).

Map building turns each planar region's occupancy raster (``contours.region_image``) into rectangles: the
filled runs of each raster row, runs of the same columns in consecutive rows joined into one rectangle,
each rectangle two triangles (``(2k, 2k + 1)`` is rectangle k: the potentially-visible sets use whole
rectangles as convex occluders). Vertices are float32 relative to a float64 ``origin`` (a georeferenced
map at 5e6 m keeps centimetres only that way).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InvalidInputError


@dataclass(frozen=True)
class Surfaces:
    """A triangle mesh: ``vertices`` (V, 3) float32 metres relative to ``origin`` (3,) float64 (world =
    origin + vertex), ``triangles`` (T, 3) int32 vertex indices."""

    vertices: np.ndarray
    triangles: np.ndarray
    origin: np.ndarray

    def __len__(self) -> int:
        return len(self.triangles)

    def world_vertices(self) -> np.ndarray:
        """Returns (V, 3) float64 vertices in the map frame."""
        return self.vertices.astype(np.float64) + self.origin

    def area_m2(self) -> float:
        """Returns the summed area of the triangles (m^2)."""
        v = self.vertices.astype(np.float64)[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


def empty_surfaces() -> Surfaces:
    return Surfaces(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros(3))


def make_surfaces(vertices: object, triangles: object, origin: object = None) -> Surfaces:
    """Returns checked Surfaces of (V, 3) vertices (map frame unless ``origin`` is given) and (T, 3) int
    triangles; InvalidInputError naming the problem otherwise."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise InvalidInputError(f"surface vertices must be a finite (V, 3) array, got shape {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or (t.size and not np.issubdtype(t.dtype, np.integer)):
        raise InvalidInputError(f"surface triangles must be an integer (T, 3) array, got shape {t.shape}")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise InvalidInputError(f"surface triangles index vertices outside 0..{len(v) - 1}")
    if origin is None:
        base = v.min(axis=0) if len(v) else np.zeros(3)
        v = v - base
    else:
        base = np.asarray(origin, dtype=np.float64).reshape(3)
    return Surfaces(v.astype(np.float32), t.astype(np.int32), base)


def shift_surfaces(surfaces: Surfaces, offset: np.ndarray) -> Surfaces:
    """Returns the mesh moved by (3,) ``offset``: a mesh of a local frame placed in the map frame."""
    origin = surfaces.origin + np.asarray(offset, dtype=np.float64).reshape(3)
    return Surfaces(surfaces.vertices, surfaces.triangles, origin)


def concat_surfaces(parts: list[Surfaces], origin: np.ndarray) -> Surfaces:
    """Returns one mesh of several, its vertices relative to (3,) ``origin``."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return Surfaces(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.asarray(origin, float))
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.concatenate([p.world_vertices() - origin for p in parts]).astype(np.float32)
    triangles = np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)])
    return Surfaces(vertices, triangles.astype(np.int32), np.asarray(origin, dtype=np.float64))


def raster_mesh(
    image: np.ndarray, lo: np.ndarray, cell: float, plane: tuple[np.ndarray, np.ndarray], mesh_cell: float
) -> Surfaces:
    """Returns the rectangles covering the filled pixels of a region's (H, W) uint8 raster (pixel (i, j)
    spans plane coordinates lo + [i, i + 1] x cell, lo + [j, j + 1] x cell), resampled to cells of at
    least ``mesh_cell`` (a coarse mesh: occluders need no detail). plane: ((3,) origin, (2, 3) in-plane
    axes) in the map frame."""
    factor = max(1, round(mesh_cell / cell))
    if factor > 1:
        h, w = image.shape
        pad = np.zeros((-(-h // factor) * factor, -(-w // factor) * factor), np.uint8)
        pad[:h, :w] = image
        # a coarse cell is surface where most of its fine cells are (area average, then half)
        image = cv2.resize(
            pad, (pad.shape[1] // factor, pad.shape[0] // factor), interpolation=cv2.INTER_AREA
        )
        image = np.where(image >= 128, 255, 0).astype(np.uint8)
    rects = raster_rectangles(image > 0)
    size = cell * factor
    u0, u1 = lo[0] + rects[:, 0] * size, lo[0] + rects[:, 1] * size
    v0, v1 = lo[1] + rects[:, 2] * size, lo[1] + rects[:, 3] * size
    corners = np.empty((len(rects), 4, 2))  # (R, 4, 2): (u0, v0), (u1, v0), (u1, v1), (u0, v1)
    corners[:, [0, 3], 0], corners[:, [1, 2], 0] = u0[:, None], u1[:, None]
    corners[:, [0, 1], 1], corners[:, [2, 3], 1] = v0[:, None], v1[:, None]
    origin, basis = plane
    vertices = origin + corners.reshape(-1, 2) @ basis
    first = 4 * np.arange(len(rects))[:, None]
    triangles = np.stack([first + np.array([0, 1, 2]), first + np.array([0, 2, 3])], axis=1).reshape(-1, 3)
    return make_surfaces(vertices, triangles)


def raster_rectangles(filled: np.ndarray) -> np.ndarray:
    """Returns (R, 4) int64 column start, column end (exclusive), row start, row end (exclusive) of
    rectangles exactly covering the True pixels of an (H, W) bool image: each row's runs, runs of the same
    columns in consecutive rows joined."""
    padded = np.zeros((filled.shape[0], filled.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = filled
    step = np.diff(padded, axis=1)
    rows_s, cols_s = np.nonzero(step == 1)
    _, cols_e = np.nonzero(step == -1)  # row-major order: the i-th start and end are one run
    if len(rows_s) == 0:
        return np.zeros((0, 4), np.int64)
    order = np.lexsort((rows_s, cols_e, cols_s))  # same columns together, by row
    c0, c1, r = cols_s[order], cols_e[order], rows_s[order]
    new = np.r_[True, (c0[1:] != c0[:-1]) | (c1[1:] != c1[:-1]) | (r[1:] != r[:-1] + 1)]
    start = np.flatnonzero(new)
    end = np.r_[start[1:], len(r)] - 1
    return np.stack([c0[start], c1[start], r[start], r[end] + 1], axis=1).astype(np.int64)
