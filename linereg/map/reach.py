"""Which map segments a camera somewhere in a region can see at all: the map a prior leaves to search.

A prior puts the camera centre in a box (a ball's bounding box) and may turn it to within an angle of a
rough pose. Two conservative tests follow, neither leaving out a segment that could project longer than
``min_px`` into the image from some pose the prior allows:

- **reach**: a segment of length L whose every point lies at least d from every centre of the box subtends
  at most L / d radians (each element ds subtends at most ds / d), and an angle maps to at most
  f (1 + tan^2 theta_max) pixels per radian inside the image (theta_max: the angle of the image's farthest
  corner off the axis). So it projects to at most ``f (1 + tan^2 theta_max) L / d`` pixels; d is bounded
  below by the distance between the box and the segment's own bounding box.
- **cone**: every camera with its centre in a ball of radius r about c and its axis within beta of u sees
  only inside the cone of half-angle alpha = theta_max + beta about u whose apex sits r / sin(alpha) behind
  c (the ball lies inside that cone, and a cone holds every cone of its axis and angle whose apex it holds).
  Along a segment, "angle to the axis minus alpha" is convex, so the segment meets the cone exactly when
  the concave ``(x - a) . u - cos(alpha) |x - a|`` reaches 0 at an end or at its one stationary point.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera


def pixels_per_radian(camera: Camera) -> float:
    """Returns the most pixels one radian of view can span inside the image: f (1 + tan^2 theta_max) of the
    larger focal length and the image corner farthest off the axis (theta_max) under the smaller one."""
    return max(camera.fx, camera.fy) * (1.0 + np.tan(half_angle(camera)) ** 2)


def half_angle(camera: Camera) -> float:
    """Returns theta_max (rad): the angle off the optical axis of the image corner farthest from it."""
    dx = max(camera.cx + 0.5, camera.width - 0.5 - camera.cx)
    dy = max(camera.cy + 0.5, camera.height - 0.5 - camera.cy)
    return float(np.arctan(np.hypot(dx, dy) / min(camera.fx, camera.fy)))


def projected_length_bound(
    segments: np.ndarray, lo: np.ndarray, hi: np.ndarray, camera: Camera
) -> np.ndarray:
    """Returns (M,) the most pixels each of the (M, 6) world segments can project to from any camera centre
    in the box [lo, hi] ((3,) each) with the intrinsics of ``camera`` (inf where the box touches the
    segment's bounding box)."""
    a, b = segments[:, :3], segments[:, 3:]
    gap = np.maximum(0.0, np.maximum(np.minimum(a, b) - hi, lo - np.maximum(a, b)))
    distance = np.linalg.norm(gap, axis=1)
    length = np.linalg.norm(b - a, axis=1)
    with np.errstate(divide="ignore"):
        return np.where(distance > 0, pixels_per_radian(camera) * length / distance, np.inf)


def in_cone(segments: np.ndarray, apex: np.ndarray, axis: np.ndarray, half_angle_rad: float) -> np.ndarray:
    """Returns (M,) bool: does each (M, 6) segment meet the cone of unit ``axis`` (3,) and half-angle
    ``half_angle_rad`` (< pi / 2; beyond it every segment is taken to) with its apex at (3,) ``apex``?"""
    if half_angle_rad >= 0.5 * np.pi:
        return np.ones(len(segments), dtype=bool)
    cos = np.cos(half_angle_rad)
    w, d = segments[:, :3] - apex, segments[:, 3:] - segments[:, :3]

    def inside(s: np.ndarray) -> np.ndarray:
        x = w + s[:, None] * d
        return x @ axis - cos * np.linalg.norm(x, axis=1) >= 0.0

    # stationary points of (w + s d) . u - cos |w + s d|: (d.u)^2 |w + s d|^2 = cos^2 (|d|^2 s + w.d)^2
    du, wd = d @ axis, np.einsum("ij,ij->i", w, d)
    dd, ww = np.einsum("ij,ij->i", d, d), np.einsum("ij,ij->i", w, w)
    qa = du**2 * dd - cos**2 * dd**2
    qb = 2.0 * (du**2 * wd - cos**2 * dd * wd)
    qc = du**2 * ww - cos**2 * wd**2
    hit = inside(np.zeros(len(w))) | inside(np.ones(len(w)))
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum(qb**2 - 4.0 * qa * qc, 0.0))
        for sign in (-1.0, 1.0):
            s = np.where(np.abs(qa) > 1e-300, (-qb + sign * root) / (2.0 * qa), -qc / qb)
            s = np.clip(np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
            hit |= inside(s)
    return hit


def seen_from(
    segments: np.ndarray,
    camera: Camera,
    centre: np.ndarray,
    radius_m: float,
    min_px: float,
    cam_from_world: np.ndarray | None = None,
    turn_rad: float | None = None,
) -> np.ndarray:
    """Returns (M,) bool: may each (M, 6) segment project longer than ``min_px`` into the image of a camera
    with its centre within ``radius_m`` of (3,) ``centre`` (any direction; with ``cam_from_world`` (4, 4)
    and ``turn_rad``, turned at most that far from its rotation)?"""
    lo, hi = centre - radius_m, centre + radius_m
    keep = projected_length_bound(segments, lo, hi, camera) >= min_px
    if cam_from_world is None or turn_rad is None:
        return keep
    alpha = half_angle(camera) + turn_rad
    if alpha >= 0.5 * np.pi:
        return keep
    axis = np.asarray(cam_from_world, dtype=np.float64)[2, :3]  # the optical axis in the world frame
    apex = centre - (radius_m / np.sin(alpha)) * axis
    keep[keep] = in_cone(segments[keep], apex, axis, alpha)
    return keep
