"""The paper's comparison method: RANSAC over random 6-line correspondences solved by DLT-Lines.

DLT-Lines (Hartley & Zisserman; Pribyl et al. 2015): a 3D point ``X`` on the line imaged as the 2D line
``l`` satisfies ``l^T [R | t] X = 0`` when ``l`` is expressed in normalised image coordinates
(``l = K^T l_px``, i.e. the interpretation-plane normal). Both endpoints of each 3D segment give one
equation each, linear in the 12 entries of ``P = [R | t]``, so 6 correspondences fix ``P`` up to scale.

``register_ransac6`` samples 6 random 2D segments and 6 random 3D segments, pairs them blindly, solves
DLT-Lines and counts inliers with the shared test (``matching.match_segments``). With ``n`` of ``N`` 2D
segments imaging one of ``M`` map segments, a sample is all-correct with probability about
``(n / N)^6 / M^6``: the method is hopeless beyond a handful of lines, which is the paper's point.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .config import RegisterConfig
from .errors import InvalidInputError
from .geometry import (
    line_coefficients,
    make_cam_from_world,
    nearest_rotation,
    pixels_to_rays,
    rotation_error_deg,
)
from .matching import match_matrix, match_segments, project_segments
from .registration import Registration, check_segments
from .timing import StageTimer

log = logging.getLogger(__name__)

SAMPLE_SIZE = 6  # DLT-Lines: 12 unknowns up to scale, 2 equations per line
_RUNNER_UP_ANGLE_DEG = 2.0  # hypotheses whose rotations differ by more are distinct poses


def dlt_lines(lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera) -> np.ndarray:
    """Returns the (4, 4) ``cam_from_world`` that best fits K >= 6 known 2D <-> 3D line correspondences.

    lines2d: (K, 4) float64 undistorted pixels; lines3d: (K, 6) float64 world; row i of each corresponds.
    Linear (algebraic) solution: no robustness to wrong correspondences, no non-linear refinement.
    """
    lines2d = check_segments(lines2d, "lines2d", 4, SAMPLE_SIZE)
    lines3d = check_segments(lines3d, "lines3d", 6, SAMPLE_SIZE)
    if len(lines2d) != len(lines3d):
        raise InvalidInputError(
            f"lines2d and lines3d must correspond row by row: {len(lines2d)} != {len(lines3d)}"
        )
    rays1 = pixels_to_rays(camera, lines2d[:, 0:2])
    rays2 = pixels_to_rays(camera, lines2d[:, 2:4])
    return _dlt(rays1, rays2, lines3d)


def _dlt(rays1: np.ndarray, rays2: np.ndarray, lines3d: np.ndarray) -> np.ndarray:
    """Returns (4, 4) ``cam_from_world`` from (K, 3) normalised endpoint rays and (K, 6) 3D segments."""
    T2 = _normalizing_2d(np.r_[rays1[:, :2], rays2[:, :2]])
    points = lines3d.reshape(-1, 3)
    T3 = _normalizing_3d(points)
    # the line through two normalised points is K^T l_px, the interpretation-plane normal
    normals = np.cross(rays1, rays2)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # lines map as l' = T2^-T l when points map as x' = T2 x; then l'^T (T2 P T3^-1) X' = 0
    lines = normals @ np.linalg.inv(T2)
    lines /= np.linalg.norm(lines, axis=1, keepdims=True)
    X = np.c_[points, np.ones(len(points))] @ T3.T
    # l^T P X = kron(l, X) . vec(P) (row-major): one row per endpoint
    A = np.einsum("ki,kj->kij", np.repeat(lines, 2, axis=0), X).reshape(-1, 12)
    P = np.linalg.inv(T2) @ np.linalg.svd(A)[2][-1].reshape(3, 4) @ T3
    return _rigid_from_projection(P, points, normals)


def _rigid_from_projection(P: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Returns (4, 4) ``cam_from_world`` closest to a (3, 4) ``P ~ [R | t]`` known up to scale and sign.

    points: (2K, 3) world endpoints, two per row of normals (K, 3) (unit interpretation-plane normals).
    """
    depth = points @ P[2, :3] + P[2, 3]
    sign = 1.0 if np.sign(depth).sum() >= 0 else -1.0  # most endpoints in front of the camera
    M = sign * P[:, :3] / np.linalg.svd(P[:, :3], compute_uv=False).mean()
    R = nearest_rotation(M)
    # t given R, linear least squares on eq. (coplanar): n_i . (R X + t) = 0 for both endpoints
    n = np.repeat(normals, 2, axis=0)
    t = np.linalg.lstsq(n, -np.einsum("kj,kj->k", n, points @ R.T), rcond=None)[0]
    return make_cam_from_world(R, t)


