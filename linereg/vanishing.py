"""2D vanishing directions: multiple RANSAC on interpretation-plane normals (Rother 2002; paper III-B).

Projections of parallel 3D lines meet in a vanishing point; on the unit sphere their interpretation planes
(normals ``n_i``) all contain the vanishing direction ``v``, so ``n_i . v = 0``. A hypothesis is
``v = n_a x n_b`` of two sampled segments (long ones preferred). Whether a segment supports ``v`` is judged in
the image: the angle between the segment and the line from its midpoint to the vanishing point ``K v``
(homogeneous, so a point at infinity, ``v_z = 0``, works too) must be below ``inlier_angle_deg`` plus the
angular uncertainty ``2 sqrt(2) noise_px / length`` of the segment itself — short segments are noisy.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from .camera import Camera
from .config import VanishingConfig
from .directions import DirectionClusters
from .geometry import interpretation_normals, segment_directions, segment_lengths
from .parallel import (
    as_segments,
    merge_clusters,
    principal_direction,
    refit_directions,
    sample_weighted,
    sort_clusters,
)

logger = logging.getLogger(__name__)


class _SegmentTest(NamedTuple):
    """Per-segment terms of the midpoint-to-VP angle test, so that an (H, N) test is two matrix products.

    A: (3, N) homogeneous line through each midpoint m along its unit direction s: ``p @ A = s x (p_xy - p_z m)``
    Q: (4, N) with ``[|p_xy|^2, p_z p_x, p_z p_y, p_z^2] @ Q = |p_xy - p_z m|^2 sin^2(tolerance)``
    """

    A: np.ndarray
    Q: np.ndarray


def vanishing_directions(
    lines2d: np.ndarray, camera: Camera, config: VanishingConfig | None = None
) -> DirectionClusters:
    """Returns the dominant vanishing directions (camera frame, unit, z >= 0) of (N, 4) undistorted pixel
    segments, strongest first; ``labels`` (N,) gives each segment's cluster (-1: none), ``support`` the
    summed member length (px)."""
    config = config or VanishingConfig()
    lines2d = as_segments(lines2d, "lines2d", 4)
    lengths = segment_lengths(lines2d)
    usable = lengths > 1e-9
    lines2d = np.where(usable[:, None], lines2d, [0.0, 0.0, 1.0, 0.0])  # keep NaN out of unusable rows
    normals = interpretation_normals(lines2d, camera)
    test = _segment_test(lines2d, lengths, config)
    rng = np.random.default_rng(config.seed)
    left = usable.copy()  # not yet in a cluster
    # one work buffer for all rounds: fresh (H, N) temporaries cost more in page faults than the math
    work = np.empty(2 * config.ransac_iterations * min(len(lines2d), config.score_sample))
    found: list[np.ndarray] = []
    found_labels = np.full(len(lines2d), -1, dtype=np.int64)
    for _ in range(config.num_clusters):
        if np.count_nonzero(left) < max(config.min_lines, 2):
            break
        v, members = _best_vd(normals, lengths, left, test, camera.K, config, rng, work)
        if np.count_nonzero(members) < config.min_lines:
            break
        found_labels[members] = len(found)
        found.append(v)
        left &= ~members
    merged, directions = merge_clusters(np.array(found).reshape(-1, 3), found_labels, config.merge_angle_deg)
    labels = merged
    # re-fit, then re-assign: a segment goes to the VD it fits best (a short one passes several and the
    # first round took it), else stays in its merged cluster
    for _ in range(2):
        directions = refit_directions(normals, lengths**2, labels, directions, largest=False)
        assigned = _assign(test, camera.K, directions, usable)
        labels = np.where(assigned >= 0, assigned, merged)
    directions = refit_directions(normals, lengths**2, labels, directions, largest=False)
    return sort_clusters(directions, labels, lengths, config.min_lines, config.top_k)


def _best_vd(
    normals: np.ndarray,
    lengths: np.ndarray,
    left: np.ndarray,
    test: _SegmentTest,
    K: np.ndarray,
    config: VanishingConfig,
    rng: np.random.Generator,
    work: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((3,) refined VD, (N,) bool members among ``left``) of the best RANSAC hypothesis.

    The VD is refitted as the smallest right singular vector of the member normals scaled by length (paper:
    SVD of the great-circle normals), i.e. weights ``length^2``: a segment's direction error ~ noise / length,
    so ``length^2`` is its inverse variance.
    """
    idx = np.flatnonzero(left)
    pairs = idx[sample_weighted(lengths[idx], 2 * config.ransac_iterations, rng)]
    na, nb = normals[pairs[0::2]], normals[pairs[1::2]]
    hyp = na[:, [1, 2, 0]] * nb[:, [2, 0, 1]] - na[:, [2, 0, 1]] * nb[:, [1, 2, 0]]  # n_a x n_b
    norm = np.linalg.norm(hyp, axis=1)
    hyp = hyp[norm > 1e-9] / norm[norm > 1e-9, None]  # drops a == b and (near-)collinear pairs
    if len(hyp) == 0:
        return np.zeros(3), np.zeros(len(left), dtype=bool)
    if len(idx) > config.score_sample:  # a random subset: the best hypothesis stands out all the same
        idx = idx[rng.integers(0, len(idx), config.score_sample)]
    sub = _SegmentTest(test.A[:, idx], test.Q[:, idx])
    score = _ratios(sub, K, hyp, work)  # (H, S): every hypothesis against every (sampled) segment
    # MSAC: an inlier adds its length times (1 - ratio), so VDs that segments point at exactly win over
    # ones that many segments only just pass (typically long outliers near a weak true VD)
    np.subtract(1.0, score, out=score)
    np.maximum(score, 0.0, out=score)
    best = hyp[np.argmax(score @ lengths[idx])]
    members = (_ratios(test, K, best[None])[0] <= 1.0) & left
    # refit on the members, then re-collect them around the refined VD (LO-RANSAC step)
    v = principal_direction(normals[members], lengths[members] ** 2, largest=False)
    return v, (_ratios(test, K, v[None])[0] <= 1.0) & left


