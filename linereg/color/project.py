"""World points into a photo: pixel coordinates (with the lens distortion of the camera) and depth.

Convention (``linereg.camera``): camera frame x right, y down, z forward; pixel (0, 0) is the centre of the
top-left pixel, so a pixel's area is ``[u - 0.5, u + 0.5) x [v - 0.5, v + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..geometry import camera_center
from . import kernels
from .config import VisibilityConfig
from .depth import depth_slope, diameter_px


@dataclass(frozen=True)
class Projection:
    """The points of a chunk a photo may see: in front of it and inside its image.

    index: (n,) int64 rows of the chunk; u, v: (n,) float32 pixels as in the photo (distorted);
    z: (n,) float32 depth along the optical axis, m.
    """

    index: np.ndarray
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray


def project(
    points: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    near_m: float,
    rows: np.ndarray | None = None,
    margin_px: float = 0.0,
) -> Projection:
    """Returns the Projection of (P, 3) float64 world points into the photo of ``camera`` at
    ``cam_from_world`` (4, 4): the points with depth > ``near_m`` whose pixel lies in the image, or at
    most ``margin_px`` outside it (what a splat reaches into the image from).

    rows: (n,) int64 the only rows to consider (``cull.rows_in_view``), default all; ``index`` counts
    rows of ``points`` either way.
    """
    if rows is None:
        rows = np.arange(len(points))
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    p = points[rows]
    # column by column, not ``p @ R.T``: BLAS threads of several pool workers would fight over the cores
    z = p[:, 0] * R[2, 0] + p[:, 1] * R[2, 1] + p[:, 2] * R[2, 2] + t[2]  # float64: UTM-sized coordinates
    front = np.flatnonzero(z > near_m)
    p, z, rows = p[front], z[front], rows[front]
    x = (p[:, 0] * R[0, 0] + p[:, 1] * R[0, 1] + p[:, 2] * R[0, 2] + t[0]) / z
    y = (p[:, 0] * R[1, 0] + p[:, 1] * R[1, 1] + p[:, 2] * R[1, 2] + t[1]) / z
    if camera.has_distortion:
        # a distortion polynomial folds back far outside the image: keep the undistorted field of view first
        lo, hi = field_of_view(camera, margin_px)
        keep = np.flatnonzero((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]))
        rows, x, y, z = rows[keep], x[keep], y[keep], z[keep]
        x, y = _distort(x, y, camera.dist)
    u = (camera.fx * x + camera.cx).astype(np.float32)
    v = (camera.fy * y + camera.cy).astype(np.float32)
    m = margin_px
    inside = np.flatnonzero(
        (u >= -0.5 - m) & (u < camera.width - 0.5 + m) & (v >= -0.5 - m) & (v < camera.height - 0.5 + m)
    )
    return Projection(rows[inside], u[inside], v[inside], z[inside].astype(np.float32))


@dataclass(frozen=True)
class ViewPoints(Projection):
    """A Projection with what the depth buffer and the depth test need of each point, all (n,) float32:
    ``diameter`` px (``depth.diameter_px``), ``slope`` (n, 2) (``depth.depth_slope``), ``distance`` m from
    the camera centre, ``cos`` |cos| of the angle between the viewing ray and the normal (1: unknown normal).
    """

    diameter: np.ndarray
    slope: np.ndarray
    distance: np.ndarray
    cos: np.ndarray


def view_points(
    points: np.ndarray,
    normals: np.ndarray,
    spacing: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    config: VisibilityConfig,
    rows: np.ndarray | None = None,
    margin_px: float = 0.0,
    compiled: bool = True,
) -> ViewPoints:
    """Returns the ViewPoints of (P, 3) float64 world points with their (P, 3) float32 normals (NaN:
    unknown) and (P,) float32 spacing m, as ``project`` selects them.

    A pinhole camera takes one compiled pass over the points (``kernels.view_geometry``); a camera with
    distortion, or ``compiled=False``, the numpy functions it does the same as.
    """
    if rows is None:
        rows = np.arange(len(points))
    centre = camera_center(cam_from_world)
    if compiled and not camera.has_distortion:
        m = margin_px
        bounds = np.array([-0.5 - m, camera.width - 0.5 + m, -0.5 - m, camera.height - 0.5 + m])
        intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64)
        focal = config.splat_scale * max(camera.fx, camera.fy)
        pose = np.ascontiguousarray(cam_from_world, dtype=np.float64)
        return ViewPoints(
            *kernels.view_geometry(
                points, np.asarray(rows, np.int64), normals, spacing, pose, centre, intrinsics, bounds,
                config.near_m, config.max_slope, focal,
            )
        )  # fmt: skip
    pr = project(points, camera, cam_from_world, config.near_m, rows, margin_px)
    # einsum, not ``@``: BLAS threads of several pool workers would fight over the cores
    normals_cam = np.einsum("nk,jk->nj", normals[pr.index], cam_from_world[:3, :3].astype(np.float32))
    slope = depth_slope(normals_cam, pr.u, pr.v, pr.z, camera, config.max_slope)
    to_eye = centre - points[pr.index]
    distance = np.sqrt(np.einsum("nk,nk->n", to_eye, to_eye)).astype(np.float32)
    cos = np.abs(np.einsum("nk,nk->n", normals[pr.index], to_eye)).astype(np.float32) / distance
    cos = np.nan_to_num(cos, nan=1.0)  # unknown normal (an isolated point): taken as facing the photo
    diameter = diameter_px(spacing[pr.index], pr.z, camera, config)
    return ViewPoints(pr.index, pr.u, pr.v, pr.z, diameter, slope, distance, cos)


def field_of_view(camera: Camera, margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((2,), (2,)) the box of normalised coordinates (x / z, y / z) the image can show, widened
    by ``margin_px`` on every side.

    Pinhole: the image border exactly; with distortion, the border undistorted, 5 % wider.
    """
    m = margin_px
    if not camera.has_distortion:
        lo = np.array([(-0.5 - m - camera.cx) / camera.fx, (-0.5 - m - camera.cy) / camera.fy])
        hi = np.array(
            [
                (camera.width - 0.5 + m - camera.cx) / camera.fx,
                (camera.height - 0.5 + m - camera.cy) / camera.fy,
            ]
        )
        return lo, hi
    lo, hi = _undistorted_bounds(camera)
    widen = m / np.array([camera.fx, camera.fy])
    return lo - widen, hi + widen


def _distort(x: np.ndarray, y: np.ndarray, dist: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Returns normalised coordinates through OpenCV's distortion (k1, k2, p1, p2[, k3[, k4, k5, k6]])."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (*dist, 0.0, 0.0, 0.0, 0.0)[:8]
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy = x * y
    return (
        x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy,
    )


def _undistorted_bounds(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((2,), (2,)) the normalised (x, y) box of the image border undistorted, 5 % wider."""
    w, h = camera.width, camera.height
    t = np.linspace(0.0, 1.0, 33)
    border = np.r_[
        np.c_[t * w - 0.5, np.full_like(t, -0.5)],
        np.c_[t * w - 0.5, np.full_like(t, h - 0.5)],
        np.c_[np.full_like(t, -0.5), t * h - 0.5],
        np.c_[np.full_like(t, w - 0.5), t * h - 0.5],
    ]
    pixels = camera.undistort_points(border)
    normalised = (pixels - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    lo, hi = normalised.min(axis=0), normalised.max(axis=0)
    margin = 0.05 * (hi - lo)
    return lo - margin, hi + margin
