"""Pose and line geometry shared by every stage; the one place conventions live.

- ``cam_from_world``: (4, 4) float64 with ``x_cam = R @ x_world + t`` (``R = T[:3, :3]``, ``t = T[:3, 3]``).
- 2D segments: (N, 4) float64 ``x1, y1, x2, y2`` pixels; 3D segments: (M, 6) float64 ``X1, Y1, Z1, X2, Y2, Z2``.
- The interpretation plane of a 2D segment is the plane through the camera centre and the segment; its
  unit normal ``n`` (camera frame) satisfies ``n . x_cam = 0`` for every point of the matching 3D line
  (paper eq. "coplanar": ``(R P + t) . n = 0``).
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .errors import InvalidInputError


def make_cam_from_world(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Returns (4, 4) float64 ``cam_from_world`` from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(a_from_b: np.ndarray) -> np.ndarray:
    """Returns ``b_from_a`` for a rigid (4, 4) transform."""
    R, t = a_from_b[:3, :3], a_from_b[:3, 3]
    return make_cam_from_world(R.T, -R.T @ t)


def camera_center(cam_from_world: np.ndarray) -> np.ndarray:
    """Returns the (3,) camera centre in world coordinates, ``-R^T t``."""
    return -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Returns (N, 3) points mapped by a (4, 4) rigid transform."""
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def transform_segments(a_from_b: np.ndarray, segments_b: np.ndarray) -> np.ndarray:
    """Returns (M, 6) segments with both endpoints mapped by a (4, 4) rigid transform."""
    ends = transform_points(a_from_b, segments_b.reshape(-1, 3))
    return ends.reshape(-1, 6)


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """Returns the (3, 3) rotation of a (3,) rotation vector (axis * angle in radians, Rodrigues' formula)."""
    omega = np.asarray(omega, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(omega))
    if angle < 1e-12:
        return np.eye(3)
    k = omega / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """Returns the proper rotation closest to M in Frobenius norm (orthogonal Procrustes via SVD)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


# a rotation read from a pose file holds only the digits written: SUN3D's pose.txt (and TUM's, COLMAP's
# images.txt with 6-7 digits) make R R^T differ from I by up to ~5e-6; anything this close is meant as one
ROTATION_TOLERANCE = 1e-3


def rigid_rotation(R: np.ndarray) -> np.ndarray | None:
    """Returns the proper rotation a (3, 3) matrix was meant to be: itself, or ``nearest_rotation`` when it
    is one written to a few digits (``R R^T`` within ``ROTATION_TOLERANCE`` of I, det > 0); None when it is
    no rotation (a reflection, a scaling, a shear)."""
    R = np.asarray(R, dtype=np.float64)
    off = np.abs(R @ R.T - np.eye(3)).max()
    if off > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        return None
    return R if off <= 1e-12 else nearest_rotation(R)


def check_rigid(value: object, name: str) -> np.ndarray:
    """Returns ``value`` as a (4, 4) float64 rigid transform (a rotation written to a few digits taken as the
    nearest rotation: ``rigid_rotation``), or raises InvalidInputError naming it."""
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a numeric (4, 4) matrix") from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInputError(f"{name} must be a finite (4, 4) matrix, got shape {T.shape}")
    R = rigid_rotation(T[:3, :3])
    if R is None:
        raise InvalidInputError(
            f"{name} is not rigid: its rotation is not orthonormal (to {ROTATION_TOLERANCE:g}) with det +1"
        )
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InvalidInputError(f"{name} is not rigid: its last row must be 0 0 0 1")
    T[:3, :3] = R
    return T


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Returns the angle in degrees of ``R_a^T R_b`` (paper: ``acos((trace(R_a^T R_b) - 1) / 2)``).

    Computed as ``atan2(sin, cos)`` from the skew part and the trace: ``acos`` near 1 turns a few ulp of
    rounding into ~1e-6 degrees, ``atan2`` resolves small angles to ~1e-14.
    """
    M = R_a.T @ R_b
    sin = 0.5 * np.linalg.norm([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    cos = 0.5 * (np.trace(M) - 1.0)
    return float(np.degrees(np.arctan2(sin, cos)))


def axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Returns the angle in degrees between two sign-free (3,) axes, in [0, 90], well conditioned near 0."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(float(a @ b)))))


def pose_errors(cam_from_world: np.ndarray, gt_cam_from_world: np.ndarray) -> tuple[float, float, float]:
    """Returns (rotation error deg, position error m, ``|t_e| / |t_gt|``) of an estimate against truth.

    Position error compares camera centres; the relative error follows the paper (``||t_e|| / ||t_GT||``).
    """
    rot = rotation_error_deg(cam_from_world[:3, :3], gt_cam_from_world[:3, :3])
    pos = float(np.linalg.norm(camera_center(cam_from_world) - camera_center(gt_cam_from_world)))
    t_gt = gt_cam_from_world[:3, 3]
    rel = float(np.linalg.norm(cam_from_world[:3, 3] - t_gt) / max(float(np.linalg.norm(t_gt)), 1e-12))
    return rot, pos, rel


def pixels_to_rays(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """Returns (N, 3) homogeneous normalized rays ``K^-1 [u, v, 1]`` for (N, 2) undistorted pixels."""
    rays = np.empty((len(pixels), 3))
    rays[:, 0] = (pixels[:, 0] - camera.cx) / camera.fx
    rays[:, 1] = (pixels[:, 1] - camera.cy) / camera.fy
    rays[:, 2] = 1.0
    return rays


def unit_vector(v: np.ndarray) -> np.ndarray:
    """Returns the (3,) finite, non-zero vector ``v`` scaled to unit length: by its largest component first,
    so that a vector of 1e200s or 1e-200s is a direction too (its norm would overflow or underflow)."""
    v = v / np.abs(v).max()
    return v / np.linalg.norm(v)


def interpretation_normals(lines2d: np.ndarray, camera: Camera) -> np.ndarray:
    """Returns (N, 3) unit normals (camera frame) of the planes through the camera centre and each segment.

    Sign: ``n = normalize(ray1 x ray2)``, so it flips if the segment's endpoints are swapped.
    """
    r1 = pixels_to_rays(camera, lines2d[:, 0:2])
    r2 = pixels_to_rays(camera, lines2d[:, 2:4])
    n = np.cross(r1, r2)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def line_coefficients(lines2d: np.ndarray) -> np.ndarray:
    """Returns (N, 3) ``(A, B, C)`` of each segment's infinite line ``A x + B y + C = 0``, ``A^2 + B^2 = 1``."""
    x1, y1, x2, y2 = lines2d[:, 0], lines2d[:, 1], lines2d[:, 2], lines2d[:, 3]
    H = np.empty((len(lines2d), 3))  # (x1, y1, 1) x (x2, y2, 1)
    np.subtract(y1, y2, out=H[:, 0])
    np.subtract(x2, x1, out=H[:, 1])
    np.subtract(x1 * y2, y1 * x2, out=H[:, 2])
    H /= np.sqrt(H[:, 0] * H[:, 0] + H[:, 1] * H[:, 1])[:, None]
    return H


def project_points(camera: Camera, points_cam: np.ndarray) -> np.ndarray:
    """Returns (N, 2) undistorted pixels of (N, 3) camera-frame points (no check that Z > 0)."""
    z = points_cam[:, 2]
    return np.c_[camera.fx * points_cam[:, 0] / z + camera.cx, camera.fy * points_cam[:, 1] / z + camera.cy]


def segment_lengths(lines: np.ndarray) -> np.ndarray:
    """Returns (N,) lengths of (N, 4) 2D or (N, 6) 3D segments."""
    d = lines.shape[1] // 2
    return np.linalg.norm(lines[:, d:] - lines[:, :d], axis=1)


def segment_angles(lines: np.ndarray) -> np.ndarray:
    """Returns (N,) angles in [0, pi) of (N, 4) 2D segments (undirected)."""
    return np.mod(np.arctan2(lines[:, 3] - lines[:, 1], lines[:, 2] - lines[:, 0]), np.pi)


def segment_directions(lines: np.ndarray) -> np.ndarray:
    """Returns (N, d) unit directions (second endpoint minus first) of 2D or 3D segments."""
    d = lines.shape[1] // 2
    v = lines[:, d:] - lines[:, :d]
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def orbited(cam_from_world: np.ndarray, depth_m: float, turn: np.ndarray) -> np.ndarray:
    """Returns the (4, 4) cam_from_world of a camera moved round the point ``depth_m`` ahead of it on its
    optical axis and turned by ``turn`` (3, 3, camera frame) so that it keeps looking at that point: the
    point stays where it was in the image, nearer and farther ones move by their parallax."""
    ahead = np.array([0.0, 0.0, depth_m])
    moved = np.eye(4)
    moved[:3, :3] = turn.T
    moved[:3, 3] = ahead - turn.T @ ahead
    return moved @ cam_from_world
