"""Camera paths for sequences: a walk round the demo building's courtyard, blank frames, drifting odometry.

The walk is a loop (an ellipse) through the free space round the site's centre at walking speed, the
camera held at eye height and turned outwards towards the facades, swaying a little. Blank frames (a
blackout: the camera faces the sky or a blank wall) are images with no lines; the path goes on under
them. Odometry is the true relative motion with a drift: a scale error of the distance, a yaw rate per
metre about the vertical and white noise, as wheel or visual odometry drifts.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..geometry import invert, make_cam_from_world, rotation_from_vector
from .building import Building
from .synthetic import look_at

EYE_HEIGHT_M = 1.6


@dataclass(frozen=True)
class WalkConfig:
    """A walk: speed, rate, length, how far it keeps from the facades, where the blackouts are."""

    speed_mps: float = 1.4  # walking
    rate_hz: float = 10.0
    duration_s: float = 32.0
    clearance_m: float = 5.0  # the loop keeps this far from the nearest facade
    outward_deg: float = 65.0  # the camera turns this far from the walking direction towards the facades
    pitch_deg: float = 8.0  # up, to see the facades' tops
    sway_deg: float = 4.0  # yaw sway of the hand-held camera (one period per 2 s)
    blackout_start_s: float = 15.0  # a blackout of this length (frames of the sky): 2 s
    blackout_s: float = 2.0
    blank_frames: tuple[int, ...] = (40, 41, 230)  # single blank frames (a blank wall, the sky)


@dataclass(frozen=True)
class OdometryDrift:
    """How simulated odometry drifts (defaults: 2 % of the distance, 0.5 deg of yaw per metre)."""

    scale_error: float = 0.02
    yaw_deg_per_m: float = 0.5
    noise_pos_fraction: float = 0.01  # white noise per step, share of the step's length
    noise_rot_deg: float = 0.05  # white rotation noise per step
    # the covariance handed to the graph: per step, this share of the distance (plus 2 mm) and degrees
    # per metre (bias and noise together)
    sigma_pos_fraction: float = 0.03
    sigma_rot_deg_per_m: float = 0.8


def courtyard_walk(building: Building, config: WalkConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K,) float64 timestamps s, (K, 4, 4) float64 cam_from_world) of a loop round the site's
    centre, ``clearance_m`` from the nearest facade, at ``speed_mps`` and ``rate_hz``."""
    cfg = config or WalkConfig()
    centre, half = _free_box(building)
    a, b = half - cfg.clearance_m
    times = np.arange(0.0, cfg.duration_s, 1.0 / cfg.rate_hz)
    # the angle along the ellipse at the arc length of each time (walking speed is constant)
    theta = np.linspace(0.0, 4.0 * np.pi, 8001)
    arc = np.r_[0.0, np.cumsum(np.hypot(np.diff(a * np.cos(theta)), np.diff(b * np.sin(theta))))]
    angle = np.interp(cfg.speed_mps * times, arc, theta)
    poses = []
    for t, phi in zip(times, angle, strict=True):
        position = np.array([centre[0] + a * np.cos(phi), centre[1] + b * np.sin(phi), EYE_HEIGHT_M])
        position[2] += 0.03 * np.sin(2.0 * np.pi * 1.8 * t)  # steps
        tangent = np.arctan2(b * np.cos(phi), -a * np.sin(phi))
        yaw = tangent - np.radians(cfg.outward_deg) + np.radians(cfg.sway_deg) * np.sin(np.pi * t)
        pitch = np.radians(cfg.pitch_deg)
        forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        poses.append(look_at(position, position + forward, np.radians(1.5) * np.sin(0.7 * t)))
    return times, np.array(poses)


def blank_frames(times: np.ndarray, config: WalkConfig | None = None) -> np.ndarray:
    """Returns (K,) bool: the frames of the blackout and the single blank frames."""
    cfg = config or WalkConfig()
    blank = (times >= cfg.blackout_start_s) & (times < cfg.blackout_start_s + cfg.blackout_s)
    blank[[k for k in cfg.blank_frames if k < len(times)]] = True
    return blank


def blank_image(camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """Returns a (H, W, 3) uint8 BGR image with no lines: a sky gradient with sensor noise."""
    v = np.linspace(0.0, 1.0, camera.height)[:, None, None]
    sky = (1.0 - v) * np.array([200.0, 130.0, 80.0]) + v * np.array([240.0, 225.0, 205.0])
    image = np.broadcast_to(sky, (camera.height, camera.width, 3)) + rng.normal(
        0.0, 2.0, (camera.height, camera.width, 3)
    )
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)


def drifting_odometry(
    cam_from_world: np.ndarray, rng: np.random.Generator, drift: OdometryDrift | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K-1, 4, 4) measured cam_k_from_cam_k+1, (K-1, 6, 6) their covariances) of (K, 4, 4) poses.

    The measured step is the true one with its length scaled by ``1 + scale_error``, turned by
    ``yaw_deg_per_m`` per metre about the world's vertical (z) and perturbed by white noise.
    """
    d = drift or OdometryDrift()
    steps, covs = [], []
    for a, b in itertools.pairwise(cam_from_world):
        true = a @ invert(b)  # cam_a_from_cam_b
        R, t = true[:3, :3], true[:3, 3]
        length = float(np.linalg.norm(t))
        up_a = a[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the world's vertical in camera a
        turn = np.radians(d.yaw_deg_per_m) * length * up_a
        turn = turn + rng.normal(0.0, np.radians(d.noise_rot_deg), 3)
        t_meas = (1.0 + d.scale_error) * t + rng.normal(0.0, d.noise_pos_fraction * length + 1e-4, 3)
        steps.append(make_cam_from_world(rotation_from_vector(turn) @ R, t_meas))
        rot = np.radians(d.sigma_rot_deg_per_m) * length + np.radians(d.noise_rot_deg)
        pos = d.sigma_pos_fraction * length + 0.002
        covs.append(np.diag([rot**2] * 3 + [pos**2] * 3))
    return np.array(steps).reshape(-1, 4, 4), np.array(covs).reshape(-1, 6, 6)


def chain(first: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Returns (K, 4, 4) cam_from_world of dead reckoning: ``first`` moved by each cam_k_from_cam_k+1."""
    poses = [first]
    for step in relative:
        poses.append(invert(step) @ poses[-1])
    return np.array(poses)


def _free_box(building: Building) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((2,) centre, (2,) half extents) of the free rectangle round the site's centre: as far as
    the nearest block along each axis (the courtyard of the demo's blocks)."""
    lo, hi = building.blocks[:, 0, :2], building.blocks[:, 1, :2]
    centre = 0.5 * (lo.min(axis=0) + hi.max(axis=0))
    half = 0.5 * (hi.max(axis=0) - lo.min(axis=0))
    for axis in (0, 1):
        other = 1 - axis
        across = (lo[:, other] < centre[other]) & (hi[:, other] > centre[other])
        ahead = lo[across, axis][lo[across, axis] > centre[axis]] - centre[axis]
        behind = centre[axis] - hi[across, axis][hi[across, axis] < centre[axis]]
        half[axis] = min(half[axis], *ahead, *behind)
    return centre, half
