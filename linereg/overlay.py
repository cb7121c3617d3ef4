"""Pictures of a registration: the image with its 2D lines and the map projected with the estimated pose."""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .matching import project_segments
from .registration import Registration

RED, GREEN, GREY = (40, 40, 230), (60, 220, 60), (170, 170, 170)  # BGR


def draw_overlay(
    image: np.ndarray,
    camera: Camera,
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    registration: Registration,
) -> np.ndarray:
    """Returns an (H, W, 3) uint8 BGR picture: map segments thin grey, 2D lines red, matched 3D lines green.

    image: the photo (any dtype/channels ``lines2d.detect`` accepts); lines2d: (N, 4) undistorted pixels;
    lines3d: (M, 6) the map segments that ``registration.matches`` index.
    """
    import cv2

    canvas = _to_bgr8(image)
    canvas = (0.6 * canvas).astype(np.uint8)  # dim the photo so the lines stand out
    if registration.success and len(lines3d):
        projected, visible = project_segments(lines3d, camera, registration.cam_from_world, 0.05)
        _draw(canvas, projected[visible], GREY, 1)
    _draw(canvas, lines2d, RED, 1)
    if registration.success and len(registration.matches):
        _draw(canvas, projected[registration.matches[:, 1]], GREEN, 2)
    text = (
        f"{registration.num_inliers} inliers, {1e3 * registration.timings.get('total', 0.0):.0f} ms"
        if registration.success
        else f"not localized: {registration.reason}"
    )
    cv2.putText(canvas, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def _draw(canvas: np.ndarray, segments: np.ndarray, color: tuple[int, int, int], thickness: int) -> None:
    import cv2

    h, w = canvas.shape[:2]
    limit = 4.0 * max(h, w)  # cv2 needs int coordinates; far-off endpoints are clipped by cv2.line anyway
    pts = np.clip(np.round(segments), -limit, limit).astype(np.int64)
    for x1, y1, x2, y2 in pts:
        cv2.line(canvas, (int(x1), int(y1)), (int(x2), int(y2)), color, thickness, cv2.LINE_AA)


def _to_bgr8(image: np.ndarray) -> np.ndarray:
    """Returns an (H, W, 3) uint8 copy of a grayscale/colour, 8/16-bit or float image."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        lo, hi = np.percentile(img, [1, 99]) if img.size else (0.0, 1.0)
        img = np.clip((img - lo) / max(hi - lo, 1e-12) * 255.0, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])
