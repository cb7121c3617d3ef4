"""Translation and 2D-3D correspondences for one rotation candidate (paper section III-C, Algorithm 2).

With R fixed, a 2D segment i and a 3D segment j correspond only if j's camera-frame direction lies in i's
interpretation plane (``translation_pairs``); each such pair gives one linear equation in t (eq.
"coplanar": ``(R P + t) . n = 0``). ``"ransac"`` samples three pairs at a time as the paper does
(``translation_ransac``); ``"search"`` (default) reads each pair as a whole-segment correspondence, which
fixes t alone, and votes (``translation_search``). Both end the same way: the best hypotheses are
scored with the shared inlier test (``matching.match_segments``), so ``num_inliers`` is the paper's
inlier count; "search" first polishes them by robust least squares on the coplanarity equations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from .camera import Camera
from .config import MatchConfig, TranslationConfig
from .directions import DirectionClusters
from .geometry import make_cam_from_world
from .matching import match_segments
from .translation_inliers import pair_matches
from .translation_pairs import Pairs, compatible_pairs

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TranslationHypothesis:
    """The best translation for one rotation candidate and what supports it.

    t: (3,) float64 so that ``cam_from_world = [R | t]``; matches: (K, 2) int64 ``(i2d, j3d)`` from
    ``match_segments`` at ``[R | t]``; num_inliers = K; runner_up_inliers: inliers of the best hypothesis
    whose camera centre is clearly elsewhere (> ``config.distinct_fraction`` of the scene size away);
    runner_up_t (3,) and runner_up_matches (K', 2): that hypothesis itself (NaN / empty if none), which
    the pipeline's contest refines too: at the true rotation of a repetitive facade the truth is
    sometimes the runner-up by a few inliers.
    """

    t: np.ndarray
    matches: np.ndarray
    num_inliers: int
    runner_up_inliers: int
    runner_up_t: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    runner_up_matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))


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
    if pairs.size < 3:
        return _empty()
    if config.method == "ransac":
        from .translation_ransac import ransac_candidates

        candidates = ransac_candidates(lines2d, lines3d, camera, R, pairs, config, match)
    else:
        from .translation_search import search_candidates

        T, scores, verified = search_candidates(lines2d, lines3d, camera, R, pairs, config, match)
        return finish(lines2d, lines3d, camera, R, pairs, (T, scores), config, match, verified)
    return finish(lines2d, lines3d, camera, R, pairs, candidates, config, match)


def screen_translation(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    clusters3d: DirectionClusters,
    config: TranslationConfig,
    match: MatchConfig,
) -> int:
    """Returns a cheap inlier count for rotation R: "search" with ``config.screen_num_verify`` voted cells
    counted on the compatible pairs (``pair_inliers``, a lower bound of ``match_segments``), unpolished.

    Ranks rotation candidates so that only the best get ``estimate_translation``; same arguments.
    """
    from .translation_search import search_candidates

    pairs = compatible_pairs(lines2d, lines3d, camera, R, clusters3d, config.coplanar_px)
    if pairs.size < 3:
        return 0
    screen = replace(config, max_hypotheses=config.screen_max_hypotheses, num_verify=config.screen_num_verify)
    _, scores, _ = search_candidates(lines2d, lines3d, camera, R, pairs, screen, match)
    return int(scores.max()) if len(scores) else 0


def _empty() -> TranslationHypothesis:
    return TranslationHypothesis(np.zeros(3), np.zeros((0, 2), dtype=np.int64), 0, 0)


def scene_size(lines3d: np.ndarray) -> float:
    """Returns the bounding-box diagonal (m) of (M, 6) segments, the scale for 'clearly different'."""
    ends = lines3d.reshape(-1, 3)
    return max(float(np.linalg.norm(ends.max(axis=0) - ends.min(axis=0))), 1e-9)


def refine_translation(
    plane: np.ndarray,
    ends: np.ndarray,
    t: np.ndarray,
    matches: np.ndarray,
    scale_rad: float,
    iterations: int = 3,
) -> np.ndarray:
    """Returns (3,) t minimising the robust, depth-weighted coplanarity residuals of matches (eq. "coplanar").

    plane: (N, 3) interpretation normals of the 2D segments; ends: (M, 6) rotated 3D endpoints ``R P``.
    Both endpoints of each matched 3D segment must lie on the 2D segment's interpretation plane; dividing
    by depth makes each residual an angle (~ pixels / f). Iteratively reweighted (Cauchy, scale_rad) so
    that accidental matches do not pull; a weak prior on the current t keeps directions no match
    constrains (e.g. along the only cluster's direction) where they were.
    """
    if len(matches) == 0:
        return t
    n = np.r_[plane[matches[:, 0]], plane[matches[:, 0]]]
    P = np.r_[ends[matches[:, 1], 0:3], ends[matches[:, 1], 3:6]]
    offset = np.einsum("pk,pk->p", n, P)
    for _ in range(iterations):
        depth = np.maximum(P[:, 2] + t[2], 1e-3)
        residual = (offset + n @ t) / depth
        w = 1.0 / (depth * np.sqrt(1.0 + (residual / scale_rad) ** 2))  # sqrt of Cauchy weight, per depth
        A, b = n * w[:, None], -offset * w
        prior = 1e-3 * float(w.mean())
        t = np.linalg.solve(A.T @ A + prior**2 * np.eye(3), A.T @ b + prior**2 * t)
    return t


def finish(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    candidates: tuple[np.ndarray, np.ndarray],
    config: TranslationConfig,
    match: MatchConfig,
    verified: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> TranslationHypothesis:
    """Returns the hypothesis from candidate translations (H, 3) ranked by approximate scores (H,).

    The best candidate is polished ("search" only: least squares, re-match) and scored with
    ``match_segments``; so is the best-scoring candidate whose camera centre lies clearly elsewhere (the
    runner-up; polished only when close). Should the runner-up end with more inliers, the two swap.
    verified: the candidates' inlier pairs ``(h, i, j)`` (``pair_matches``), if known: polishing starts there.
    """
    T, scores = candidates
    if len(T) == 0:
        return _empty()
    order = np.argsort(-scores, kind="stable")
    # the paper's RANSAC keeps its best sample as is (refinement comes later, section III-D)
    polish = config.polish_rounds if config.method == "search" else 0
    best_t, best = _polish(
        lines2d, lines3d, camera, R, pairs, T[order[0]], polish, match, _of(verified, order[0])
    )
    far = config.distinct_fraction * scene_size(lines3d)
    # camera centres are -R^T t, so centre distances equal translation distances
    distinct = order[np.linalg.norm(T[order] - best_t, axis=1) > far]
    if len(distinct) == 0:
        return TranslationHypothesis(best_t, best, len(best), 0)
    # a distant second (under 2/3 of the best's score) cannot win: counted exactly, not polished
    rounds = min(polish, 1) if scores[distinct[0]] >= (2.0 / 3.0) * scores[order[0]] else 0
    first = _of(verified, distinct[0])
    other_t, other = _polish(lines2d, lines3d, camera, R, pairs, T[distinct[0]], rounds, match, first)
    if len(other) > len(best):
        best_t, best, other = other_t, other, best
    log.debug("translation: %d inliers, runner-up %d", len(best), len(other))
    return TranslationHypothesis(best_t, best, len(best), len(other), other_t, other)


def _of(
    verified: tuple[np.ndarray, np.ndarray, np.ndarray] | None, k: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns candidate k's inlier pairs ``(i, j)`` from all candidates' ``(h, i, j)``, if known."""
    if verified is None:
        return None
    h, i, j = verified
    sel = np.flatnonzero(h == k)
    return i.take(sel), j.take(sel)


def _polish(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    t: np.ndarray,
    rounds: int,
    match: MatchConfig,
    first: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((3,) t, (K, 2) matches) after alternating least squares and re-matching, keeping the best.

    The rounds re-match on the compatible pairs (cheap); the result is matched once with match_segments.
    first: t's inlier pairs ``(i, j)`` if already known.
    """
    best_t = np.asarray(t, float)
    if rounds == 0:  # nothing to polish: the exact count only
        return best_t, match_segments(lines2d, lines3d, camera, make_cam_from_world(R, best_t), match)
    scale = 0.5 * match.distance_px / max(camera.fx, camera.fy)
    i, j = first if first is not None else pair_matches(lines2d, camera, pairs, best_t[None], match)[1:]
    best_count = np.count_nonzero(np.bincount(i, minlength=len(lines2d)))
    for _ in range(rounds):
        t_new = refine_translation(pairs.plane, pairs.ends, best_t, np.c_[i, j], scale)
        _, i_new, j_new = pair_matches(lines2d, camera, pairs, t_new[None], match)
        count = np.count_nonzero(np.bincount(i_new, minlength=len(lines2d)))
        if count < best_count:
            break
        best_t, best_count, i, j = t_new, count, i_new, j_new
    return best_t, match_segments(lines2d, lines3d, camera, make_cam_from_world(R, best_t), match)
