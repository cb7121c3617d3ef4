"""Pieces of multi-frame GTSAM graphs (sequence smoothing, live tracking): one ``Pose3`` per frame.

A frame's image lines enter as ONE line-projection factor (``line_factor``, the refinement's vectorised
``CustomFactor``) on the matched fragments of the map lines (``refine.fragments``); odometry enters as
``BetweenFactorPose3``. GTSAM's ``Pose3`` is ``world_T_cam`` (= ``world_from_cam``), so the measured
``cam_k_from_cam_k+1`` is exactly gtsam's ``between(X_k, X_k+1) = X_k^-1 X_k+1``; its covariance is on
gtsam's tangent of that relative pose, (rotation rad, translation m) in the frame of camera k+1.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import gtsam
import numpy as np

from .camera import Camera
from .config import LineDetectConfig, RegisterConfig
from .errors import InvalidInputError
from .geometry import invert, line_coefficients
from .line_factor import LineProjection, line_factor
from .lines2d import detect
from .refine import fragments, residual_variance, robust_noise
from .registration import check_segments
from .score import ImageLines, score_pose


def frame_key(k: int) -> int:
    """Returns the gtsam key of frame k's pose."""
    return int(gtsam.symbol("x", k))


def lines_key(k: int) -> int:
    """Returns the gtsam key of the pose frame k's lines give against the map (``sequence.smooth``: the
    frame's pose up to the map's own error)."""
    return int(gtsam.symbol("l", k))


