"""Synthetic 2D/3D line scenes with known pose and known correspondences, for tests and benchmarks.

- ``paper_scene``: the paper's Monte-Carlo generator (section IV-A): random parallel 3D lines in
  ``[-1, 1]^3``, projected into a 640x480, f = 800 camera with noise, 3D and 2D outliers.
- the helpers both it and ``building_scene.building_scene`` (edges of a procedural Manhattan building seen
  from the street, with occlusion, fragmentation, partial segments and clutter) build on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import InvalidInputError
from ..geometry import make_cam_from_world, segment_lengths
from ..score import project_segments

MIN_LENGTH_PX = 20.0  # shorter projections are dropped: LSD would not report them reliably either
MIN_DEPTH_M = 1e-3  # segments are cut where they come nearer to the camera plane than this


@dataclass(frozen=True)
class Scene:
    """A synthetic registration problem with its answer.

    lines2d: (N, 4) float64 pixels (undistorted); lines3d: (M, 6) float64 world;
    cam_from_world: (4, 4) float64 ground truth; true_matches: (K, 2) int64 ``(i2d, j3d)`` sorted by i2d,
    one row per 2D segment that images a 3D segment (2D rows not listed are outliers).
    """

    lines2d: np.ndarray
    lines3d: np.ndarray
    camera: Camera
    cam_from_world: np.ndarray
    true_matches: np.ndarray


def paper_camera() -> Camera:
    """Returns the paper's synthetic camera: 640x480 pixels, f = 800, centred principal point."""
    return Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)


def random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    """Returns (n, 3) float64 unit vectors uniform on the sphere."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def look_at(center: np.ndarray, target: np.ndarray, roll_rad: float = 0.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Returns (4, 4) ``cam_from_world`` of a camera at ``center`` whose optical axis points at ``target``.

    With ``roll_rad = 0`` the image y axis (down) is the projection of ``-up``; roll turns about the axis.
    """
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    up = np.asarray(up, float)
    if abs(z @ up) > 0.999:  # looking straight along ``up``: any other reference works
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # x right, y down, z forward: x cross y = z
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    R = np.stack([c * x + s * y, -s * x + c * y, z])
    return make_cam_from_world(R, -R @ np.asarray(center, float))


def clip_to_box(
    p: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray, t0: np.ndarray, t1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (t0, t1) (N,) narrowed so that ``p + t d`` stays in the box ``[lo, hi]`` (Liang-Barsky).

    p, d: (N, k) points and directions; the interval is empty where ``t0 > t1`` afterwards.
    """
    t0, t1 = np.array(t0, dtype=float), np.array(t1, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - p) / d
        tb = (hi - p) / d
    flat = d == 0
    inside = (p >= lo) & (p <= hi)
    enter = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    leave = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(t0, enter.max(axis=1)), np.minimum(t1, leave.min(axis=1))


def clip_to_image(lines2d: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N, 4) segments clipped to the image rectangle, (N,) bool non-empty)."""
    p, d = lines2d[:, 0:2], lines2d[:, 2:4] - lines2d[:, 0:2]
    lo, hi = np.array([0.0, 0.0]), np.array([camera.width - 1.0, camera.height - 1.0])
    t0, t1 = clip_to_box(p, d, lo, hi, np.zeros(len(p)), np.ones(len(p)))
    keep = t0 < t1
    t0, t1 = np.where(keep, t0, 0.0), np.where(keep, t1, 0.0)  # empty ones: no inf * 0
    return np.c_[p + t0[:, None] * d, p + t1[:, None] * d], keep


def project_visible(
    lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_length_px: float = MIN_LENGTH_PX
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 4) image segments, (K,) int64 indices into lines3d) of the projections long enough.

    Segments are cut at the near plane, clipped to the image, and dropped below ``min_length_px``.
    """
    seg, visible = project_segments(lines3d, camera, cam_from_world, MIN_DEPTH_M)
    seg, inside = clip_to_image(seg, camera)
    keep = visible & inside & (segment_lengths(seg) >= min_length_px)
    return seg[keep], np.flatnonzero(keep)


def decoy_scene(camera: Camera, seed: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((M, 6) map segments, (4, 4) true cam_from_world, (N, 4) image segments) of 20 random lines
    (12 along the axes) seen from 4 m, where half the image's lines have a second edge 3 px beside them,
    30 % longer (a frame's other side): a refinement associating loosely settles between the two."""
    rng = np.random.default_rng(seed)
    directions = np.r_[np.tile(np.eye(3), (12, 1)), rng.normal(size=(8, 3))]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = rng.uniform(-1.5, 1.5, (len(directions), 3))
    lines3d = np.c_[starts, starts + rng.uniform(0.4, 1.2, (len(directions), 1)) * directions]
    truth = look_at(np.array([4.0, 0.0, 0.8]), np.zeros(3))
    segments = project_visible(lines3d, camera, truth)[0]
    d = segments[:, 2:] - segments[:, :2]
    side = 3.0 * np.c_[-d[:, 1], d[:, 0]] / np.linalg.norm(d, axis=1, keepdims=True)
    half = len(segments) // 2
    decoys = np.c_[segments[:half, :2] - 0.15 * d[:half], segments[:half, 2:] + 0.15 * d[:half]]
    decoys += np.tile(side[:half], 2)
    return lines3d, truth, np.r_[segments, decoys]


