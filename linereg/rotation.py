"""Rotation candidates from vanishing-direction <-> 3D-direction pairings (paper III-B, Algorithm 1, eq. 2).

A vanishing direction is the image of a 3D direction: ``v_2d = R v_3d`` (eq. 1). Two pairs fix R (eq. 2,
the third column being the cross product of the first two). Which VD goes with which 3D cluster is unknown
and a 3D line has no sign, so every pairing and every sign is a candidate: 8 for two pairs (paper) when the
two directions are perpendicular; a pairing whose angle(VD1, VD2) differs from angle(s1 D1, s2 D2) cannot
be a rotation and is rejected (for non-perpendicular directions that leaves 4). A third pair, where both
sides have one, validates a candidate: validated ones come first, the best others after them. VD signs are arbitrary (z >= 0), so signs live on the 3D side.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from .camera import Camera
from .config import RegisterConfig, RotationConfig
from .directions import DirectionClusters
from .geometry import interpretation_normals, rotation_error_deg, rotation_from_vector, segment_lengths
from .parallel import parallel_clusters
from .vanishing import vanishing_directions

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class RotationCandidate:
    """A world -> camera rotation ``R`` (``v_cam = R d_world``) and the pairings it was fitted on.

    pairs: ((vd index, cluster index, sign), ...) with ``R (sign * D[cluster]) ~ V[vd]``; two or three.
    residual_deg: largest angle between ``R (sign * D)`` and its VD over the pairs.
    score: plausibility used for ordering (higher first): support of the directions paired, less residual.
    """

    R: np.ndarray
    pairs: tuple[tuple[int, int, int], ...]
    residual_deg: float
    score: float


def rotation_candidates(
    vds: DirectionClusters,
    clusters: DirectionClusters,
    config: RotationConfig | None = None,
    admit: Callable[[np.ndarray], bool] | None = None,
) -> list[RotationCandidate]:
    """Returns distinct rotation candidates, most plausible first, at most ``config.max_candidates``.

    Order: confirmed by a third pair first, then by ``config.ranking`` (default: the image's share of
    support of the paired VDs plus the map's share of the paired clusters, less 0.01 per degree of residual).

    vds: camera-frame vanishing directions (strongest first); clusters: world-frame parallel clusters.
    Pairings are tried among the ``config.top_k`` strongest of each (an image may not show the map's
    second-strongest direction). Empty when either side has fewer than two non-parallel directions.
    ``admit(R)``: what a prior allows; the pairings it refuses are dropped before any is ranked or cut (a
    true pairing that a wrong one confirmed by accident would push out of the list stays in it).
    """
    config = config or RotationConfig()
    V, D = vds.directions[: config.top_k], clusters.directions[: config.top_k]
    pairs = _consistent_pairings(V, D, config)  # (P, 2, 3)
    if admit is not None and len(pairs):
        pairs = pairs[[admit(R) for R in _fit(V, D, pairs)]]
    if len(pairs) == 0:
        return []
    third = _third_pairs(_fit(V, D, pairs), V, D, pairs, config.third_pair_tolerance_deg)  # (P, 3), -1: none
    confirmed = third[:, 0] >= 0
    # a third pair confirming some candidates does not refute the others: with noisy real directions an 8 deg
    # tolerance confirms wrong rotations by accident, so the best ``max_unconfirmed`` others follow them
    groups = [np.concatenate([pairs, third[:, None, :]], axis=1)[confirmed], pairs[~confirmed]]
    wv, wd = _weights(vds.support[: len(V)]), _weights(clusters.support[: len(D)])
    found = [_scored(V, D, g, wv, wd, config.ranking) for g in groups if len(g)]
    R = np.concatenate([f[0] for f in found])
    residual, score = np.concatenate([f[1] for f in found]), np.concatenate([f[2] for f in found])
    paired = [p for f in found for p in f[3]]
    rank = np.lexsort((-score, -np.array([len(p) for p in paired])))  # confirmed (three pairs) first
    order = _dedupe(R, rank, config.dedupe_angle_deg)
    if confirmed.any():
        unconfirmed = [n for n in order if len(paired[n]) == 2][: config.max_unconfirmed]
        order = [n for n in order if len(paired[n]) == 3] + unconfirmed
    order = order[: config.max_candidates]
    logger.debug(
        "%d pairings, %d confirmed by a third, %d distinct", len(confirmed), confirmed.sum(), len(order)
    )
    return [RotationCandidate(R[n], paired[n], float(residual[n]), float(score[n])) for n in order]


def _scored(
    V: np.ndarray, D: np.ndarray, pairs: np.ndarray, wv: np.ndarray, wd: np.ndarray, ranking: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[tuple[int, int, int], ...]]]:
    """Returns (R (P, 3, 3), residual_deg (P,), score (P,), pairs as tuples) of (P, k, 3) pairings.

    "separate": the paired VDs' share of the image support plus the paired clusters' share of the map
    support; which VD goes with which cluster is left to the angles (residual). A map's and an image's
    support do not rank a direction alike (a LiDAR map's vertical edges are few, an image's many), so the
    "product" ranking (sum of sqrt(VD share x cluster share): strongest with strongest) cuts true pairings.
    """
    R = _fit(V, D, pairs)
    residual = _residual_deg(R, V, D, pairs)
    if ranking == "product":
        support = np.sqrt(wv[pairs[..., 0]] * wd[pairs[..., 1]]).sum(axis=1)
    else:
        support = wv[pairs[..., 0]].sum(axis=1) + wd[pairs[..., 1]].sum(axis=1)
    tuples = [tuple((int(i), int(a), int(s)) for i, a, s in p) for p in pairs]
    return R, residual, support - 0.01 * residual, tuples


def single_direction_candidates(
    vds: DirectionClusters,
    clusters: DirectionClusters,
    lines2d: np.ndarray,
    camera: Camera,
    config: RotationConfig | None = None,
) -> list[np.ndarray]:
    """Returns (3, 3) rotations that map a 3D cluster direction (either sense) onto one of the ``top_k``
    strongest vanishing directions, at the angles about it where the map's other directions explain the most
    image segments: those of the strongest direction first (``_one_direction_candidates``), then those of
    the next that no earlier one duplicates.

    Every strong direction is matched, not only the strongest: where these rotations are needed, a chance
    alignment of clutter may be the strongest (on two paper scenes with 60 % outlier segments the strongest
    lay 10 and 34 deg from every true direction, the second or third 2-9 deg from one). Each direction
    keeps its own ``max_candidates``: ranked together, a wrong direction's angles pushed the true
    direction's out of a shared list, where they rank low (16th-22nd of 24: the score of an angle counts
    clutter too; docs/measurements.md, session 47).

    Used when two directions do not pair (an image with one vanishing direction: a single facade seen
    head-on, a corridor, clutter hiding the second direction's VD), and when no pose under the paired
    candidates explains the image (``pipeline.register_undistorted``: the second direction may be a chance
    alignment of clutter). Beside every paired candidate they would multiply the rotations searched (4 ->
    28 on the paper's scenes) and the search's time with them.
    """
    config = config or RotationConfig()
    if len(vds) == 0 or len(clusters) == 0:
        return []
    normals = interpretation_normals(lines2d, camera)
    lengths = segment_lengths(lines2d)
    found = [
        R
        for k in range(min(len(vds), config.top_k))
        for R in _one_direction_candidates(vds, k, clusters, normals, lengths, config)
    ]
    if not found:
        return []
    R = np.array(found)
    return [R[n] for n in _dedupe(R, np.arange(len(R)), config.dedupe_angle_deg)]


def _one_direction_candidates(
    vds: DirectionClusters,
    k: int,
    clusters: DirectionClusters,
    normals: np.ndarray,
    lengths: np.ndarray,
    config: RotationConfig,
) -> list[np.ndarray]:
    """Returns ``single_direction_candidates``' rotations of vanishing direction ``k`` alone: for each of
    the ``top_k`` strongest clusters and each sense, every angle about it is scored by the length of the
    image segments ((N, 3) interpretation-plane ``normals``, (N,) ``lengths``; those not of VD ``k``) whose
    plane holds some other map direction within ``single_tolerance_deg`` (``free_angle_scores``: on a grid
    with a bound, so no angle is skipped). The local maxima holding at least ``single_min_share`` of the best
    are re-fitted to their segments (``_refit``); at most ``max_candidates``, best first."""
    v = vds.directions[k]
    free = vds.labels != k if len(vds.labels) == len(normals) else np.ones(len(normals), bool)
    # a segment whose plane holds the matched direction is explained whatever the angle: it says nothing
    free &= np.abs(normals @ v) > np.sin(np.radians(config.single_tolerance_deg))
    found: list[tuple[float, np.ndarray]] = []
    for c in range(min(len(clusters), config.top_k)):
        for sign in (1.0, -1.0):
            R0 = _align(sign * clusters.directions[c], v)
            others = clusters.directions[np.abs(clusters.directions @ clusters.directions[c]) < 0.99]
            if len(others) == 0:
                continue
            angles, score = free_angle_scores(
                v, normals[free], lengths[free], others @ R0.T, config.single_tolerance_deg
            )
            for peak in _circular_peaks(score, config.single_min_share * float(score.max())):
                R = rotation_from_vector(angles[peak] * v) @ R0
                found.append(
                    (float(score[peak]), _refit_free(R, v, c, sign, normals, lengths, free, clusters, config))
                )
    if not found:
        return []
    found.sort(key=lambda f: -f[0])
    R = np.array([f[1] for f in found])
    order = _dedupe(R, np.arange(len(R)), config.dedupe_angle_deg)[: config.max_candidates]
    return [R[n] for n in order]


def free_angle_scores(
    axis: np.ndarray, normals: np.ndarray, lengths: np.ndarray, directions: np.ndarray, tolerance_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((A,) angles in radians, (A,) scores): the length of the segments ((N, 3) interpretation-plane
    normals, (N,) lengths; camera frame) whose plane holds some of the (K, 3) camera-frame ``directions``
    within ``tolerance_deg`` once they are turned by the angle about ``axis``.

    A bound, not a sample: turning by t moves ``n . R(t) d`` by at most |t| (radians), so each grid angle
    is scored with the tolerance widened by half the grid step and no angle between grid points can score
    more than the larger of its neighbours. The step is half the tolerance.
    """
    step = np.radians(tolerance_deg) / 2.0
    angles = np.arange(0.0, 2.0 * np.pi, step)
    # n . Rot(axis, t) R0 d with R0 d = p + q (p along the axis, q across) is n.p + cos t n.q + sin t n.(axis x q)
    along = directions @ axis
    across = directions - along[:, None] * axis
    side = np.cross(axis, across)
    a, b, c = normals @ across.T, normals @ side.T, np.outer(normals @ axis, along)  # (N, K)
    limit = np.sin(np.radians(tolerance_deg)) + step / 2.0
    score = np.empty(len(angles))
    for k, t in enumerate(angles):
        near = np.abs(c + np.cos(t) * a + np.sin(t) * b) <= limit  # (N, K)
        score[k] = lengths[near.any(axis=1)].sum()
    return angles, score


def _circular_peaks(score: np.ndarray, floor: float) -> np.ndarray:
    """Returns the indices of the local maxima of a circular (A,) score at or above ``floor``, one per
    plateau (its middle)."""
    up = score >= np.roll(score, 1)
    down = score >= np.roll(score, -1)
    peak = up & down & (score >= floor) & (score > 0)
    index = np.flatnonzero(peak)
    # a plateau is one run of peak flags: keep its middle
    if len(index) == 0 or len(index) == len(score):
        return index[:1]
    runs = np.split(index, np.flatnonzero(np.diff(index) > 1) + 1)
    if len(runs) > 1 and runs[0][0] == 0 and runs[-1][-1] == len(score) - 1:
        runs = [np.concatenate([runs[-1], runs[0] + len(score)]), *runs[1:-1]]
    return np.array([r[len(r) // 2] % len(score) for r in runs], dtype=np.int64)


def _refit_free(
    R: np.ndarray,
    v: np.ndarray,
    c: int,
    sign: float,
    normals: np.ndarray,
    lengths: np.ndarray,
    free: np.ndarray,
    clusters: DirectionClusters,
    config: RotationConfig,
) -> np.ndarray:
    """Returns R re-fitted (``_refit``) to the segments of the matched direction and the free segments that
    a map direction explains under R (each with its nearest), or R if it would move more than the tolerance."""
    D = clusters.directions
    labels = np.full(len(normals), -1, dtype=np.int64)
    labels[~free & (np.abs(normals @ v) <= np.sin(np.radians(config.single_tolerance_deg)))] = 0
    dots = np.abs(normals @ R @ D.T)  # (N, K)
    nearest = np.argmin(dots, axis=1)
    explained = free & (
        dots[np.arange(len(normals)), nearest] <= np.sin(np.radians(config.single_tolerance_deg))
    )
    labels[explained] = 1 + nearest[explained]
    pairs = ((0, c, int(sign)), *((1 + b, b, 1) for b in range(len(D)) if b != c))
    refit = _refit(R, pairs, labels, normals, lengths**2, D, 3)
    return refit if rotation_error_deg(refit, R) < 2.0 * config.single_tolerance_deg else R


def _align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns the smallest rotation taking unit vector a onto unit vector b."""
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        other = np.eye(3)[int(np.argmin(np.abs(a)))]  # any axis perpendicular to a: half a turn about it
        return rotation_from_vector(np.pi * _unit(np.cross(a, other)))
    return rotation_from_vector(axis / sin * np.arctan2(sin, cos))


def rotation_candidates_from_segments(
    lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig | None = None
) -> tuple[list[RotationCandidate], DirectionClusters, DirectionClusters]:
    """Returns (rotation candidates, vanishing directions, 3D parallel clusters) of (N, 4) undistorted pixel
    and (M, 6) world segments: Algorithm 1 end to end."""
    config = config or RegisterConfig()
    vds = vanishing_directions(lines2d, camera, config.vanishing)
    clusters = parallel_clusters(lines3d, config.parallel)
    return rotation_candidates(vds, clusters, config.rotation), vds, clusters


def refine_candidates(
    candidates: list[RotationCandidate],
    vds: DirectionClusters,
    clusters: DirectionClusters,
    lines2d: np.ndarray,
    camera: Camera,
    iterations: int = 3,
) -> list[RotationCandidate]:
    """Returns the candidates with R re-fitted to the 2D segments of their paired VDs (eq. 1 per segment).

    A VD estimated from few or short segments is off by degrees, and Procrustes on the VDs (eq. 2) passes
    that on to R. Fitting R to every member segment at once (``n_i . R s D_a = 0`` for segment i of VD k
    paired with cluster a, weighted by squared length like the VD fit) lets the well-observed directions
    fix what a weak one cannot. Gauss-Newton on a small rotation; a candidate that would move more than
    the pairing tolerance is kept as it was.
    """
    if len(candidates) == 0 or len(vds.labels) != len(lines2d):
        return candidates
    normals = interpretation_normals(lines2d, camera)
    weights = segment_lengths(lines2d) ** 2
    out = []
    for c in candidates:
        R = _refit(c.R, c.pairs, vds.labels, normals, weights, clusters.directions, iterations)
        out.append(replace(c, R=R) if rotation_error_deg(R, c.R) < 5.0 else c)
    return out


def _refit(
    R: np.ndarray,
    pairs: tuple[tuple[int, int, int], ...],
    labels: np.ndarray,
    normals: np.ndarray,
    weights: np.ndarray,
    D: np.ndarray,
    iterations: int,
) -> np.ndarray:
    """Returns (3, 3) R minimising sum w_i (n_i . R d_i)^2 over the member segments of the paired VDs."""
    rows = [(np.flatnonzero(labels == k), s * D[a]) for k, a, s in pairs]
    index = np.concatenate([r for r, _ in rows])
    if len(index) < 4:
        return R
    d = np.concatenate([np.broadcast_to(v, (len(r), 3)) for r, v in rows])
    n, w = normals[index], np.sqrt(weights[index])
    for _ in range(iterations):
        Rd = d @ R.T
        r = np.einsum("pk,pk->p", n, Rd)  # n . (I + [w]x) R d = r + w . (R d x n)
        J = np.cross(Rd, n)
        # Cauchy reweighting at 2 robust sigmas: a few mislabelled segments must not pull
        scaled = r * w
        sigma = 2.0 * 1.4826 * float(np.median(np.abs(scaled))) + 1e-12
        c = w / np.sqrt(1.0 + (scaled / sigma) ** 2)
        omega = np.linalg.lstsq(J * c[:, None], -r * c, rcond=None)[0]
        R = rotation_from_vector(omega) @ R
    return R


def _consistent_pairings(V: np.ndarray, D: np.ndarray, config: RotationConfig) -> np.ndarray:
    """Returns (P, 2, 3) int64 pairings ((i, a, s1), (j, b, s2)), i < j, a != b, whose angles agree:
    angle(V_i, V_j) ~ angle(s1 D_a, s2 D_b); directions (anti)parallel within ``min_pair_angle_deg`` are
    never paired (they cannot fix a rotation)."""
    combos = [
        ((i, a, s1), (j, b, s2))
        for i, j in itertools.combinations(range(len(V)), 2)
        for a, b in itertools.permutations(range(len(D)), 2)
        for s1, s2 in itertools.product((1, -1), repeat=2)
    ]
    pairs = np.array(combos, dtype=np.int64).reshape(-1, 2, 3)
    i, j, a, b = pairs[:, 0, 0], pairs[:, 1, 0], pairs[:, 0, 1], pairs[:, 1, 1]
    cos_v = np.einsum("pk,pk->p", V[i], V[j])
    cos_d = np.einsum("pk,pk->p", D[a], D[b]) * pairs[:, 0, 2] * pairs[:, 1, 2]
    max_cos = np.cos(np.radians(config.min_pair_angle_deg))
    gap = np.abs(_angle_deg(cos_v) - _angle_deg(cos_d))
    ok = (np.abs(cos_v) <= max_cos) & (np.abs(cos_d) <= max_cos) & (gap <= config.pair_angle_tolerance_deg)
    return pairs[ok]


def _fit(V: np.ndarray, D: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Returns (P, 3, 3) proper rotations best mapping each ``s D_a`` onto ``V_i`` over (P, k, 3) pairings
    (orthogonal Procrustes, eq. 2). With two pairs the cross products ``V_i x V_j <-> s1 D_a x s2 D_b`` are
    added as the third column (paper), so the fit is well-posed."""
    v = V[pairs[..., 0]]  # (P, k, 3)
    d = pairs[..., 2, None] * D[pairs[..., 1]]
    if pairs.shape[1] == 2:
        v = np.concatenate([v, _unit(np.cross(v[:, 0], v[:, 1]))[:, None]], axis=1)
        d = np.concatenate([d, _unit(np.cross(d[:, 0], d[:, 1]))[:, None]], axis=1)
    return _nearest_rotations(np.einsum("pki,pkj->pij", v, d))  # argmax_R sum_k v_k . R d_k


def _nearest_rotations(M: np.ndarray) -> np.ndarray:
    """Returns (P, 3, 3) proper rotations closest to each (P, 3, 3) M: ``geometry.nearest_rotation`` batched."""
    U, _, Vt = np.linalg.svd(M)
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1.0  # never a reflection: det(R) = +1
    return U @ Vt


def _third_pairs(
    R: np.ndarray, V: np.ndarray, D: np.ndarray, pairs: np.ndarray, tolerance_deg: float
) -> np.ndarray:
    """Returns (P, 3) int64 (vd, cluster, sign): for each rotation, the unused VD and unused cluster it maps
    closest within ``tolerance_deg`` (sign-free: VD signs are arbitrary), or a row of -1."""
    cos = np.einsum("ki,pij,cj->pkc", V, R, D)  # (P, VDs, clusters): V_k . R D_c
    p = np.arange(len(pairs))[:, None]
    cos[p, pairs[..., 0], :] = 0.0  # used VDs and clusters cannot pair again
    cos[p, :, pairs[..., 1]] = 0.0
    flat = np.abs(cos).reshape(len(pairs), -1)
    best = np.argmax(flat, axis=1)
    k, c = np.unravel_index(best, cos.shape[1:])
    ok = flat[np.arange(len(pairs)), best] >= np.cos(np.radians(tolerance_deg))
    sign = np.where(cos[np.arange(len(pairs)), k, c] > 0, 1, -1)
    return np.where(ok[:, None], np.stack([k, c, sign], axis=1), -1).astype(np.int64)


def _residual_deg(R: np.ndarray, V: np.ndarray, D: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Returns (P,) the largest angle (deg) between ``R s D_a`` and ``V_i`` over each rotation's pairs."""
    d = np.einsum("pij,pkj->pki", R, pairs[..., 2, None] * D[pairs[..., 1]])  # (P, k, 3): R s D_a
    v = V[pairs[..., 0]]
    # atan2(|v x Rd|, v . Rd): arccos of the dot product cannot resolve angles below ~1e-6 degrees
    angle = np.arctan2(np.linalg.norm(np.cross(v, d), axis=-1), np.einsum("pki,pki->pk", v, d))
    return np.degrees(angle.max(axis=1))


def _dedupe(R: np.ndarray, order: np.ndarray, angle_deg: float) -> list[int]:
    """Returns the indices in ``order`` whose rotation is not within ``angle_deg`` of an earlier kept one."""
    flat = R.reshape(len(R), 9)
    # trace(R_a^T R_b) = <R_a, R_b>; angle < a  <=>  trace > 1 + 2 cos(a)
    close = flat @ flat.T > 1.0 + 2.0 * np.cos(np.radians(angle_deg))
    kept: list[int] = []
    for n in order:
        if not close[n, kept].any():
            kept.append(int(n))
    return kept


def _weights(support: np.ndarray) -> np.ndarray:
    """Returns support normalised to sum 1 (uniform if all zero)."""
    total = float(np.sum(support))
    return support / total if total > 0 else np.full(len(support), 1.0 / max(len(support), 1))


def _angle_deg(cos: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
