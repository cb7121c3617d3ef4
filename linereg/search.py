"""The pose search: for each rotation candidate, every image point votes for the camera centres it allows.

Under a rotation R, an image point (a corner or a free segment end, ``points.py``) whose arms agree with
those of a map point X can only be X's image if the camera centre lies on the ray ``X - lambda r`` through
it (r: the point's viewing ray, in world coordinates). Every such pair votes along its ray in a voxel grid
over the search region, each image point at most once per voxel; where the rays of many image points meet,
the camera is. No pair is left out: the votes are exhaustive over point correspondences, and a point need
not be the end of a whole segment (a corner stays where it is when LSD breaks or shortens a line).

The best voxels of each rotation (local maxima) are then solved locally: the score's covering pairs at a
tolerance spanning the voxel, Gauss-Newton on the endpoint-to-line distances for the whole pose (rotation
too: a candidate rotation from vanishing directions is off by a degree or two), the tolerance shrinking
to the score's own. What comes out are scored poses; the composer refines the best and decides.
"""

from __future__ import annotations

import itertools
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numba
import numpy as np

from .camera import Camera
from .chunks import NO_CHUNKS, Chunks
from .config import ScoreConfig, SearchConfig
from .geometry import camera_center, make_cam_from_world, rotation_error_deg
from .kernels import invert_rigid, jacobi_rotation, numpy_sum, prefetch, stable_argsort
from .points import Points
from .score import (
    ImageLines,
    Score,
    _angle_limits,
    _covering_candidates,
    _covering_pairs,
    _greedy,
    _length_in_cells,
    _project_clipped,
    _tighter,
    _union_lengths,
    grow,
)
from .threads import map_threads, run_parallel, thread_count

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Found:
    """A pose the search solved: (4, 4) cam_from_world, its Score and the rotation candidate it came from."""

    cam_from_world: np.ndarray
    score: Score
    rotation: int

    @property
    def centre(self) -> np.ndarray:
        return camera_center(self.cam_from_world)


@dataclass
class SearchStats:
    """What the search did: rays voted, voxels of the grid and their size, peaks solved."""

    rays: int = 0
    voxels: int = 0
    voxel_m: float = 0.0
    solved: int = 0
    per_rotation: list[int] = field(default_factory=list)


def search(
    image: ImageLines,
    image_pts: Points,
    lines3d: np.ndarray,
    map_pts: Points,
    signatures: MapSignatures,
    camera: Camera,
    rotations: list[np.ndarray],
    regions: list[tuple[np.ndarray, np.ndarray]],
    config: SearchConfig,
    score_config: ScoreConfig,
    visible: np.ndarray | None = None,
    seen_score: Callable[[np.ndarray], Score] | None = None,
    chunks: Chunks | None = None,
) -> tuple[list[Found], SearchStats]:
    """Returns (the solved poses, best score first; SearchStats) for camera centres in ``regions`` (boxes
    ((3,) low, (3,) high corner) in world metres, each voted on its own grid: a box near the map gets fine
    voxels, a wider one around it coarser ones) and each (3, 3) world -> camera rotation in ``rotations``.

    image, image_pts: the image side; lines3d, map_pts, signatures: (M, 6) world map segments, their points
    and those grouped by arm directions (``map_signatures``);
    camera: undistorted; visible: (M,) bool of segments that take part in the score (None: all);
    seen_score: a pose's Score with what the map's surfaces hide from it (``pipeline.view_score``; None: the
    map hides nothing): the poses are ranked by it (a pose of the truth is scored with the facades behind
    the building hidden, the same pose unhidden can score below zero); chunks: of ``lines3d`` (None: none),
    for the local solves' projections (``score.project_clipped``).
    """
    boxes = []
    for lo, hi in regions:
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        voxel = float(np.cbrt(np.prod(np.maximum(hi - lo, 1e-9)) / config.voxels))
        boxes.append((lo, hi, voxel, np.maximum(np.ceil((hi - lo) / voxel).astype(np.int64), 1)))
    stats = SearchStats(voxels=sum(int(np.prod(b[3])) for b in boxes), voxel_m=boxes[0][2])
    peaks, rays_of = _vote_peaks(image_pts, map_pts, signatures, camera, rotations, boxes, config)
    stats.rays, stats.per_rotation = int(rays_of.sum()), [int(n) for n in rays_of]
    # a symmetric building gives every rotation as many votes as the truth: each fine peak gets a quick
    # solve (``quick_rounds`` rounds from pairs at a tolerance spanning its voxel and the rotation's error),
    # is scored at the score's own tolerance, and the best of those are solved fully
    quick = replace(config, solve_rounds=config.quick_rounds)
    starts = [
        (make_cam_from_world(rotations[r], -rotations[r] @ centre), size) for _, r, centre, size in peaks
    ]
    solved = solve_all(starts, image, lines3d, camera, quick, score_config, visible, chunks)
    stats.solved += len(peaks)
    screened = [
        (s[1], r, s[0], size) for s, (_, r, _, size) in zip(solved, peaks, strict=True) if s is not None
    ]
    best = screen(screened, config, seen_score)
    starts = [(pose, 0.5 * size) for _, _, pose, size in best]
    solved = solve_all(starts, image, lines3d, camera, config, score_config, visible, chunks)
    found = [
        Found(s[0], s[1] if seen_score is None else seen_score(s[0]), r)
        for s, (_, r, _, _) in zip(solved, best, strict=True)
        if s is not None
    ]
    found.sort(key=lambda p: -p.score.value)
    return found, stats


_Box = tuple[np.ndarray, np.ndarray, float, np.ndarray]  # (low corner, high corner, voxel m, (3,) voxels)
_Peak = tuple[float, int, np.ndarray, float]  # (votes, rotation, (3,) centre, voxel m) of a fine peak


def _vote_peaks(
    image_pts: Points,
    map_pts: Points,
    signatures: MapSignatures,
    camera: Camera,
    rotations: list[np.ndarray],
    boxes: list[_Box],
    config: SearchConfig,
) -> tuple[list[_Peak], np.ndarray]:
    """Returns (the fine peaks of every rotation and box, rotation by rotation, box by box; (R,) the rays
    each rotation voted with): for each box, coarse votes over the whole box, then finer ones round its
    best coarse voxels.

    The (rotation, box) votes run in threads (the kernels release the GIL), each on grids of its own, each
    taken by the first thread free (dealt by rotation, 7 rotations left one of 2 threads idle for a
    rotation's two boxes); a rotation's rays are made by the first of its votes taken. A box's peaks do not
    depend on which thread voted it."""
    workers = thread_count(min(config.max_threads, len(rotations)))
    rays: list[tuple[np.ndarray, ...] | None] = [None for _ in rotations]
    locks = [threading.Lock() for _ in rotations]
    # box by box: two threads starting on one rotation's two boxes waited for its rays one after the other
    tasks = [(r, b) for b in range(len(boxes)) for r in range(len(rotations))]
    found: list[list[list[_Peak]]] = [[[] for _ in boxes] for _ in rotations]
    taken = itertools.count()  # the next task; next() on it is atomic under the GIL

    def rays_of_rotation(r: int) -> tuple[np.ndarray, ...]:
        with locks[r]:  # made once, by the first of the rotation's tasks taken
            made = rays[r]
            if made is None:
                made = rays[r] = _pair_rays(
                    image_pts, map_pts, signatures, camera, rotations[r], config, boxes
                )
            return made

    def vote(worker: int) -> None:
        # one grid per thread serves every box in turn (a vote clears the last one's); kept between searches
        grid = _Grid.take(max(int(np.prod(box[3])) for box in boxes))
        fine = _FineGrids(config.coarse_peaks, config.fine_voxels)
        while (t := next(taken)) < len(tasks):
            r, b = tasks[t]
            ray_set = rays_of_rotation(r)
            lo, _, voxel, _ = boxes[b]
            near = config.min_range_voxels * voxel
            grid.vote(boxes[b], ray_set, map_pts.positions, image_pts.weight, near)
            centres, _ = _peaks(grid.votes, lo, voxel, config.coarse_peaks, grid.voted)
            half = config.fine_span * voxel
            fine_votes = fine.vote(centres, half, ray_set, map_pts.positions, image_pts.weight, near)
            found[r][b] = [(v, r, centre, size) for centre, v, size in fine_votes]
        grid.give_back()  # not after an error: its votes may be half cleared

    run_parallel(vote, workers)
    rays_of = np.array([0 if made is None else len(made[0]) for made in rays], np.int64)
    return [p for by_box in found for peaks in by_box for p in peaks], rays_of