def _normalizing_2d(points: np.ndarray) -> np.ndarray:
    """Returns (3, 3) similarity moving (K, 2) points to centroid 0 and mean distance sqrt(2) (Hartley)."""
    centroid = points.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.linalg.norm(points - centroid, axis=1).mean(), 1e-12)
    return np.array([[scale, 0.0, -scale * centroid[0]], [0.0, scale, -scale * centroid[1]], [0.0, 0.0, 1.0]])


def _normalizing_3d(points: np.ndarray) -> np.ndarray:
    """Returns (4, 4) similarity moving (K, 3) points to centroid 0 and mean distance sqrt(3) (Hartley)."""
    centroid = points.mean(axis=0)
    scale = np.sqrt(3.0) / max(np.linalg.norm(points - centroid, axis=1).mean(), 1e-12)
    T = np.diag([scale, scale, scale, 1.0])
    T[:3, 3] = -scale * centroid
    return T


@dataclass
class _Best:
    """The best hypothesis so far and the inlier counts of every fully tested one."""

    cam_from_world: np.ndarray
    matches: np.ndarray
    iterations: int = 0
    tested: list[tuple[int, np.ndarray]] | None = None

    @property
    def num_inliers(self) -> int:
        return len(self.matches)


def register_ransac6(
    lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig | None = None
) -> Registration:
    """Returns the Registration found by RANSAC over random 6-line correspondences (the paper's baseline).

    lines2d: (N, 4) float64 undistorted pixels; lines3d: (M, 6) float64 world. Stops at
    ``ransac6.stop_inlier_fraction`` of N inliers or ``ransac6.max_iterations``, then refines like ``register``.
    """
    config = config or RegisterConfig()
    timer = StageTimer()
    lines2d = check_segments(lines2d, "lines2d", 4)
    lines3d = check_segments(lines3d, "lines3d", 6)
    need = max(SAMPLE_SIZE, config.min_lines2d, config.min_lines3d)
    if min(len(lines2d), len(lines3d)) < need:
        reason = f"ransac6 needs >= {need} segments, got {len(lines2d)} 2D and {len(lines3d)} 3D"
        return Registration(success=False, reason=reason, timings=timer.finish())
    with timer("ransac6"):
        best = _ransac(lines2d, lines3d, camera, config)
    if best.num_inliers < config.min_inliers:
        reason = (
            f"ransac6: best of {best.iterations} hypotheses has {best.num_inliers} inliers, "
            f"fewer than {config.min_inliers}"
        )
        return Registration(
            success=False, reason=reason, num_inliers=best.num_inliers, timings=timer.finish()
        )
    with timer("refine"):
        result = _refine(lines2d, lines3d, camera, best, config)
    result.runner_up_inliers = max(
        [
            n
            for n, R in best.tested or []
            if rotation_error_deg(R, result.cam_from_world[:3, :3]) > _RUNNER_UP_ANGLE_DEG
        ],
        default=0,
    )
    result.timings = timer.finish()
    return result


