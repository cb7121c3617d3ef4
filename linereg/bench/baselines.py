"""The paper's comparison methods, for ``bench synthetic``: RANSAC over random 6-line correspondences
solved by DLT-Lines (``ransac6``), and the paper's own translation stage, random 3-pair RANSAC per rotation
candidate (``ransac3``, section III-C, Algorithm 2).

DLT-Lines (Hartley & Zisserman; Pribyl et al. 2015): a 3D point ``X`` on the line imaged as the 2D line
``l`` satisfies ``l^T [R | t] X = 0`` when ``l`` is expressed in normalised image coordinates
(``l = K^T l_px``, i.e. the interpretation-plane normal). Both endpoints of each 3D segment give one
equation each, linear in the 12 entries of ``P = [R | t]``, so 6 correspondences fix ``P`` up to scale. With
``n`` of ``N`` 2D segments imaging one of ``M`` map segments, a blind 6-sample is all-correct with
probability about ``(n / N)^6 / M^6``: the method is hopeless beyond a handful of lines (the paper's point).

Both count inliers with the score's pair test (``score.Score.matches``: the image segments a single map
segment covers over more than half their length, the paper's overlap test) and refine like ``register``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..config import RegisterConfig
from ..errors import InvalidInputError
from ..geometry import make_cam_from_world, nearest_rotation, pixels_to_rays
from ..parallel import parallel_clusters
from ..refine import refine_pose
from ..registration import Registration, check_segments
from ..rotation import refine_candidates, rotation_candidates
from ..score import ImageLines, image_lines, score_pose
from ..timing import StageTimer
from ..vanishing import vanishing_directions

log = logging.getLogger(__name__)

SAMPLE_SIZE = 6  # DLT-Lines: 12 unknowns up to scale, 2 equations per line
BATCH = 32  # hypotheses solved together (speed only)


@dataclass(frozen=True)
class BaselineConfig:
    """The paper's RANSAC budgets and stopping rule."""

    max_iterations: int = 2000  # paper-faithful budget; rarely enough among many lines
    stop_inlier_fraction: float = 0.7  # paper: stop at 70 % of the 2D segments as inliers
    seed: int = 0


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


def ransac6(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    config: RegisterConfig | None = None,
    baseline: BaselineConfig | None = None,
) -> Registration:
    """Returns the Registration found by RANSAC over random 6-line correspondences (the paper's baseline).

    lines2d: (N, 4) float64 undistorted pixels; lines3d: (M, 6) float64 world. Stops at
    ``stop_inlier_fraction`` of N inliers or ``max_iterations``, then refines like ``register``.
    """
    config, baseline = config or RegisterConfig(), baseline or BaselineConfig()
    timer = StageTimer()
    lines2d = check_segments(lines2d, "lines2d", 4, SAMPLE_SIZE)
    lines3d = check_segments(lines3d, "lines3d", 6, SAMPLE_SIZE)
    image = image_lines(lines2d, camera, config.score)
    rng = np.random.default_rng(baseline.seed)
    rays1, rays2 = pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4])
    best, best_count = np.eye(4), -1
    stop = baseline.stop_inlier_fraction * len(lines2d)
    with timer("ransac6"):
        for start in range(0, baseline.max_iterations, BATCH):
            size = min(BATCH, baseline.max_iterations - start)
            i2d, j3d = _draw(rng, len(lines2d), size), _draw(rng, len(lines3d), size)
            with np.errstate(all="ignore"):
                P, normals = _projections(rays1[i2d], rays2[i2d], lines3d[j3d])
            for b in range(size):
                if not np.isfinite(P[b]).all():
                    continue
                pose = _rigid_from_projection(P[b], lines3d[j3d[b]].reshape(-1, 3), normals[b])
                count = len(inliers(image, lines3d, camera, pose, config))
                if count > best_count:
                    best, best_count = pose, count
            if best_count >= stop:
                break
    return _refined(image, lines3d, camera, best, config, timer, "ransac6")


