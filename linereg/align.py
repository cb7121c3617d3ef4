"""Window alignment: the rotation of a stretch of frames that odometry holds together, from their summed score.

A single frame's refinement starts from its prediction and re-associates within a few pixels of it, so it
cannot bring back a rotation error of more than ~2x ``distance_px / f`` (on the 7-Scenes kitchen's sparse map a
2 deg error came back 1.8 deg, a 4 deg one 3.8 deg: docs/measurements.md, issue 11). The score itself, summed over
several frames of a window, tells a 1-2 deg error from the truth where one frame's does not. While odometry
holds the window's frames rigid to within the score's resolution (its ``distance_px`` as an angle), turning
the whole window about the newest frame's centre moves every frame's projection alike, and the turn that
explains the most of all the frames' lines is a measurement of the window's rotation, independent of the
prediction within the searched range.

Search: coarse to fine over world-frame rotation vectors, a 5 x 5 x 5 grid over the range, then 3 x 3 x 3
around the best at half the step, down to the resolution. The turns scoring within the decision's
``margin`` of the best are the ones the score cannot tell apart: their spread (plus the grid's own
quantization, step^2 / 12) is the measurement's covariance.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from .camera import Camera
from .config import RegisterConfig
from .geometry import camera_center, invert, rotation_from_vector
from .score import ImageLines, score_pose


@dataclass(frozen=True)
class WindowAlignment:
    """The best turn of a window of frames about a centre.

    rotation: (3,) world-frame rotation vector (rad) applied about ``centre`` (3,) world (``turned_about``);
    covariance: (3, 3) of that rotation vector (world frame, rad^2); value: the window's summed score at the
    best turn, ``at_zero`` at no turn; evaluations: turns scored.
    """

    rotation: np.ndarray
    centre: np.ndarray
    covariance: np.ndarray
    value: float
    at_zero: float
    evaluations: int


def turned_about(cam_from_world: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Returns the (4, 4) cam_from_world of a camera whose world is turned by a (3,) rotation vector about
    a (3,) world point: ``world_from_cam' = M world_from_cam`` with ``M x = R (x - centre) + centre``."""
    R = rotation_from_vector(rotation)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, centre - R @ centre
    return cam_from_world @ invert(M)


def align_window(
    images: Sequence[ImageLines],
    poses: Sequence[np.ndarray],
    lines3d: np.ndarray,
    camera: Camera,
    half_range_rad: float,
    resolution_rad: float,
    config: RegisterConfig,
    visible: np.ndarray | None = None,
) -> WindowAlignment | None:
    """Returns the turn of the window (images with their (4, 4) cam_from_world ``poses``, the newest last)
    about the newest centre that explains the most of their lines, within ``half_range_rad`` on each axis,
    to ``resolution_rad``; None when no turn explains anything (a window of blank frames).

    lines3d: (M, 6) world map segments; visible: (M,) bool of the segments taking part (None: all).
    """
    centre = camera_center(poses[-1])

    def value(w: np.ndarray) -> float:
        return sum(
            float(score_pose(im, lines3d, camera, turned_about(T, w, centre), config.score, visible).value)
            for im, T in zip(images, poses, strict=True)
        )

    scored: dict[tuple[float, ...], float] = {}
    best, step, reach = np.zeros(3), half_range_rad / 2, 2
    while True:
        for offset in itertools.product(range(-reach, reach + 1), repeat=3):
            w = best + step * np.array(offset)
            key = tuple(np.round(w, 12))
            if key not in scored:
                scored[key] = value(w)
        best = np.array(max(scored, key=lambda k: scored[k]))
        if step <= resolution_rad:
            break
        step, reach = step / 2, 1
    turns, values = np.array(list(scored)), np.array(list(scored.values()))
    top = float(values.max())
    if top <= 0.0:
        return None
    alike = turns[values >= (1.0 - config.decide.margin) * top] - best
    covariance = alike.T @ alike / len(alike) + np.eye(3) * step**2 / 12.0
    zero = scored[(0.0, 0.0, 0.0)]  # the first grid's centre
    return WindowAlignment(best, centre, covariance, top, zero, len(scored))


def rotation_prior(key: int, cam_from_world: np.ndarray, alignment: WindowAlignment) -> gtsam.NonlinearFactor:
    """Returns the factor of a window alignment on the newest frame's pose (gtsam key): its rotation
    measured (turned by the alignment), its position left free.

    ``PoseRotationPrior3D`` measures gtsam's ``world_R_cam`` with a right (camera-frame) perturbation:
    ``Exp(w) R = R Exp(R^T w)``, so the world-frame covariance C becomes ``R^T C R``."""
    turned = invert(turned_about(cam_from_world, alignment.rotation, alignment.centre))
    R = turned[:3, :3]  # world_R_cam
    noise = gtsam.noiseModel.Gaussian.Covariance(R.T @ alignment.covariance @ R)
    return gtsam.PoseRotationPrior3D(key, gtsam.Rot3(R), noise)
