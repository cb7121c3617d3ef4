"""Pose refinement (paper section III-D) on fragments: GTSAM Levenberg-Marquardt on the distances of the
matched stretch of each map line to its image segment's infinite line, re-associating at each refined pose.

The score (``score.py``) says which image segment each projected map segment covers, and over which stretch.
The two ends of that stretch, carried back onto the map line, are the points whose projections must lie
on the image line (eq. "costs"): only the part of a map segment that is seen and matched pulls, not its
far ends, which may be hidden or cut at the image border, and three fragments along one edge each pull
where they are. Each round re-scores at the refined pose with a tolerance of a few robust sigmas of the
residuals, until the covering pairs no longer change.

One ``CustomFactor`` (``line_factor``) holds every point of the image; a robust kernel with gtsam's
``Scalar`` reweight scheme weights each residual on its own. The noise model has sigma = 1 px, so
``kernel_px`` is in pixels; the covariance is rescaled by the a-posteriori residual variance.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numba
import numpy as np

from .camera import Camera
from .config import RefineConfig, ScoreConfig
from .errors import InvalidInputError
from .geometry import camera_center, invert, line_coefficients, segment_directions
from .kernels import numpy_sum
from .line_factor import LineProjection, line_factor
from .score import ImageLines, Score, score_pose

log = logging.getLogger(__name__)

POSE_KEY = 0
_KERNELS: dict[str, Any] = {
    "huber": gtsam.noiseModel.mEstimator.Huber.Create,
    "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create,
    "tukey": gtsam.noiseModel.mEstimator.Tukey.Create,
}


@dataclass(frozen=True)
class Refinement:
    """A refined pose and its score.

    cam_from_world: (4, 4) float64, ``x_cam = R x_world + t``.
    score: the Score at the refined pose (the score's own tolerance).
    covariance: (6, 6) float64 of gtsam's tangent ``xi = (omega rad, v m)`` of ``world_T_cam * Exp(xi)``,
        i.e. rotation and translation perturbations in the CAMERA (body) frame, (rotation, translation)
        order, scaled by the residuals' own variance; NaN when the refinement was degenerate.
    rms_px: root mean square distance of the fitted points to their image lines at the refined pose.
    rounds: optimise -> re-associate rounds run.
    """

    cam_from_world: np.ndarray
    score: Score
    covariance: np.ndarray
    rms_px: float
    rounds: int


def refine_pose(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    config: RefineConfig,
    score_config: ScoreConfig,
    visible: np.ndarray | None = None,
) -> Refinement:
    """Returns the Refinement of a pose by line reprojection of matched fragments (eq. "costs").

    image: the image side of the score; lines3d: (M, 6) world; cam_from_world: (4, 4) initial pose;
    visible: (M,) bool of the segments taking part (None: all). Degenerate input (fewer than
    ``config.min_matches`` stretches, all map lines parallel, a singular system) returns the input pose
    with NaN covariance, never raises (an unknown ``config.kernel`` or ``noise_model`` raises
    InvalidInputError).
    """
    if config.kernel not in (*_KERNELS, "none"):
        raise InvalidInputError(
            f"refine.kernel must be one of {', '.join(_KERNELS)}, none; got {config.kernel!r}"
        )
    if config.noise_model not in ("mixture", "mad"):
        raise InvalidInputError(f"refine.noise_model must be mixture or mad; got {config.noise_model!r}")
    coeffs = line_coefficients(image.segments)
    pose, rounds, problem, previous = cam_from_world, 0, None, None
    tolerance = config.start_factor * score_config.distance_px  # the start pose is only roughly right
    while rounds < config.max_rounds:
        scored = score_pose(
            image, lines3d, camera, pose, replace(score_config, distance_px=tolerance), visible
        )
        pairs, stretches = fragments(image, lines3d, camera, pose, scored, config)
        if previous is not None and _same(pairs, previous):
            break
        problem = _problem(coeffs, stretches, pairs, camera, config)
        if problem is None:
            return _unrefined(image, lines3d, camera, cam_from_world, score_config, visible, rounds)
        rounds += 1
        try:
            pose = optimise(problem.graph, pose, config)
        except RuntimeError as e:  # gtsam: indeterminant linear system
            log.debug("refinement failed: %s", e)
            return _unrefined(image, lines3d, camera, cam_from_world, score_config, visible, rounds)
        tolerance = _threshold_px(problem, pose, config, tolerance)
        previous = pairs
    if problem is None:
        return _unrefined(image, lines3d, camera, cam_from_world, score_config, visible, rounds)
    covariance = problem_covariance(problem, pose, config)
    final = score_pose(image, lines3d, camera, pose, score_config, visible)
    if not np.isfinite(covariance).all():
        return Refinement(pose, final, np.full((6, 6), np.nan), _rms_px(problem, pose), rounds)
    return Refinement(pose, final, covariance, _rms_px(problem, pose), rounds)


def fragments(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    scored: Score,
    config: RefineConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P, 2) ``(i2d, j3d)`` pairs, (P, 6) world points): the ends of each covered stretch of at
    least ``min_cover_px``, carried back onto the map line (the point of line j nearest the viewing ray)."""
    keep = _one_per_stretch(scored.pairs[:, 0], scored.cover, config.min_cover_px)
    pairs, cover = scored.pairs[keep], scored.cover[keep]
    if len(pairs) == 0:
        return pairs, np.zeros((0, 6))
    seg = image.segments[pairs[:, 0]]
    unit = (seg[:, 2:4] - seg[:, 0:2]) / image.lengths[pairs[:, 0], None]
    ends = np.stack([seg[:, 0:2] + cover[:, k, None] * unit for k in (0, 1)], axis=1)  # (P, 2, 2) pixels
    rays = np.concatenate([ends, np.ones((len(pairs), 2, 1))], axis=2) @ np.linalg.inv(camera.K).T
    rays = rays @ cam_from_world[:3, :3]  # world directions
    centre = camera_center(cam_from_world)
    a, b = lines3d[pairs[:, 1], 0:3], lines3d[pairs[:, 1], 3:6]
    d = b - a
    points = np.stack([_nearest_on_line(a, d, centre, rays[:, k]) for k in (0, 1)], axis=1)
    return pairs, points.reshape(-1, 6)


def _one_per_stretch(i: np.ndarray, cover: np.ndarray, min_px: float) -> np.ndarray:
    """Returns (P,) bool: covers of at least ``min_px`` that do not overlap a longer cover of the same image
    segment by more than half (two map lines on one image stretch: only the better one is fitted; map
    fragments along it each keep their own stretch)."""
    length = cover[:, 1] - cover[:, 0]
    order = np.lexsort((-length, i))  # by image segment, longest cover first
    keep = length >= min_px
    return _free_stretches(order, np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(cover), keep)


@numba.njit(cache=True, nogil=True)
def _free_stretches(order: np.ndarray, i: np.ndarray, cover: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Returns ``keep`` with every cover dropped that overlaps one taken before it (in ``order``, which
    holds each image segment's covers together) on the same image segment by more than half its length."""
    taken = np.empty((len(order), 2))
    n, current = 0, -1
    for k in order:
        if not keep[k]:
            continue
        if i[k] != current:
            current, n = i[k], 0
        lo, hi = cover[k, 0], cover[k, 1]
        for s in range(n):
            if min(hi, taken[s, 1]) - max(lo, taken[s, 0]) > 0.5 * (hi - lo):
                keep[k] = False
                break
        if keep[k]:
            taken[n, 0], taken[n, 1] = lo, hi
            n += 1
    return keep


def _nearest_on_line(a: np.ndarray, d: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Returns (P, 3) the points of lines ``a + s d`` nearest to the rays ``c + t r`` (P, 3 each)."""
    w = a - c
    dd, dr, rr = (np.einsum("pk,pk->p", x, y) for x, y in ((d, d), (d, r), (r, r)))
    wd, wr = np.einsum("pk,pk->p", w, d), np.einsum("pk,pk->p", w, r)
    den = dd * rr - dr * dr
    s = np.where(den > 1e-12 * dd * rr, (dr * wr - rr * wd) / np.maximum(den, 1e-300), 0.0)
    return a + s[:, None] * d


@dataclass(frozen=True)
class Problem:
    """One set of fitted points: its factor graph (one factor) and the factor's precomputation."""

    graph: gtsam.NonlinearFactorGraph
    projection: LineProjection


def _problem(
    coeffs: np.ndarray, points: np.ndarray, pairs: np.ndarray, camera: Camera, config: RefineConfig
) -> Problem | None:
    """Returns the factor graph of eq. "costs" over (P, 6) fitted points, or None if degenerate."""
    if _degenerate(points, config):
        return None
    return line_problem(coeffs[pairs[:, 0]], points, camera, config)


def line_problem(
    lines: np.ndarray, points: np.ndarray, camera: Camera, config: RefineConfig, sigma_px: float = 1.0
) -> Problem:
    """Returns the one-factor graph of (P, 6) fitted points on their (P, 3) image lines' coefficients,
    residuals of ``sigma_px`` under the configured robust kernel."""
    projection = LineProjection.build(lines, points, camera, config.min_depth_m)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(line_factor(POSE_KEY, projection, robust_noise(2 * len(points), sigma_px, config)))
    return Problem(graph, projection)


def robust_noise(dim: int, sigma_px: float, config: RefineConfig) -> gtsam.noiseModel.Base:
    """Returns the noise model of ``dim`` point-to-line residuals of ``sigma_px`` under the configured robust
    kernel, its threshold ``kernel_px`` in pixels whatever the sigma (gtsam applies the kernel to whitened
    residuals). Scalar reweighting: each point residual gets its own weight (and loss); Block would weight
    the whole image as one."""
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(dim, sigma_px)
    if config.kernel == "none":
        return noise
    kernel = _KERNELS[config.kernel](
        config.kernel_px / sigma_px, gtsam.noiseModel.mEstimator.Base.ReweightScheme.Scalar
    )
    return gtsam.noiseModel.Robust.Create(kernel, noise)


def _values(cam_from_world: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(POSE_KEY, gtsam.Pose3(invert(cam_from_world)))  # gtsam Pose3 is world_T_cam
    return values


def optimise(
    graph: gtsam.NonlinearFactorGraph, cam_from_world: np.ndarray, config: RefineConfig
) -> np.ndarray:
    """Returns the (4, 4) cam_from_world minimising a graph's robust cost on ``POSE_KEY``, by
    Levenberg-Marquardt from ``cam_from_world``."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, _values(cam_from_world), params)
    result = optimizer.optimize().atPose3(POSE_KEY).matrix()
    if not np.isfinite(result).all():
        raise RuntimeError("non-finite pose")
    return invert(result)


def residuals_px(problem: Problem, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (P, 2) point-to-line distances px of every pair at ``cam_from_world``."""
    world_from_cam = invert(cam_from_world)
    points = problem.projection.points_cam(world_from_cam[:3, :3], world_from_cam[:3, 3])
    return problem.projection.evaluate(points, jacobian=False)[0].reshape(-1, 2)


def _threshold_px(
    problem: Problem, cam_from_world: np.ndarray, config: RefineConfig, ceiling: float
) -> float:
    """Returns the next round's covering tolerance px: ``outlier_sigmas`` sigmas of the residuals' noise
    (``config.noise_model``: the inliers' of a mixture, ``inlier_sigma``, or the MAD's), clipped to
    ``[min_outlier_px, ceiling]`` (``ceiling``: this round's tolerance)."""
    residuals = residuals_px(problem, cam_from_world)
    if config.noise_model == "mad":
        sigma = 1.4826 * float(np.median(np.abs(residuals)))
    else:
        sigma = inlier_sigma(residuals, ceiling)
    return float(np.clip(config.outlier_sigmas * sigma, config.min_outlier_px, ceiling))


def inlier_sigma(residuals: np.ndarray, window_px: float, iterations: int = 30) -> float:
    """Returns the noise sigma px of point-to-line residuals of pairs covered within ``window_px``: the
    inliers' half-normal in a mixture with outliers spread evenly over the window, fitted by
    expectation-maximisation from the MAD.

    Pairs covered at a start's wide tolerance hold many outliers, and the MAD is then theirs: 70 % inliers
    of sigma 1.3 px among outliers spread over 10 px give a MAD sigma of 2.0 px, the mixture 1.3. Three MAD
    sigmas held the capture of a rendered office photo's refinement at 7 px round after round, its clutter
    pulling the pose from the exact one to 1.6 deg off (docs/measurements.md, session 49)."""
    r = np.abs(np.asarray(residuals, dtype=np.float64).ravel())
    r = r[r <= window_px]
    if len(r) == 0:
        return window_px
    floor = 0.1  # px: exact residuals (noise-free scenes) must not drive the sigma to zero
    sigma = max(1.4826 * float(np.median(r)), floor)
    if len(r) < 8:  # too few to tell inliers from outliers
        return sigma
    share = 0.8  # of inliers, at the start; kept within [0.05, 0.99] so that neither side vanishes
    root_2pi = np.sqrt(2 * np.pi)
    exponent = np.empty_like(r)
    for _ in range(iterations):
        # share 2 exp(-(r / sigma)^2 / 2) / (sqrt(2 pi) sigma): numpy's exp (its own vectorised one, which
        # a compiled loop's would not match to the bit) between two compiled loops doing the rest, as the
        # numpy expressions did on a few hundred residuals in a dozen calls
        _half_squares(r, sigma, exponent)
        np.exp(exponent, out=exponent)
        total, spread = _weights(exponent, r, share * 2.0, root_2pi * sigma, (1 - share) / window_px)
        sigma = max(math.sqrt(spread / max(total, 1e-9)), floor)
        share = min(max(total / len(r), 0.05), 0.99)  # the mean weight
    return sigma


@numba.njit(cache=True, nogil=True)
def _half_squares(r: np.ndarray, sigma: float, out: np.ndarray) -> None:  # pragma: no cover - numba
    """Fills (n,) ``out`` with ``-0.5 * (r / sigma) ** 2`` of (n,) ``r``."""
    for k in range(len(r)):
        x = r[k] / sigma
        out[k] = -0.5 * (x * x)


@numba.njit(cache=True, nogil=True)
def _weights(
    density: np.ndarray, r: np.ndarray, scale: float, norm: float, outlier: float
) -> tuple[float, float]:  # pragma: no cover - numba
    """Returns (sum w, sum w r^2) of the inlier weights ``w = d / (d + outlier + 1e-300)``,
    ``d = scale * density / norm`` of (n,) ``density`` and residuals ``r``, summed as ``np.sum`` sums."""
    weight, spread = np.empty(len(r)), np.empty(len(r))
    for k in range(len(r)):
        d = scale * density[k] / norm
        weight[k] = d / (d + outlier + 1e-300)
        spread[k] = weight[k] * r[k] * r[k]
    return numpy_sum(weight), numpy_sum(spread)


def _rms_px(problem: Problem, cam_from_world: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(residuals_px(problem, cam_from_world)))))


def problem_covariance(problem: Problem, cam_from_world: np.ndarray, config: RefineConfig) -> np.ndarray:
    """Returns (6, 6) pose covariance (body frame, rotation first) in px-noise units, NaN if singular.

    ``Marginals`` gives ``(J^T W J)^-1`` for sigma = 1 px with the kernel's weights W at the optimum. It is
    scaled by Huber's M-estimator variance ``sum(psi^2) / (2K - 6) / mean(psi')^2`` (Huber 1981, eq. 7.10),
    which is calibrated on synthetic scenes; plain ``sum(w r^2) / (2K - 6)`` is overconfident by ~1.4x.
    """
    try:
        marginal = gtsam.Marginals(problem.graph, _values(cam_from_world)).marginalCovariance(POSE_KEY)
    except RuntimeError as e:  # indeterminant system: the matches do not fix all 6 DoF
        log.debug("marginals failed: %s", e)
        return np.full((6, 6), np.nan)
    return marginal * residual_variance(residuals_px(problem, cam_from_world).ravel(), config, 6)


def residual_variance(r: np.ndarray, config: RefineConfig, num_params: int) -> float:
    """Returns Huber's M-estimator variance px^2 ``sum(psi^2) / (n - num_params) / mean(psi')^2`` of (n,)
    residuals px under the configured kernel (Huber 1981, eq. 7.10): the noise level of fitted lines."""
    psi, dpsi = _influence(r, config)
    dof = max(len(psi) - num_params, 1)
    return float(psi @ psi) / dof / max(float(dpsi.mean()), 0.1) ** 2


def _influence(r: np.ndarray, config: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (psi(r), psi'(r)) of the configured kernel (gtsam's definitions) for residuals r px."""
    k = config.kernel_px
    if config.kernel == "huber":
        return np.clip(r, -k, k), (np.abs(r) <= k).astype(np.float64)
    if config.kernel == "cauchy":  # w = k^2 / (k^2 + r^2)
        d = k * k + r * r
        return r * k * k / d, k * k * (k * k - r * r) / (d * d)
    if config.kernel == "tukey":  # w = (1 - (r/k)^2)^2 inside |r| <= k, else 0
        u = np.where(np.abs(r) <= k, (r / k) ** 2, 1.0)
        return r * (1.0 - u) ** 2, (1.0 - u) * (1.0 - 5.0 * u)
    return r, np.ones_like(r)


def _degenerate(points: np.ndarray, config: RefineConfig) -> bool:
    """Returns True when (P, 6) fitted map stretches cannot fix a pose: too few, or all parallel."""
    if len(points) < config.min_matches:
        return True
    d = segment_directions(points)
    eig = np.linalg.eigvalsh(d.T @ d)  # squared singular values, ascending; 3x3 is cheaper than an SVD
    return bool(eig[1] < np.sin(np.radians(config.parallel_angle_deg)) ** 2 * eig[2])


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Returns True if two (K, 2) pair sets hold the same rows, in any order."""
    if a.shape != b.shape:
        return False
    return bool(np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])]))


def _unrefined(
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    score_config: ScoreConfig,
    visible: np.ndarray | None,
    rounds: int,
) -> Refinement:
    """Returns the input pose with NaN covariance: the degenerate outcome."""
    log.debug("degenerate refinement: keeping the input pose")
    score = score_pose(image, lines3d, camera, cam_from_world, score_config, visible)
    return Refinement(cam_from_world.copy(), score, np.full((6, 6), np.nan), float("nan"), rounds)