def ransac3(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    config: RegisterConfig | None = None,
    baseline: BaselineConfig | None = None,
) -> Registration:
    """Returns the Registration of the paper's section III: rotation candidates (Algorithm 1), then per
    candidate random 3-pair RANSAC on eq. "coplanar" for t (Algorithm 2); most inliers wins, refined."""
    config, baseline = config or RegisterConfig(), baseline or BaselineConfig()
    timer = StageTimer()
    lines2d = check_segments(lines2d, "lines2d", 4, 3)
    lines3d = check_segments(lines3d, "lines3d", 6, 3)
    image = image_lines(lines2d, camera, config.score)
    with timer("rotation"):
        vds = vanishing_directions(lines2d, camera, config.vanishing)
        clusters = parallel_clusters(lines3d, config.parallel)
        candidates = refine_candidates(
            rotation_candidates(vds, clusters, config.rotation), vds, clusters, lines2d, camera
        )
    if not candidates:
        return Registration(False, "ransac3: no rotation candidate", timings=timer.finish())
    rng = np.random.default_rng(baseline.seed)
    normals = np.cross(pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4]))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mid = 0.5 * (lines3d[:, 0:3] + lines3d[:, 3:6])
    direction = lines3d[:, 3:6] - lines3d[:, 0:3]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    best, best_count = np.eye(4), -1
    stop = baseline.stop_inlier_fraction * len(lines2d)
    with timer("translation"):
        for candidate in candidates:
            R = candidate.R
            # compatible pairs: the map direction lies in the image segment's interpretation plane
            i, j = np.nonzero(np.abs(normals @ (direction @ R.T).T) < np.sin(np.radians(3.0)))
            if len(i) < 3:
                continue
            for _ in range(baseline.max_iterations // len(candidates)):
                pick = rng.integers(0, len(i), 3)
                A = normals[i[pick]]  # eq. "coplanar": n . (R P + t) = 0
                if abs(np.linalg.det(A)) < 1e-3:
                    continue
                t = np.linalg.solve(A, -np.einsum("kj,kj->k", A, mid[j[pick]] @ R.T))
                pose = make_cam_from_world(R, t)
                count = len(inliers(image, lines3d, camera, pose, config))
                if count > best_count:
                    best, best_count = pose, count
                if best_count >= stop:
                    break
            if best_count >= stop:  # paper: stop at 70 % inliers
                break
    return _refined(image, lines3d, camera, best, config, timer, "ransac3")


def inliers(
    image: ImageLines, lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, config: RegisterConfig
) -> np.ndarray:
    """Returns (K, 2) ``(i2d, j3d)``: the image segments one map segment covers over more than
    ``decide.min_cover`` of their length at the pose (the paper's overlap test, the score's pair test)."""
    return score_pose(image, lines3d, camera, cam_from_world, config.score).matches(config.decide.min_cover)


def _refined(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    pose: np.ndarray,
    config: RegisterConfig,
    timer: StageTimer,
    name: str,
) -> Registration:
    """Returns the Registration of the best hypothesis after ``refine_pose``: success with enough inliers."""
    with timer("refine"):
        refined = refine_pose(image, lines3d, camera, pose, config.refine, config.score)
    matches = refined.score.matches(config.decide.min_cover)
    if len(matches) < config.min_inliers:
        reason = f"{name}: {len(matches)} inliers, fewer than {config.min_inliers}"
        return Registration(False, reason, num_inliers=len(matches), timings=timer.finish())
    return Registration(
        success=True,
        cam_from_world=refined.cam_from_world,
        matches=matches,
        num_inliers=len(matches),
        covariance=refined.covariance,
        rms_px=refined.rms_px,
        score=refined.score.value,
        explained_fraction=refined.score.explained_length / max(image.total_length, 1e-9),
        timings=timer.finish(),
    )


def _draw(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    """Returns (size, 6) int64: each row 6 distinct random indices below n."""
    return np.argpartition(rng.random((size, n)), SAMPLE_SIZE - 1, axis=1)[:, :SAMPLE_SIZE]
