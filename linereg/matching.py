"""The correspondence test every stage shares: is a projected 3D segment an inlier of a 2D segment?

Paper section III-C: a 3D segment matches a 2D segment when it lies on the 2D segment's interpretation
plane (eq. "coplanar", tested here in pixels as the distance of both projected endpoints to the 2D
segment's infinite line) and its projection overlaps more than half of the 2D segment.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .config import MatchConfig


def project_segments(
    lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((M, 4) projected pixel segments, (M,) bool visible) after clipping to ``z >= min_depth_m``.

    A segment wholly behind the camera is not visible; one crossing the near plane is cut there.
    """
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    a = lines3d[:, 0:3] @ R.T + t
    b = lines3d[:, 3:6] @ R.T + t
    za, zb = a[:, 2], b[:, 2]
    visible = (za >= min_depth_m) | (zb >= min_depth_m)
    # move the endpoint behind the near plane onto it, along the segment
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip((min_depth_m - za) / (zb - za), 0.0, 1.0)
    a = np.where((za < min_depth_m)[:, None], a + s[:, None] * (b - a), a)
    s = np.clip((min_depth_m - zb) / np.where(za != zb, za - zb, 1.0), 0.0, 1.0)
    b = np.where((zb < min_depth_m)[:, None], b + s[:, None] * (a - b), b)
    za, zb = np.maximum(a[:, 2], min_depth_m), np.maximum(b[:, 2], min_depth_m)
    seg = np.empty((len(lines3d), 4))
    seg[:, 0] = camera.fx * a[:, 0] / za + camera.cx
    seg[:, 1] = camera.fy * a[:, 1] / za + camera.cy
    seg[:, 2] = camera.fx * b[:, 0] / zb + camera.cx
    seg[:, 3] = camera.fy * b[:, 1] / zb + camera.cy
    return seg, visible


def _lines(lines2d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((N, 3) normalized line coefficients, (N, 2) unit directions, (N,) lengths, (N,) offsets).

    Same as ``geometry.line_coefficients`` / ``segment_directions`` / ``segment_lengths`` in one pass.
    """
    d = lines2d[:, 2:4] - lines2d[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    inv = 1.0 / np.maximum(length, 1e-300)
    u = d * inv[:, None]
    # (x1, y1, 1) x (x2, y2, 1) = (y1 - y2, x2 - x1, x1 y2 - x2 y1), scaled to A^2 + B^2 = 1
    H = np.c_[-u[:, 1], u[:, 0], (lines2d[:, 0] * lines2d[:, 3] - lines2d[:, 2] * lines2d[:, 1]) * inv]
    offset = u[:, 0] * lines2d[:, 0] + u[:, 1] * lines2d[:, 1]
    return H, u, length, offset


def match_matrix(
    lines2d: np.ndarray, projected: np.ndarray, config: MatchConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N, M) bool inlier, (N, M) float64 mean endpoint distance px) of 2D vs projected segments."""
    H, u, length, offset = _lines(lines2d)
    d1 = np.abs(H[:, :2] @ projected[:, 0:2].T + H[:, 2:3])
    d2 = np.abs(H[:, :2] @ projected[:, 2:4].T + H[:, 2:3])
    close = (d1 <= config.distance_px) & (d2 <= config.distance_px)
    s1 = u @ projected[:, 0:2].T - offset[:, None]  # position of each projected endpoint along the 2D segment
    s2 = u @ projected[:, 2:4].T - offset[:, None]
    lo = np.maximum(np.minimum(s1, s2), 0.0)
    hi = np.minimum(np.maximum(s1, s2), length[:, None])
    overlap = (hi - lo) / length[:, None]
    return close & (overlap > config.min_overlap), 0.5 * (d1 + d2)


def match_segments(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    config: MatchConfig,
) -> np.ndarray:
    """Returns (K, 2) int64 ``(i2d, j3d)``: for each 2D segment its closest inlier 3D segment, if any.

    lines2d: (N, 4) undistorted pixels; lines3d: (M, 6) world; several 2D fragments may share a 3D segment.
    Same result as ``match_matrix`` + argmin of the mean distance (ties: lowest j), but the overlap is
    only evaluated on the few pairs that pass the distance test.
    """
    if len(lines2d) == 0 or len(lines3d) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    projected, visible = project_segments(lines3d, camera, cam_from_world, config.min_depth_m)
    # an inlier passes within distance_px of a point of its 2D segment: projections wholly beyond one side
    # of the 2D segments' box (grown by distance_px) cannot match, which drops most of a large map
    lo = lines2d.reshape(-1, 2).min(axis=0) - config.distance_px
    hi = lines2d.reshape(-1, 2).max(axis=0) + config.distance_px
    xs, ys = projected[:, 0::2], projected[:, 1::2]
    outside = (xs < lo[0]).all(1) | (xs > hi[0]).all(1) | (ys < lo[1]).all(1) | (ys > hi[1]).all(1)
    cols = np.flatnonzero(visible & ~outside)
    projected = projected[cols]
    H, u, length, offset = _lines(lines2d)
    d1 = np.abs(H[:, :2] @ projected[:, 0:2].T + H[:, 2:3])
    i, j = np.nonzero(d1 <= config.distance_px)
    d1 = d1[i, j]
    d2 = np.abs(H[i, 0] * projected[j, 2] + H[i, 1] * projected[j, 3] + H[i, 2])
    near = d2 <= config.distance_px
    i, j, d1, d2 = i[near], j[near], d1[near], d2[near]
    s1 = np.einsum("pk,pk->p", u[i], projected[j, 0:2]) - offset[i]
    s2 = np.einsum("pk,pk->p", u[i], projected[j, 2:4]) - offset[i]
    lo = np.maximum(np.minimum(s1, s2), 0.0)
    hi = np.minimum(np.maximum(s1, s2), length[i])
    keep = (hi - lo) / length[i] > config.min_overlap
    i, j = i[keep], j[keep]
    dist = 0.5 * (d1[keep] + d2[keep])
    order = np.lexsort((j, dist, i))  # by 2D segment, then distance, then lowest 3D index
    first = order[np.r_[True, i[order][1:] != i[order][:-1]]] if len(order) else order
    return np.c_[i[first], cols[j[first]]].astype(np.int64).reshape(-1, 2)
