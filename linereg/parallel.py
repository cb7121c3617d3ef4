"""3D parallel clusters: multiple RANSAC on segment directions (paper section III-B, Algorithm 1 steps 3-4).

A hypothesis is the direction of one sampled segment (long ones preferred); a segment supports it when
the (sign-free: a 3D line has no orientation) angle between them is within the segment's tolerance: the
paper's 1 degree, widened by the angular uncertainty ``2 sqrt(2) noise_m / length`` of a segment whose
endpoints are off by ``noise_m`` (capped at ``max_angle_deg``) -- real clouds give short segments whose
directions are off by degrees, which a fixed 1 degree leaves unclustered. The best hypothesis by MSAC score
(each inlier adds its length times ``1 - angle^2 / tolerance^2``, so a precise mode beats a broad one) is
refined, its members removed, and the search repeated ``num_clusters`` (paper: c = 5) times; near-duplicate
directions are then merged (with their members), segments no round took are assigned to a direction they
pass, and the clusters are sorted by support.

The helpers below (scatter eigenvectors, merging, sorting, sign) are shared with ``vanishing``.
"""

from __future__ import annotations

import logging

import numpy as np

from .config import ParallelConfig
from .directions import DirectionClusters
from .errors import InvalidInputError

logger = logging.getLogger(__name__)


def parallel_clusters(lines3d: np.ndarray, config: ParallelConfig | None = None) -> DirectionClusters:
    """Returns the dominant 3D directions (world frame, z >= 0) of (M, 6) float64 segments, strongest first.

    ``labels`` (M,) gives each segment's cluster (-1: none); ``support`` is the summed member length (m).
    """
    config = config or ParallelConfig()
    lines3d = as_segments(lines3d, "lines3d", 6)
    d, lengths = _directions_and_lengths(lines3d)
    usable = lengths > 0.0
    cos_thr = np.cos(tolerance_rad(lengths, config))
    rng = np.random.default_rng(config.seed)
    left = usable.copy()  # not yet in a cluster
    # one (H, S) work buffer for all rounds: fresh large temporaries cost more in page faults than the math
    work = np.empty(config.ransac_iterations * min(len(d), config.score_sample), dtype=np.float32)
    found: list[np.ndarray] = []
    labels = np.full(len(d), -1, dtype=np.int64)
    for _ in range(config.num_clusters):
        if np.count_nonzero(left) < max(config.min_lines, 1):
            break
        members = _best_cluster(d, lengths, left, cos_thr, config, rng, work)
        if np.count_nonzero(members) < config.min_lines:
            break
        labels[members] = len(found)
        found.append(principal_direction(d[members], lengths[members] ** 2, largest=True))
        left &= ~members
    labels, directions = merge_clusters(np.array(found).reshape(-1, 3), labels, config.merge_angle_deg)
    directions = refit_directions(d, lengths**2, labels, directions, largest=True)
    # segments left out by RANSAC join a merged direction they pass; merged members stay
    assigned = nearest_direction(d, directions, cos_thr, usable)
    labels = np.where(assigned >= 0, assigned, labels)
    directions = refit_directions(d, lengths**2, labels, directions, largest=True)
    return sort_clusters(directions, labels, lengths, config.min_lines, config.top_k, diverse=True)


def tolerance_rad(lengths: np.ndarray, config: ParallelConfig) -> np.ndarray:
    """Returns (M,) float64 the angle (rad) within which a segment of each length is parallel to a direction:
    ``hypot(parallel_angle_deg, 2 sqrt(2) noise_m / length)``, at most ``max(max_angle_deg, parallel_angle_deg)``.

    Endpoint noise sigma tilts a segment by ~ sqrt(2) sigma / L rad (1 std); 2 std of it are allowed.
    """
    slack = 2.0 * np.sqrt(2.0) * config.noise_m / np.maximum(lengths, 1e-12)
    cap = np.radians(max(config.max_angle_deg, config.parallel_angle_deg))
    return np.minimum(np.hypot(np.radians(config.parallel_angle_deg), slack), cap)


