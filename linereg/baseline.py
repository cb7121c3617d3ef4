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

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera
from .config import RegisterConfig
from .errors import InvalidInputError
from .geometry import (
    line_coefficients,
    make_cam_from_world,
    nearest_rotation,
    pixels_to_rays,
    project_points,
    rotation_error_deg,
)
from .matching import match_matrix, match_segments, project_segments
from .registration import Registration, check_segments
from .timing import StageTimer

log = logging.getLogger(__name__)

SAMPLE_SIZE = 6  # DLT-Lines: 12 unknowns up to scale, 2 equations per line
_BATCH = 32  # hypotheses solved together; bounds the (6 B)^2 pretest matrix
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
    P, normals = _projections(rays1[None], rays2[None], lines3d[None])
    return _rigid_from_projection(P[0], lines3d.reshape(-1, 3), normals[0])


def _projections(rays1: np.ndarray, rays2: np.ndarray, lines3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((B, 3, 4) ``P ~ [R | t]``, (B, K, 3) unit plane normals) of B sets of K correspondences.

    rays1, rays2: (B, K, 3) normalised endpoint rays; lines3d: (B, K, 6). P is scaled to mean singular
    value 1 of its 3x3 part and signed so that most endpoints lie in front of the camera.
    """
    points = lines3d.reshape(len(lines3d), -1, 3)
    # the line through two normalised points is K^T l_px, the interpretation-plane normal
    normals = np.cross(rays1, rays2)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    T2 = _normalizing(np.concatenate([rays1[..., :2], rays2[..., :2]], axis=1))
    T3 = _normalizing(points)
    # lines map as l' = T2^-T l when points map as x' = T2 x; then l'^T (T2 P T3^-1) X' = 0
    lines = np.einsum("bki,bij->bkj", normals, np.linalg.inv(T2))
    lines /= np.linalg.norm(lines, axis=-1, keepdims=True)
    X = np.einsum("bij,bkj->bki", T3, np.concatenate([points, np.ones((*points.shape[:2], 1))], axis=-1))
    # l^T P X = kron(l, X) . vec(P) (row-major): one row per endpoint
    A = np.einsum("bki,bkj->bkij", np.repeat(lines, 2, axis=1), X).reshape(len(X), -1, 12)
    P = np.linalg.inv(T2) @ np.linalg.svd(A, full_matrices=False)[2][:, -1].reshape(-1, 3, 4) @ T3
    depth = np.einsum("bj,bkj->bk", P[:, 2, :3], points) + P[:, 2, 3:4]
    sign = np.where(np.sign(depth).sum(axis=1) >= 0, 1.0, -1.0)  # most endpoints in front of the camera
    scale = np.linalg.svd(P[:, :, :3], compute_uv=False).mean(axis=1)
    return P * (sign / scale)[:, None, None], normals


def _rigid_from_projection(P: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Returns (4, 4) ``cam_from_world`` closest to a (3, 4) ``P ~ [R | t]`` scaled and signed.

    points: (2K, 3) world endpoints, two per row of normals (K, 3) (unit interpretation-plane normals).
    """
    R = nearest_rotation(P[:, :3])
    # t given R, linear least squares on eq. (coplanar): n_i . (R X + t) = 0 for both endpoints
    n = np.repeat(normals, 2, axis=0)
    t = np.linalg.lstsq(n, -np.einsum("kj,kj->k", n, points @ R.T), rcond=None)[0]
    return make_cam_from_world(R, t)


def _normalizing(points: np.ndarray) -> np.ndarray:
    """Returns (B, d+1, d+1) similarities moving (B, K, d) points to centroid 0, mean distance sqrt(d).

    Hartley's normalisation, per batch element, for d = 2 (image) or d = 3 (world).
    """
    d = points.shape[-1]
    centroid = points.mean(axis=1)
    spread = np.linalg.norm(points - centroid[:, None], axis=-1).mean(axis=1)
    scale = np.sqrt(d) / np.maximum(spread, 1e-12)
    T = np.zeros((len(points), d + 1, d + 1))
    T[:, np.arange(d), np.arange(d)] = scale[:, None]
    T[:, :d, d] = -scale[:, None] * centroid
    T[:, d, d] = 1.0
    return T


@dataclass
class _Best:
    """The best hypothesis so far and the inlier counts of every fully tested one."""

    cam_from_world: np.ndarray
    matches: np.ndarray
    iterations: int = 0
    tested: list[tuple[int, np.ndarray]] = field(default_factory=list)

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
    runner_up = max(
        [
            n
            for n, R in best.tested
            if rotation_error_deg(R, result.cam_from_world[:3, :3]) > _RUNNER_UP_ANGLE_DEG
        ],
        default=0,
    )
    return dataclasses.replace(result, runner_up_inliers=runner_up, timings=timer.finish())


def _ransac(lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig) -> _Best:
    """Returns the hypothesis with most inliers over random 6-pair samples (paper's RANSAC baseline).

    Samples are drawn and solved in batches (numpy, not Python, loops); hypotheses are then visited in
    draw order, so stopping and the iteration count are those of the one-at-a-time algorithm.
    """
    cfg = config.ransac6
    rng = np.random.default_rng(cfg.seed)
    rays1 = pixels_to_rays(camera, lines2d[:, 0:2])
    rays2 = pixels_to_rays(camera, lines2d[:, 2:4])
    best = _Best(np.eye(4), np.zeros((0, 2), dtype=np.int64))
    stop = cfg.stop_inlier_fraction * len(lines2d)
    for start in range(0, cfg.max_iterations, _BATCH):
        size = min(_BATCH, cfg.max_iterations - start)
        i2d, j3d = _draw(rng, len(lines2d), size), _draw(rng, len(lines3d), size)
        with np.errstate(all="ignore"):
            P, normals = _projections(rays1[i2d], rays2[i2d], lines3d[j3d])
            # cheap pretest: a hypothesis that does not explain its own sample cannot win
            passed = _pretest(P, lines2d[i2d], lines3d[j3d], camera, config) >= cfg.min_sample_inliers
        best.iterations = start + size
        for b in np.flatnonzero(passed):
            cam_from_world = _rigid_from_projection(P[b], lines3d[j3d[b]].reshape(-1, 3), normals[b])
            matches = match_segments(lines2d, lines3d, camera, cam_from_world, config.match)
            best.tested.append((len(matches), cam_from_world[:3, :3]))
            if len(matches) > best.num_inliers:
                best.cam_from_world, best.matches = cam_from_world, matches
                if best.num_inliers >= stop:
                    best.iterations = start + int(b) + 1
                    return best
    log.debug("ransac6: %d iterations, %d inliers", best.iterations, best.num_inliers)
    return best


def _draw(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    """Returns (size, 6) int64: each row 6 distinct random indices below n."""
    return np.argpartition(rng.random((size, n)), SAMPLE_SIZE - 1, axis=1)[:, :SAMPLE_SIZE]


def _pretest(
    P: np.ndarray, lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig
) -> np.ndarray:
    """Returns (B,) how many of each hypothesis' own K pairs pass the shared inlier test under P.

    P: (B, 3, 4) scaled, signed projections; lines2d: (B, K, 4); lines3d: (B, K, 6), row k with row k.
    """
    B, K = lines2d.shape[:2]
    ends = np.einsum("bij,bkj->bki", P[:, :, :3], lines3d.reshape(B, 2 * K, 3)) + P[:, None, :, 3]
    visible = (ends[..., 2] >= config.match.min_depth_m).reshape(B, K, 2).all(axis=2)
    projected = project_points(camera, ends.reshape(-1, 3)).reshape(B * K, 4)
    inlier, _ = match_matrix(lines2d.reshape(B * K, 4), projected, config.match)  # diagonal: own pairs
    return (np.diagonal(inlier).reshape(B, K) & visible).sum(axis=1)


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
