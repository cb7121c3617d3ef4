"""Pose refinement (paper section III-D): GTSAM Levenberg-Marquardt on endpoint-to-line distances,
then reject outliers and re-associate at the refined pose, until the match set is stable.

One ``CustomFactor`` (``line_factor``) holds every correspondence of the image; a robust kernel with gtsam's
``Scalar`` reweight scheme weights each endpoint residual on its own (``Block`` would weight the whole
image by the norm of all its residuals at once). The noise model has sigma = 1 px, so ``kernel_px`` is in
pixels; the covariance is rescaled by the a-posteriori residual variance. The outlier threshold tightens
from ``outlier_px`` to 3 robust sigmas of the residuals as the pose converges.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numpy as np

from .camera import Camera
from .config import MatchConfig, RefineConfig
from .errors import InvalidInputError
from .geometry import invert, line_coefficients, segment_directions
from .line_factor import LineProjection, line_factor
from .matching import match_segments

log = logging.getLogger(__name__)

POSE_KEY = 0
_KERNELS: dict[str, Any] = {
    "huber": gtsam.noiseModel.mEstimator.Huber.Create,
    "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create,
    "tukey": gtsam.noiseModel.mEstimator.Tukey.Create,
}


@dataclass(frozen=True)
class Refinement:
    """A refined pose and the correspondences it explains.

    cam_from_world: (4, 4) float64, ``x_cam = R x_world + t``.
    matches: (K, 2) int64 ``(i2d, j3d)``, each within the last outlier threshold (<= ``outlier_px``) at
        the refined pose; the input matches when the refinement was degenerate.
    covariance: (6, 6) float64 of gtsam's tangent ``xi = (omega rad, v m)`` of ``world_T_cam * Exp(xi)``,
        i.e. rotation and translation perturbations in the CAMERA (body) frame, (rotation, translation)
        order, scaled by the residuals' own variance (so it reflects the actual pixel noise); NaN when
        the refinement was degenerate.
    rms_px: root mean square endpoint-to-line distance of ``matches`` at the refined pose.
    rounds: optimise -> reject -> re-associate rounds run.
    """

    cam_from_world: np.ndarray
    matches: np.ndarray
    covariance: np.ndarray
    rms_px: float
    rounds: int


def refine_pose(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    matches: np.ndarray,
    config: RefineConfig,
    match: MatchConfig,
) -> Refinement:
    """Returns the Refinement of an initial pose by line reprojection (eq. "costs"), outliers removed.

    lines2d: (N, 4) undistorted pixels; lines3d: (M, 6) world; cam_from_world: (4, 4) initial pose;
    matches: (K, 2) int64 ``(i2d, j3d)`` initial correspondences. Degenerate input (fewer than
    ``config.min_matches`` matches, all 3D lines parallel, singular system) returns the input pose with
    NaN covariance, never raises (an unknown ``config.kernel`` raises InvalidInputError).
    """
    if config.kernel not in (*_KERNELS, "none"):
        raise InvalidInputError(
            f"refine.kernel must be one of {', '.join(_KERNELS)}, none; got {config.kernel!r}"
        )
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    coeffs = line_coefficients(lines2d)  # (N, 3): once, every round indexes it
    current, pose, rounds, problem = matches, cam_from_world, 0, None
    while rounds < config.max_rounds:
        problem, current = _problem(coeffs, lines3d, camera, current, pose, config)
        if problem is None:
            return _unrefined(coeffs, lines3d, camera, cam_from_world, matches, config, rounds)
        rounds += 1
        try:
            pose = _optimise(problem, pose, config)
        except RuntimeError as e:  # gtsam: indeterminant linear system
            log.debug("refinement failed: %s", e)
            return _unrefined(coeffs, lines3d, camera, cam_from_world, matches, config, rounds)
        # paper: reject the matches the refined pose does not explain, re-associate at that pose, repeat
        threshold_px = _threshold_px(problem, pose, config)
        if config.reassociate:
            rematch = replace(match, distance_px=min(match.distance_px, threshold_px))
            new = match_segments(lines2d, lines3d, camera, pose, rematch)
        else:
            new = current[_worst_px(problem, pose) <= threshold_px]
        log.debug("round %d: %d -> %d matches within %.2f px", rounds, len(current), len(new), threshold_px)
        if _same(new, current):
            break
        current, problem = new, None
    if problem is None:  # the last round changed the set: report the new set at the last pose
        problem, current = _problem(coeffs, lines3d, camera, current, pose, config)
        if problem is None:
            return _unrefined(coeffs, lines3d, camera, cam_from_world, matches, config, rounds)
    covariance = _covariance(problem, pose, config)
    if not np.isfinite(covariance).all():
        return _unrefined(coeffs, lines3d, camera, cam_from_world, matches, config, rounds)
    return Refinement(pose, current, covariance, _rms_px(problem, pose), rounds)


@dataclass(frozen=True)
class _Problem:
    """One match set ready to optimise: its factor graph (one factor) and the factor's precomputation."""

    graph: gtsam.NonlinearFactorGraph
    projection: LineProjection


