"""The rules ``map.visibility``'s compiled sampling (``_samples``) implements, written plainly with numpy:
the reference the tests hold it to, to the bit."""

from __future__ import annotations

import numpy as np

from linereg.camera import Camera
from linereg.chunks import inward_normals


def pixel(camera: Camera, x: np.ndarray) -> np.ndarray:
    """Returns (N, 2) pixels of (N, 3) camera-frame points in front of the camera."""
    return np.c_[camera.fx * x[:, 0] / x[:, 2] + camera.cx, camera.fy * x[:, 1] / x[:, 2] + camera.cy]


def in_pyramid(a: np.ndarray, b: np.ndarray, camera: Camera, near: float) -> np.ndarray:
    """Returns (N,) bool: False where both camera-frame ends of a segment, (N, 3) ``a`` and ``b``, lie
    nearer than ``near`` or both outside one side face of the pyramid through the camera centre and the
    image border widened by a pixel (the exact clipping's border lies half a pixel out): the outside of a
    face is convex, so the whole segment lies there and no part of it can project into the image."""
    inward = inward_normals(camera)
    outside = ((a @ inward) < 0.0) & ((b @ inward) < 0.0)
    return ~(outside.any(axis=1) | ((a[:, 2] < near) & (b[:, 2] < near)))


def clip_near(za: np.ndarray, zb: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (t0, t1, ok) (N,) each: the parameter range of a + t (b - a) with depth >= near."""
    t0, t1 = np.zeros(len(za)), np.ones(len(za))
    dz = zb - za
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = (near - za) / dz
    t0 = np.where((za < near) & (zb >= near), cross, t0)
    t1 = np.where((zb < near) & (za >= near), cross, t1)
    return t0, t1, ~((za < near) & (zb < near))


def clip_image(
    a: np.ndarray, b: np.ndarray, t0: np.ndarray, t1: np.ndarray, ok: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (t0, t1, ok) narrowed to the stretch whose projection lies inside the image (Liang-Barsky
    on the 2D segment, its parameters mapped back to 3D: t = s z_a / (z_b (1 - s) + s z_a))."""
    pa, pb = a + t0[:, None] * (b - a), a + t1[:, None] * (b - a)
    with np.errstate(divide="ignore", invalid="ignore"):
        p0, p1 = pixel(camera, pa), pixel(camera, pb)
        d = p1 - p0
        s0, s1 = np.zeros(len(a)), np.ones(len(a))
        bounds = (
            (0, -0.5, 1.0),
            (0, camera.width - 0.5, -1.0),
            (1, -0.5, 1.0),
            (1, camera.height - 0.5, -1.0),
        )
        for axis, edge, inward in bounds:
            q = inward * (p0[:, axis] - edge)  # >= 0: inside this edge at s = 0
            r = inward * d[:, axis]
            cut = -q / r
            s0 = np.where(r > 0, np.maximum(s0, cut), s0)
            s1 = np.where(r < 0, np.minimum(s1, cut), s1)
            ok = ok & ~((r == 0) & (q < 0))
        ok = ok & (s1 > s0) & np.isfinite(s0) & np.isfinite(s1)
        za, zb = pa[:, 2], pb[:, 2]
        u0 = s0 * za / (zb * (1 - s0) + s0 * za)
        u1 = s1 * za / (zb * (1 - s1) + s1 * za)
    span = t1 - t0
    return np.where(ok, t0 + u0 * span, 0.0), np.where(ok, t0 + u1 * span, 0.0), ok


def samples(
    segments: np.ndarray, rows: np.ndarray, a: np.ndarray, b: np.ndarray, camera: Camera, near: float,
    sample_px: float, max_samples: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``visibility._samples`` by numpy's rules: (kept positions in ``rows``, samples per kept segment,
    each sample's owner, parameter and world point)."""
    kept = np.flatnonzero(in_pyramid(a, b, camera, near))
    a, b = a[kept], b[kept]
    t0, t1, ok = clip_near(a[:, 2], b[:, 2], near)
    t0, t1, ok = clip_image(a, b, t0, t1, ok, camera)
    kept, a, b, t0, t1 = kept[ok], a[ok], b[ok], t0[ok], t1[ok]
    p0, p1 = pixel(camera, a + t0[:, None] * (b - a)), pixel(camera, a + t1[:, None] * (b - a))
    count = np.clip(np.ceil(np.linalg.norm(p1 - p0, axis=1) / sample_px), 1, max_samples)
    count = count.astype(np.int64) + 1
    owner = np.repeat(np.arange(len(kept)), count)
    first = np.cumsum(count) - count
    s = (np.arange(len(owner)) - first[owner]) / (count[owner] - 1)
    za, zb = (a + t0[:, None] * (b - a))[:, 2], (a + t1[:, None] * (b - a))[:, 2]
    u = s * za[owner] / (zb[owner] * (1.0 - s) + s * za[owner])
    tt = t0[owner] + u * (t1 - t0)[owner]
    world = segments[rows[kept]][owner]
    points = world[:, :3] + tt[:, None] * (world[:, 3:] - world[:, :3])
    return kept, count, owner, tt, points


def chunks_in_view(
    centre: np.ndarray, half: np.ndarray, camera: Camera, cam_from_world: np.ndarray, near: float
):
    """``chunks.kept_chunks`` by numpy's rules: (C,) bool, the boxes not wholly outside a face of the view's
    pyramid (widened by a pixel) nor wholly nearer than ``near``."""
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    normals = np.c_[inward_normals(camera), [0.0, 0.0, 1.0]]  # (3, 5) camera frame; the last: depth
    w = R.T @ normals
    offset = normals.T @ t - np.r_[0.0, 0.0, 0.0, 0.0, near]
    reach = centre @ w + half @ np.abs(w) + offset
    scale = 1e-9 * (1.0 + np.abs(centre @ w).max(axis=1, initial=0.0) + np.abs(offset).max())
    return (reach >= -scale[:, None]).all(axis=1)
