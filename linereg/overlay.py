"""Pictures of a registration: the image with its 2D lines and the map projected with the estimated pose,
a caption (outcome, inliers, ambiguity) and a legend of the colours."""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .registration import Registration
from .score import project_segments

RED, GREEN, GREY = (40, 40, 230), (60, 220, 60), (170, 170, 170)  # BGR
WHITE, BLACK = (255, 255, 255), (0, 0, 0)
LEGEND = ((RED, "detected 2D lines"), (GREEN, "matched map lines"), (GREY, "other map lines"))


def draw_overlay(
    image: np.ndarray,
    camera: Camera,
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    registration: Registration,
    caption: str | None = None,
) -> np.ndarray:
    """Returns an (H, W, 3) uint8 BGR picture: map segments thin grey, 2D lines red, matched 3D lines green.

    image: the photo (any dtype/channels ``lines2d.detect`` accepts); lines2d: (N, 4) undistorted pixels;
    lines3d: (M, 6) the map segments that ``registration.matches`` index. The map is drawn only with a
    pose (``registration.success``). caption: the top line, by default ``overlay_caption(registration)``;
    a legend of the colours drawn sits in the bottom-left corner.
    """
    canvas = _to_bgr8(image)
    canvas = (0.6 * canvas).astype(np.uint8)  # dim the photo so the lines stand out
    drawn = [RED]
    if registration.success and len(lines3d):
        projected, visible = project_segments(lines3d, camera, registration.cam_from_world, 0.05)
        _draw(canvas, projected[visible], GREY, 1)
        drawn.append(GREY)
    _draw(canvas, lines2d, RED, 1)
    if registration.success and len(lines3d) and len(registration.matches):
        _draw(canvas, projected[registration.matches[:, 1]], GREEN, 2)
        drawn.append(GREEN)
    style = _TextStyle.for_size(canvas.shape[1], canvas.shape[0])
    _caption(canvas, overlay_caption(registration) if caption is None else caption, style)
    _legend(canvas, [(color, text) for color, text in LEGEND if color in drawn], style)
    return canvas


def overlay_caption(registration: Registration) -> str:
    """Returns the one-line outcome: localized or not, inlier count, ambiguity, time, the reason last (it
    may be long: a cut caption keeps the numbers)."""
    r = registration
    total_s = r.timings.get("total")
    time = f", {1e3 * total_s:.0f} ms" if total_s else ""
    numbers = f"{r.num_inliers} inliers, {100 * r.explained_fraction:.0f} % explained, ambiguity {r.ambiguity:.2f}{time}"
    if r.success:
        return f"localized | {numbers}"
    return f"not localized | {numbers} | {r.reason or 'no reason given'}"


class _TextStyle:
    """Font size and line metrics scaled with the image size (readable from 640x480 up to 4K)."""

    def __init__(self, scale: float) -> None:
        import cv2

        self.font, self.scale = cv2.FONT_HERSHEY_SIMPLEX, scale
        self.thickness = 1 if scale < 0.9 else 2
        (_, self.height), self.baseline = cv2.getTextSize("Ag", self.font, scale, self.thickness)
        self.pad = max(3, round(0.5 * self.height))

    @classmethod
    def for_size(cls, width: int, height: int) -> _TextStyle:
        # the width of the image's 4:3 part: a wide, short frame (KITTI 1242x375) gets the small font
        return cls(float(np.clip(min(width, height * 4 / 3) / 1100.0, 0.4, 1.6)))

    def width_of(self, text: str) -> int:
        import cv2

        return cv2.getTextSize(text, self.font, self.scale, self.thickness)[0][0]

    def put(self, canvas: np.ndarray, text: str, x: int, y: int) -> None:
        """Writes ``text`` with its baseline at ``y``."""
        import cv2

        cv2.putText(canvas, text, (x, y), self.font, self.scale, WHITE, self.thickness, cv2.LINE_AA)


def _caption(canvas: np.ndarray, text: str, style: _TextStyle) -> None:
    """A dark band across the top with ``text``, cut with '...' to the image width."""
    width = canvas.shape[1]
    room = width - 2 * style.pad
    if style.width_of(text) > room:
        while text and style.width_of(text + "...") > room:
            text = text[:-1]
        text += "..."
    bottom = style.height + style.baseline + 2 * style.pad
    _shade(canvas, 0, 0, width, bottom)
    style.put(canvas, text, style.pad, style.pad + style.height)


def _legend(canvas: np.ndarray, entries: list[tuple[tuple[int, int, int], str]], style: _TextStyle) -> None:
    """A dark box in the bottom-left corner: one short line of each colour and its meaning."""
    import cv2

    if not entries:
        return
    row = style.height + style.baseline + style.pad
    sample = 2 * style.height
    box_w = 3 * style.pad + sample + max(style.width_of(text) for _, text in entries)
    box_h = len(entries) * row + style.pad
    top = canvas.shape[0] - box_h - style.pad
    _shade(canvas, style.pad, top, style.pad + box_w, top + box_h)
    for k, (color, text) in enumerate(entries):
        y = top + style.pad + k * row + style.height  # text baseline
        x = 2 * style.pad
        mid = y - style.height // 2
        cv2.line(canvas, (x, mid), (x + sample, mid), color, 2, cv2.LINE_AA)
        style.put(canvas, text, x + sample + style.pad, y)


def _shade(canvas: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> None:
    """Darkens a rectangle (clipped to the canvas) so white text on it is legible over any photo."""
    h, w = canvas.shape[:2]
    x0, x1, y0, y1 = max(x0, 0), min(x1, w), max(y0, 0), min(y1, h)
    if x1 > x0 and y1 > y0:
        canvas[y0:y1, x0:x1] = (0.3 * canvas[y0:y1, x0:x1]).astype(np.uint8)


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