def _problem(
    coeffs: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    matches: np.ndarray,
    cam_from_world: np.ndarray,
    config: RefineConfig,
) -> tuple[_Problem | None, np.ndarray]:
    """Returns (factor graph of eq. "costs", or None if degenerate; (K', 2) matches it holds).

    coeffs: (N, 3) lines of all 2D segments. Matched 3D segments are cut to their part in front of the
    camera at ``cam_from_world``; segments wholly behind it are dropped.
    """
    segments, front = _front_part(lines3d[matches[:, 1]], cam_from_world, config)
    matches, segments = matches[front], segments[front]
    if _degenerate(segments, config):
        return None, matches
    projection = LineProjection.build(coeffs[matches[:, 0]], segments, camera, config.min_depth_m)
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(2 * len(matches), 1.0)  # kernel_px is px
    if config.kernel != "none":
        # Scalar: each endpoint residual gets its own weight (and loss); Block would weight the whole image
        kernel = _KERNELS[config.kernel](
            config.kernel_px, gtsam.noiseModel.mEstimator.Base.ReweightScheme.Scalar
        )
        noise = gtsam.noiseModel.Robust.Create(kernel, noise)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(line_factor(POSE_KEY, projection, noise))
    return _Problem(graph, projection), matches


def _front_part(
    segments: np.ndarray, cam_from_world: np.ndarray, config: RefineConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 6) segments cut at the near plane, (K,) bool some part in front of it).

    The cost only needs two points of each 3D line (eq. "costs" is collinearity), so an endpoint behind
    the camera is replaced by the segment's crossing of a near plane at ``near_fraction`` of the mean
    depth: near-zero depths would give huge Jacobians that drag the pose even under a robust kernel.
    """
    a, b = segments[:, 0:3], segments[:, 3:6]
    za = a @ cam_from_world[2, :3] + cam_from_world[2, 3]
    zb = b @ cam_from_world[2, :3] + cam_from_world[2, 3]
    depth = 0.5 * float(za.mean() + zb.mean()) if len(segments) else 0.0
    near = max(config.min_depth_m, config.near_fraction * depth)
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = a + ((near - za) / (zb - za))[:, None] * (b - a)
    a = np.where((za < near)[:, None], crossing, a)
    b = np.where((zb < near)[:, None], crossing, b)
    return np.c_[a, b], (za >= near) | (zb >= near)


def _values(cam_from_world: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(POSE_KEY, gtsam.Pose3(invert(cam_from_world)))  # gtsam Pose3 is world_T_cam
    return values


def _optimise(problem: _Problem, cam_from_world: np.ndarray, config: RefineConfig) -> np.ndarray:
    """Returns the (4, 4) cam_from_world minimising the robust cost, by Levenberg-Marquardt."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    optimizer = gtsam.LevenbergMarquardtOptimizer(problem.graph, _values(cam_from_world), params)
    result = optimizer.optimize().atPose3(POSE_KEY).matrix()
    if not np.isfinite(result).all():
        raise RuntimeError("non-finite pose")
    return invert(result)