def _directions_and_lengths(lines3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((M, 3) unit directions, (M,) lengths) in one pass (``geometry.segment_directions`` and
    ``segment_lengths`` in one: the temporaries of two passes cost more than the arithmetic)."""
    d = lines3d[:, 3:6] - lines3d[:, 0:3]
    lengths = np.sqrt(np.einsum("ij,ij->i", d, d))
    d /= np.maximum(lengths, 1e-300)[:, None]
    return d, lengths


def _best_cluster(
    d: np.ndarray,
    w: np.ndarray,
    left: np.ndarray,
    cos_thr: np.ndarray,
    config: ParallelConfig,
    rng: np.random.Generator,
    work: np.ndarray,
) -> np.ndarray:
    """Returns the (M,) bool members among ``left`` of the best sign-free parallel set, after one refit.

    cos_thr: (M,) cosine of each segment's tolerance. ``ransac_iterations`` hypotheses (segments drawn by
    length) are scored (MSAC, lengths ``w``) on at most ``score_sample`` random segments left, which
    estimate a cluster's share of the length well enough to choose the best; its members then come from
    all segments left. The refit weighs members by ``w^2`` (a direction's error ~ noise / length).
    ``work``: float32 buffer of >= iterations * S elements.
    """
    iterations = config.ransac_iterations
    idx = np.flatnonzero(left)
    hypotheses = d[idx[sample_weighted(w[idx], iterations, rng)]].astype(np.float32)
    if len(idx) > config.score_sample:
        idx = idx[rng.integers(0, len(idx), config.score_sample)]
    score = work[: iterations * len(idx)].reshape(iterations, len(idx))
    np.matmul(hypotheses, d[idx].T.astype(np.float32), out=score)  # (H, S): all hypotheses against all
    np.abs(score, out=score)
    # 1 - cos ~ angle^2 / 2: (1 - cos) / (1 - cos_thr) is (angle / tolerance)^2, <= 1 for an inlier
    np.subtract(1.0, score, out=score)
    np.divide(score, (1.0 - cos_thr[idx]).astype(np.float32), out=score)
    np.subtract(1.0, score, out=score)
    np.maximum(score, 0.0, out=score)
    best = hypotheses[np.argmax(score @ w[idx].astype(np.float32))].astype(np.float64)
    members = (np.abs(d @ best) >= cos_thr) & left
    refined = principal_direction(d[members], w[members] ** 2, largest=True)
    return (np.abs(d @ refined) >= cos_thr) & left


def nearest_direction(
    d: np.ndarray, directions: np.ndarray, cos_thr: np.ndarray, usable: np.ndarray
) -> np.ndarray:
    """Returns (M,) int64 index of the most parallel direction within each segment's (M,) threshold, else -1."""
    if len(directions) == 0:
        return np.full(len(d), -1, dtype=np.int64)
    cos = d @ directions.T
    np.abs(cos, out=cos)
    best = np.argmax(cos, axis=1)
    ok = (np.take_along_axis(cos, best[:, None], axis=1)[:, 0] >= cos_thr) & usable
    return np.where(ok, best, -1).astype(np.int64)


def as_segments(array: object, name: str, width: int) -> np.ndarray:
    """Returns ``array`` as finite (N, width) float64, or raises InvalidInputError (zero length allowed)."""
    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != width:
        raise InvalidInputError(f"{name} must have shape (N, {width}), got {a.shape}")
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{name} contains NaN or inf")
    return a


def sample_weighted(w: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Returns (count,) int64 indices drawn with replacement, with probability proportional to ``w`` (n,)."""
    cdf = np.cumsum(w)
    idx = np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right")
    return np.minimum(idx, len(w) - 1)


def principal_direction(vectors: np.ndarray, weights: np.ndarray, largest: bool) -> np.ndarray:
    """Returns the (3,) unit eigenvector of ``sum w_i v_i v_i^T`` with the largest (or smallest) eigenvalue.

    Largest: the mean axis of sign-free 3D directions (paper: PCA of the cluster). Smallest: the vector most
    orthogonal to all rows, i.e. the smallest right singular vector of ``sqrt(w_i) v_i`` (Rother's VD).
    """
    scatter = (vectors.T * weights) @ vectors
    _, vecs = np.linalg.eigh(scatter)  # ascending eigenvalues
    return vecs[:, -1] if largest else vecs[:, 0]


def refit_directions(
    vectors: np.ndarray, weights: np.ndarray, labels: np.ndarray, directions: np.ndarray, largest: bool
) -> np.ndarray:
    """Returns (K, 3) directions re-fitted by ``principal_direction`` on each cluster's members, all clusters
    at once; a cluster without members keeps its direction (an empty scatter has no eigenvector)."""
    k = len(directions)
    ok = labels >= 0
    lab, v, w = labels[ok], vectors[ok], weights[ok]
    scatter = np.empty((k, 3, 3))
    for p, q in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):  # the 6 distinct entries, per cluster
        scatter[:, p, q] = scatter[:, q, p] = np.bincount(lab, weights=w * v[:, p] * v[:, q], minlength=k)
    _, vecs = np.linalg.eigh(scatter)  # ascending eigenvalues, (K, 3, 3)
    fitted = vecs[:, :, -1] if largest else vecs[:, :, 0]
    empty = np.bincount(lab, minlength=k) == 0
    return np.where(empty[:, None], directions, fitted)


def merge_clusters(
    directions: np.ndarray, labels: np.ndarray, merge_angle_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N,) labels, (G, 3) directions) after joining each cluster whose direction lies within
    ``merge_angle_deg`` (sign-free) of an earlier (stronger) one to it (paper: merge adjacent directions).

    directions: (K, 3) in the order found; labels: (N,) int64 in [-1, K).
    """
    cos_merge = np.cos(np.radians(merge_angle_deg))
    group = np.empty(len(directions) + 1, dtype=np.int64)
    group[-1] = -1  # unassigned segments stay unassigned
    kept: list[int] = []
    for k, v in enumerate(directions):
        near = [g for g, r in enumerate(kept) if abs(float(v @ directions[r])) >= cos_merge]
        group[k] = near[0] if near else len(kept)
        if not near:
            kept.append(k)
    return group[labels], directions[kept].reshape(-1, 3)


def canonical_sign(directions: np.ndarray) -> np.ndarray:
    """Returns (K, 3) directions flipped so that z >= 0 (at z = 0: y > 0; at y = z = 0: x > 0)."""
    key = np.where(
        directions[:, 2] != 0, directions[:, 2], np.where(directions[:, 1] != 0, directions[:, 1], 1)
    )
    key = np.where((directions[:, 2] == 0) & (directions[:, 1] == 0), directions[:, 0], key)
    return np.where((key < 0)[:, None], -directions, directions)


def sort_clusters(
    directions: np.ndarray,
    labels: np.ndarray,
    lengths: np.ndarray,
    min_lines: int,
    top_k: int,
    diverse: bool = False,
) -> DirectionClusters:
    """Returns clusters with >= ``min_lines`` members, by summed member length descending, at most ``top_k``.

    ``diverse``: which ``top_k`` are kept is decided by ``diverse_order`` (support times how far a direction
    is from those already kept), then they are sorted by support as always.
    """
    k = len(directions)
    assigned = labels >= 0
    support = np.bincount(labels[assigned], weights=lengths[assigned], minlength=k)
    count = np.bincount(labels[assigned], minlength=k)
    eligible = np.array(
        [c for c in np.argsort(-support, kind="stable") if count[c] >= min_lines], dtype=np.int64
    )
    if diverse and len(eligible) > top_k:
        chosen = eligible[diverse_order(directions[eligible], support[eligible], top_k)]
        eligible = chosen[np.argsort(-support[chosen], kind="stable")]
    order = list(eligible[:top_k])
    remap = np.full(k + 1, -1, dtype=np.int64)  # remap[-1] stays -1 for unassigned segments
    remap[order] = np.arange(len(order))
    directions = canonical_sign(directions[order].reshape(-1, 3))
    return DirectionClusters(directions, remap[labels], support[order].astype(np.float64))


def diverse_order(directions: np.ndarray, support: np.ndarray, count: int) -> np.ndarray:
    """Returns (<= count,) int64 indices of (K, 3) sign-free directions picked greedily: the strongest, then
    each time the one with the most ``support * sin(angle to the nearest picked)``.

    A direction a few degrees from one already picked adds no rotational information (the rotation stage
    cannot pair near-parallel directions), however long its members: on a LiDAR street map the ground's
    scan-ring contours give several near-horizontal clusters that would push the vertical one out.
    """
    picked = [int(np.argmax(support))] if len(support) else []
    sine = np.ones(len(support))
    while 0 < len(picked) < min(count, len(support)):
        cos = np.abs(directions @ directions[picked[-1]])
        sine = np.minimum(sine, np.sqrt(np.maximum(1.0 - cos**2, 0.0)))
        gain = np.where(np.isin(np.arange(len(support)), picked), -1.0, support * sine)
        picked.append(int(np.argmax(gain)))
    return np.array(picked, dtype=np.int64)