_Screened = tuple[Score, int, np.ndarray, float]  # (score, rotation, pose, voxel size) of a quick solve


def screen(
    screened: list[_Screened], config: SearchConfig, seen_score: Callable[[np.ndarray], Score] | None
) -> list[_Screened]:
    """Returns the ``peaks`` quick solves to solve fully: the best scoring, by ``seen_score`` where given.

    A pose's explained length with every map segment bounds its score with what the surfaces hide
    (hiding removes map lines: it can only lower what they explain and what they predict in empty areas),
    so the poses are scored with occlusion in the order of that bound until it falls below
    ``screen_fraction`` of the best so far: none left out could come that close. The places left are
    filled in the order of the bound. Not quite a bound: a segment cut into visible parts can cover a
    stretch of an image segment that the whole does not (``score._cover`` takes a shared stretch whole or
    not at all), so 13 of a crossroad photo's 377 quick solves explained up to 236 px more with occlusion
    than without (docs/measurements.md, session 40)."""
    if seen_score is None:
        return _one_each(sorted(screened, key=lambda p: -p[0].value), config)
    bound = np.array([s[0].explained_length for s in screened])
    order = np.argsort(-bound, kind="stable")
    seen: list[_Screened] = []
    top = -np.inf
    for k in order:
        if bound[k] < config.screen_fraction * top:
            break
        score, r, pose, size = screened[k]
        score = seen_score(pose)
        top = max(top, score.value)
        seen.append((score, r, pose, size))
    seen.sort(key=lambda p: -p[0].value)
    rest = [screened[k] for k in order[len(seen) :]]
    return _one_each(seen + rest, config)


def _one_each(ranked: list[_Screened], config: SearchConfig) -> list[_Screened]:
    """Returns the first ``peaks`` of the ranked quick solves that are not the same pose as a better one
    kept: rotations within ``rotation_slack_deg`` and centres within the larger fine voxel (the full solve
    would take both to one place; peaks of one camera often converge together and took the places of the
    poses the decision needs as rivals)."""
    kept: list[_Screened] = []
    centres: list[np.ndarray] = []  # of the poses kept
    for item in ranked:
        _, _, pose, size = item
        centre = camera_center(pose)
        # the centres first: the cheaper test, and the one most pairs fail
        if any(
            np.linalg.norm(centre - other_centre) <= max(size, other_size)
            and rotation_error_deg(pose[:3, :3], other[:3, :3]) <= config.rotation_slack_deg
            for (_, _, other, other_size), other_centre in zip(kept, centres, strict=True)
        ):
            continue
        kept.append(item)
        centres.append(centre)
        if len(kept) == config.peaks:
            break
    return kept


def solve_all(
    starts: list[tuple[np.ndarray, float]],
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    config: SearchConfig,
    score_config: ScoreConfig,
    visible: np.ndarray | None,
    chunks: Chunks | None = None,
) -> list[tuple[np.ndarray, Score] | None]:
    """Returns ``solve_locally`` of each (start pose, size) in order, the starts shared among threads as
    the rotations are (the compiled kernels release the GIL; each result depends on its start alone)."""

    def solve(start: tuple[np.ndarray, float]) -> tuple[np.ndarray, Score] | None:
        return solve_locally(image, lines3d, camera, *start, config, score_config, visible, chunks)

    return map_threads(solve, starts, config.max_threads)


@dataclass(frozen=True)
class MapSignatures:
    """The map points grouped by the direction clusters of their arms, so that the image points of a
    rotation find their compatible map points without testing every pair.

    order: (K,) map point indices sorted by key; keys: (K,) sorted keys (two arms: ``lo * 2C + hi`` of the
    arm codes ``2 c + (arm against cluster c's direction)``, ``lo <= hi``; one arm: ``(2C)^2 + code``; -1:
    an arm outside every cluster); swapped: (K,) True where the canonical order swaps the point's arms;
    codes: (K, 2) each point's arm codes in point order (-1: an arm outside every cluster, -2: no arm).
    """

    order: np.ndarray
    keys: np.ndarray
    swapped: np.ndarray
    directions: np.ndarray
    loose: np.ndarray  # map points with an arm outside every cluster: tested one by one
    codes: np.ndarray


def map_signatures(map_pts: Points, labels: np.ndarray, directions: np.ndarray) -> MapSignatures:
    """Returns the MapSignatures of map points whose arms lie on segments with cluster ``labels`` (M,)
    (-1: none) of the (C, 3) cluster ``directions``."""
    seg = map_pts.arm_segments
    label = np.where(seg >= 0, labels[np.maximum(seg, 0)], -2) if len(labels) else np.full(seg.shape, -2)
    label = np.where((seg >= 0) & (label < 0), -1, label)  # -1: an arm outside every cluster, -2: no arm
    arms = np.nan_to_num(map_pts.arms)
    dirs = directions[np.maximum(label, 0)] if len(directions) else np.zeros((*seg.shape, 3))
    against = np.einsum("kad,kad->ka", arms, dirs) < 0
    code = np.where(label >= 0, 2 * label + against, label)
    nc = 2 * len(directions)
    two = seg[:, 1] >= 0
    loose = (label[:, 0] == -1) | (two & (label[:, 1] == -1))
    swapped = two & (code[:, 0] > code[:, 1])
    lo_code = np.where(swapped, code[:, 1], code[:, 0])
    hi_code = np.where(swapped, code[:, 0], code[:, 1])
    keys = np.where(two, lo_code * nc + hi_code, nc * nc + code[:, 0])
    keys = np.where(loose, -1, keys)
    order = np.argsort(keys, kind="stable")
    return MapSignatures(
        order, keys[order], swapped, directions, np.flatnonzero(loose), code.astype(np.int64)
    )


RAY_BUFFER = 256  # the voxels a ray's votes look up at a time (``_ray``): about a ray's samples
PREFETCH_AHEAD = 16  # ``_top_pooled`` asks for the vote this many voxels ahead of the one it reads
GRID_ROOM = 25  # a new grid holds 1 / GRID_ROOM more voxels than asked for (``_Grid.take``)
GRIDS_KEPT = 4  # vote grids kept between searches (one per search thread: ``SearchConfig.max_threads``)
_kept_grids: list[_Grid] = []
_kept_lock = threading.Lock()