def _residuals(problem: _Problem, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (K, 2) endpoint-to-line distances px of every match at ``cam_from_world``."""
    world_from_cam = invert(cam_from_world)
    points = problem.projection.points_cam(world_from_cam[:3, :3], world_from_cam[:3, 3])
    return problem.projection.evaluate(points, jacobian=False)[0].reshape(-1, 2)


def _worst_px(problem: _Problem, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (K,) the larger endpoint distance of each match, px."""
    return np.abs(_residuals(problem, cam_from_world)).max(axis=1)


def _threshold_px(problem: _Problem, cam_from_world: np.ndarray, config: RefineConfig) -> float:
    """Returns the outlier distance px: ``outlier_sigmas`` robust sigmas of the residuals, clipped to
    ``[min_outlier_px, outlier_px]``, so the test tightens as the pose converges on clean data."""
    if config.outlier_sigmas <= 0:
        return config.outlier_px
    sigma = 1.4826 * float(
        np.median(np.abs(_residuals(problem, cam_from_world)))
    )  # MAD of zero-mean residuals
    return float(np.clip(config.outlier_sigmas * sigma, config.min_outlier_px, config.outlier_px))


def _rms_px(problem: _Problem, cam_from_world: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(_residuals(problem, cam_from_world)))))


def _covariance(problem: _Problem, cam_from_world: np.ndarray, config: RefineConfig) -> np.ndarray:
    """Returns (6, 6) pose covariance (body frame, rotation first) in px-noise units, NaN if singular.

    ``Marginals`` gives ``(J^T W J)^-1`` for sigma = 1 px with the kernel's weights W at the optimum. It is
    scaled by Huber's M-estimator variance ``sum(psi^2) / (2K - 6) / mean(psi')^2`` (Huber 1981, eq. 7.10),
    which is calibrated on synthetic scenes; plain ``sum(w r^2) / (2K - 6)`` is overconfident by ~1.4x.
    """
    try:
        marginal = gtsam.Marginals(problem.graph, _values(cam_from_world)).marginalCovariance(POSE_KEY)
    except RuntimeError as e:  # indeterminant system: the matches do not fix all 6 DoF
        log.debug("marginals failed: %s", e)
        return np.full((6, 6), np.nan)
    psi, dpsi = _influence(_residuals(problem, cam_from_world).ravel(), config)
    dof = max(len(psi) - 6, 1)
    return marginal * (float(psi @ psi) / dof / max(float(dpsi.mean()), 0.1) ** 2)


def _influence(r: np.ndarray, config: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (psi(r), psi'(r)) of the configured kernel (gtsam's definitions) for residuals r px."""
    k = config.kernel_px
    if config.kernel == "huber":
        return np.clip(r, -k, k), (np.abs(r) <= k).astype(np.float64)
    if config.kernel == "cauchy":  # w = k^2 / (k^2 + r^2)
        d = k * k + r * r
        return r * k * k / d, k * k * (k * k - r * r) / (d * d)
    if config.kernel == "tukey":  # w = (1 - (r/k)^2)^2 inside |r| <= k, else 0
        u = np.where(np.abs(r) <= k, (r / k) ** 2, 1.0)
        return r * (1.0 - u) ** 2, (1.0 - u) * (1.0 - 5.0 * u)
    return r, np.ones_like(r)


def _degenerate(segments3d: np.ndarray, config: RefineConfig) -> bool:
    """Returns True when (K, 6) matched 3D segments cannot fix a pose: too few, or all parallel."""
    if len(segments3d) < config.min_matches:
        return True
    d = segment_directions(segments3d)
    eig = np.linalg.eigvalsh(d.T @ d)  # squared singular values, ascending; 3x3 is cheaper than an SVD
    return bool(eig[1] < np.sin(np.radians(config.parallel_angle_deg)) ** 2 * eig[2])


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Returns True if two (K, 2) match sets hold the same rows, in any order."""
    if a.shape != b.shape:
        return False
    return bool(np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])]))


def _unrefined(
    coeffs: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    matches: np.ndarray,
    config: RefineConfig,
    rounds: int,
) -> Refinement:
    """Returns the input pose with NaN covariance: the degenerate outcome."""
    log.debug("degenerate refinement with %d matches: keeping the input pose", len(matches))
    rms = float("nan")
    if len(matches):
        projection = LineProjection.build(
            coeffs[matches[:, 0]], lines3d[matches[:, 1]], camera, config.min_depth_m
        )
        rms = _rms_px(_Problem(gtsam.NonlinearFactorGraph(), projection), cam_from_world)
    return Refinement(cam_from_world.copy(), matches, np.full((6, 6), np.nan), rms, rounds)