def random_image_segments(
    rng: np.random.Generator, n: int, camera: Camera, lengths_px: np.ndarray, top: float = 0.0
) -> np.ndarray:
    """Returns (n, 4) random segments in the image: uniform centre and angle, lengths drawn from lengths_px.

    Centres lie below ``top`` (a fraction of the image height); segments that clipping leaves shorter
    than ``MIN_LENGTH_PX`` are redrawn.
    """
    out = np.zeros((0, 4))
    size = np.array([camera.width - 1.0, camera.height - 1.0])
    while len(out) < n:
        m = 2 * (n - len(out)) + 8
        centre = rng.uniform([0.0, top], [1.0, 1.0], size=(m, 2)) * size
        angle = rng.uniform(0.0, np.pi, size=m)
        half = 0.5 * rng.choice(lengths_px, size=m)[:, None] * np.c_[np.cos(angle), np.sin(angle)]
        seg, keep = clip_to_image(np.c_[centre - half, centre + half], camera)
        seg = seg[keep & (segment_lengths(seg) >= MIN_LENGTH_PX)]
        out = np.r_[out, seg]
    return out[:n]


def add_outliers_and_shuffle(
    rng: np.random.Generator, inliers2d: np.ndarray, inlier_j3d: np.ndarray, outliers2d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N, 4) shuffled 2D segments, (K, 2) int64 true matches sorted by i2d)."""
    lines2d = np.r_[inliers2d, outliers2d]
    order = rng.permutation(len(lines2d))
    lines2d = lines2d[order]
    new_index = np.empty(len(order), dtype=np.int64)
    new_index[order] = np.arange(len(order))
    matches = np.c_[new_index[: len(inliers2d)], inlier_j3d].astype(np.int64).reshape(-1, 2)
    return lines2d, matches[np.argsort(matches[:, 0])]


def num_outliers(num_inliers: int, fraction: float) -> int:
    """Returns how many outliers make them ``fraction`` of ``num_inliers + outliers``."""
    if not 0.0 <= fraction < 1.0:
        raise InvalidInputError(f"outlier fraction must lie in [0, 1), got {fraction}")
    return round(fraction * num_inliers / (1.0 - fraction))


def _paper_directions(rng: np.random.Generator, num_lines: int, random_fraction: float) -> np.ndarray:
    """Returns (num_lines, 3) unit directions: two parallel families well apart plus random ones."""
    d1 = random_unit(rng, 1)[0]
    d2 = random_unit(rng, 1)[0]
    while abs(d1 @ d2) > np.cos(np.radians(60.0)):  # families at least 60 degrees apart
        d2 = random_unit(rng, 1)[0]
    n_random = round(random_fraction * num_lines)
    n1 = (num_lines - n_random + 1) // 2
    n2 = num_lines - n_random - n1
    return np.r_[np.tile(d1, (n1, 1)), np.tile(d2, (n2, 1)), random_unit(rng, n_random)]


def _segments_in_cube(
    rng: np.random.Generator, directions: np.ndarray, min_length: float = 0.4
) -> np.ndarray:
    """Returns (M, 6) segments along ``directions`` lying in [-1, 1]^3, lengths uniform in [0.4, 1.6]."""
    n = len(directions)
    out = np.zeros((n, 6))
    todo = np.arange(n)
    lo, hi = -np.ones(3), np.ones(3)
    while len(todo):
        p, d = rng.uniform(-1.0, 1.0, size=(len(todo), 3)), directions[todo]
        ta, tb = clip_to_box(p, d, lo, hi, np.full(len(p), -np.inf), np.full(len(p), np.inf))
        length = np.minimum(rng.uniform(min_length, 1.6, size=len(p)), tb - ta)
        s = ta + rng.uniform(size=len(p)) * (tb - ta - length)
        out[todo] = np.c_[p + s[:, None] * d, p + (s + length)[:, None] * d]
        todo = todo[length < min_length]  # chord through a corner too short: draw again
    return out


def paper_scene(
    rng: np.random.Generator,
    num_lines: int = 100,
    outlier3d_fraction: float = 0.3,
    outlier2d_fraction: float = 0.3,
    noise_px: float = 2.0,
    camera: Camera | None = None,
) -> Scene:
    """Returns the paper's Monte-Carlo scene (section IV-A) with its true pose and correspondences.

    Choices (the paper leaves them open):
    - 3D map: ``num_lines`` segments in ``[-1, 1]^3``; 20 % have random directions, the rest split evenly
      between two parallel families whose directions are random and at least 60 degrees apart (not
      necessarily orthogonal). Lengths are uniform in [0.4, 1.6] (shortened to fit the cube).
    - Camera: default ``paper_camera()`` (640x480, f = 800); centre uniform on a sphere of radius 3-5
      around the origin, looking at a point within 0.2 of the origin, roll uniform in [0, 2 pi). The cube
      then spans roughly 300-550 px.
    - 3D outliers: ``round(outlier3d_fraction * num_lines)`` random map lines are not imaged (occlusion).
    - The others are projected, clipped to the image and dropped when shorter than 20 px; only kept ones
      appear in ``true_matches``. Gaussian noise (sigma = ``noise_px``, per coordinate) is added to the
      endpoints after clipping, so noisy endpoints may lie up to a few sigma outside the image.
    - 2D outliers: random centre, uniform angle, lengths drawn from the inlier lengths, clipped to the
      image (>= 20 px); their number makes them ``outlier2d_fraction`` of all 2D segments (rounded).
    - 2D segments are shuffled; ``true_matches`` (K, 2) int64 ``(i2d, j3d)`` is sorted by i2d.
    """
    camera = camera or paper_camera()
    if num_lines < 1 or not 0.0 <= outlier3d_fraction <= 1.0 or noise_px < 0:
        raise InvalidInputError("paper_scene: need num_lines >= 1, outlier3d_fraction in [0, 1], noise >= 0")
    lines3d = _segments_in_cube(rng, _paper_directions(rng, num_lines, random_fraction=0.2))
    centre = random_unit(rng, 1)[0] * rng.uniform(3.0, 5.0)
    cam_from_world = look_at(centre, rng.uniform(-0.2, 0.2, size=3), rng.uniform(0.0, 2 * np.pi))
    imaged = np.sort(rng.permutation(num_lines)[round(outlier3d_fraction * num_lines) :])
    seg, kept = project_visible(lines3d[imaged], camera, cam_from_world)
    inlier_j3d = imaged[kept]
    seg = seg + rng.normal(scale=noise_px, size=seg.shape)
    lengths = segment_lengths(seg) if len(seg) else np.array([50.0, 200.0])
    outliers = random_image_segments(rng, num_outliers(len(seg), outlier2d_fraction), camera, lengths)
    lines2d, matches = add_outliers_and_shuffle(rng, seg, inlier_j3d, outliers)
    return Scene(lines2d, lines3d, camera, cam_from_world, matches)


def fragment(
    rng: np.random.Generator, lines2d: np.ndarray, partial: float = 0.3, split: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P, 4) pieces, (P,) int64 source row) of segments shortened and split like a detector's.

    A fraction ``partial`` loses 0-25 % at each end; a fraction ``split`` of those of 80 px or more breaks
    into 2 or 3 pieces with gaps of 5-15 % of the length. Pieces under ``MIN_LENGTH_PX`` are dropped.
    """
    pieces, source = [], []
    for i, length in enumerate(segment_lengths(lines2d)):
        a, b = (
            (rng.uniform(0.0, 0.25), 1.0 - rng.uniform(0.0, 0.25)) if rng.uniform() < partial else (0.0, 1.0)
        )
        cuts = np.array([a, b])
        if length >= 80.0 and rng.uniform() < split:
            centres = np.sort(rng.uniform(a + 0.1, b - 0.1, size=rng.integers(1, 3)))
            gaps = rng.uniform(0.025, 0.075, size=len(centres))
            cuts = np.r_[a, np.ravel(np.c_[centres - gaps, centres + gaps]), b]
        for lo, hi in cuts.reshape(-1, 2):
            if hi > lo and (hi - lo) * length >= MIN_LENGTH_PX:
                p, q = lines2d[i, 0:2], lines2d[i, 2:4]
                pieces.append(np.r_[p + lo * (q - p), p + hi * (q - p)])
                source.append(i)
    return np.array(pieces, dtype=np.float64).reshape(-1, 4), np.array(source, dtype=np.int64)
