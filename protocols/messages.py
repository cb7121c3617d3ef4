"""The protocol's messages as frozen dataclasses (wire form: ``codec.py``; language-neutral: ``SPEC.md``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from linereg.camera import Camera
from linereg.registration import Registration

PROTOCOL_VERSION = 2  # major: a decoder rejects any other with ``unsupported_version``
IMAGE_FORMATS = ("png", "jpeg", "raw")


@dataclass(frozen=True)
class Limits:
    """Sizes a decoder accepts; anything larger is answered ``too_large`` before it is decoded further."""

    max_payload_bytes: int = 16 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096
    max_segments: int = 200_000
    max_matches: int = 200_000
    max_id_chars: int = 128
    max_deadline_ms: int = 120_000
    default_deadline_ms: int = 10_000


@dataclass(frozen=True)
class Prior:
    """What the robot already knows: a position within ``radius_m`` or a pose with sigmas (world metres),
    and/or the direction of gravity in the camera frame (an IMU).

    At most one of ``position`` ((3,) float64 world metres) and ``cam_from_world`` ((4, 4) float64) is set;
    ``gravity``: (3,) float64 unit vector (down, camera frame) within ``gravity_sigma_deg``, or None.
    """

    position: np.ndarray | None = None
    radius_m: float = math.inf
    cam_from_world: np.ndarray | None = None
    sigma_rot_deg: float = math.inf
    sigma_pos_m: float = math.inf
    gravity: np.ndarray | None = None
    gravity_sigma_deg: float = 5.0


@dataclass(frozen=True)
class LocalizeRequest:
    """Where is this image? Exactly one of ``image`` and ``segments`` is set.

    image: encoded PNG/JPEG bytes (``image_format`` "png"/"jpeg") or raw pixels ("raw"): (H, W) or (H, W, C)
        uint8/uint16 array, C in {1, 3, 4} (BGR[A] order, OpenCV's); H, W equal the camera's height, width.
    segments: (N, 4) float64 ``x1, y1, x2, y2`` pixels, detected by the robot (distorted, like the image).
    deadline_ms: time budget from arrival at the service; None = the service's default.
    """

    id: str
    camera: Camera
    image: bytes | np.ndarray | None = None
    image_format: str = ""
    segments: np.ndarray | None = None
    prior: Prior | None = None
    deadline_ms: int | None = None
    return_matches: bool = False
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class LocalizeReply:
    """The answer to a LocalizeRequest the service could process (``success`` False: not localized).

    cam_from_world: (4, 4) float64 (x_cam = R x_world + t); covariance: (6, 6) float64 (rotation rad,
    translation m) in the camera frame, NaN when unknown; matches: (K, 2) int64 (i2d, j3d) or None;
    score, runner_up_score: px (``linereg.score``); ambiguity: runner-up / winner score in [0, 1];
    log10_nfa: log10 of the chance poses that would match as well (``linereg.significance``), NaN unknown;
    alternatives: (A, 4, 4) float64 distinct poses with alternative_scores (A,); timings: stage -> seconds.
    """

    id: str
    success: bool
    reason: str = ""
    cam_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    num_inliers: int = 0
    score: float = 0.0
    explained_fraction: float = 0.0
    log10_nfa: float = math.nan
    runner_up_score: float = 0.0
    ambiguity: float = 1.0
    rms_px: float = math.nan
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    alternative_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    matches: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    map_name: str = ""
    map_version: str = ""
    map_id: str = ""  # unique id of the map's content (another build of the same place has another id)
    version: int = PROTOCOL_VERSION

    @classmethod
    def from_registration(
        cls,
        id: str,
        reg: Registration,
        map_name: str,
        map_version: str,
        return_matches: bool,
        map_id: str = "",
    ) -> LocalizeReply:
        """Returns the reply carrying ``reg`` (matches only when asked for)."""
        return cls(
            id=id,
            success=bool(reg.success),
            reason=str(reg.reason),
            cam_from_world=np.asarray(reg.cam_from_world, dtype=np.float64),
            covariance=np.asarray(reg.covariance, dtype=np.float64),
            num_inliers=int(reg.num_inliers),
            score=float(reg.score),
            explained_fraction=float(reg.explained_fraction),
            log10_nfa=float(reg.log10_nfa),
            runner_up_score=float(reg.runner_up_score),
            ambiguity=float(reg.ambiguity),
            rms_px=float(reg.rms_px),
            alternatives=np.asarray(reg.alternatives, dtype=np.float64).reshape(-1, 4, 4),
            alternative_scores=np.asarray(reg.alternative_scores, dtype=np.float64).reshape(-1),
            matches=np.asarray(reg.matches, dtype=np.int64).reshape(-1, 2) if return_matches else None,
            timings={str(k): float(v) for k, v in reg.timings.items()},
            map_name=map_name,
            map_version=map_version,
            map_id=map_id,
        )

    def to_registration(self) -> Registration:
        """Returns the Registration this reply carries (empty matches when none were sent)."""
        matches = self.matches if self.matches is not None else np.zeros((0, 2), dtype=np.int64)
        return Registration(
            success=self.success,
            reason=self.reason,
            cam_from_world=np.array(self.cam_from_world),
            matches=np.array(matches),
            num_inliers=self.num_inliers,
            covariance=np.array(self.covariance),
            rms_px=self.rms_px,
            score=self.score,
            explained_fraction=self.explained_fraction,
            log10_nfa=self.log10_nfa,
            runner_up_score=self.runner_up_score,
            alternatives=np.array(self.alternatives),
            alternative_scores=np.array(self.alternative_scores),
            timings=dict(self.timings),
        )


@dataclass(frozen=True)
class Error:
    """A request the service could not process; ``code`` is one of ``errors.ERROR_CODES``."""

    code: str
    message: str
    id: str = ""
    version: int = PROTOCOL_VERSION