def _segment_test(lines2d: np.ndarray, lengths: np.ndarray, config: VanishingConfig) -> _SegmentTest:
    """Returns the precomputed terms of the midpoint-to-VP angle test for (N, 4) segments."""
    s = segment_directions(lines2d)
    mid = 0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4])
    A = np.stack([-s[:, 1], s[:, 0], mid[:, 0] * s[:, 1] - mid[:, 1] * s[:, 0]])
    # endpoint noise sigma tilts a segment by ~ sqrt(2) sigma / L rad (1 std); allow 2 std on top of the base
    slack = 2.0 * np.sqrt(2.0) * config.noise_px / np.maximum(lengths, 1e-9)
    sin2_tol = np.sin(np.minimum(np.hypot(np.radians(config.inlier_angle_deg), slack), np.pi / 2)) ** 2
    Q = np.stack([np.ones(len(mid)), -2.0 * mid[:, 0], -2.0 * mid[:, 1], (mid**2).sum(axis=1)]) * sin2_tol
    return _SegmentTest(A, Q)


def _ratios(
    test: _SegmentTest, K: np.ndarray, directions: np.ndarray, work: np.ndarray | None = None
) -> np.ndarray:
    """Returns (H, N) squared sine of the angle between each segment and the line from its midpoint to each
    VP ``p = K v``, over the segment's squared tolerance (<= 1: inlier); a view of ``work`` if given
    (float64, >= 2 H N elements)."""
    H, N = len(directions), test.A.shape[1]
    work = np.empty(2 * H * N) if work is None else work
    ratio, bound = work[: H * N].reshape(H, N), work[H * N : 2 * H * N].reshape(H, N)
    p = directions @ K.T  # (H, 3) homogeneous vanishing points, z = 0 at infinity
    pz = p[:, 2:3]
    np.matmul(
        np.hstack([(p[:, :2] ** 2).sum(axis=1, keepdims=True), pz * p[:, :2], pz**2]), test.Q, out=bound
    )
    # a VP on the midpoint itself (bound = 0): the segment passes through it, an inlier
    np.maximum(bound, 1e-300, out=bound)
    np.matmul(p, test.A, out=ratio)  # sine times |p_xy - p_z m|
    np.square(ratio, out=ratio)
    return np.divide(ratio, bound, out=ratio)


def _assign(test: _SegmentTest, K: np.ndarray, directions: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Returns (N,) int64 index of the VD each segment fits best (lowest ratio, if <= 1), else -1."""
    if len(directions) == 0:
        return np.full(len(usable), -1, dtype=np.int64)
    ratios = _ratios(test, K, directions)
    best = np.argmin(ratios, axis=0)
    ok = (ratios[best, np.arange(ratios.shape[1])] <= 1.0) & usable
    return np.where(ok, best, -1).astype(np.int64)
