"""2D line segments of an image: OpenCV LSD, undistortion, merging of collinear fragments (paper III).

The paper runs LSD (von Gioi 2008), then merges adjacent collinear segments and removes short isolated
ones. Thresholds scale with the image diagonal so one config serves 640x480 and 4K alike.
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from .camera import Camera
from .config import LineDetectConfig
from .errors import InvalidInputError
from .geometry import segment_lengths
from .lines2d_merge import merge_collinear
from .threads import run_parallel

log = logging.getLogger(__name__)

__all__ = [
    "along_border",
    "detect",
    "frame_margins",
    "lsd_bands",
    "lsd_segments",
    "merge_collinear",
    "to_gray8",
]

FLOAT_DTYPES = (np.float16, np.float32, np.float64)  # float image dtypes ``to_gray8`` accepts


def detect(image: np.ndarray, camera: Camera, config: LineDetectConfig | None = None) -> np.ndarray:
    """Returns (N, 4) float64 segments ``x1, y1, x2, y2`` in undistorted pixels of ``camera``.

    image: (H, W) grey, (H, W, 3) BGR or (H, W, 4) BGRA; uint8, uint16 or float, with ``H, W`` equal to
    ``camera.height, camera.width``.
    """
    config = config or LineDetectConfig()
    gray = to_gray8(image)
    if gray.shape != (camera.height, camera.width):
        raise InvalidInputError(
            f"image is {gray.shape[1]}x{gray.shape[0]} px but the camera is {camera.width}x{camera.height}"
        )
    segments = lsd_segments(gray, config)
    segments = segments[~along_border(segments, gray.shape, frame_margins(gray), config)]
    if camera.has_distortion and len(segments):
        segments = camera.undistort_points(segments.reshape(-1, 2)).reshape(-1, 4)
    diagonal = math.hypot(camera.width, camera.height)
    merged = merge_collinear(segments, config.merge_gap_frac * diagonal, config)
    kept = merged[segment_lengths(merged) >= config.min_length_frac * diagonal]
    log.debug("lines2d: %d LSD segments, %d merged, %d kept", len(segments), len(merged), len(kept))
    return kept


def to_gray8(image: np.ndarray) -> np.ndarray:
    """Returns the (H, W) uint8 grey version of an image; 16-bit and float are stretched robustly."""
    if not isinstance(image, np.ndarray):
        raise InvalidInputError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype not in (np.uint8, np.uint16, *FLOAT_DTYPES):
        raise InvalidInputError(f"image dtype must be uint8, uint16 or float, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)) or 0 in image.shape:
        raise InvalidInputError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got shape {image.shape}")
    if image.dtype.kind == "f":
        image = image.astype(np.float32, copy=False)  # cvtColor takes 8U, 16U and 32F only
    if image.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(image), code)
    if image.dtype == np.uint8:
        return image
    # OpenCV's single vectorised passes: numpy's chains of float temporaries cost several times more
    if image.dtype.kind == "f":
        lo, hi = float(image.min()), float(image.max())  # NaN propagates, and inf is a bound
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InvalidInputError("image holds NaN or infinite values")
        if lo >= 0.0 and hi <= 255.0:  # convertScaleAbs rounds and saturates to uint8
            return cv2.convertScaleAbs(image, alpha=255.0 if hi <= 1.0 else 1.0)
    return _stretch(image)


def _stretch(gray: np.ndarray) -> np.ndarray:
    """Returns uint8 of a grey image mapped linearly from its 0.5 / 99.5 percentiles to 0 / 255.

    Percentiles (not min/max) so that a few hot pixels of a 16-bit sensor do not squash the contrast;
    taken on a grid of ~50 000 pixels, plenty for two quantiles, so that 4K images stay cheap.
    """
    step = max(1, math.isqrt(gray.size // 50_000))
    lo, hi = (float(q) for q in np.percentile(gray[::step, ::step], [0.5, 99.5]))
    scale = 255.0 / max(hi - lo, 1e-12)
    # clipped at lo (rounded up for integers) first: convertScaleAbs's absolute value would mirror darker
    # pixels to bright ones
    floor = np.asarray(math.ceil(lo) if gray.dtype.kind == "u" else lo, dtype=gray.dtype)
    return cv2.convertScaleAbs(np.maximum(gray, floor), alpha=scale, beta=-lo * scale)


def lsd_segments(gray: np.ndarray, config: LineDetectConfig) -> np.ndarray:
    """Returns (N, 4) float64 LSD segments in pixels (pixel (0, 0) centred at 0) of a (H, W) uint8 image.

    LSD subsamples by ``lsd_scale`` itself, further for images above ``max_work_pixels``; below half
    size its Gaussian gets costly, so very large images are first halved by area averaging (the
    endpoints are scaled back). LSD is single-threaded, so the image is cut into ``lsd_bands`` bands
    overlapping by ``lsd_band_overlap_px``, detected in parallel (OpenCV releases the GIL); a segment cut
    at a band's edge comes back as overlapping pieces that ``merge_collinear`` joins.
    """
    total = min(config.lsd_scale, math.sqrt(config.max_work_pixels / gray.size))  # of the full image
    small, scale = gray, total
    while scale < 0.5 and min(small.shape) >= 64:
        half = ((small.shape[1] + 1) // 2, (small.shape[0] + 1) // 2)
        small = cv2.resize(small, half, interpolation=cv2.INTER_AREA)
        scale = total * gray.shape[1] / small.shape[1]
    axis = 1 if small.shape[1] >= small.shape[0] else 0  # cut the longer side
    overlap = math.ceil(config.lsd_band_overlap_px / scale)
    n = max(1, min(lsd_bands(config), small.shape[axis] // (4 * overlap + 1)))  # no thin bands
    cuts = np.linspace(0, small.shape[axis], n + 1).round().astype(int)
    found: list[np.ndarray] = [np.zeros((0, 4))] * n

    def run(k: int) -> None:
        found[k] = _lsd_band(small, scale, axis, (int(cuts[k]), int(cuts[k + 1])), overlap)

    run_parallel(run, n)
    segments = np.concatenate(found)
    # OpenCV divides subsampled coordinates by the scale without the half-pixel shift of the resize,
    # which moves every edge by 0.5 / scale - 0.5 px towards the origin (0.21 px at 0.7); undo it.
    segments += 0.5 / scale - 0.5
    if small is not gray:  # pixel centres: x_full + 0.5 = (x_small + 0.5) * (full size / small size)
        factor = np.array([gray.shape[1] / small.shape[1], gray.shape[0] / small.shape[0]] * 2)
        segments = (segments + 0.5) * factor - 0.5
    return segments


def lsd_bands(config: LineDetectConfig) -> int:
    """Returns how many bands LSD runs on (``config.lsd_bands``, at least 1)."""
    return max(1, config.lsd_bands)


def _lsd_band(small: np.ndarray, scale: float, axis: int, span: tuple[int, int], overlap: int) -> np.ndarray:
    """Returns (N, 4) float64 LSD segments (OpenCV's coordinates) of the band ``span`` (start, stop) of a
    (H, W) uint8 image along ``axis`` (0 rows, 1 columns), detected with ``overlap`` px more each side.

    Segments lying wholly in that extra margin are dropped: the neighbouring band has them well inside.
    The band starts where LSD's subsampling grid meets the whole image's, so that it sees the same
    subsampled pixels as a single band would.
    """
    starts = np.arange(max(span[0] - overlap - 20, 0), max(span[0] - overlap, 0) + 1)
    lo = int(starts[np.argmin(np.abs(starts * scale - np.round(starts * scale)))])
    hi = min(span[1] + overlap, small.shape[axis])
    band = small[:, lo:hi] if axis == 1 else small[lo:hi]
    found = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, scale).detect(band)[0]
    if found is None:
        return np.zeros((0, 4))
    segments = np.asarray(found, dtype=np.float64).reshape(-1, 4)  # OpenCV 4: (N, 1, 4); OpenCV 5: (N, 4)
    cols = [0, 2] if axis == 1 else [1, 3]
    segments[:, cols] += lo
    along = segments[:, cols]
    outside = (along[:, 0] < span[0]) & (along[:, 1] < span[0]) & (span[0] > 0)
    outside |= (along[:, 0] > span[1]) & (along[:, 1] > span[1]) & (span[1] < small.shape[axis])
    return segments[~outside]


def frame_margins(gray: np.ndarray, max_frac: float = 0.02, flat_std: float = 0.5) -> np.ndarray:
    """Returns (4,) int64 widths (left, top, right, bottom) of a flat frame round a (H, W) uint8 image.

    Some cameras and converters pad or mask the picture (a Kinect's registered RGB has a ~5 px frame):
    border columns / rows of one constant grey (std below flat_std: no sensor is that quiet) are frame,
    up to max_frac of the size.
    """
    h, w = gray.shape
    out = []
    for strips, limit in ((gray.T, w), (gray, h), (gray.T[::-1], w), (gray[::-1], h)):
        n = max(int(max_frac * limit), 0)
        flat = strips[:n].std(axis=1) < flat_std if n else np.zeros(0, dtype=bool)
        out.append(int(np.argmin(np.r_[flat, False])))  # leading run of flat strips
    return np.array(out, dtype=np.int64)


def along_border(
    segments: np.ndarray, shape: tuple[int, ...], margins: np.ndarray, config: LineDetectConfig
) -> np.ndarray:
    """Returns (N,) bool: segments that run along the picture's border (within border_px of it or of the
    frame ``margins`` (4,) and within border_angle_deg of parallel to it).

    Their "edge" is the end of the picture (or of its frame), not a line of the scene, and a long one
    makes a false vanishing direction.
    """
    if config.border_px <= 0 or len(segments) == 0:
        return np.zeros(len(segments), dtype=bool)
    h, w = shape[:2]
    x, y = segments[:, [0, 2]], segments[:, [1, 3]]
    dx, dy = np.abs(segments[:, 2] - segments[:, 0]), np.abs(segments[:, 3] - segments[:, 1])
    tan = math.tan(math.radians(config.border_angle_deg))
    vertical, horizontal = dx <= tan * dy, dy <= tan * dx
    left, top, right, bottom = margins.astype(np.float64) - 0.5 + config.border_px  # pixel centres at 0
    near_x = (x <= left).all(axis=1) | (x >= w - 1 - right).all(axis=1)
    near_y = (y <= top).all(axis=1) | (y >= h - 1 - bottom).all(axis=1)
    return (vertical & near_x) | (horizontal & near_y)