def _ransac(lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig) -> _Best:
    """Returns the hypothesis with most inliers over random 6-pair samples (paper's RANSAC baseline)."""
    cfg = config.ransac6
    rng = np.random.default_rng(cfg.seed)
    rays1 = pixels_to_rays(camera, lines2d[:, 0:2])
    rays2 = pixels_to_rays(camera, lines2d[:, 2:4])
    best = _Best(np.eye(4), np.zeros((0, 2), dtype=np.int64), tested=[])
    stop = cfg.stop_inlier_fraction * len(lines2d)
    for iteration in range(1, cfg.max_iterations + 1):
        best.iterations = iteration
        i2d = rng.choice(len(lines2d), SAMPLE_SIZE, replace=False)
        j3d = rng.choice(len(lines3d), SAMPLE_SIZE, replace=False)
        with np.errstate(all="ignore"):
            cam_from_world = _dlt(rays1[i2d], rays2[i2d], lines3d[j3d])
        if not np.isfinite(cam_from_world).all():
            continue
        if (
            _sample_inliers(lines2d[i2d], lines3d[j3d], camera, cam_from_world, config)
            < cfg.min_sample_inliers
        ):
            continue  # cheap pretest: a pose that does not explain its own sample cannot win
        matches = match_segments(lines2d, lines3d, camera, cam_from_world, config.match)
        best.tested.append((len(matches), cam_from_world[:3, :3]))
        if len(matches) > best.num_inliers:
            best.cam_from_world, best.matches = cam_from_world, matches
            if best.num_inliers >= stop:
                break
    log.debug("ransac6: %d iterations, %d inliers", best.iterations, best.num_inliers)
    return best


def _sample_inliers(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    config: RegisterConfig,
) -> int:
    """Returns how many of K sampled pairs (row i with row i) pass the shared inlier test."""
    projected, visible = project_segments(lines3d, camera, cam_from_world, config.match.min_depth_m)
    inlier, _ = match_matrix(lines2d, projected, config.match)
    return int((np.diagonal(inlier) & visible).sum())


def _refine(
    lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, best: _Best, config: RegisterConfig
) -> Registration:
    """Returns the Registration after ``refine.refine_pose`` (same as ours), or unrefined if it is absent."""
    try:
        from .refine import refine_pose
    except ImportError:  # refinement not available in this build: report the RANSAC pose as is
        log.warning("linereg.refine unavailable: ransac6 pose is not refined")
        rms = reprojection_rms_px(lines2d, lines3d, camera, best.cam_from_world, best.matches)
        return Registration(True, "", best.cam_from_world, best.matches, best.num_inliers, rms_px=rms)
    refined = refine_pose(
        lines2d, lines3d, camera, best.cam_from_world, best.matches, config.refine, config.match
    )
    num_inliers = len(refined.matches)
    if num_inliers < config.min_inliers:
        reason = f"ransac6: refinement kept {num_inliers} inliers, fewer than {config.min_inliers}"
        return Registration(success=False, reason=reason, num_inliers=num_inliers)
    return Registration(
        success=True,
        cam_from_world=refined.cam_from_world,
        matches=refined.matches,
        num_inliers=num_inliers,
        covariance=refined.covariance,
        rms_px=refined.rms_px,
    )


def reprojection_rms_px(
    lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, matches: np.ndarray
) -> float:
    """Returns the RMS distance (px) of projected 3D endpoints to their matched 2D lines (NaN if none)."""
    if len(matches) == 0:
        return float("nan")
    projected, _ = project_segments(lines3d[matches[:, 1]], camera, cam_from_world, 1e-3)
    H = line_coefficients(lines2d[matches[:, 0]])
    d1 = np.einsum("kj,kj->k", H[:, :2], projected[:, 0:2]) + H[:, 2]
    d2 = np.einsum("kj,kj->k", H[:, :2], projected[:, 2:4]) + H[:, 2]
    return float(np.sqrt(np.mean(np.r_[d1, d2] ** 2)))
