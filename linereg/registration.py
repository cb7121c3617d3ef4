"""The result type of every registration, and validation of the segments that go in."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import MAX_COORDINATE, InvalidInputError, beyond_bound


@dataclass(frozen=True)
class Registration:
    """Outcome of registering one image; ``success=False`` carries a ``reason``.

    cam_from_world: (4, 4) float64, ``x_cam = R x_world + t`` (identity when nothing was found; the best
        pose found when the answer is ambiguous: then ``alternatives`` holds its rivals).
    matches: (K, 2) int64 ``(i2d, j3d)``: for each matched image segment the map segment covering most of it.
    covariance: (6, 6) float64 from GTSAM marginals, (rotation rad, translation m) order, in the camera
        (body) frame of the ``world_T_cam`` pose GTSAM optimises, plus what the map's own accuracy adds
        (``pipeline.map_floor``; nothing for a map of given segments); NaN when unavailable.
    rms_px: root mean square distance of the matched map points to their image lines.
    score: the pose's score (px): image line length the visible map explains, less what it predicts in
        empty image areas (``score.py``); explained_fraction: explained length / the image's line length.
    log10_nfa: log10 of the number of poses among those searched that would match as many image segments by
        chance (``significance.py``); an answer needs it below ``DecideConfig.max_log10_nfa`` (0); NaN when
        not computed.
    runner_up_score: the best score of a pose clearly distinct from the winner (another rotation, or a
        camera centre clearly elsewhere); 0 when none was found.
    alternatives: (A, 4, 4) float64 distinct poses found, best first (the winner not included), with
        alternative_scores (A,): what a caller with more knowledge (odometry, a prior) can choose from.
    timings: stage name -> seconds.
    """

    success: bool
    reason: str = ""
    cam_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    num_inliers: int = 0
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    rms_px: float = float("nan")
    score: float = 0.0
    explained_fraction: float = 0.0
    log10_nfa: float = float("nan")
    runner_up_score: float = 0.0
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    alternative_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def ambiguity(self) -> float:
        """Returns runner-up score / winner score in [0, 1]: near 1 = a distinct pose explains the image as
        well; 1 when nothing scored."""
        if self.score <= 0:
            return 1.0
        return float(min(1.0, max(0.0, self.runner_up_score / self.score)))

    def to_dict(self) -> dict:
        """Returns a JSON-friendly dict (lists instead of arrays, None for NaN)."""
        return {
            "success": self.success,
            "reason": self.reason,
            "cam_from_world": self.cam_from_world.tolist(),
            "num_inliers": self.num_inliers,
            "score": self.score,
            "explained_fraction": self.explained_fraction,
            "log10_nfa": None if not np.isfinite(self.log10_nfa) else self.log10_nfa,
            "runner_up_score": self.runner_up_score,
            "ambiguity": self.ambiguity,
            "rms_px": None if not np.isfinite(self.rms_px) else self.rms_px,
            "covariance": [[float(x) if np.isfinite(x) else None for x in row] for row in self.covariance],
            "matches": self.matches.tolist(),
            "alternatives": [
                {"cam_from_world": a.tolist(), "score": float(s)}
                for a, s in zip(self.alternatives, self.alternative_scores, strict=True)
            ],
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
    if (row := beyond_bound(a)) is not None:
        raise InvalidInputError(f"{name} has a coordinate beyond +-{MAX_COORDINATE:g} (row {row})")
    if len(a) < min_count:
        raise InvalidInputError(f"{name} has {len(a)} segments; at least {min_count} are needed")
    d = width // 2
    if len(a) and (np.linalg.norm(a[:, d:] - a[:, :d], axis=1) == 0).any():
        raise InvalidInputError(f"{name} contains zero-length segments")
    return a
