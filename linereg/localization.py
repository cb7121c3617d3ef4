"""``localize``: pixels and a line map in, a Registration out (2D lines, visibility culling, register)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .config import LineDetectConfig, RegisterConfig
from .directions import subset_clusters
from .errors import InvalidInputError
from .geometry import camera_center, segment_lengths
from .lines2d import detect
from .map.linemap import LineMap
from .pipeline import register_undistorted
from .registration import Registration, check_segments
from .timing import StageTimer


@dataclass(frozen=True)
class Prior:
    """What is known of the pose beforehand: a position within ``radius_m``, or a whole pose with sigmas.

    position: (3,) world metres; cam_from_world: (4, 4). With a pose, the position is its camera centre and
    the radius ``3 * sigma_pos_m``; only map segments near the position are searched.
    """

    position: np.ndarray | None = None
    radius_m: float | None = None
    cam_from_world: np.ndarray | None = None
    sigma_rot_deg: float | None = None
    sigma_pos_m: float | None = None

    def __post_init__(self) -> None:
        if self.cam_from_world is not None:
            T = np.asarray(self.cam_from_world, dtype=np.float64)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise InvalidInputError("prior cam_from_world must be a finite (4, 4) matrix")
            object.__setattr__(self, "cam_from_world", T)
            if self.position is None:
                object.__setattr__(self, "position", camera_center(T))
            if self.radius_m is None and self.sigma_pos_m is not None:
                object.__setattr__(self, "radius_m", 3.0 * float(self.sigma_pos_m))
        if self.position is not None:
            p = np.asarray(self.position, dtype=np.float64).reshape(-1)
            if p.shape != (3,) or not np.isfinite(p).all():
                raise InvalidInputError("prior position must be 3 finite numbers")
            object.__setattr__(self, "position", p)
        if self.radius_m is not None and not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise InvalidInputError(f"prior radius_m must be positive, got {self.radius_m}")


def localize(
    image: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None = None,
    prior: Prior | None = None,
    detect_config: LineDetectConfig | None = None,
) -> Registration:
    """Returns the Registration of an image (H, W[, C], uint8/uint16/float) in a line map.

    Matches index ``line_map.segments``; timings include ``lines2d`` (detection).
    """
    timer = StageTimer()
    with timer("lines2d"):
        lines2d = detect(image, camera, detect_config)  # undistorted pixels
    return _localize_undistorted(lines2d, line_map, camera.undistorted(), config, prior, timer)


def localize_segments(
    lines2d: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None = None,
    prior: Prior | None = None,
) -> Registration:
    """Returns the Registration of precomputed (N, 4) 2D segments (distorted pixels if camera.dist) in a map."""
    lines2d = check_segments(lines2d, "lines2d", 4)
    if camera.has_distortion:
        lines2d = camera.undistort_points(lines2d.reshape(-1, 2)).reshape(-1, 4)
    return _localize_undistorted(lines2d, line_map, camera.undistorted(), config, prior, StageTimer())


def _localize_undistorted(
    lines2d: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    config: RegisterConfig | None,
    prior: Prior | None,
    timer: StageTimer,
) -> Registration:
    config = config or RegisterConfig()
    if len(lines2d) < config.min_lines2d:
        reason = f"only {len(lines2d)} line segments in the image; at least {config.min_lines2d} are needed"
        return Registration(success=False, reason=reason, timings=timer.finish())
    with timer("culling"):
        position = None if prior is None else prior.position
        radius = None if prior is None else prior.radius_m
        visible = line_map.visible(camera, None, prior_position=position, radius_m=radius)
        lines3d = line_map.segments[visible]
        clusters = subset_clusters(line_map.clusters, visible, segment_lengths(lines3d))
    if len(lines3d) < config.min_lines3d:
        reason = f"only {len(lines3d)} map segments near the prior; at least {config.min_lines3d} are needed"
        return Registration(success=False, reason=reason, timings=timer.finish())
    result = register_undistorted(lines2d, lines3d, clusters, camera, config, timer)
    matches = np.c_[result.matches[:, 0], visible[result.matches[:, 1]]].astype(np.int64)
    return dataclasses.replace(result, matches=matches)
