"""Translation and 2D-3D correspondences for one rotation candidate (paper section III-C, Algorithm 2).

With R fixed, a 2D segment i and a 3D segment j correspond only if j's camera-frame direction lies in i's
interpretation plane; each such pair gives one linear equation in t (eq. "coplanar": ``(R P + t) . n = 0``).
``"ransac"`` samples three pairs at a time as the paper does (``translation_ransac``); ``"search"`` (default)
votes over the pairs of the parallel clusters (``translation_search``). Both end the same way: the best
hypotheses are scored with the shared inlier test (``matching.match_segments``), so ``num_inliers`` is the
paper's inlier count, and ``t`` is polished by weighted least squares on the coplanarity equations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .config import MatchConfig, TranslationConfig
from .directions import DirectionClusters
from .geometry import make_cam_from_world, pixels_to_rays
from .matching import match_segments

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TranslationHypothesis:
    """The best translation for one rotation candidate and what supports it.

    t: (3,) float64 so that ``cam_from_world = [R | t]``; matches: (K, 2) int64 ``(i2d, j3d)`` from
    ``match_segments`` at ``[R | t]``; num_inliers = K; runner_up_inliers: inliers of the best hypothesis
    whose camera centre is clearly elsewhere (> ``config.distinct_fraction`` of the scene size away).
    """

    t: np.ndarray
    matches: np.ndarray
    num_inliers: int
    runner_up_inliers: int


@dataclass(frozen=True)
class Pairs:
    """Every 2D-3D pair whose 3D direction lies on the 2D interpretation plane under R (camera frame).

    i, j: (P,) int64 2D / 3D indices; group: (P,) int64 direction group of j (its 3D cluster, or
    ``len(clusters) + j`` for an unclustered segment); normal: (P, 3) the interpretation normal of i made
    to contain j's direction; offset: (P,) ``normal . R P_j`` so eq. "coplanar" reads
    ``normal . t = -offset``. directions: (G, 3) camera-frame direction of each group. Per segment, computed
    once: ends (M, 6) rotated 3D endpoints ``R P1, R P2``; point (M, 3) their midpoints; plane (N, 3) the
    plain interpretation normals of the 2D segments; per pair, plane_ij (P, 3) = plane[i] and
    plane_offset (P,) = ``plane[i] . point[j]`` (the midpoint's distance to the plane is
    ``plane_offset + plane_ij . t``).
    """

    i: np.ndarray
    j: np.ndarray
    group: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    directions: np.ndarray
    ends: np.ndarray
    point: np.ndarray
    plane: np.ndarray
    plane_ij: np.ndarray
    plane_offset: np.ndarray


def estimate_translation(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    clusters3d: DirectionClusters,
    config: TranslationConfig,
    match: MatchConfig,
) -> TranslationHypothesis:
    """Returns the translation with most inliers for rotation R, its matches and the runner-up count.

    lines2d: (N, 4) float64 undistorted pixels; lines3d: (M, 6) float64 world; R: (3, 3) cam_from_world
    rotation; clusters3d: the 3D parallel clusters (world directions, labels). Never raises on degenerate
    input (no compatible pair, one cluster): it returns ``num_inliers = 0`` and ``t = 0``.
    """
    pairs = compatible_pairs(lines2d, lines3d, camera, R, clusters3d, config.coplanar_px)
    if len(pairs.i) < 3:
        return _empty()
    if config.method == "ransac":
        from .translation_ransac import ransac_candidates

        candidates = ransac_candidates(lines2d, lines3d, camera, R, pairs, config, match)
    else:
        from .translation_search import search_candidates

        candidates = search_candidates(lines2d, lines3d, camera, R, pairs, config, match)
    return finish(lines2d, lines3d, camera, R, pairs, candidates, config, match)


def _empty() -> TranslationHypothesis:
    return TranslationHypothesis(np.zeros(3), np.zeros((0, 2), dtype=np.int64), 0, 0)


def compatible_pairs(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    clusters3d: DirectionClusters,
    tolerance_px: float,
) -> Pairs:
    """Returns the Pairs whose 3D direction (under R) lies on the 2D segment's interpretation plane.

    The test is in pixels so that short, noisy segments are judged fairly: the 2D segment's endpoints must
    lie within ``tolerance_px`` of the image line through its midpoint and the direction's vanishing point.
    Clustered 3D segments use their cluster's direction (less noisy than their own).
    """
    labels = np.asarray(clusters3d.labels, dtype=np.int64)
    if len(labels) != len(lines3d):
        labels = np.full(len(lines3d), -1, dtype=np.int64)
    K = len(clusters3d)
    loose = np.flatnonzero(labels < 0)
    own = lines3d[loose, 3:6] - lines3d[loose, 0:3]
    world_dirs = np.r_[np.asarray(clusters3d.directions, float).reshape(-1, 3), own]
    dirs = world_dirs @ R.T
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
    group_of_j = np.where(labels >= 0, labels, 0)
    group_of_j[loose] = K + np.arange(len(loose))
    compat = _vanishing_compatible(lines2d, camera, dirs, tolerance_px)  # (N, G)
    # expand each compatible (i, group) into (i, j) for every member j of the group
    order = np.argsort(group_of_j, kind="stable")
    starts = np.searchsorted(group_of_j[order], np.arange(len(dirs) + 1))
    ii, gg = np.nonzero(compat)
    counts = starts[gg + 1] - starts[gg]
    i, g = np.repeat(ii, counts), np.repeat(gg, counts)
    j = order[np.arange(len(i)) + np.repeat(starts[gg] - np.cumsum(counts) + counts, counts)]
    ends = (lines3d.reshape(-1, 3) @ R.T).reshape(-1, 6)
    point = 0.5 * (ends[:, 0:3] + ends[:, 3:6])
    mid = pixels_to_rays(camera, 0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4]))
    normal = np.repeat(_unit(cross(mid[ii], dirs[gg])), counts, axis=0)  # depends on (i, group) only
    offset = np.einsum("pk,pk->p", normal, point[j])
    plane = _unit(cross(pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4])))
    plane_ij = plane[i]
    plane_offset = np.einsum("pk,pk->p", plane_ij, point[j])
    return Pairs(i, j, g, normal, offset, dirs, ends, point, plane, plane_ij, plane_offset)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (P, 3) row-wise cross products of (P, 3) arrays (np.cross is several times slower here)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _vanishing_compatible(
    lines2d: np.ndarray, camera: Camera, dirs: np.ndarray, tolerance_px: float
) -> np.ndarray:
    """Returns (N, G) bool: segment i points at the vanishing point of direction g within tolerance_px."""
    mid = np.c_[0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4]), np.ones(len(lines2d))]
    end = np.c_[lines2d[:, 0:2], np.ones(len(lines2d))]
    vp = dirs @ camera.K.T  # (G, 3) homogeneous vanishing points (may be at infinity)
    # line through midpoint and vanishing point: l = mid x vp; endpoint distance |l . end| / |l_xy|
    lx = mid[:, 1:2] * vp[None, :, 2] - vp[None, :, 1]
    ly = vp[None, :, 0] - mid[:, 0:1] * vp[None, :, 2]
    lc = mid[:, 0:1] * vp[None, :, 1] - mid[:, 1:2] * vp[None, :, 0]
    num = np.abs(lx * end[:, 0:1] + ly * end[:, 1:2] + lc)
    den = np.hypot(lx, ly)
    return (num <= tolerance_px * den) & (den > 1e-9 * np.abs(lc).clip(1.0))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def scene_size(lines3d: np.ndarray) -> float:
    """Returns the bounding-box diagonal (m) of (M, 6) segments, the scale for 'clearly different'."""
    ends = lines3d.reshape(-1, 3)
    return float(max(np.linalg.norm(ends.max(axis=0) - ends.min(axis=0)), 1e-9))


def pair_inliers(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, T: np.ndarray, match: MatchConfig
) -> np.ndarray:
    """Returns (H,) int64 inlier counts of translations T (H, 3): the shared test, on the pairs only.

    Counts 2D segments with at least one inlier pair (``pair_matches``): a fast lower bound of the
    number of ``match_segments`` rows.
    """
    h, i, _ = pair_matches(lines2d, camera, pairs, T, match)
    ok = np.zeros((len(T), len(lines2d)), dtype=bool)
    ok[h, i] = True
    return ok.sum(axis=1)


def pair_matches(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, T: np.ndarray, match: MatchConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (K,) int64 ``(h, i, j)``: the compatible pairs that pass the inlier test at translation T[h].

    Same test as ``matching.match_matrix`` (endpoint distance and overlap), evaluated only on the pairs.
    A pair whose 3D midpoint is farther from i's interpretation plane than ``distance_px * z / f`` cannot
    pass (both endpoints are within that, and the midpoint is their mean), so only the others are tested.
    """
    res = pairs.plane_offset[None, :] + T @ pairs.plane_ij.T  # (H, P) midpoint off the plane (m)
    z = pairs.point[pairs.j, 2][None, :] + T[:, 2:3]
    h, p = np.nonzero(np.abs(res) <= (match.distance_px / max(camera.fx, camera.fy)) * z)
    i, j = pairs.i[p], pairs.j[p]
    t = T[h]
    seg = lines2d[i]
    d = seg[:, 2:4] - seg[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    u = d / np.maximum(length, 1e-300)[:, None]
    close = np.ones(len(p), dtype=bool)
    along = []
    for x in (pairs.ends[j, 0:3] + t, pairs.ends[j, 3:6] + t):
        front = x[:, 2] >= match.min_depth_m
        zs = np.where(front, x[:, 2], 1.0)
        rel_x = camera.fx * x[:, 0] / zs + camera.cx - seg[:, 0]
        rel_y = camera.fy * x[:, 1] / zs + camera.cy - seg[:, 1]
        close &= front & (np.abs(u[:, 0] * rel_y - u[:, 1] * rel_x) <= match.distance_px)
        along.append(u[:, 0] * rel_x + u[:, 1] * rel_y)
    lo = np.maximum(np.minimum(along[0], along[1]), 0.0)
    hi = np.minimum(np.maximum(along[0], along[1]), length)
    keep = close & (hi - lo > match.min_overlap * length)
    return h[keep], i[keep], j[keep]


def refine_translation(plane: np.ndarray, ends: np.ndarray, t: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """Returns (3,) t minimising the depth-weighted coplanarity residuals of matches (eq. "coplanar").

    plane: (N, 3) interpretation normals of the 2D segments; ends: (M, 6) rotated 3D endpoints ``R P``.
    Both endpoints of each matched 3D segment must lie on the 2D segment's interpretation plane; dividing
    by depth makes each residual an angle (~ pixels / f). A weak prior on the current t keeps directions
    no match constrains (e.g. along the only cluster's direction) where they were.
    """
    if len(matches) == 0:
        return t
    n = np.r_[plane[matches[:, 0]], plane[matches[:, 0]]]
    P = np.r_[ends[matches[:, 1], 0:3], ends[matches[:, 1], 3:6]]
    depth = np.maximum(P[:, 2] + t[2], 1e-3)
    A = n / depth[:, None]
    b = -np.einsum("pk,pk->p", n, P) / depth
    prior = 1e-3 / max(float(depth.mean()), 1e-3)
    lhs = A.T @ A + prior**2 * np.eye(3)
    rhs = A.T @ b + prior**2 * t
    return np.linalg.solve(lhs, rhs)


def finish(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    candidates: tuple[np.ndarray, np.ndarray],
    config: TranslationConfig,
    match: MatchConfig,
) -> TranslationHypothesis:
    """Returns the hypothesis from candidate translations (H, 3) ranked by approximate scores (H,).

    The best candidate is polished (least squares, re-match) and scored with ``match_segments``; so is
    the best-scoring candidate whose camera centre lies clearly elsewhere (the runner-up). Should the
    runner-up end with more inliers, the two swap.
    """
    T, scores = candidates
    if len(T) == 0:
        return _empty()
    order = np.argsort(-scores, kind="stable")
    best_t, best = _polish(lines2d, lines3d, camera, R, pairs, T[order[0]], config.polish_rounds, match)
    far = config.distinct_fraction * scene_size(lines3d)
    # camera centres are -R^T t, so centre distances equal translation distances
    distinct = order[np.linalg.norm(T[order] - best_t, axis=1) > far]
    if len(distinct) == 0:
        return TranslationHypothesis(best_t, best, len(best), 0)
    other_t, other = _polish(lines2d, lines3d, camera, R, pairs, T[distinct[0]], 1, match)
    if len(other) > len(best):
        best_t, best, other = other_t, other, best
    log.debug("translation: %d inliers, runner-up %d", len(best), len(other))
    return TranslationHypothesis(best_t, best, len(best), len(other))


def _polish(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    t: np.ndarray,
    rounds: int,
    match: MatchConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((3,) t, (K, 2) matches) after alternating least squares and re-matching, keeping the best.

    The rounds re-match on the compatible pairs (cheap); the result is matched once with match_segments.
    """
    best_t = np.asarray(t, float)
    _, i, j = pair_matches(lines2d, camera, pairs, best_t[None], match)
    best_count = len(np.unique(i))
    for _ in range(rounds):
        t_new = refine_translation(pairs.plane, pairs.ends, best_t, np.c_[i, j])
        _, i_new, j_new = pair_matches(lines2d, camera, pairs, t_new[None], match)
        count = len(np.unique(i_new))
        if count < best_count:
            break
        best_t, best_count, i, j = t_new, count, i_new, j_new
    return best_t, match_segments(lines2d, lines3d, camera, make_cam_from_world(R, best_t), match)
