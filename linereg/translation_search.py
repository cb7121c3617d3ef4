"""Translation by voting of single-pair hypotheses ("search", the default of ``estimate_translation``).

With R fixed, a compatible pair (2D segment i, 3D segment j) whose 2D segment images the whole 3D segment
fixes t on its own: the endpoint rays ``r1, r2`` and the rotated endpoints ``R P1, R P2`` satisfy
``l1 r1 - R P1 = l2 r2 - R P2 = t`` (eq. "coplanar" at both endpoints, plus the segment's extent), two
unknown depths from three equations, exactly solvable because the direction already agrees. Every pair
gives one hypothesis; the true t collects the hypotheses of all fully seen inliers, wrong pairs scatter.
Hypotheses vote for camera centres in a grid whose cells are a fraction of the typical depth (a pair's
error is a fraction of its depth), on two grids shifted by half a cell; the fullest cells' mean
translations are counted with the inlier test. A 2D segment that is a fragment or that touches the image
border gives a wrong or no hypothesis; it still counts as an inlier when the hypotheses are tested.
"""

from __future__ import annotations

import functools

import numpy as np

from .camera import Camera
from .config import MatchConfig, TranslationConfig
from .geometry import pixels_to_rays, segment_lengths
from .translation_inliers import count_inliers, pair_matches
from .translation_pairs import Pairs, dot

_BORDER_PX = 2.0  # a 2D endpoint this close to the image border may be clipped: no hypothesis from it
_KEY_BITS = 20  # grid coordinates are packed into one int64 key, 20 bits each
_CORNER_PX = 4.0  # two segment ends this close form a corner


def search_candidates(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    config: TranslationConfig,
    match: MatchConfig,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Returns ((H, 3) translations, (H,) inlier counts, their (K,) ``(h, i, j)`` inlier pairs) of the best
    voted hypotheses (may be empty): ``pair_inliers`` with what it counted.
    """
    T, depth = pair_hypotheses(lines2d, camera, pairs, config.seed_min_length_px, config.max_hypotheses)
    if len(T) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return np.zeros((0, 3)), np.zeros(0), (empty, empty, empty)
    cell = config.cell_fraction * float(np.partition(depth, len(depth) // 2)[len(depth) // 2])
    T = vote_cells(T, R, cell, config.num_verify, config.verify_fraction)
    h, i, j = pair_matches(lines2d, camera, pairs, T, match)
    return T, count_inliers(h, i, len(T), len(lines2d)).astype(float), (h, i, j)


def pair_hypotheses(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, min_length_px: float, max_hypotheses: int = 1 << 62
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((H, 3) t, (H,) mean endpoint depth) of the pairs read as whole-segment correspondences.

    Solves ``a r2 - b r1 = R (P2 - P1)`` in least squares: ``a, b > 0`` matches P1 to r1 and P2 to r2,
    both negative the swapped order; mixed signs (a segment behind the camera) give no hypothesis.
    Only 2D segments inside the image (not clipped) and at least min_length_px long seed; beyond
    max_hypotheses pairs, the likeliest whole ones are kept.
    """
    i, j = _seed_pairs(lines2d, camera, pairs, min_length_px, max_hypotheses)
    if len(i) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    r1, r2 = pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4])
    # the 2x2 normal equations per 2D segment, solved once: a = alpha . D, b = beta . D (D = R (P2 - P1))
    a11, a22, a12 = dot(r2, r2), dot(r1, r1), -dot(r1, r2)
    det = a11 * a22 - a12 * a12  # > 0 unless the two rays coincide (a point-like segment)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = (a22[:, None] * r2 + a12[:, None] * r1) / det[:, None]
        beta = -(a11[:, None] * r1 + a12[:, None] * r2) / det[:, None]
    # one product per (seeding segment, 3D segment) beats gathering (P, 3) rows; i ascends (combo order)
    change = np.r_[True, i[1:] != i[:-1]]
    rows = i[change]
    D = (pairs.ends[:, 3:6] - pairs.ends[:, 0:3]).T
    flat = (np.cumsum(change) - 1) * D.shape[1] + j
    a, b = (alpha[rows] @ D).ravel().take(flat), (beta[rows] @ D).ravel().take(flat)
    forward = (a > 0) & (b > 0)
    ok = np.flatnonzero(forward | ((a < 0) & (b < 0)))
    i, j, a, b = i.take(ok), j.take(ok), np.abs(a.take(ok)), np.abs(b.take(ok))
    # the 3D ends seen at r1 and r2 are (P1, P2) or (P2, P1): their mean is the midpoint either way
    T = np.empty((len(i), 3))
    for k in range(2):  # T = 0.5 (b r1 + a r2) - midpoint, in place: fresh large arrays cost page faults
        x, y = r1[:, k].take(i), r2[:, k].take(i)
        x *= b
        y *= a
        x += y
        x *= 0.5
        np.subtract(x, pairs.point[:, k].take(j), out=T[:, k])
    depth = 0.5 * (a + b)  # rays have z = 1
    np.subtract(depth, pairs.point[:, 2].take(j), out=T[:, 2])
    return T, depth