class _Grid:
    """Votes in a voxel grid over a box, ``size`` voxels at most: accumulator, the ids of the image and the
    map point that voted last in each voxel (one vote per image point and voxel, and per map point and
    voxel; ids start at 1 and grow with every vote pass, so stamps need no reset: an id from an earlier
    pass never equals a later one; 0 is no vote), and the voxels voted in, in the order they were first
    voted (the rays reach 1-2 % of the voxels: clearing the votes and finding their peaks reads only those).

    All start as zeros, which the system maps lazily: a grid costs the memory its rays reach, but a fresh
    one pays a page fault for every page they reach (a copy search's 2 rotations voted in 0.1 s, 0.02 s in a
    kept grid). So each search thread takes one grid for all its boxes, kept between searches (``take``,
    ``give_back``): each box gets the votes a fresh grid would give it. On the demo a process's peak memory
    fell by ~0.15 GB (one grid per thread, not per box) and it keeps ~0.2 GB more between queries."""

    def __init__(self, size: int) -> None:
        self.accumulator = np.zeros(size, np.float32)
        self.stamp = np.zeros(size, np.int32)
        self.stamp_map = np.zeros(size, np.int32)
        self.touched = np.zeros(size, np.int32)  # each voxel enters once: it never overflows
        self.count = np.zeros(1, np.int64)
        self.next_id = self.next_map_id = 1
        self.dims = np.zeros(3, np.int64)  # the box of the last vote

    @staticmethod
    def take(size: int) -> _Grid:
        """Returns a kept grid of at least ``size`` voxels, or a new one with room to spare."""
        with _kept_lock:
            for k, grid in enumerate(_kept_grids):
                if len(grid.accumulator) >= size:
                    return _kept_grids.pop(k)
        # a box's voxels are ``SearchConfig.voxels`` rounded up on each axis: up to ~1.5 % more, varying
        # from map to map and with a prior, and a grid of exactly one box's size was outgrown by the next
        # query's (2 of the paper scenes' 20 queries paid a fresh grid's page faults, 40 ms); the room
        # costs address space only (the pages the rays reach are the memory)
        return _Grid(size + size // GRID_ROOM)

    def give_back(self) -> None:
        """Keeps the grid for a later search (at most ``GRIDS_KEPT``, the largest)."""
        with _kept_lock:
            _kept_grids.append(self)
            _kept_grids.sort(key=lambda g: -len(g.accumulator))
            del _kept_grids[GRIDS_KEPT:]

    def vote(
        self,
        box: tuple[np.ndarray, np.ndarray, float, np.ndarray],
        rays: tuple[np.ndarray, ...],
        positions: np.ndarray,
        weight: np.ndarray,
        lam_min: float,
    ) -> None:
        """Clears the votes, then lets every ray ``(k, m, lambda_max, direction)`` vote where it crosses the
        box ``(lo, hi, voxel, dims)``, farther than ``lam_min`` from its map point."""
        lo, hi, voxel, dims = box
        if int(np.prod(dims)) > len(self.accumulator):
            raise ValueError(f"a box of {int(np.prod(dims))} voxels in a grid of {len(self.accumulator)}")
        _clear(self.accumulator, self.voted)
        self.count[0] = 0
        k, m, lam_max, direction = rays
        ids = int(k.max()) + 1 if len(k) else 0
        if max(self.next_id + ids, self.next_map_id + len(positions)) >= np.iinfo(np.int32).max:
            self.stamp[:], self.stamp_map[:] = 0, 0  # ids would wrap: start them again
            self.next_id = self.next_map_id = 1
        self.dims = np.asarray(dims, dtype=np.int64)
        _vote_rays(
            k, m, lam_max, direction, positions, weight, lo, hi, voxel, self.dims, self.accumulator,
            self.stamp, self.stamp_map, self.touched, self.count, self.next_id, self.next_map_id, lam_min,
        )  # fmt: skip
        self.next_id += ids
        self.next_map_id += len(positions)

    @property
    def votes(self) -> np.ndarray:
        """The last box's votes, (dims) float32."""
        return self.accumulator[: int(np.prod(self.dims))].reshape(self.dims)

    @property
    def voted(self) -> np.ndarray:
        """Returns the (V,) flat indices of the voxels with votes, each once."""
        return self.touched[: self.count[0]]


@numba.njit(cache=True, nogil=True)
def _clear(accumulator: np.ndarray, voted: np.ndarray) -> None:  # pragma: no cover - numba
    """Sets ``accumulator`` (flat) to 0 at the (V,) indices ``voted`` (scattered: each is requested a few
    indices ahead, ``PREFETCH_AHEAD``)."""
    for j in range(len(voted)):
        if j + PREFETCH_AHEAD < len(voted):
            prefetch(accumulator, voted[j + PREFETCH_AHEAD])
        accumulator[voted[j]] = 0.0


class _FineGrids:
    """Cubic grids of ``side``**3 voxels round up to ``count`` coarse peaks, voted in one pass over the rays
    (a ray is tested against each box; each grid keeps its own votes and stamps, as a ``_Grid`` would)."""

    def __init__(self, count: int, side: int) -> None:
        self.side = side
        self.accumulator = np.zeros((count, side**3), np.float32)
        self.stamp = np.zeros((count, side**3), np.int32)
        self.stamp_map = np.zeros((count, side**3), np.int32)
        self.touched = np.zeros((count, side**3), np.int32)
        self.count = np.zeros(count, np.int64)
        self.next_id = self.next_map_id = 1

    def vote(
        self,
        centres: np.ndarray,
        half: float,
        rays: tuple[np.ndarray, ...],
        positions: np.ndarray,
        weight: np.ndarray,
        lam_min: float,
    ) -> list[tuple[np.ndarray, float, float]]:
        """Returns (centre, votes, voxel size) of the best voxel (``_peaks``) of the grid spanning
        ``centre +- half`` round each (B, 3) centre, for those with votes."""
        n = len(centres)
        lo = np.ascontiguousarray(centres - half, dtype=np.float64).reshape(-1, 3)
        hi = np.ascontiguousarray(centres + half, dtype=np.float64).reshape(-1, 3)
        voxel = np.max(hi - lo, axis=1) / self.side
        dims = np.full(3, self.side, dtype=np.int64)
        self.accumulator[:n] = 0.0
        self.count[:] = 0
        k, m, lam_max, direction = rays
        _vote_boxes(
            k, m, lam_max, direction, positions, weight, lo, hi, voxel, dims, self.accumulator,
            self.stamp, self.stamp_map, self.touched, self.count, self.next_id, self.next_map_id, lam_min,
        )  # fmt: skip
        self.next_id += int(k.max()) + 1 if len(k) else 0
        self.next_map_id += len(positions)
        boxes, best, votes = _best_in_boxes(
            self.accumulator, self.touched, self.count, n, self.side, lo, voxel
        )
        return [(c, float(v), float(voxel[b])) for b, c, v in zip(boxes, best, votes, strict=True)]


@numba.njit(cache=True, nogil=True)
def _best_in_boxes(
    accumulator: np.ndarray,
    touched: np.ndarray,
    count: np.ndarray,
    n: int,
    side: int,
    lo: np.ndarray,
    voxel: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((K,) boxes, (K, 3) centres, (K,) votes): ``_peaks`` of each of the first n fine grids (rows
    of ``accumulator`` and ``touched``, ``count`` voxels voted each) that has one, one compiled call for
    all (the numpy glue of a call per grid held the GIL the voting threads share)."""
    boxes, centres, votes = np.empty(n, np.int64), np.empty((n, 3)), np.empty(n)
    k = 0
    for b in range(n):
        grid = accumulator[b].reshape((side, side, side))
        best, value = _peaks_compiled(grid, touched[b, : count[b]], 1, lo[b], voxel[b])
        for q in range(len(best)):
            boxes[k], votes[k] = b, value[q]
            centres[k, 0], centres[k, 1], centres[k, 2] = best[q, 0], best[q, 1], best[q, 2]
            k += 1
    return boxes[:k], centres[:k], votes[:k]


def _pair_rays(
    image_pts: Points,
    map_pts: Points,
    signatures: MapSignatures,
    camera: Camera,
    R: np.ndarray,
    config: SearchConfig,
    boxes: list[_Box] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns the rays of every compatible (image point k, map point m) pair under rotation R:
    ((P,) k, (P,) m, (P,) farthest lambda, (N, 3) each image point's viewing direction, world frame); the
    camera centre lies on ``X_m - lambda direction_k``, 0 < lambda <= farthest. With ``boxes``, only the
    pairs whose map point some camera centre in one of them sees inside the image points' cone
    (``in_swept_view``): the others' rays cannot enter a box, and vote nowhere."""
    rays = np.c_[image_pts.positions, np.ones(len(image_pts))] @ np.linalg.inv(camera.K).T
    directions = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ R
    order, keys, loose = signatures.order, signatures.keys, signatures.loose
    if boxes is not None and len(rays):
        usable = in_swept_view(map_pts.positions, rays[:, :2], R, [(lo, hi) for lo, hi, _, _ in boxes])
        if not usable.all():  # the signature lists without the others: the same pairs, in the same order
            kept = usable[order]
            order, keys, loose = order[kept], keys[kept], loose[usable[loose]]
    k, m, lam = _pairs_kernel(
        image_pts.positions,
        np.nan_to_num(image_pts.arms),
        image_pts.two_armed,
        image_pts.arm_lengths,
        map_pts.positions,
        # the arms of the points outside every cluster, turned (the only arms the kernel reads), as one
        # (2L, 3) product: row for row what the (L, 2, 3) product gives, a fraction of its time
        np.ascontiguousarray((np.nan_to_num(map_pts.arms[loose]).reshape(-1, 3) @ R.T).reshape(-1, 2, 3)),
        map_pts.two_armed,
        map_pts.arm_lengths,
        order,
        keys,
        signatures.swapped,
        loose,
        np.ascontiguousarray(signatures.directions @ R.T),
        camera.K,
        np.cos(np.radians(config.arm_angle_deg)),
        config.arm_length_ratio * max(camera.fx, camera.fy),
    )
    return k, m, lam, np.ascontiguousarray(directions)


@numba.njit(cache=True, nogil=True)
def _direction_at(d: np.ndarray, qx: float, qy: float, K: np.ndarray) -> tuple[float, float]:
    """Returns the unit image direction at pixel (qx, qy) of a line along camera-frame direction d (3,)."""
    xn, yn = (qx - K[0, 2]) / K[0, 0], (qy - K[1, 2]) / K[1, 1]
    vx, vy = K[0, 0] * (d[0] - xn * d[2]), K[1, 1] * (d[1] - yn * d[2])
    norm = np.hypot(vx, vy)
    if norm == 0.0:
        return 0.0, 0.0
    return vx / norm, vy / norm


@numba.njit(cache=True, nogil=True)
def _ray(
    k: int,
    m: int,
    Xm: np.ndarray,
    ray: np.ndarray,
    lam_min: float,
    lam_max: float,
    weight: float,
    lo: np.ndarray,
    hi: np.ndarray,
    voxel: float,
    dims: np.ndarray,
    accumulator: np.ndarray,
    stamp: np.ndarray,
    stamp_map: np.ndarray,
    touched: np.ndarray,
    count: np.ndarray,
    slot: int,
    buffer: np.ndarray,
) -> int:
    """Votes image point k's weight (>= 0) along ``Xm - lambda ray``, lam_min < lambda <= lam_max, inside
    [lo, hi], in the voxels where neither image point k nor map point m has voted yet (ids ``k`` and ``m``);
    a voxel getting its first votes is appended to ``touched`` (its ``count[slot]`` entries). ``buffer``:
    (B,) int64 scratch, the voxels of up to B samples at a time."""
    lam0, lam1 = lam_min, lam_max
    for axis in range(3):  # the part of the ray inside the region (slab method)
        d = -ray[axis]
        if d == 0.0:
            if Xm[axis] < lo[axis] or Xm[axis] > hi[axis]:
                return 0
            continue
        t0, t1 = (lo[axis] - Xm[axis]) / d, (hi[axis] - Xm[axis]) / d
        lam0, lam1 = max(lam0, min(t0, t1)), min(lam1, max(t0, t1))
    if lam1 <= lam0:
        return 0
    nx, ny, nz = dims[0], dims[1], dims[2]
    # samples every half voxel: lambda = s voxel / 2, in voxel units from the grid's corner
    inv = 1.0 / voxel
    ox, oy, oz = (Xm[0] - lo[0]) * inv, (Xm[1] - lo[1]) * inv, (Xm[2] - lo[2]) * inv
    rx, ry, rz = 0.5 * ray[0], 0.5 * ray[1], 0.5 * ray[2]
    first, end = int(lam0 / (0.5 * voxel)) + 1, int(lam1 / (0.5 * voxel)) + 1
    while first < end:
        # a stretch of samples at a time: their voxels (a loop without branches, which the compiler runs
        # on vectors), then each voxel's cache lines requested (the votes took one cache miss after
        # another), then the votes. A sample in the voxel of the one before it is passed over: that
        # voxel's stamps hold k already, or m.
        last = min(first + len(buffer), end)
        for q in range(last - first):
            s = first + q
            ix = min(max(int(ox - s * rx), 0), nx - 1)
            iy = min(max(int(oy - s * ry), 0), ny - 1)
            iz = min(max(int(oz - s * rz), 0), nz - 1)
            buffer[q] = (ix * ny + iy) * nz + iz
        n, previous = 0, -1
        for q in range(last - first):
            v = buffer[q]
            if v != previous:
                buffer[n], previous = v, v
                n += 1
                prefetch(stamp, v)
                prefetch(stamp_map, v)
                prefetch(accumulator, v)
        for q in range(n):
            v = buffer[q]
            if stamp[v] != k and stamp_map[v] != m:
                stamp[v] = k
                stamp_map[v] = m
                if weight > 0.0 and accumulator[v] == 0.0:
                    touched[count[slot]] = v
                    count[slot] += 1
                accumulator[v] += weight
        first = last
    return 1


def in_swept_view(
    X: np.ndarray, normalized: np.ndarray, R: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """Returns (P,) bool: may a camera of (3, 3) world -> camera rotation R with its centre in one of the
    ``boxes`` ((3,) low, (3,) high) see the (P, 3) world point inside the cone of the (N, 2) normalized
    image coordinates (x/z, y/z) ``normalized`` (the cone through their bounding rectangle, in front of
    the camera)?

    X - c, c in a box, seen from the camera: a point lies outside a face of the cone (inward normal n,
    camera frame) from every centre of the box when n . R (X - c) < 0 for the c maximising it, i.e. when
    w . X < min over the box of w . c = w . centre - |w| . half, w = R^T n. False only when that holds for
    a face of every box (with room for rounding): a ray X - lambda d of an image point's direction d,
    lambda > 0, enters a box only at a centre that sees X along d."""
    x0, y0 = normalized.min(axis=0)
    x1, y1 = normalized.max(axis=0)
    inward = np.array([[1.0, 0.0, -x0], [-1.0, 0.0, x1], [0.0, 1.0, -y0], [0.0, -1.0, y1], [0.0, 0.0, 1.0]])
    w = np.ascontiguousarray(inward @ R)  # (5, 3): rows R^T n
    least = np.array([w @ (0.5 * (lo + hi)) - np.abs(w) @ (0.5 * (hi - lo)) for lo, hi in boxes])
    room = 1e-9 * (1.0 + np.abs(least) + np.array([np.abs(w) @ np.abs(0.5 * (lo + hi)) for lo, hi in boxes]))
    return _inside_faces(np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3), w, least - room)


@numba.njit(cache=True, nogil=True)
def _inside_faces(X: np.ndarray, w: np.ndarray, least: np.ndarray) -> np.ndarray:  # pragma: no cover - numba
    """Returns (P,) bool: for some box b, w[f] . X[p] >= least[b, f] less rounding's room (1e-9 of
    |w[f]| . |X[p]|) for every face f of (F, 3) ``w``; ``least``: (B, F)."""
    out = np.zeros(len(X), np.bool_)
    values, room = np.empty(len(w)), np.empty(len(w))
    for p in range(len(X)):
        for f in range(len(w)):
            values[f] = w[f, 0] * X[p, 0] + w[f, 1] * X[p, 1] + w[f, 2] * X[p, 2]
            room[f] = 1e-9 * (abs(w[f, 0] * X[p, 0]) + abs(w[f, 1] * X[p, 1]) + abs(w[f, 2] * X[p, 2]))
        for b in range(len(least)):
            inside = True
            for f in range(len(w)):
                if values[f] < least[b, f] - room[f]:
                    inside = False
                    break
            if inside:
                out[p] = True
                break
    return out


@numba.njit(cache=True, nogil=True)
def _pairs_kernel(
    q: np.ndarray,
    q_arms: np.ndarray,
    q_two: np.ndarray,
    q_len: np.ndarray,
    X: np.ndarray,
    loose_arms: np.ndarray,
    x_two: np.ndarray,
    x_len: np.ndarray,
    order: np.ndarray,
    keys: np.ndarray,
    swapped: np.ndarray,
    loose: np.ndarray,
    dirs: np.ndarray,
    K: np.ndarray,
    cos_tol: float,
    length_ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``_pair_rays``' pairs: ((P,) image point k, (P,) map point m, (P,) farthest lambda) of every image
    point (pixel ``q``, arms ``q_arms``) with the map points of its arms' signature keys (``order`` sorted by
    ``keys``, ``MapSignatures``), then with the ``loose`` points, tested one by one on their turned arms
    ``loose_arms`` ((L, 2, 3), row for row); ``dirs``: the cluster directions turned into the camera."""
    nc = 2 * len(dirs)
    count = 0
    cap = 1024
    out_k = np.empty(cap, np.int64)
    out_m = np.empty(cap, np.int64)
    out_lam = np.empty(cap)
    codes = np.empty((2, nc), np.int64)
    ncodes = np.zeros(2, np.int64)
    for k in range(len(q)):
        arms = 2 if q_two[k] else 1
        # the cluster directions (either sense) that each image arm can be, at this pixel
        for a in range(arms):
            ncodes[a] = 0
            for c in range(len(dirs)):
                ux, uy = _direction_at(dirs[c], q[k, 0], q[k, 1], K)
                dot = ux * q_arms[k, a, 0] + uy * q_arms[k, a, 1]
                if dot >= cos_tol:
                    codes[a, ncodes[a]] = 2 * c
                    ncodes[a] += 1
                elif -dot >= cos_tol:
                    codes[a, ncodes[a]] = 2 * c + 1
                    ncodes[a] += 1
        for u in range(ncodes[0]):
            for w in range(ncodes[1] if arms == 2 else 1):
                if arms == 2:
                    c0, c1 = codes[0, u], codes[1, w]
                    if c0 // 2 == c1 // 2:
                        continue
                    key = min(c0, c1) * nc + max(c0, c1)
                    image_swapped = c0 > c1
                else:
                    key = nc * nc + codes[0, u]
                    image_swapped = False
                first = np.searchsorted(keys, key)
                last = np.searchsorted(keys, key, side="right")
                for p in range(first, last):
                    m = order[p]
                    # arm lengths in the same order: the map arm seen from lambda looks ~ f len / lambda
                    if arms == 2:
                        same = swapped[m] == image_swapped
                        l0 = x_len[m, 0] if same else x_len[m, 1]
                        l1 = x_len[m, 1] if same else x_len[m, 0]
                        far = min(l0 / max(q_len[k, 0], 1e-9), l1 / max(q_len[k, 1], 1e-9))
                    else:
                        far = x_len[m, 0] / max(q_len[k, 0], 1e-9)
                    if count == cap:
                        cap *= 2
                        out_k, out_m, out_lam = grow(out_k, cap), grow(out_m, cap), grow(out_lam, cap)
                    out_k[count], out_m[count], out_lam[count] = k, m, length_ratio * far
                    count += 1
        # map points with an arm outside every cluster: the direct test
        for p in range(len(loose)):
            m = loose[p]
            if x_two[m] != q_two[k]:
                continue
            ax, ay = _direction_at(loose_arms[p, 0], q[k, 0], q[k, 1], K)
            if arms == 1:
                if ax * q_arms[k, 0, 0] + ay * q_arms[k, 0, 1] < cos_tol:
                    continue
                far = x_len[m, 0] / max(q_len[k, 0], 1e-9)
            else:
                bx, by = _direction_at(loose_arms[p, 1], q[k, 0], q[k, 1], K)
                d00 = ax * q_arms[k, 0, 0] + ay * q_arms[k, 0, 1]
                d11 = bx * q_arms[k, 1, 0] + by * q_arms[k, 1, 1]
                d01 = ax * q_arms[k, 1, 0] + ay * q_arms[k, 1, 1]
                d10 = bx * q_arms[k, 0, 0] + by * q_arms[k, 0, 1]
                if d00 >= cos_tol and d11 >= cos_tol:
                    far = min(x_len[m, 0] / max(q_len[k, 0], 1e-9), x_len[m, 1] / max(q_len[k, 1], 1e-9))
                elif d01 >= cos_tol and d10 >= cos_tol:
                    far = min(x_len[m, 0] / max(q_len[k, 1], 1e-9), x_len[m, 1] / max(q_len[k, 0], 1e-9))
                else:
                    continue
            if count == cap:
                cap *= 2
                out_k, out_m, out_lam = grow(out_k, cap), grow(out_m, cap), grow(out_lam, cap)
            out_k[count], out_m[count], out_lam[count] = k, m, length_ratio * far
            count += 1
    return out_k[:count].copy(), out_m[:count].copy(), out_lam[:count].copy()


@numba.njit(cache=True, nogil=True)
def _vote_rays(
    k: np.ndarray,
    m: np.ndarray,
    lam_max: np.ndarray,
    direction: np.ndarray,
    X: np.ndarray,
    weight: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    voxel: float,
    dims: np.ndarray,
    accumulator: np.ndarray,
    stamp: np.ndarray,
    stamp_map: np.ndarray,
    touched: np.ndarray,
    count: np.ndarray,
    first_id: int,
    first_map_id: int,
    lam_min: float,
) -> None:
    buffer = np.empty(RAY_BUFFER, np.int64)
    for p in range(len(k)):
        _ray(
            first_id + k[p],
            first_map_id + m[p],
            X[m[p]],
            direction[k[p]],
            lam_min,
            lam_max[p],
            weight[k[p]],
            lo,
            hi,
            voxel,
            dims,
            accumulator,
            stamp,
            stamp_map,
            touched,
            count,
            0,
            buffer,
        )


@numba.njit(cache=True, nogil=True)
def _vote_boxes(
    k: np.ndarray,
    m: np.ndarray,
    lam_max: np.ndarray,
    direction: np.ndarray,
    X: np.ndarray,
    weight: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    voxel: np.ndarray,
    dims: np.ndarray,
    accumulator: np.ndarray,
    stamp: np.ndarray,
    stamp_map: np.ndarray,
    touched: np.ndarray,
    count: np.ndarray,
    first_id: int,
    first_map_id: int,
    lam_min: float,
) -> None:  # pragma: no cover - numba
    """``_vote_rays`` into each of the grids over boxes [lo[b], hi[b]] of voxels ``voxel[b]`` (rows of
    ``accumulator``, ``stamp``, ``stamp_map`` and ``touched``, entries of ``count``); a ray whose stretch
    stays outside a box's circumscribed sphere skips that box's exact test (it cannot cross the box), so
    every grid gets the votes ``_vote_rays`` would give it."""
    centre = 0.5 * (lo + hi)
    buffer = np.empty(RAY_BUFFER, np.int64)
    radius2 = np.empty(len(lo))
    for b in range(len(lo)):  # (half diagonal)^2, with room for rounding
        half = 0.5 * (hi[b] - lo[b])
        radius2[b] = (half[0] ** 2 + half[1] ** 2 + half[2] ** 2) * (1.0 + 1e-9) + 1e-12
    for p in range(len(k)):
        Xm, ray, far = X[m[p]], direction[k[p]], lam_max[p]
        for b in range(len(lo)):
            cx, cy, cz = Xm[0] - centre[b, 0], Xm[1] - centre[b, 1], Xm[2] - centre[b, 2]
            lam = min(max(cx * ray[0] + cy * ray[1] + cz * ray[2], 0.0), far)  # nearest along the stretch
            dx, dy, dz = cx - lam * ray[0], cy - lam * ray[1], cz - lam * ray[2]
            if dx * dx + dy * dy + dz * dz > radius2[b]:
                continue
            _ray(
                first_id + k[p],
                first_map_id + m[p],
                Xm,
                ray,
                lam_min,
                far,
                weight[k[p]],
                lo[b],
                hi[b],
                voxel[b],
                dims,
                accumulator[b],
                stamp[b],
                stamp_map[b],
                touched[b],
                count,
                b,
                buffer,
            )


def _peaks(
    votes: np.ndarray, lo: np.ndarray, voxel: float, count: int, voted: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((<= count, 3) world centres, their votes) of the voxels with the most ``votes`` (a grid with
    lower corner ``lo`` and cubic voxels of ``voxel`` m), 3 voxels apart, after pooling votes over 2 x 2 x 2
    neighbourhoods (the rays of one camera meet within a voxel or two); ``voted``: the flat indices of every
    voxel with votes, each once (``_Grid.voted``)."""
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    return _peaks_compiled(np.ascontiguousarray(votes), voted, count, lo, float(voxel))


@numba.njit(cache=True, nogil=True)
def _peaks_compiled(
    votes: np.ndarray, voted: np.ndarray, count: int, lo: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``_peaks`` in one compiled call (the fine grids of every coarse peak find theirs: a hundred calls
    an image, whose numpy glue held the GIL the voting threads share)."""
    top, values = _top_pooled(votes, voted, 64 * count)
    # most votes first, ties in voxel order (``np.lexsort((top, -values))``: the pairs are distinct)
    by_voxel = stable_argsort(top)
    order = by_voxel[stable_argsort(-values[by_voxel])]
    _, Y, Z = votes.shape
    cells = np.empty((len(order), 3), np.int64)
    ranked = np.empty(len(order))
    n = 0
    for k in order:
        if values[k] > 0:
            x, rest = divmod(top[k], Y * Z)
            cells[n, 0], cells[n, 1], cells[n, 2] = x, rest // Z, rest % Z
            ranked[n] = values[k]
            n += 1
    kept = _apart(cells[:n], count, 3)  # plateaus of equal maxima: one per neighbourhood
    centres = np.empty((len(kept), 3))
    for k in range(len(kept)):
        for axis in range(3):
            centres[k, axis] = lo[axis] + (cells[kept[k], axis] + 0.5) * voxel
    return centres, ranked[kept]


@numba.njit(cache=True, nogil=True)
def _apart(cells: np.ndarray, count: int, gap: int) -> np.ndarray:  # pragma: no cover - numba
    """Returns the indices of the (K, 3) int ``cells`` kept in order, each kept when it lies ``gap`` or more
    (in some axis) from every cell kept before it, until ``count`` are kept (``count`` <= 0: no limit)."""
    limit = count if count > 0 else len(cells)
    kept = np.empty(min(limit, len(cells)), np.int64)
    n = 0
    for i in range(len(cells)):
        if n == limit:
            break
        near = False
        for j in range(n):
            k = kept[j]
            if (
                abs(cells[i, 0] - cells[k, 0]) < gap
                and abs(cells[i, 1] - cells[k, 1]) < gap
                and abs(cells[i, 2] - cells[k, 2]) < gap
            ):
                near = True
                break
        if not near:
            kept[n] = i
            n += 1
    return kept[:n]


@numba.njit(cache=True, nogil=True)
def _top_pooled(
    votes: np.ndarray, voted: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((<= n,) flat indices, their values) of the largest positive values of ``votes`` pooled by the
    max over the 2 x 2 x 2 voxels ending at each voxel (its lower neighbours), unordered: the n largest by
    (value, then lower index first). ``voted``: the flat indices of every voxel with a positive vote, each
    once, in any order (a pooled value is the vote of one voxel of its block: only those can raise one).

    Each pooled voxel is offered once, by the voxel of its block that holds its maximum (the first of them
    in index order); the heap's ranking is a total order, so the answer does not depend on ``voted``'s."""
    X, Y, Z = votes.shape
    heap_v = np.full(n, -1.0, np.float64)
    heap_i = np.full(n, -1, np.int64)
    flat = votes.reshape(-1)
    for j in range(len(voted)):
        if j + PREFETCH_AHEAD < len(voted):  # the voxels are scattered over the grid: one miss after another
            prefetch(flat, voted[j + PREFETCH_AHEAD])
        v_index = int(voted[j])
        w = flat[v_index]
        # every pooled voxel it offers has an index >= its own: none can beat the root if (w, v_index) does not
        if w <= 0.0 or not _worse(heap_v[0], heap_i[0], w, v_index):
            continue
        x, rest = divmod(v_index, Y * Z)
        y, z = divmod(rest, Z)
        # the pooled voxels whose block holds this voxel: (x, y, z) + (0 or 1 on each axis)
        for px in range(x, min(x + 2, X)):
            for py in range(y, min(y + 2, Y)):
                for pz in range(z, min(z + 2, Z)):
                    p = (px * Y + py) * Z + pz
                    # the root is the heap's worst entry
                    if _worse(heap_v[0], heap_i[0], w, p) and _owns(votes, px, py, pz, w, v_index):
                        _replace_root(heap_v, heap_i, w, p)
    keep = heap_i >= 0
    return heap_i[keep], heap_v[keep]


@numba.njit(cache=True, nogil=True)
def _owns(votes: np.ndarray, px: int, py: int, pz: int, w: float, v_index: int) -> bool:  # pragma: no cover
    """Returns True if the voxel ``v_index`` (value w) is the first voxel of pooled voxel (px, py, pz)'s
    2 x 2 x 2 block (it and its lower neighbours) holding the block's maximum."""
    _, Y, Z = votes.shape
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                qx, qy, qz = px - dx, py - dy, pz - dz
                if qx < 0 or qy < 0 or qz < 0:
                    continue
                u = votes[qx, qy, qz]
                if u > w or (u == w and (qx * Y + qy) * Z + qz < v_index):
                    return False
    return True


@numba.njit(cache=True, nogil=True)
def _replace_root(heap_v: np.ndarray, heap_i: np.ndarray, w: float, p: int) -> None:  # pragma: no cover
    """Puts (w, p) at the root of the min-heap (worst entry first, ``_worse``) and sifts it down."""
    n = len(heap_v)
    heap_v[0], heap_i[0] = w, p
    i = 0
    while True:
        a, b, s = 2 * i + 1, 2 * i + 2, i
        if a < n and _worse(heap_v[a], heap_i[a], heap_v[s], heap_i[s]):
            s = a
        if b < n and _worse(heap_v[b], heap_i[b], heap_v[s], heap_i[s]):
            s = b
        if s == i:
            break
        heap_v[i], heap_v[s] = heap_v[s], heap_v[i]
        heap_i[i], heap_i[s] = heap_i[s], heap_i[i]
        i = s


@numba.njit(cache=True, nogil=True)
def _worse(va: float, ia: int, vb: float, ib: int) -> bool:  # pragma: no cover - numba
    """Returns True if heap entry a ranks below b: a smaller value, or an equal value at a greater index
    (an empty slot, index -1 and value -1, ranks below every vote)."""
    if va != vb:
        return va < vb
    return ia > ib


def solve_locally(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    size_m: float,
    config: SearchConfig,
    score_config: ScoreConfig,
    visible: np.ndarray | None = None,
    chunks: Chunks | None = None,
) -> tuple[np.ndarray, Score] | None:
    """Returns (cam_from_world, Score) of the best pose near a start pose whose camera centre is known to
    within ``size_m``, or None when nothing matches there (``chunks``: of ``lines3d``, or None; see
    ``score.project_clipped``).

    Rounds: the score's covering pairs at a tolerance spanning the uncertainty (the pixels ``size_m`` moves
    the median matched point), one per image and per map segment (``Score.one_to_one``), then the pose
    minimising their endpoint-to-line distances; the tolerance halves each round down to the score's own.
    The start itself is scored too, and the better of it and the solved pose returned: at a tolerance
    spanning a coarse voxel, wrong pairs can pull a start lying on the truth away from it (a demo photo's
    start 0.2 m from the truth was solved to 1.3 m / 4 deg off, and dropped). The rounds run twice: from
    that tolerance, and from the score's own with no rotation slack.
    """
    tolerances = np.array(
        [
            _start_tolerance(lines3d, camera, cam_from_world, size, slack, score_config)
            for size, slack in ((size_m, config.rotation_slack_deg), (0.0, 0.0))
        ]
    )
    # the start's score and both passes' rounds run in one compiled call: the starts solve in threads, and
    # numpy glue between kernels held the GIL (the start's covering pairs at every tolerance it is tested at
    # come from one pass over the image grid: ``score._tighter``)
    segments = np.ascontiguousarray(lines3d, dtype=np.float64).reshape(-1, 6)
    mask = np.ones(len(segments), np.bool_) if visible is None else np.asarray(visible, dtype=np.bool_)
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=np.float64)
    c = NO_CHUNKS if chunks is None else chunks
    found, pose, explained, unexplained, pairs, cover = _solve_compiled(
        segments, np.ascontiguousarray(cam_from_world, dtype=np.float64), intrinsics, float(camera.width),
        float(camera.height), score_config.min_depth_m, mask, c.of, c.centre, c.half, image.segments, image.angles, image.lengths,
        image.grid_ptr, image.grid_items, image.grid_w, image.grid_px, image.empty, image.cell_px,
        image.empty_sum, tolerances, config.solve_rounds, score_config.distance_px,
        float(np.radians(score_config.angle_deg)), float(np.radians(score_config.angle_deg + 2.0)),
        score_config.unexplained_weight,
    )  # fmt: skip
    if not found:
        return None
    value = float(explained.sum()) - score_config.unexplained_weight * unexplained  # as score_projected
    return pose, Score(value, explained, unexplained, pairs, cover)


def _start_tolerance(
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    size_m: float,
    slack_deg: float,
    score_config: ScoreConfig,
) -> float:
    """Returns the tolerance (px) the rounds start at: the score's own, plus the pixels a camera shift of
    ``size_m`` moves the median point, plus what a rotation off by ``slack_deg`` moves the image."""
    tolerance = score_config.distance_px + _pixels_moved(lines3d, camera, cam_from_world, size_m)
    tolerance += max(camera.fx, camera.fy) * np.tan(np.radians(slack_deg))  # the rotation candidate's error
    return tolerance


@numba.njit(cache=True, nogil=True)
def _solve_compiled(
    lines3d: np.ndarray,
    cam_from_world: np.ndarray,
    intrinsics: np.ndarray,
    width: float,
    height: float,
    near: float,
    visible: np.ndarray,
    chunk_of: np.ndarray,
    chunk_centre: np.ndarray,
    chunk_half: np.ndarray,
    segments: np.ndarray,
    angles: np.ndarray,
    lengths: np.ndarray,
    grid_ptr: np.ndarray,
    grid_items: np.ndarray,
    grid_w: int,
    grid_px: float,
    empty: np.ndarray,
    cell_px: float,
    empty_sum: np.ndarray,
    tolerances: np.ndarray,
    rounds: int,
    distance: float,
    angle_score: float,
    angle_solve: float,
    weight: float,
) -> tuple[bool, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``solve_locally`` from the start ``cam_from_world``: its score (at ``distance``, ``angle_score``),
    then for each of the (2,) start ``tolerances`` the rounds (``_round``, at ``angle_solve``) and the score
    of the pose they end at. Returns (False, ...) when nothing scores above 0 or solves, else (True, pose,
    the Score's explained, unexplained, pairs and cover) of the best, as ``score_pose`` makes them."""
    projected, index = _project_clipped(
        lines3d, cam_from_world, intrinsics, width, height, near, visible, chunk_of, chunk_centre, chunk_half
    )
    widest = max(distance, tolerances.max())
    i, j, cover, gap, offsets = _covering_candidates(
        segments, angles, lengths, grid_ptr, grid_items, grid_w, grid_px, projected,
        _angle_limits(lengths, widest, max(angle_score, angle_solve)), widest,
    )  # fmt: skip
    k = _tighter(i, gap, offsets, lengths, distance, angle_score)
    best = _scored(
        cam_from_world, projected, index, i[k], j[k], cover[k], len(segments), empty, cell_px, empty_sum
    )
    best_value = numpy_sum(best[1]) - weight * best[2]
    found = best_value > 0
    for tolerance in tolerances:
        pose, solved = cam_from_world, True
        for r in range(rounds):
            if r == 0:  # the start's pairs at this tolerance
                k = _tighter(i, gap, offsets, lengths, tolerance, angle_solve)
                world_from_cam = _fit(
                    lines3d, intrinsics, segments, i[k], index[j[k]], cover[k], invert_rigid(pose)
                )
            else:
                world_from_cam = _round(
                    lines3d, pose, intrinsics, width, height, near, visible, chunk_of, chunk_centre, chunk_half,
                    segments, angles, lengths, grid_ptr, grid_items, grid_w, grid_px, tolerance, angle_solve,
                )  # fmt: skip
            if world_from_cam is None:
                solved = False
                break
            pose = invert_rigid(world_from_cam)
            if tolerance <= distance:
                break
            tolerance = max(0.5 * tolerance, distance)
        if not solved:
            continue
        p, q = _project_clipped(
            lines3d, pose, intrinsics, width, height, near, visible, chunk_of, chunk_centre, chunk_half
        )
        a, b, c = _covering_pairs(
            segments, angles, lengths, grid_ptr, grid_items, grid_w, grid_px, p, distance, angle_score
        )
        score = _scored(pose, p, q, a, b, c, len(segments), empty, cell_px, empty_sum)
        value = numpy_sum(score[1]) - weight * score[2]
        if not found or value > best_value:
            best, best_value, found = score, value, True
    return found, best[0], best[1], best[2], best[3], best[4]


@numba.njit(cache=True, nogil=True)
def _scored(
    pose: np.ndarray,
    projected: np.ndarray,
    index: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    cover: np.ndarray,
    n_image: int,
    empty: np.ndarray,
    cell_px: float,
    empty_sum: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns (pose, explained, unexplained, (P, 2) pairs (i, map row), cover) of ``score_projected`` from
    the covering pairs (i, projected rows j, cover) of (K, 4) ``projected`` segments of map rows ``index``."""
    explained = _union_lengths(i, cover, n_image)
    unexplained = _length_in_cells(projected, empty, cell_px, empty_sum)
    pairs = np.empty((len(i), 2), np.int64)
    for k in range(len(i)):
        pairs[k, 0], pairs[k, 1] = i[k], index[j[k]]
    return pose, explained, unexplained, pairs, cover


@numba.njit(cache=True, nogil=True)
def _round(
    lines3d: np.ndarray,
    cam_from_world: np.ndarray,
    intrinsics: np.ndarray,
    width: float,
    height: float,
    near: float,
    visible: np.ndarray,
    chunk_of: np.ndarray,
    chunk_centre: np.ndarray,
    chunk_half: np.ndarray,
    segments: np.ndarray,
    angles: np.ndarray,
    lengths: np.ndarray,
    grid_ptr: np.ndarray,
    grid_items: np.ndarray,
    grid_w: int,
    grid_px: float,
    distance: float,
    angle_tol: float,
) -> np.ndarray | None:  # pragma: no cover - numba
    """One round of ``_solve_compiled`` from a pose: the covering pairs at ``distance`` and ``angle_tol``,
    then the pose fitted to them (``_fit``). Returns the new world_from_cam, or None."""
    projected, index = _project_clipped(
        lines3d, cam_from_world, intrinsics, width, height, near, visible, chunk_of, chunk_centre, chunk_half
    )
    i, j, cover = _covering_pairs(
        segments, angles, lengths, grid_ptr, grid_items, grid_w, grid_px, projected, distance, angle_tol
    )
    return _fit(lines3d, intrinsics, segments, i, index[j], cover, invert_rigid(cam_from_world))


@numba.njit(cache=True, nogil=True)
def _fit(
    lines3d: np.ndarray,
    intrinsics: np.ndarray,
    segments: np.ndarray,
    i: np.ndarray,
    rows: np.ndarray,
    cover: np.ndarray,
    world_from_cam: np.ndarray,
) -> np.ndarray | None:  # pragma: no cover - numba
    """The pose fitted to covering pairs (image segments i, map ``rows``, (P, 2) cover), starting from
    ``world_from_cam``: the pairs taken one per image and per map segment, longest cover first
    (``Score.one_to_one``), then ``_gauss_newton`` on the arrays ``geometry.line_coefficients`` and
    ``LineProjection.build`` make, written out here in the same operations and order (numpy cannot be
    called from here). Returns the new world_from_cam, or None (fewer than 4 pairs, a singular system)."""
    if len(i) < 4:
        return None
    order = stable_argsort(-(cover[:, 1] - cover[:, 0]))  # as greedy_pairs sorts
    pairs = np.empty((len(i), 2), np.int64)
    for k in range(len(order)):
        pairs[k, 0], pairs[k, 1] = i[order[k]], rows[order[k]]
    keep = _greedy(pairs, pairs[:, 0].max() + 1, pairs[:, 1].max() + 1)
    n = int(keep.sum())
    if n < 4:
        return None
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    points = np.empty((2 * n, 3))
    a, b, c = np.empty(2 * n), np.empty(2 * n), np.empty(2 * n)
    m = 0
    for k in range(len(pairs)):
        if not keep[k]:
            continue
        s = segments[pairs[k, 0]]
        h0, h1, h2 = s[1] - s[3], s[2] - s[0], s[0] * s[3] - s[1] * s[2]
        norm = np.sqrt(h0 * h0 + h1 * h1)
        h0, h1, h2 = h0 / norm, h1 / norm, h2 / norm
        for e in range(2):
            for d in range(3):
                points[2 * m + e, d] = lines3d[pairs[k, 1], 3 * e + d]
            a[2 * m + e], b[2 * m + e] = h0 * fx, h1 * fy
            c[2 * m + e] = h0 * cx + h1 * cy + h2
        m += 1
    return _gauss_newton(points, a, b, c, 1e-3, world_from_cam, 5)


def _pixels_moved(lines3d: np.ndarray, camera: Camera, cam_from_world: np.ndarray, size_m: float) -> float:
    """Returns how many pixels a camera shift of ``size_m`` moves a map point at the median depth in view."""
    if size_m == 0.0:  # no depth needed (the local solve's second pass)
        return 0.0
    depth = transform_depths(lines3d, cam_from_world)
    return max(camera.fx, camera.fy) * size_m / _median(depth[depth > 0.1], 1.0)


def _median(values: np.ndarray, empty: float) -> float:
    """Returns ``np.median`` of (n,) finite values to the last bit (the middle one, or the mean of the
    middle two), ``empty`` for none: without np.median's checks, which cost more than the partition of a
    map's few hundred depths (it runs once per local solve)."""
    if len(values) == 0:
        return empty
    half = len(values) // 2
    # the one or two middle values in their sorted places, without sorting the rest (a large map's
    # hundreds of thousands of depths)
    ordered = np.partition(values, [half - 1, half] if half > 0 else [0])
    if len(ordered) % 2:
        return float(ordered[half])
    return float((ordered[half - 1] + ordered[half]) / 2)


def transform_depths(lines3d: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (2M,) camera-frame depths of both endpoints of (M, 6) world segments."""
    return lines3d.reshape(-1, 3) @ cam_from_world[2, :3] + cam_from_world[2, 3]


@numba.njit(cache=True, nogil=True)
def _gauss_newton(
    points: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    min_depth: float,
    world_from_cam: np.ndarray,
    iterations: int,
) -> np.ndarray | None:  # pragma: no cover - numba
    """The pose putting both ends of each paired map segment on its image segment's line (paper eq.
    "costs"), by Gauss-Newton with Huber weights at 2 px: the iterations on a ``LineProjection``'s arrays
    (its ``evaluate``, with the normal equations summed in place). Returns the (4, 4) world_from_cam, or
    None for a singular system."""
    T = world_from_cam.copy()
    step = np.empty(6)
    # per point: its Jacobian row J, w2 J (Huber's squared weight w2) and error e, then the normal
    # equations H = sum (w2 J) J^T, rhs = -sum (w2 J) e summed row by row: each entry sums its terms in
    # point order as a sum in place per point would, in registers rather than memory
    J, weighted, errors = np.empty((len(points), 6)), np.empty((len(points), 6)), np.empty(len(points))
    H, rhs = np.empty((6, 6)), np.empty(6)
    for _ in range(iterations):
        for i in range(len(points)):
            d0, d1, d2 = points[i, 0] - T[0, 3], points[i, 1] - T[1, 3], points[i, 2] - T[2, 3]
            X = d0 * T[0, 0] + d1 * T[1, 0] + d2 * T[2, 0]  # camera frame: (x - t) @ R
            Y = d0 * T[0, 1] + d1 * T[1, 1] + d2 * T[2, 1]
            Z = d0 * T[0, 2] + d1 * T[1, 2] + d2 * T[2, 2]
            inv_z = 1.0 / max(Z, min_depth)
            num = a[i] * X + b[i] * Y
            e = num * inv_z + c[i]
            g0, g1 = a[i] * inv_z, b[i] * inv_z
            g2 = 0.0 if Z < min_depth else -num * inv_z * inv_z
            J[i, 0], J[i, 1], J[i, 2] = g1 * Z - g2 * Y, g2 * X - g0 * Z, g0 * Y - g1 * X
            J[i, 3], J[i, 4], J[i, 5] = -g0, -g1, -g2
            w2 = min(1.0, 2.0 / max(abs(e), 1e-9))  # Huber at 2 px, squared weight
            for r in range(6):
                weighted[i, r] = w2 * J[i, r]
            errors[i] = e
        _normal_equations(J, weighted, errors, H, rhs)
        if not _solve_symmetric(H, rhs, 1e12, step):
            return None
        delta = np.eye(4)
        angle = np.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
        if angle >= 1e-12:  # Rodrigues (geometry.rotation_from_vector): I + sin K + (1 - cos) K K
            k0, k1, k2 = step[0] / angle, step[1] / angle, step[2] / angle
            s, v = np.sin(angle), 1.0 - np.cos(angle)  # K K = k k^T - I for the unit axis k
            delta[0, 0] = 1.0 - v * (k1 * k1 + k2 * k2)
            delta[1, 1] = 1.0 - v * (k0 * k0 + k2 * k2)
            delta[2, 2] = 1.0 - v * (k0 * k0 + k1 * k1)
            delta[0, 1], delta[1, 0] = -s * k2 + v * k0 * k1, s * k2 + v * k0 * k1
            delta[0, 2], delta[2, 0] = s * k1 + v * k0 * k2, -s * k1 + v * k0 * k2
            delta[1, 2], delta[2, 1] = -s * k0 + v * k1 * k2, s * k0 + v * k1 * k2
        # gtsam's Pose3 retract to first order (translation in the body frame); element by element, as a
        # slice assignment's overloads cost seconds of compile
        delta[0, 3], delta[1, 3], delta[2, 3] = step[3], step[4], step[5]
        # T @ delta written out (numba's matrix product and linalg cost seconds of compile in every process)
        moved = np.zeros((4, 4))
        for r in range(4):
            for q in range(4):
                for e in range(4):
                    moved[r, q] += T[r, e] * delta[e, q]
        T = moved
        if np.sqrt(np.sum(step**2)) < 1e-7:
            break
    return T


@numba.njit(cache=True, nogil=True)
def _normal_equations(
    J: np.ndarray, weighted: np.ndarray, errors: np.ndarray, H: np.ndarray, rhs: np.ndarray
) -> None:  # pragma: no cover - numba
    """Fills (6, 6) ``H`` with sum_i weighted_i J_i^T and (6,) ``rhs`` with -sum_i weighted_i e_i over the
    (n, 6) rows ``J`` and ``weighted`` and the (n,) ``errors``, each entry's terms added in row order."""
    for r in range(6):
        h0 = h1 = h2 = h3 = h4 = h5 = g = 0.0
        for i in range(len(errors)):
            w = weighted[i, r]
            h0 += w * J[i, 0]
            h1 += w * J[i, 1]
            h2 += w * J[i, 2]
            h3 += w * J[i, 3]
            h4 += w * J[i, 4]
            h5 += w * J[i, 5]
            g -= w * errors[i]
        H[r, 0], H[r, 1], H[r, 2], H[r, 3], H[r, 4], H[r, 5] = h0, h1, h2, h3, h4, h5
        rhs[r] = g


@numba.njit(cache=True, nogil=True)
def _solve_symmetric(
    H: np.ndarray, rhs: np.ndarray, max_cond: float, out: np.ndarray
) -> bool:  # pragma: no cover - numba
    """Solves H x = rhs for a symmetric (n, n) H into ``out`` (n,) from its eigen-decomposition (cyclic
    Jacobi rotations); returns False, leaving ``out`` undefined, where H is not finite or its condition
    number (largest over smallest absolute eigenvalue, as ``np.linalg.cond`` of a symmetric matrix) exceeds
    ``max_cond``. Written out instead of ``np.linalg``: numba compiles its LAPACK bindings and their error
    messages for seconds in every fresh process."""
    n = len(rhs)
    A, V = np.empty((n, n)), np.zeros((n, n))
    for r in range(n):
        V[r, r] = 1.0
        for q in range(n):
            A[r, q] = H[r, q]
    for r in range(n):
        for q in range(n):
            if not np.isfinite(A[r, q]):
                return False
    for _ in range(64):
        off, scale = 0.0, 0.0
        for r in range(n):
            scale += A[r, r] ** 2
            for q in range(r + 1, n):
                off += A[r, q] ** 2
        if off <= 1e-32 * scale or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                jacobi_rotation(A, V, p, q)
    smallest, largest = np.inf, 0.0
    for r in range(n):
        smallest, largest = min(smallest, abs(A[r, r])), max(largest, abs(A[r, r]))
    if smallest == 0.0 or largest > max_cond * smallest:
        return False
    for r in range(n):
        out[r] = 0.0
    for e in range(n):  # x = V diag(1 / lambda) V^T rhs
        along = 0.0
        for k in range(n):
            along += V[k, e] * rhs[k]
        along /= A[e, e]
        for r in range(n):
            out[r] += V[r, e] * along
    return True
