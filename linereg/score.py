"""The score of a pose, without correspondences: how much of the image's line length the visible map explains.

One scoring function serves the search, the decision, the benchmarks and the overlays (issue 9):

- **explained** (px): for every image segment, the length of it that projected map segments cover. A map
  segment covers the part of an image segment where it runs within ``distance_px`` of the image segment's
  line (tested at both ends of the shared stretch) at an angle below ``angle_deg``. Per image segment the
  covered stretches are united, so three map fragments along an image line explain it as well as one whole
  segment, and two map lines on one image line do not count it twice.
- **unexplained** (px): the projected length of visible map segments that falls where the image shows no
  line at all (farther than ``empty_radius_fraction`` of the image diagonal from every image segment): a
  wrong pose puts facade edges into the sky, onto blank walls or the empty ground.
- **score** = explained - ``unexplained_weight`` x unexplained.

The image side (``ImageLines``: lines, angles, the empty-area raster) is computed once per image. The pair
test and the union run in compiled loops (numba): the search scores thousands of poses per image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from .camera import Camera
from .chunks import NO_CHUNKS, Chunks, kept_chunks
from .config import ScoreConfig
from .geometry import segment_angles, segment_lengths
from .kernels import stable_argsort
from .threads import run_parallel, thread_count

CELLS_PER_RADIUS = 8  # the empty-area raster: cells of radius / 8, fine next to the radius, cheap
GRID_PX = 24.0  # cells of the candidate grid of the pair test: speed only, the same pairs for any size


@dataclass(frozen=True)
class ImageLines:
    """The image side of the score, computed once per image (``image_lines``).

    segments: (N, 4) float64 undistorted pixels; lengths: (N,); angles: (N,) in [0, pi).
    grid_ptr, grid_items: the segments near each cell of a ``grid_px`` raster over the image (CSR: the
        segments of cell (r, c) are ``grid_items[grid_ptr[r * grid_w + c]:grid_ptr[r * grid_w + c + 1]]``),
        each listed wherever it passes within ``distance_px + grid_px / 2`` (the pair test's candidates).
    empty: (h, w) bool raster of cells of ``cell_px`` pixels farther than the empty radius from every
        segment (cell (r, c) covers pixels [c, c + 1) x [r, r + 1) times cell_px).
    empty_sum: (h + 1, w + 1) int64 counts of empty cells above and left of each corner (a summed-area
        table: a projected segment whose box holds no empty cell is not sampled for the penalty).
    """

    segments: np.ndarray
    lengths: np.ndarray
    angles: np.ndarray
    grid_ptr: np.ndarray
    grid_items: np.ndarray
    grid_w: int
    grid_px: float
    empty: np.ndarray
    cell_px: float
    width: int
    height: int
    empty_sum: np.ndarray

    @property
    def total_length(self) -> float:
        return float(self.lengths.sum())


def image_lines(lines2d: np.ndarray, camera: Camera, config: ScoreConfig) -> ImageLines:
    """Returns the image side of the score for (N, 4) undistorted pixel segments of an image of ``camera``."""
    lines2d = np.ascontiguousarray(lines2d, dtype=np.float64).reshape(-1, 4)
    angles = segment_angles(lines2d)
    radius = config.empty_radius_fraction * float(np.hypot(camera.width, camera.height))
    empty, cell = _empty_cells(lines2d, camera.width, camera.height, radius)
    ptr, items, grid_w = _segment_grid(lines2d, camera.width, camera.height, GRID_PX, config.distance_px)
    return ImageLines(
        lines2d, segment_lengths(lines2d), angles, ptr, items, grid_w, GRID_PX, empty, cell, camera.width,
        camera.height, summed_area(empty),
    )  # fmt: skip


@dataclass(frozen=True)
class Score:
    """A pose's score and what it is made of.

    explained: (N,) px of each image segment covered by the visible map; unexplained: px of visible map
    length in empty image areas; value: ``explained.sum() - weight * unexplained``.
    pairs: (P, 2) int64 ``(i2d, j3d)`` of every covering pair, with cover: (P, 2) float64 the covered
        stretch of image segment i, as distances (px) from its first endpoint along it.
    """

    value: float
    explained: np.ndarray
    unexplained: float
    pairs: np.ndarray
    cover: np.ndarray

    @property
    def explained_length(self) -> float:
        return float(self.explained.sum())

    def one_to_one(self) -> np.ndarray:
        """Returns (K, 2) int64 ``(i2d, j3d)``: the covering pairs taken longest cover first, each image
        segment and each map segment in at most one (a greedy assignment). A loose tolerance lets a map
        line cover several image lines of clutter and the truth's: pose fits on all of them average the
        pulls, on these the longest agreement wins (docs/measurements.md: the local solve's basin)."""
        return greedy_pairs(self.pairs, self.cover)

    def matches(self, min_cover: float) -> np.ndarray:
        """Returns (K, 2) int64 ``(i2d, j3d)``: for each image segment the map segment covering most of it,
        if that covers at least ``min_cover`` of its length (the correspondences refinement starts from).

        ``min_cover`` is a fraction of the image segment's length (the paper's overlap test: 0.5).
        """
        if len(self.pairs) == 0:
            return np.zeros((0, 2), dtype=np.int64)
        covered = self.cover[:, 1] - self.cover[:, 0]
        order = np.lexsort((-covered, self.pairs[:, 0]))
        first = order[np.r_[True, self.pairs[order[1:], 0] != self.pairs[order[:-1], 0]]]
        return self.pairs[first].astype(np.int64).reshape(-1, 2)


def score_pose(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    config: ScoreConfig,
    visible: np.ndarray | None = None,
    chunks: Chunks | None = None,
) -> Score:
    """Returns the Score of a pose: (M, 6) world map segments seen by an undistorted ``camera`` at (4, 4)
    ``cam_from_world``; ``visible``: (M,) bool of the segments not hidden by the map's surfaces (None: all);
    ``chunks``: theirs, or None (``project_clipped``)."""
    projected, index = project_clipped(lines3d, camera, cam_from_world, config.min_depth_m, visible, chunks)
    return score_projected(image, projected, index, config)


def score_projected(
    image: ImageLines, projected: np.ndarray, index: np.ndarray, config: ScoreConfig
) -> Score:
    """Returns the Score of (K, 4) projected map segments already clipped to the image; ``index`` (K,) gives
    each one's row in the map (``Score.pairs`` use it)."""
    pairs, cover = _pairs_of(image, projected, index, config)
    explained = _union_lengths(np.ascontiguousarray(pairs[:, 0]), cover, len(image.segments))
    unexplained = _length_in_cells(projected, image.empty, image.cell_px, image.empty_sum)
    value = float(explained.sum()) - config.unexplained_weight * unexplained
    return Score(value, explained, unexplained, pairs, cover)


def greedy_pairs(pairs: np.ndarray, cover: np.ndarray) -> np.ndarray:
    """Returns (K, 2) int64 of (P, 2) covering pairs (their (P, 2) covered stretches) taken longest cover
    first, each image segment and each map segment in at most one (``Score.one_to_one``)."""
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    order = np.argsort(-(cover[:, 1] - cover[:, 0]), kind="stable")
    pairs = np.ascontiguousarray(pairs[order], dtype=np.int64)
    return pairs[_greedy(pairs, int(pairs[:, 0].max()) + 1, int(pairs[:, 1].max()) + 1)]


def _pairs_of(
    image: ImageLines, projected: np.ndarray, index: np.ndarray, config: ScoreConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P, 2) int64 covering pairs (i2d, map row), (P, 2) covered stretches) of (K, 4) projected
    map segments whose map rows ``index`` gives."""
    i, j, cover = _covering_pairs(
        image.segments,
        image.angles,
        image.lengths,
        image.grid_ptr,
        image.grid_items,
        image.grid_w,
        image.grid_px,
        projected,
        config.distance_px,
        np.radians(config.angle_deg),
    )
    pairs = np.stack([i, index[j]], axis=1) if len(i) else np.zeros((0, 2), dtype=np.int64)
    return pairs, cover


def shifted_values(
    image: ImageLines, projected: np.ndarray, shifts: np.ndarray, config: ScoreConfig
) -> np.ndarray:
    """Returns (S,) the score values of (K, 4) projected map segments moved by each of (S, 2) pixel
    ``shifts``: ``score_projected(image, projected + (dx, dy, dx, dy), ...).value`` for every shift, in one
    compiled loop (the decision compares a pose with these displaced copies of itself, ``pipeline.decide``),
    the shifts shared among threads (each value depends on its shift alone)."""
    projected = np.ascontiguousarray(projected, dtype=np.float64).reshape(-1, 4)
    shifts = np.ascontiguousarray(shifts, dtype=np.float64).reshape(-1, 2)
    out = np.empty(len(shifts))
    workers = thread_count(2 if len(shifts) * len(projected) > 10_000 else 1)
    bounds = np.linspace(0, len(shifts), workers + 1).astype(np.int64)

    def run(worker: int) -> None:
        part = slice(bounds[worker], bounds[worker + 1])
        out[part] = _shifted_values(
            image.segments, image.angles, image.lengths, image.empty, image.empty_sum, image.cell_px, projected,
            shifts[part], config.distance_px, np.radians(config.angle_deg), config.unexplained_weight,
        )  # fmt: skip

    run_parallel(run, workers)
    return out


def project_segments(
    lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((M, 4) projected pixel segments, (M,) bool some part at depth >= ``min_depth_m``).

    A segment crossing the near plane ``z = min_depth_m`` is cut there (the one near-plane clipping every
    stage shares); one wholly behind it is not visible (its row holds the clamped, meaningless projection).
    """
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    a = lines3d[:, 0:3] @ R.T + t
    b = lines3d[:, 3:6] @ R.T + t
    a, b, visible = clip_near(a, b, min_depth_m)
    seg = np.empty((len(lines3d), 4))
    seg[:, 0] = camera.fx * a[:, 0] / a[:, 2] + camera.cx
    seg[:, 1] = camera.fy * a[:, 1] / a[:, 2] + camera.cy
    seg[:, 2] = camera.fx * b[:, 0] / b[:, 2] + camera.cx
    seg[:, 3] = camera.fy * b[:, 1] / b[:, 2] + camera.cy
    return seg, visible


def clip_near(a: np.ndarray, b: np.ndarray, near_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((K, 3) a, (K, 3) b, (K,) bool kept): camera-frame segments cut at the plane ``z = near_m``.

    An endpoint behind the plane moves onto it along the segment; a segment wholly behind keeps clamped
    endpoints (depth ``near_m``) and ``kept`` False.
    """
    za, zb = a[:, 2], b[:, 2]
    kept = (za >= near_m) | (zb >= near_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(za != zb, (near_m - za) / (zb - za), 0.0)
    crossing = a + np.clip(s, 0.0, 1.0)[:, None] * (b - a)
    a = np.where((za < near_m)[:, None], crossing, a)
    b = np.where((zb < near_m)[:, None], crossing, b)
    a[:, 2] = np.maximum(a[:, 2], near_m)
    b[:, 2] = np.maximum(b[:, 2], near_m)
    return a, b, kept


def project_clipped(
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    min_depth_m: float,
    visible: np.ndarray | None = None,
    chunks: Chunks | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 4) projected segments cut to the image rectangle, (K,) int64 their rows in ``lines3d``).

    Segments behind the camera, outside the image (Liang-Barsky on the rectangle from the outer edge of the
    first pixel to that of the last, [-0.5, width - 0.5]) or not ``visible`` are left out:
    ``project_segments`` (its near-plane cut) and the clip in one compiled pass (the search scores thousands
    of poses). ``chunks`` (of ``lines3d``; None: none): the segments of chunks wholly outside the view are
    passed over first (the same result, sooner on a large map).
    """
    lines3d = np.ascontiguousarray(lines3d, dtype=np.float64).reshape(-1, 6)
    mask = np.ones(len(lines3d), np.bool_) if visible is None else np.asarray(visible, dtype=np.bool_)
    T = np.ascontiguousarray(cam_from_world, dtype=np.float64)
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64)
    c = NO_CHUNKS if chunks is None else chunks
    return _project_clipped(
        lines3d, T, intrinsics, float(camera.width), float(camera.height), min_depth_m, mask, c.of, c.centre,
        c.half,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _project_clipped(
    lines3d: np.ndarray,
    T: np.ndarray,
    intrinsics: np.ndarray,
    width: float,
    height: float,
    near: float,
    visible: np.ndarray,
    chunk_of: np.ndarray,
    chunk_centre: np.ndarray,
    chunk_half: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``project_clipped``; the segments of the chunks (``chunk_of``: (M,) each segment's, or (0,): none;
    boxes ``chunk_centre`` +- ``chunk_half``) that ``chunks.kept_chunks`` leaves out are passed over: each
    lies outside the pyramid that the clipping below keeps inside, or nearer than ``near``."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    chunked = len(chunk_of) > 0
    kept = np.ones(0, np.bool_)
    if chunked:
        kept = kept_chunks(chunk_centre, chunk_half, T, intrinsics, width, height, near)
    out = np.empty((len(lines3d), 4))
    rows = np.empty(len(lines3d), np.int64)
    a, b = np.empty(3), np.empty(3)
    p, d, lo, hi = np.empty(2), np.empty(2), np.array([-0.5, -0.5]), np.array([width - 0.5, height - 0.5])
    n = 0
    for m in range(len(lines3d)):
        if not visible[m] or (chunked and not kept[chunk_of[m]]):
            continue
        for i in range(3):
            a[i] = T[i, 0] * lines3d[m, 0] + T[i, 1] * lines3d[m, 1] + T[i, 2] * lines3d[m, 2] + T[i, 3]
            b[i] = T[i, 0] * lines3d[m, 3] + T[i, 1] * lines3d[m, 4] + T[i, 2] * lines3d[m, 5] + T[i, 3]
        za, zb = a[2], b[2]
        if za < near and zb < near:
            continue
        if za < near or zb < near:  # cut at the near plane (clip_near)
            s = min(max((near - za) / (zb - za), 0.0), 1.0)
            for i in range(3):
                cut = a[i] + s * (b[i] - a[i])
                if za < near:
                    a[i] = cut
                else:
                    b[i] = cut
        za, zb = max(a[2], near), max(b[2], near)
        p[0], p[1] = fx * a[0] / za + cx, fy * a[1] / za + cy
        d[0], d[1] = fx * b[0] / zb + cx - p[0], fy * b[1] / zb + cy - p[1]
        t0, t1 = 0.0, 1.0  # Liang-Barsky on [-0.5, size - 0.5]
        for axis in range(2):
            if d[axis] != 0.0:
                e1, e2 = (lo[axis] - p[axis]) / d[axis], (hi[axis] - p[axis]) / d[axis]
                t0, t1 = max(t0, min(e1, e2)), min(t1, max(e1, e2))
            elif p[axis] < lo[axis] or p[axis] > hi[axis]:
                t0, t1 = 1.0, 0.0
        if not t1 > t0:
            continue
        out[n, 0], out[n, 1] = p[0] + t0 * d[0], p[1] + t0 * d[1]
        out[n, 2], out[n, 3] = p[0] + t1 * d[0], p[1] + t1 * d[1]
        rows[n] = m
        n += 1
    return out[:n].copy(), rows[:n].copy()


# ---------------------------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)
def _greedy(pairs: np.ndarray, n_image: int, n_map: int) -> np.ndarray:
    """Returns (P,) bool: the pairs, in the given order, whose image and map segments are both still free."""
    used_i = np.zeros(n_image, np.bool_)
    used_j = np.zeros(n_map, np.bool_)
    keep = np.zeros(len(pairs), np.bool_)
    for k in range(len(pairs)):
        i, j = pairs[k, 0], pairs[k, 1]
        if not used_i[i] and not used_j[j]:
            used_i[i] = True
            used_j[j] = True
            keep[k] = True
    return keep


@numba.njit(cache=True, nogil=True)
def _cover(seg: np.ndarray, length: float, p: np.ndarray, distance: float) -> tuple[float, float]:
    """Returns (lo, hi) px along image segment ``seg`` (4,) covered by projected segment ``p`` (4,), or
    (0, 0) when it does not cover: the shared stretch along the image segment, where the projected line
    must lie within ``distance`` of the image segment's line at both ends."""
    lo, hi, off_lo, off_hi = _overlap(seg, length, p)
    if hi <= lo or off_lo > distance or off_hi > distance:
        return 0.0, 0.0
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _overlap(seg: np.ndarray, length: float, p: np.ndarray) -> tuple[float, float, float, float]:
    """Returns (lo, hi, |offset at lo|, |offset at hi|): the stretch (px along image segment ``seg`` (4,))
    that projected segment ``p`` (4,) shares with it and p's distances from seg's line at its two ends
    (``_cover`` at any distance); (0, 0, inf, inf) when they share none."""
    ux = (seg[2] - seg[0]) / length
    uy = (seg[3] - seg[1]) / length
    s1 = (p[0] - seg[0]) * ux + (p[1] - seg[1]) * uy
    s2 = (p[2] - seg[0]) * ux + (p[3] - seg[1]) * uy
    e1 = (p[1] - seg[1]) * ux - (p[0] - seg[0]) * uy
    e2 = (p[3] - seg[1]) * ux - (p[2] - seg[0]) * uy
    lo = max(min(s1, s2), 0.0)
    hi = min(max(s1, s2), length)
    if hi <= lo or s1 == s2:
        return 0.0, 0.0, np.inf, np.inf
    slope = (e2 - e1) / (s2 - s1)
    return lo, hi, abs(e1 + slope * (lo - s1)), abs(e1 + slope * (hi - s1))


@numba.njit(cache=True, nogil=True)
def _covering_pairs(
    segments: np.ndarray,
    angles: np.ndarray,
    lengths: np.ndarray,
    grid_ptr: np.ndarray,
    grid_items: np.ndarray,
    grid_w: int,
    grid_px: float,
    projected: np.ndarray,
    distance: float,
    angle_tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((P,) image rows i, (P,) projected rows j, (P, 2) covered stretch along i) of every pair
    where projected segment j covers part of image segment i at an angle within ``angle_tol``.

    Candidates: the image segments listed in the grid cells of points every half cell along j (an image
    segment is listed wherever it passes within the grid's own ``ScoreConfig.distance_px + grid_px / 2``,
    so none that j passes within ``distance`` of is missed up to that reach). A wider ``distance`` (a local
    solve's first rounds) finds the pairs within the reach for certain and farther ones only where the
    cells happen to hold them: 20-36 px at the defaults. Looking in the rings of cells a wider distance
    needs was measured (session 57): 26 % more time on the paper scenes, no local solve's basin wider
    than a quarter metre on the street photos, the demo's answers the same (docs/measurements.md).
    """
    i, j, cover, _, _ = _covering_candidates(
        segments, angles, lengths, grid_ptr, grid_items, grid_w, grid_px, projected,
        _angle_limits(lengths, distance, angle_tol), distance,
    )  # fmt: skip
    return i, j, cover


@numba.njit(cache=True, nogil=True)
def _angle_limits(lengths: np.ndarray, distance: float, angle_tol: float) -> np.ndarray:
    """Returns (N,) the largest angle (rad) at which a projected segment may cover each image segment of
    ``lengths`` (N,): ``angle_tol``, or more for short segments, whose angles are as uncertain as the
    distance test allows at their ends."""
    out = np.empty(len(lengths))
    for i in range(len(lengths)):
        out[i] = max(angle_tol, np.arctan(2.0 * distance / lengths[i]))
    return out


@numba.njit(cache=True, nogil=True)
def _covering_candidates(
    segments: np.ndarray,
    angles: np.ndarray,
    lengths: np.ndarray,
    grid_ptr: np.ndarray,
    grid_items: np.ndarray,
    grid_w: int,
    grid_px: float,
    projected: np.ndarray,
    limits: np.ndarray,
    distance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``_covering_pairs`` at ``distance`` and (N,) per image segment angle ``limits`` (``_angle_limits``),
    with what a tighter test needs: returns ((P,) i, (P,) j, (P, 2) cover, (P,) angle between them (rad),
    (P, 2) |offsets| at the cover's ends). The pairs of any tighter tolerance are those passing it, in the
    same order (``_tighter``): one pass over the grid serves every tolerance a pose is tested at."""
    grid_h = (len(grid_ptr) - 1) // grid_w
    seen = np.full(len(segments), -1, np.int64)
    cap = 4 * (len(projected) + len(segments)) + 64
    out_i = np.empty(cap, np.int64)
    out_j = np.empty(cap, np.int64)
    out_c = np.empty((cap, 2))
    out_a = np.empty(cap)
    out_e = np.empty((cap, 2))
    cells = np.empty(256, np.int64)  # the cell of each sample along j (-1: outside the grid)
    n = 0
    for j in range(len(projected)):
        p = projected[j]
        dx, dy = p[2] - p[0], p[3] - p[1]
        length = np.hypot(dx, dy)
        if length == 0.0:
            continue
        angle = np.arctan2(dy, dx) % np.pi
        count = int(length / (0.5 * grid_px)) + 1
        if count + 1 > len(cells):
            cells = np.empty(2 * (count + 1), np.int64)
        for s in range(count + 1):  # without branches: the compiler runs it on vectors
            t = s / count
            c = int((p[0] + t * dx + 0.5) / grid_px)
            r = int((p[1] + t * dy + 0.5) / grid_px)
            inside = (r >= 0) & (r < grid_h) & (c >= 0) & (c < grid_w)
            cells[s] = r * grid_w + c if inside else -1
        last = -1
        for s in range(count + 1):
            cell = cells[s]
            if cell < 0 or cell == last:  # samples half a cell apart: its segments are all seen already
                continue
            last = cell
            for q in range(grid_ptr[cell], grid_ptr[cell + 1]):
                i = grid_items[q]
                if seen[i] == j:
                    continue
                seen[i] = j
                gap = abs(angles[i] - angle)
                gap = min(gap, np.pi - gap)
                if gap > limits[i]:
                    continue
                lo, hi, off_lo, off_hi = _overlap(segments[i], lengths[i], p)
                if hi <= lo or off_lo > distance or off_hi > distance:
                    continue
                if n == cap:
                    cap *= 2
                    out_i, out_j, out_a = grow(out_i, cap), grow(out_j, cap), grow(out_a, cap)
                    out_c, out_e = _grow_2(out_c, cap), _grow_2(out_e, cap)
                out_i[n], out_j[n], out_a[n] = i, j, gap
                out_c[n, 0], out_c[n, 1] = lo, hi
                out_e[n, 0], out_e[n, 1] = off_lo, off_hi
                n += 1
    return out_i[:n].copy(), out_j[:n].copy(), out_c[:n].copy(), out_a[:n].copy(), out_e[:n].copy()


@numba.njit(cache=True, nogil=True)
def _tighter(
    i: np.ndarray,
    gap: np.ndarray,
    offsets: np.ndarray,
    lengths: np.ndarray,
    distance: float,
    angle_tol: float,
) -> np.ndarray:  # pragma: no cover - numba
    """Returns the indices of the ``_covering_candidates`` (their (P,) image rows i, angles and (P, 2)
    offsets) that pass ``_covering_pairs``' test at ``distance`` and ``angle_tol``, in order."""
    limits = _angle_limits(lengths, distance, angle_tol)
    keep = np.empty(len(i), np.int64)
    n = 0
    for k in range(len(i)):
        if gap[k] > limits[i[k]] or offsets[k, 0] > distance or offsets[k, 1] > distance:
            continue
        keep[n] = k
        n += 1
    return keep[:n].copy()


@numba.njit(cache=True, nogil=True)
def grow(a: np.ndarray, cap: int) -> np.ndarray:
    """Returns a 1-D array of ``cap`` slots of ``a``'s dtype starting with ``a`` (compiled kernels' buffers)."""
    out = np.empty(cap, a.dtype)
    for i in range(len(a)):  # a loop: a slice copy costs seconds of compile in every caller's types
        out[i] = a[i]
    return out


@numba.njit(cache=True, nogil=True)
def _grow_2(a: np.ndarray, cap: int) -> np.ndarray:
    out = np.empty((cap, 2))
    for i in range(len(a)):
        out[i, 0], out[i, 1] = a[i, 0], a[i, 1]
    return out


@numba.njit(cache=True, nogil=True)
def _union_lengths(i: np.ndarray, cover: np.ndarray, n: int) -> np.ndarray:
    """Returns (n,) the length of the union of the covered stretches (P, 2) of each image segment ``i``."""
    out = np.zeros(n)
    if len(i) == 0:
        return out
    order = stable_argsort(i * 1e7 + cover[:, 0])  # by segment, then start (stretches are < 1e7 px)
    current, start, end = -1, 0.0, 0.0
    for k in order:
        if i[k] != current:
            if current >= 0:
                out[current] += end - start
            current, start, end = i[k], cover[k, 0], cover[k, 1]
        elif cover[k, 0] > end:
            out[current] += end - start
            start, end = cover[k, 0], cover[k, 1]
        else:
            end = max(end, cover[k, 1])
    out[current] += end - start
    return out


def coverable_length(
    image: ImageLines,
    camera: Camera,
    cam_from_world: np.ndarray,
    parts: np.ndarray,
    surfaces: np.ndarray | None,
    config: ScoreConfig,
) -> float:
    """Returns the image's line length (px) lying where a map could explain it at a pose: within the score's
    distance of the projected (K, 6) world map ``parts`` the pose sees, or of the map's surfaces
    (``surfaces``: (h, w) bool cells of ``distance_px`` pixels whose ray meets one, ``Visibility.footprint``).
    A map without surfaces (None) says nothing of what it covers: the whole image's line length.

    A single LiDAR sweep covers the lower half of a street photo: the image lines above it (trees, upper
    facades, the sky's wires) are beyond what any pose could explain with it."""
    if surfaces is None:
        return image.total_length
    cell = config.distance_px
    mask = surfaces.copy()
    projected, _ = project_clipped(parts, camera, cam_from_world, config.min_depth_m)
    if len(projected):  # every half cell along each projected part (cells as ``_in_cells`` reads them)
        _, points = _points_along(projected, 0.5 * cell)
        c = ((points[:, 0] + 0.5) / cell).astype(np.int64)
        r = ((points[:, 1] + 0.5) / cell).astype(np.int64)
        inside = (r >= 0) & (r < mask.shape[0]) & (c >= 0) & (c < mask.shape[1])
        mask[r[inside], c[inside]] = True
    # a line within the score's distance (one cell) of a marked cell could be explained
    mask = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return _length_in_cells(image.segments, mask, cell, summed_area(mask))


def summed_area(mask: np.ndarray) -> np.ndarray:
    """Returns (h + 1, w + 1) int64: the count of True cells of (h, w) ``mask`` above and left of each corner."""
    out = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), np.int64)
    out[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0, dtype=np.int64), axis=1)
    return out


@numba.njit(cache=True, nogil=True)
def _length_in_cells(projected: np.ndarray, mask: np.ndarray, cell: float, counts: np.ndarray) -> float:
    """Returns the length (px) of (K, 4) segments inside the True cells of ``mask``, sampled every half cell
    (``counts``: its ``summed_area``; a segment whose box holds no True cell is not sampled)."""
    total = 0.0
    for k in range(len(projected)):
        if _may_touch(projected[k], counts, cell, 0.0, 0.0, 0.0, 0.0):
            total = _in_cells(projected[k], mask, cell, total)
    return total


@numba.njit(cache=True, nogil=True)
def _in_cells(p: np.ndarray, mask: np.ndarray, cell: float, total: float) -> float:
    """Returns ``total`` plus the length (px) of segment (4,) ``p`` inside the True cells of ``mask``, sampled
    every half cell (added sample by sample: a sum over segments comes out the same whichever are skipped)."""
    h, w = mask.shape
    length = np.hypot(p[2] - p[0], p[3] - p[1])
    count = max(int(np.ceil(length / (0.5 * cell))), 1)
    step = length / count
    for s in range(count):
        t = (s + 0.5) / count
        c = int((p[0] + t * (p[2] - p[0]) + 0.5) / cell)
        r = int((p[1] + t * (p[3] - p[1]) + 0.5) / cell)
        if 0 <= r < h and 0 <= c < w and mask[r, c]:
            total += step
    return total


@numba.njit(cache=True, nogil=True)
def _may_touch(
    p: np.ndarray, counts: np.ndarray, cell: float, x0: float, y0: float, x1: float, y1: float
) -> bool:
    """Returns False if segment (4,) ``p`` moved by any shift in [x0, x1] x [y0, y1] px samples no True
    cell (``_in_cells``): no True cell (``counts``: ``summed_area``) in the cells of its box, widened by a
    pixel for the samples' rounding (a cell index truncates, as ``_in_cells``' does: monotone in x)."""
    h, w = counts.shape[0] - 1, counts.shape[1] - 1
    c0 = max(int((min(p[0], p[2]) + x0 - 1.0 + 0.5) / cell), 0)
    c1 = min(int((max(p[0], p[2]) + x1 + 1.0 + 0.5) / cell), w - 1)
    r0 = max(int((min(p[1], p[3]) + y0 - 1.0 + 0.5) / cell), 0)
    r1 = min(int((max(p[1], p[3]) + y1 + 1.0 + 0.5) / cell), h - 1)
    if c0 > c1 or r0 > r1:
        return False
    return counts[r1 + 1, c1 + 1] - counts[r0, c1 + 1] - counts[r1 + 1, c0] + counts[r0, c0] > 0


@numba.njit(cache=True, nogil=True)
def _shifted_values(
    segments: np.ndarray,
    angles: np.ndarray,
    lengths: np.ndarray,
    empty: np.ndarray,
    empty_sum: np.ndarray,
    cell_px: float,
    projected: np.ndarray,
    shifts: np.ndarray,
    distance: float,
    angle_tol: float,
    weight: float,
) -> np.ndarray:
    """The score value of ``projected`` moved by each shift (``shifted_values``): the pairs of
    ``_covering_pairs`` at each shift, found among the pairs that some shift can bring within ``distance``
    (their boxes within ``distance`` plus the longest shift) at an angle the test can pass (a shift keeps a
    segment's direction; the test itself is made on the shifted coordinates, as ``_covering_pairs`` does)."""
    out = np.empty(len(shifts))
    moved = np.empty_like(projected)
    reach = 0.0
    for k in range(len(shifts)):
        reach = max(reach, np.hypot(shifts[k, 0], shifts[k, 1]))
    # the segments some shift brings near an empty cell: the only ones the penalty samples
    x0, y0 = shifts[:, 0].min() if len(shifts) else 0.0, shifts[:, 1].min() if len(shifts) else 0.0
    x1, y1 = shifts[:, 0].max() if len(shifts) else 0.0, shifts[:, 1].max() if len(shifts) else 0.0
    touching = np.empty(len(projected), np.int64)
    n_touching = 0
    for j in range(len(projected)):
        if _may_touch(projected[j], empty_sum, cell_px, x0, y0, x1, y1):
            touching[n_touching] = j
            n_touching += 1
    margin = distance + reach + 1e-6
    slack = 1e-6  # the angle of a shifted segment may differ from its own in the last bits
    cand_i = np.empty(len(segments) * len(projected) + 1, np.int64)
    cand_j = np.empty(len(segments) * len(projected) + 1, np.int64)
    n_cand = 0
    for j in range(len(projected)):
        p = projected[j]
        dx, dy = p[2] - p[0], p[3] - p[1]
        angle = np.arctan2(dy, dx) % np.pi
        x0, x1 = min(p[0], p[2]) - margin, max(p[0], p[2]) + margin
        y0, y1 = min(p[1], p[3]) - margin, max(p[1], p[3]) + margin
        for i in range(len(segments)):
            q = segments[i]
            if max(q[0], q[2]) < x0 or min(q[0], q[2]) > x1 or max(q[1], q[3]) < y0 or min(q[1], q[3]) > y1:
                continue
            gap = abs(angles[i] - angle)
            if min(gap, np.pi - gap) > max(angle_tol, np.arctan(2.0 * distance / lengths[i])) + slack:
                continue
            cand_i[n_cand], cand_j[n_cand] = i, j
            n_cand += 1
    # a shift moves a pair's offsets from the image segment's line (``_cover``'s e1, e2) by its component
    # along the segment's normal alike: a pair covers only where that component brings the nearer offset
    # within ``distance`` (a necessary test; the pair's own test decides), so most pairs are passed over at
    # most shifts without their angle or cover being computed
    band = np.empty((n_cand + 1, 2))
    normal = np.empty((n_cand + 1, 2))
    tol = np.empty(n_cand + 1)
    for c in range(n_cand):
        q, p = segments[cand_i[c]], projected[cand_j[c]]
        ux = (q[2] - q[0]) / lengths[cand_i[c]]
        uy = (q[3] - q[1]) / lengths[cand_i[c]]
        e1 = (p[1] - q[1]) * ux - (p[0] - q[0]) * uy
        e2 = (p[3] - q[1]) * ux - (p[2] - q[0]) * uy
        band[c, 0], band[c, 1] = -distance - max(e1, e2) - 1e-6, distance - min(e1, e2) + 1e-6
        normal[c, 0], normal[c, 1] = -uy, ux
        tol[c] = max(angle_tol, np.arctan(2.0 * distance / lengths[cand_i[c]]))
    pair_i = np.empty(n_cand + 1, np.int64)
    cover = np.empty((n_cand + 1, 2))
    seg_angle = np.empty(len(projected))
    seg_ok = np.empty(len(projected), np.bool_)
    seen = np.full(len(projected), -1, np.int64)  # the shift a moved segment's angle was computed for
    for k in range(len(shifts)):
        sx, sy = shifts[k, 0], shifts[k, 1]
        for j in range(len(projected)):
            moved[j, 0] = projected[j, 0] + sx
            moved[j, 1] = projected[j, 1] + sy
            moved[j, 2] = projected[j, 2] + sx
            moved[j, 3] = projected[j, 3] + sy
        n = 0
        for c in range(n_cand):
            b = sx * normal[c, 0] + sy * normal[c, 1]
            if b < band[c, 0] or b > band[c, 1]:
                continue
            i, j = cand_i[c], cand_j[c]
            if seen[j] != k:
                dx, dy = moved[j, 2] - moved[j, 0], moved[j, 3] - moved[j, 1]
                seg_ok[j] = np.hypot(dx, dy) != 0.0
                seg_angle[j] = np.arctan2(dy, dx) % np.pi
                seen[j] = k
            if not seg_ok[j]:
                continue
            gap = abs(angles[i] - seg_angle[j])
            if min(gap, np.pi - gap) > tol[c]:
                continue
            lo, hi = _cover(segments[i], lengths[i], moved[j], distance)
            if hi > lo:
                pair_i[n] = i
                cover[n, 0], cover[n, 1] = lo, hi
                n += 1
        explained = _union_lengths(pair_i[:n], cover[:n], len(segments)).sum()
        unexplained = _length_in_cells(moved[touching[:n_touching]], empty, cell_px, empty_sum)
        out[k] = explained - weight * unexplained
    return out


def _segment_grid(
    lines2d: np.ndarray, width: int, height: int, cell: float, distance_px: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (ptr, items, grid width) of the CSR table: the segments passing within ``distance_px +
    cell / 2`` of each cell of a ``cell`` px raster (sampled every quarter cell, each sample marking the
    cells of its dilated box)."""
    w, h = int(np.ceil((width + 0.5) / cell)), int(np.ceil((height + 0.5) / cell))
    reach = distance_px + 0.5 * cell
    owner, points = _points_along(lines2d, 0.25 * cell)
    keys = []
    for ox in (-reach, 0.0, reach):
        for oy in (-reach, 0.0, reach):
            c = np.floor((points[:, 0] + ox + 0.5) / cell).astype(np.int64)
            r = np.floor((points[:, 1] + oy + 0.5) / cell).astype(np.int64)
            ok = (c >= 0) & (c < w) & (r >= 0) & (r < h)
            keys.append((r[ok] * w + c[ok]) * len(lines2d) + owner[ok])
    pairs = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    cells, items = np.divmod(pairs, max(len(lines2d), 1))
    ptr = np.searchsorted(cells, np.arange(w * h + 1)).astype(np.int64)
    return ptr, items.astype(np.int64), w


def _points_along(lines2d: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P,) int64 the segment of each point, (P, 2) points) along (N, 4) segments, both ends
    included, at most ``spacing`` apart."""
    count = np.maximum(np.ceil(segment_lengths(lines2d) / spacing).astype(np.int64), 1) + 1
    owner = np.repeat(np.arange(len(lines2d)), count)
    t = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)) / (count[owner] - 1)
    return owner, lines2d[owner, 0:2] + t[:, None] * (lines2d[owner, 2:4] - lines2d[owner, 0:2])


def _empty_cells(lines2d: np.ndarray, width: int, height: int, radius_px: float) -> tuple[np.ndarray, float]:
    """Returns ((h, w) bool cells farther than ``radius_px`` from every segment, cell size px)."""
    cell = max(radius_px / CELLS_PER_RADIUS, 1.0)
    h, w = int(np.ceil((height + 0.5) / cell)), int(np.ceil((width + 0.5) / cell))
    occupied = np.zeros((h, w), np.uint8)
    if len(lines2d):
        length = segment_lengths(lines2d)
        count = np.maximum(np.ceil(length / (0.5 * cell)).astype(np.int64), 1)
        owner = np.repeat(np.arange(len(lines2d)), count)
        t = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + 0.5) / count[owner]
        points = lines2d[owner, 0:2] + t[:, None] * (lines2d[owner, 2:4] - lines2d[owner, 0:2])
        c = np.clip(((points[:, 0] + 0.5) / cell).astype(np.int64), 0, w - 1)
        r = np.clip(((points[:, 1] + 0.5) / cell).astype(np.int64), 0, h - 1)
        occupied[r, c] = 1
    else:
        return np.ones((h, w), bool), cell
    distance = cv2.distanceTransform(1 - occupied, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return distance * cell > radius_px, cell