def _seed_pairs(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, min_length_px: float, max_hypotheses: int
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (K,) int64 ``(i, j)``: the pairs whose 2D segment may seed a hypothesis (pair order)."""
    shape = (camera.width, camera.height, min_length_px)
    data = np.ascontiguousarray(lines2d, dtype=np.float64).tobytes()
    usable, rank = (a.copy() for a in _seed_order(data, len(lines2d), *shape))
    per_segment = np.bincount(pairs.combo_i, pairs.counts(), minlength=len(lines2d)).astype(np.int64) * usable
    usable[rank[np.cumsum(per_segment[rank]) > max_hypotheses]] = False
    combo, j = pairs.expand(np.flatnonzero(usable[pairs.combo_i]))
    return pairs.combo_i[combo], j


# every rotation candidate of an image asks for the same order: computed once per image (keyed by content)
@functools.lru_cache(maxsize=4)
def _seed_order(
    data: bytes, n: int, width: float, height: float, min_length_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N,) bool usable, (N,) int64 rank) of the 2D segments (N, 4) stored in ``data``.

    Only 2D segments inside the image (not clipped) and at least min_length_px long seed. On large maps
    only the likeliest whole segments seed, up to a budget: those whose both ends meet another segment's
    end (a corner: not a fragment), then one end, then none; longest first within (``rank``).
    """
    lines2d = np.frombuffer(data, dtype=np.float64).reshape(n, 4)
    lo, hi = _BORDER_PX, np.array([width, height]) - 1.0 - _BORDER_PX
    inside = np.all((lines2d[:, 0:2] > lo) & (lines2d[:, 0:2] < hi), axis=1)
    inside &= np.all((lines2d[:, 2:4] > lo) & (lines2d[:, 2:4] < hi), axis=1)
    lengths = segment_lengths(lines2d)
    return inside & (lengths >= min_length_px), np.lexsort((-lengths, -_corner_ends(lines2d, _CORNER_PX)))


def vote_cells(T: np.ndarray, R: np.ndarray, cell: float, top: int, min_fraction: float = 0.0) -> np.ndarray:
    """Returns (K, 3) mean translations of the fullest camera-centre cells, fullest first (K <= top).

    Two grids shifted by half a cell; a cell of the second grid whose mean lies within a cell of an
    already chosen one is the same hypothesis and is skipped. Cells with fewer than ``min_fraction`` of
    the fullest cell's votes are left out (a clear winner needs no rivals checked; repeated structure
    gives many full cells, and they all are), and so are cells beyond as many as the fullest has votes.
    """
    # camera centres -R^T t (world frame), in cells; in place: fresh large arrays cost page faults
    scaled = T @ R
    np.negative(scaled, out=scaled)
    scaled /= cell
    found, counts = [], []
    buffers = np.empty_like(scaled), np.empty(scaled.shape, dtype=np.int64)
    for shift in (0.0, 0.5):
        mean, count = _fullest_cells(T, _cell_keys(scaled, shift, buffers), top)
        found.append(mean)
        counts.append(count)
    T_all, c_all = np.concatenate(found), np.concatenate(counts)
    order = np.argsort(-c_all, kind="stable")
    # weak peaks (a wrong rotation) get few rivals checked: no more than the fullest cell has votes
    order = order[c_all[order] >= min_fraction * c_all[order[0]]][: max(4, int(c_all[order[0]]))]
    T_all = T_all[order]
    # greedy: keep a cell unless a fuller kept one lies within a cell size (same hypothesis, other grid)
    near = np.linalg.norm(T_all[:, None, :] - T_all[None, :, :], axis=2) <= cell
    kept: list[int] = []
    for k in range(len(T_all)):
        if not near[k, kept].any():
            kept.append(k)
    return T_all[kept[:top]]


def _cell_keys(scaled: np.ndarray, shift: float, buffers: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Returns (H,) int64 keys of the grid cells (shifted by shift cells) of points (H, 3) in cell units.

    buffers: (H, 3) float64 and int64 scratch arrays.
    """
    half = 1 << (_KEY_BITS - 1)
    g, gi = buffers
    np.add(scaled, shift, out=g)
    np.floor(g, out=g)
    np.clip(g, -half + 1, half - 1, out=g)
    np.copyto(gi, g, casting="unsafe")
    # each coordinate + half lies in [1, 2^20 - 1]: packing them is the sum of the shifted fields
    key = gi[:, 0] << (2 * _KEY_BITS)
    key += gi[:, 1] << _KEY_BITS
    key += gi[:, 2]
    key += half * ((1 << (2 * _KEY_BITS)) + (1 << _KEY_BITS) + 1)
    return key


def _fullest_cells(T: np.ndarray, key: np.ndarray, top: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 3) mean T, (K,) votes) of the (K <= top) fullest cells, fullest first, ties by key.

    Most votes are alone in their cell. A cell has at most the votes of its hash bucket, so only votes in
    buckets with ``least`` votes are sorted; that is exact once ``top`` of their cells have ``least`` votes
    (every cell at least as full as the top-th is then among them, wholly).
    """
    bits = int(np.clip(np.ceil(np.log2(max(len(key), 1))) - 1, 10, 16))  # ~2 votes a bucket: a small table
    bucket = key.view(np.uint64) * np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: spreads nearby keys
    bucket >>= np.uint64(64 - bits)
    votes = np.bincount(bucket.view(np.int64), minlength=1 << bits).take(bucket.view(np.int64))
    for least in (4, 2, 1):
        rows = np.flatnonzero(votes >= least) if least > 1 else np.arange(len(key))
        found = _ranked_cells(T, key, rows, top)
        if least == 1 or (len(found[1]) == top and found[1][-1] >= least):
            return found
    raise AssertionError("unreachable")


def _ranked_cells(
    T: np.ndarray, key: np.ndarray, rows: np.ndarray, top: int
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ``_fullest_cells`` among the votes ``rows`` (ascending) only."""
    if len(rows) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    order = rows[np.argsort(key[rows])]
    sorted_key = key[order]
    first = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    count = np.diff(np.r_[first, len(order)])
    if len(count) > top:  # only the top few are ranked: those at least as full as the top-th fullest
        cand = np.flatnonzero(count >= np.partition(count, len(count) - top)[len(count) - top])
    else:
        cand = np.arange(len(count))
    best = cand[np.argsort(-count[cand], kind="stable")[:top]]
    # their members, summed in input order (as a bincount over all votes would): sorted by (cell, row)
    n = count[best]
    label = np.repeat(np.arange(len(best)), n)
    members = order[np.repeat(first[best] - np.cumsum(n) + n, n) + np.arange(len(label))]
    members = np.sort(label * len(key) + members) % len(key)
    sums = np.stack(
        [np.bincount(label, weights=T[:, k].take(members), minlength=len(best)) for k in range(3)], 1
    )
    return sums / n[:, None], n


def _corner_ends(lines2d: np.ndarray, radius_px: float) -> np.ndarray:
    """Returns (N,) int64 how many of each segment's two ends lie within radius_px of another segment's end."""
    ends = lines2d.reshape(-1, 2)
    order = np.argsort(ends[:, 0], kind="stable")
    xs = ends[order, 0]
    lo = np.searchsorted(xs, xs - radius_px)
    hi = np.searchsorted(xs, xs + radius_px, side="right")
    n = hi - lo  # candidates by x, each end's window in the sorted order
    a = np.repeat(np.arange(len(xs)), n)
    b = np.repeat(lo - np.cumsum(n) + n, n) + np.arange(n.sum())
    a, b = order[a], order[b]
    near = (a // 2 != b // 2) & (np.hypot(*(ends[a] - ends[b]).T) <= radius_px)
    met = np.zeros(len(ends), dtype=bool)
    met[a[near]] = True
    return met.reshape(-1, 2).sum(axis=1)
