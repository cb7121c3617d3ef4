"""The compiled loops of colorization (numba): voxel sums, splats into the depth buffer, the depth test.

Each loop computes what the numpy expressions it replaced did, in the same floating-point types and order
(float32 where those were float32, sums in row order), so its results are the same bit for bit: the point of
compiling is only to make one pass over the points instead of a temporary array per step. Division by
zero gives inf / NaN as in numpy (``error_model="numpy"``), not an exception.
"""

from __future__ import annotations

import numba
import numpy as np

EMPTY = np.int64(-1)


@numba.njit(cache=True, error_model="numpy")
def voxel_ids(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((n,) int64 voxel id of each point, numbered in order of first appearance, (V,) int64 count)
    of (n,) float64 integral voxel keys (exact below 2^53), with an open-addressing hash table."""
    n = len(key)
    size = 1
    while size < 2 * n + 2:
        size *= 2
    mask = size - 1
    slot_key = np.empty(size, np.int64)
    slot_id = np.full(size, EMPTY, np.int64)
    ids = np.empty(n, np.int64)
    count = np.zeros(n, np.int64)
    voxels = 0
    for i in range(n):
        k = np.int64(key[i])
        h = (k * np.int64(-7046029254386353131)) & mask  # Fibonacci hashing: spreads neighbouring keys
        while slot_id[h] != EMPTY and slot_key[h] != k:
            h = (h + 1) & mask
        if slot_id[h] == EMPTY:
            slot_key[h] = k
            slot_id[h] = voxels
            voxels += 1
        ids[i] = slot_id[h]
        count[ids[i]] += 1
    return ids, count[:voxels]


@numba.njit(cache=True, error_model="numpy")
def voxel_moments(
    ids: np.ndarray, local: np.ndarray, voxels: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((V, 3) sums of x, y, z, (V, 6) sums of xx, xy, xz, yy, yz, zz) per voxel, added in row
    order (as ``np.bincount(ids, weights=...)`` adds them)."""
    first = np.zeros((voxels, 3))
    second = np.zeros((voxels, 6))
    for i in range(len(ids)):
        v = ids[i]
        x, y, z = local[i, 0], local[i, 1], local[i, 2]
        first[v, 0] += x
        first[v, 1] += y
        first[v, 2] += z
        second[v, 0] += x * x
        second[v, 1] += x * y
        second[v, 2] += x * z
        second[v, 3] += y * y
        second[v, 4] += y * z
        second[v, 5] += z * z
    return first, second


@numba.njit(cache=True, error_model="numpy")
def splat_squares(
    buffer: np.ndarray,
    stride: int,
    pad: int,
    width: int,
    height: int,
    u: np.ndarray,
    v: np.ndarray,
    z: np.ndarray,
    side: np.ndarray,
    slope: np.ndarray,
    tilted: bool,
) -> None:  # pragma: no cover - numba
    """Writes the minimum depth of each point's ``side`` x ``side`` square of pixels into the pixel level
    of ``buffer`` (rows of ``stride`` floats, a margin of ``pad`` pixels), in place.

    As ``depth._square_pixels`` and ``depth.splat``: the first column ``floor(u - side / 2 + 1)`` in
    float32, pixels clipped to the margin's outer edge, the depth of the tangent plane at each pixel
    centre ``z + slope_u (col - u) + slope_v (row - v)`` in float64, stored as float32.
    """
    lo_col, hi_col = -pad, width - 1 + pad
    lo_row, hi_row = -pad, height - 1 + pad
    for i in range(len(u)):
        s = side[i]
        half = np.float32(0.5 * s)
        first_col = int(np.floor(u[i] - half + np.float32(1.0)))
        first_row = int(np.floor(v[i] - half + np.float32(1.0)))
        zi = np.float64(z[i])
        su, sv = np.float64(slope[i, 0]), np.float64(slope[i, 1])
        ui, vi = np.float64(u[i]), np.float64(v[i])
        for a in range(s):
            row = _clamp(first_row + a, lo_row, hi_row)
            base = (row + pad) * stride + pad
            for b in range(s):
                col = _clamp(first_col + b, lo_col, hi_col)
                if tilted:
                    d = np.float32(zi + su * (np.float64(col) - ui) + sv * (np.float64(row) - vi))
                else:
                    d = z[i]
                j = base + col
                if d < buffer[j]:
                    buffer[j] = d


@numba.njit(cache=True, error_model="numpy")
def _clamp(x: int, lo: int, hi: int) -> int:  # pragma: no cover - numba
    return lo if x < lo else (hi if x > hi else x)


@numba.njit(cache=True, error_model="numpy")
def splat_blocks(buffer: np.ndarray, index: np.ndarray, z: np.ndarray) -> None:  # pragma: no cover - numba
    """Writes ``buffer[index] = min(buffer[index], z)`` for the indices >= 0 (pyramid blocks), in place."""
    for i in range(len(index)):
        j = index[i]
        if j >= 0 and z[i] < buffer[j]:
            buffer[j] = z[i]


@numba.njit(cache=True, error_model="numpy")
def behind(
    depth: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray, slope: np.ndarray, radius: np.ndarray
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (n,) float32 the most any point's tangent plane lies behind ``depth`` (H, W) over the pixels
    within ``radius`` (Chebyshev) of its own; pixels beyond the border take the border's depth.

    As ``depth.behind_m`` computed it: in float32, the plane at the centre of the point's pixel
    ``z + slope_u (col - u) + slope_v (row - v)``, then ``+ slope_u dx + slope_v dy`` per pixel.
    """
    h, w = depth.shape
    out = np.empty(len(u), np.float32)
    for i in range(len(u)):
        col = np.floor(u[i] + np.float32(0.5))
        row = np.floor(v[i] + np.float32(0.5))
        su, sv = slope[i, 0], slope[i, 1]
        plane = z[i] + su * (col - u[i]) + sv * (row - v[i])
        c0, r0 = int(col), int(row)
        worst = plane - depth[_clamp(r0, 0, h - 1), _clamp(c0, 0, w - 1)]
        r = radius[i]
        for dy in range(-r, r + 1):
            y = _clamp(r0 + dy, 0, h - 1)
            for dx in range(-r, r + 1):
                if dx == 0 and dy == 0:
                    continue
                x = _clamp(c0 + dx, 0, w - 1)
                here = plane + su * np.float32(dx) + sv * np.float32(dy) - depth[y, x]
                if here > worst:
                    worst = here
        out[i] = worst
    return out


@numba.njit(cache=True, error_model="numpy")
def view_geometry(
    points: np.ndarray,
    rows: np.ndarray,
    normals: np.ndarray,
    spacing: np.ndarray,
    cam_from_world: np.ndarray,
    centre: np.ndarray,
    intrinsics: np.ndarray,
    bounds: np.ndarray,
    near_m: float,
    max_slope: float,
    splat_focal: float,
):  # pragma: no cover - numba
    """Returns (index, u, v, z, diameter, slope, distance, cos) of the rows a pinhole photo sees, in one
    pass: ``project.project``, ``depth.depth_slope`` of the normals turned into the camera frame,
    ``depth.diameter_px``, and the range and |cos| of the viewing angle ``blend.observe`` weighs by.

    centre: (3,) the camera centre in the world (``geometry.camera_center``); intrinsics: (fx, fy, cx, cy); bounds: (lo_u, hi_u, lo_v, hi_v) the pixels kept, lo <= u < hi;
    splat_focal: ``splat_scale * max(fx, fy)``. Types and order of operations as those functions have them.
    """
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    Rf = R.astype(np.float32)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    fx32, fy32, cx32, cy32 = np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy)
    per_px = np.float32(max_slope / max(fx, fy))
    focal32 = np.float32(splat_focal)
    n = len(rows)
    index = np.empty(n, np.int64)
    u = np.empty(n, np.float32)
    v = np.empty(n, np.float32)
    z = np.empty(n, np.float32)
    diameter = np.empty(n, np.float32)
    slope = np.empty((n, 2), np.float32)
    distance = np.empty(n, np.float32)
    cos = np.empty(n, np.float32)
    m = 0
    for k in range(n):
        r = rows[k]
        p0, p1, p2 = points[r, 0], points[r, 1], points[r, 2]
        depth = p0 * R[2, 0] + p1 * R[2, 1] + p2 * R[2, 2] + t[2]
        if not depth > near_m:
            continue
        x = (p0 * R[0, 0] + p1 * R[0, 1] + p2 * R[0, 2] + t[0]) / depth
        y = (p0 * R[1, 0] + p1 * R[1, 1] + p2 * R[1, 2] + t[1]) / depth
        uu, vv = np.float32(fx * x + cx), np.float32(fy * y + cy)
        if not (uu >= bounds[0] and uu < bounds[1] and vv >= bounds[2] and vv < bounds[3]):
            continue
        zz = np.float32(depth)
        index[m], u[m], v[m], z[m] = r, uu, vv, zz
        # depth_slope: the normal in the camera frame (float32), the plane's dz/du, dz/dv clipped
        n0, n1, n2 = normals[r, 0], normals[r, 1], normals[r, 2]
        c0 = n0 * Rf[0, 0] + n1 * Rf[0, 1] + n2 * Rf[0, 2]
        c1 = n0 * Rf[1, 0] + n1 * Rf[1, 1] + n2 * Rf[1, 2]
        c2 = n0 * Rf[2, 0] + n1 * Rf[2, 1] + n2 * Rf[2, 2]
        facing = c0 * ((uu - cx32) / fx32) + c1 * ((vv - cy32) / fy32) + c2
        limit = np.float64(per_px * zz)
        slope[m, 0] = _clipped(np.float64(-zz * c0) / (fx * np.float64(facing)), limit)
        slope[m, 1] = _clipped(np.float64(-zz * c1) / (fy * np.float64(facing)), limit)
        diameter[m] = focal32 * spacing[r] / zz
        # observe: range and |cos| of the angle between the viewing ray and the normal (NaN: facing)
        e0, e1, e2 = centre[0] - p0, centre[1] - p1, centre[2] - p2
        distance[m] = np.float32(np.sqrt(e0 * e0 + e1 * e1 + e2 * e2))
        c = np.float32(abs(n0 * e0 + n1 * e1 + n2 * e2)) / distance[m]
        cos[m] = np.float32(1.0) if c != c else c
        m += 1
    return index[:m], u[:m], v[:m], z[:m], diameter[:m], slope[:m], distance[:m], cos[:m]


@numba.njit(cache=True, error_model="numpy")
def _clipped(g: float, limit: float) -> np.float32:  # pragma: no cover - numba
    """Returns ``g`` clipped to [-limit, limit] as float32, 0 for NaN (``np.nan_to_num(np.clip(...))``)."""
    if g != g:
        return np.float32(0.0)
    return np.float32(min(max(g, -limit), limit))


@numba.njit(cache=True, error_model="numpy")
def voxel_keys(
    points: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((n,) float64 voxel key, (n, 3) float64 position inside the voxel) of (n, 3) points, as
    ``surface._voxel_statistics`` numbers voxels: ``floor(p / voxel_m)`` from the lowest voxel up."""
    n = len(points)
    cell = np.empty((n, 3))
    local = np.empty((n, 3))
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(n):
        for a in range(3):
            c = np.floor(points[i, a] / voxel_m)
            cell[i, a] = c
            local[i, a] = points[i, a] - c * voxel_m  # in [0, voxel_m): no cancellation with UTM coordinates
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    dims1, dims2 = hi[1] - lo[1] + 1.0, hi[2] - lo[2] + 1.0
    key = np.empty(n)
    for i in range(n):
        key[i] = ((cell[i, 0] - lo[0]) * dims1 + (cell[i, 1] - lo[1])) * dims2 + (cell[i, 2] - lo[2])
    return key, local
