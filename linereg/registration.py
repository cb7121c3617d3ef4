"""The result type of every registration, and validation of the segments that go in."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InvalidInputError


@dataclass(frozen=True)
class Registration:
    """Outcome of registering one image; ``success=False`` carries a ``reason`` and no pose.

    cam_from_world: (4, 4) float64, ``x_cam = R x_world + t`` (identity when not successful).
    matches: (K, 2) int64 ``(i2d, j3d)`` inlier correspondences.
    covariance: (6, 6) float64 from GTSAM marginals, (rotation rad, translation m) order, in the
        camera (body) frame of the ``world_T_cam`` pose GTSAM optimises; NaN when unavailable.
    runner_up_inliers: inlier count, BEFORE refinement, of the best hypothesis that differs from the winner
        (another rotation candidate or a translation clearly away from it).
    inliers_before_refinement: the winner's inlier count at that same stage (the shared inlier test at its
        unrefined pose), so that ``ambiguity`` compares like with like: refinement re-associates with a
        tighter threshold and usually keeps fewer matches than the unrefined count. 0 = unknown (then
        ``num_inliers`` is the reference).
    timings: stage name -> seconds.
    """

    success: bool
    reason: str = ""
    cam_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    num_inliers: int = 0
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    runner_up_inliers: int = 0
    rms_px: float = float("nan")
    inliers_before_refinement: int = 0
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def ambiguity(self) -> float:
        """Returns runner-up / winner inlier ratio in [0, 1]: near 1 = another pose explains the image as well.

        Both counts are taken before refinement (``inliers_before_refinement``, else ``num_inliers``); the
        winner is chosen by its refined fit, so a runner-up may count more unrefined inliers: clipped to 1.
        """
        reference = self.inliers_before_refinement or self.num_inliers
        return min(1.0, self.runner_up_inliers / reference) if reference else 1.0

    def to_dict(self) -> dict:
        """Returns a JSON-friendly dict (lists instead of arrays)."""
        return {
            "success": self.success,
            "reason": self.reason,
            "cam_from_world": self.cam_from_world.tolist(),
            "num_inliers": self.num_inliers,
            "runner_up_inliers": self.runner_up_inliers,
            "inliers_before_refinement": self.inliers_before_refinement,
            "ambiguity": self.ambiguity,
            "rms_px": None if not np.isfinite(self.rms_px) else self.rms_px,
            "covariance": [[float(x) if np.isfinite(x) else None for x in row] for row in self.covariance],
            "matches": self.matches.tolist(),
            "timings": dict(self.timings),
        }


def check_segments(array: object, name: str, width: int, min_count: int = 0) -> np.ndarray:
    """Returns ``array`` as (N, width) float64, or raises InvalidInputError naming ``name``."""
    try:
        a = np.asarray(array, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a numeric (N, {width}) array") from None
    if a.ndim != 2 or a.shape[1] != width:
        raise InvalidInputError(f"{name} must have shape (N, {width}), got {a.shape}")
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{name} contains NaN or inf (row {int(np.argwhere(~np.isfinite(a))[0, 0])})")
    if len(a) < min_count:
        raise InvalidInputError(f"{name} has {len(a)} segments; at least {min_count} are needed")
    d = width // 2
    if len(a) and (np.linalg.norm(a[:, d:] - a[:, :d], axis=1) == 0).any():
        raise InvalidInputError(f"{name} contains zero-length segments")
    return a