def to_pose3(cam_from_world: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(invert(cam_from_world))  # gtsam Pose3 is world_T_cam


def from_pose3(pose: gtsam.Pose3) -> np.ndarray:
    return invert(pose.matrix())


def predict(cam_from_world: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Returns the (4, 4) cam_k+1_from_world of frame k's pose moved by ``relative`` = cam_k_from_cam_k+1."""
    return invert(relative) @ cam_from_world


def relative_pose(cam_a_from_world: np.ndarray, cam_b_from_world: np.ndarray) -> np.ndarray:
    """Returns the (4, 4) cam_a_from_cam_b between two poses (what odometry measures from a to b)."""
    return cam_a_from_world @ invert(cam_b_from_world)


def check_covariance(value: object, name: str) -> np.ndarray:
    """Returns ``value`` as a (6, 6) symmetric positive definite float64 matrix, or raises naming it."""
    try:
        C = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a numeric (6, 6) matrix") from None
    if C.shape != (6, 6) or not np.isfinite(C).all():
        raise InvalidInputError(f"{name} must be a finite (6, 6) matrix, got shape {C.shape}")
    if not np.allclose(C, C.T, atol=1e-12 + 1e-9 * np.abs(C).max()) or np.linalg.eigvalsh(C)[0] <= 0:
        raise InvalidInputError(f"{name} must be symmetric positive definite")
    return C


def frame_lines(frame: object, camera: Camera, detect_config: LineDetectConfig | None = None) -> np.ndarray:
    """Returns (N, 4) float64 undistorted pixel segments of a frame: an image (H, W[, C]) of the camera's
    size, detected here, or (N, 4) segments in the camera's (distorted) pixels."""
    if isinstance(frame, np.ndarray) and frame.ndim == 2 and frame.shape[1] == 4 and frame.dtype.kind == "f":
        segments = check_segments(frame, "segments", 4)
        if camera.has_distortion and len(segments):
            segments = camera.undistort_points(segments.reshape(-1, 2)).reshape(-1, 4)
        return segments
    if not isinstance(frame, np.ndarray):
        frame = check_segments(frame, "segments", 4)
        return frame_lines(frame, camera, detect_config)
    return detect(frame, camera, detect_config)


def odometry_factor(k: int, relative: np.ndarray, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """Returns the factor of a measured cam_k_from_cam_k+1 (4, 4) with its (6, 6) tangent covariance."""
    noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
    return gtsam.BetweenFactorPose3(frame_key(k), frame_key(k + 1), gtsam.Pose3(relative), noise)


def step_covariance(
    relative: np.ndarray, sigma_rot_deg: float, sigma_pos_fraction: float, floor_m: float
) -> np.ndarray:
    """Returns a (6, 6) diagonal covariance of one odometry step: rotation ``sigma_rot_deg`` per metre
    moved (at least a tenth of it), translation ``sigma_pos_fraction`` of the distance plus ``floor_m``."""
    distance = float(np.linalg.norm(relative[:3, 3]))
    rot = np.radians(sigma_rot_deg) * max(distance, 0.1)
    pos = sigma_pos_fraction * distance + floor_m
    return np.diag([rot**2] * 3 + [pos**2] * 3)


@dataclass(frozen=True)
class LineFit:
    """A frame's line factor at one pose: the (P, 2) ``(i2d, j3d)`` pairs it fits and the factor."""

    pairs: np.ndarray
    projection: LineProjection
    factor: gtsam.CustomFactor

    def residuals(self, cam_from_world: np.ndarray) -> np.ndarray:
        """Returns (2P,) signed point-to-line distances px at ``cam_from_world``."""
        world_from_cam = invert(cam_from_world)
        points = self.projection.points_cam(world_from_cam[:3, :3], world_from_cam[:3, 3])
        return self.projection.evaluate(points, jacobian=False)[0]


def line_fit(
    key: int,
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    tolerance_px: float,
    sigma_px: float,
    config: RegisterConfig,
    visible: np.ndarray | None = None,
) -> LineFit | None:
    """Returns the line factor of a frame's fragments covered within ``tolerance_px`` at a pose, with noise
    ``sigma_px`` and the refinement's robust kernel (its ``kernel_px`` stays in pixels); None when fewer than
    ``refine.min_matches`` fragments are covered."""
    score = score_pose(
        image, lines3d, camera, cam_from_world, replace(config.score, distance_px=tolerance_px), visible
    )
    pairs, points = fragments(image, lines3d, camera, cam_from_world, score, config.refine)
    if len(pairs) < config.refine.min_matches:
        return None
    coeffs = line_coefficients(image.segments[pairs[:, 0]])
    projection = LineProjection.build(coeffs, points, camera, config.refine.min_depth_m)
    noise = robust_noise(2 * len(pairs), sigma_px, config.refine)
    return LineFit(pairs, projection, line_factor(key, projection, noise))


def noise_px(residuals: np.ndarray, config: RegisterConfig, floor_px: float) -> float:
    """Returns the px noise of a frame's line residuals (2P,): Huber's variance, at least ``floor_px``."""
    return max(float(np.sqrt(residual_variance(residuals, config.refine, 6))), floor_px)


def next_tolerance(residuals: np.ndarray, config: RegisterConfig) -> float:
    """Returns the covering tolerance px of the next association round: ``outlier_sigmas`` robust sigmas
    (MAD) of the residuals, within ``[min_outlier_px, score.distance_px]``."""
    sigma = 1.4826 * float(np.median(np.abs(residuals))) if len(residuals) else np.inf
    rc = config.refine
    return float(np.clip(rc.outlier_sigmas * sigma, rc.min_outlier_px, config.score.distance_px))


def fuse(
    predicted: np.ndarray, predicted_cov: np.ndarray, fixed: np.ndarray, fix_cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns the (4, 4) cam_from_world and (6, 6) covariance of two independent estimates of one pose
    combined (a Kalman update in gtsam's right-perturbation tangent of ``predicted``): what the tracker's
    graph makes of an odometry prediction and a fix. Non-finite covariances count as zero."""
    P, R = _finite(predicted_cov), _finite(fix_cov)
    gain = P @ np.linalg.pinv(P + R)
    xi = gtsam.Pose3.Logmap(to_pose3(predicted).between(to_pose3(fixed)))
    pose = to_pose3(predicted).compose(gtsam.Pose3.Expmap(gain @ xi))
    covariance = (np.eye(6) - gain) @ P
    return from_pose3(pose), 0.5 * (covariance + covariance.T)


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """Returns the chi-square quantile (scipy; remembered: the tracker asks for the same few every step)."""
    from scipy.stats import chi2

    return float(chi2.ppf(probability, dof))


def carry(covariance: np.ndarray | None, step: np.ndarray, step_cov: np.ndarray) -> np.ndarray:
    """Returns the (6, 6) covariance of a pose moved by ``step`` (cam_prev_from_cam_this) from a pose of
    ``covariance`` (gtsam's right perturbation, camera frame, rotation first), plus the step's ``step_cov``.
    A non-finite or missing covariance counts as zero (an unknown pose: what is known is used)."""
    ad = gtsam.Pose3(step).inverse().AdjointMap()
    return ad @ _finite(covariance) @ ad.T + step_cov


def _finite(c: np.ndarray | None) -> np.ndarray:
    return c if c is not None and c.shape == (6, 6) and np.isfinite(c).all() else np.zeros((6, 6))


def innovation_distance(
    predicted: np.ndarray,
    fixed: np.ndarray,
    previous_covariance: np.ndarray,
    step: np.ndarray,
    step_cov: np.ndarray,
    fix_covariance: np.ndarray,
) -> float:
    """Returns the squared Mahalanobis distance of a fix (4, 4 cam_from_world) from its prediction.

    The prediction is the previous pose moved by ``step`` (cam_prev_from_cam_this); its (6, 6) covariance is
    the previous pose's marginal carried through the step (gtsam's right-perturbation convention, in the
    camera frame, rotation first) plus ``step_cov``; the fix's own covariance is added (independent
    measurements). Non-finite covariances count as zero (an unknown previous pose or fix: the gate uses
    what is known)."""
    covariance = carry(previous_covariance, step, step_cov) + _finite(fix_covariance)
    xi = gtsam.Pose3.Logmap(to_pose3(predicted).between(to_pose3(fixed)))
    return float(xi @ np.linalg.solve(covariance, xi))
