"""Camera-LiDAR calibration: one camera pose in the frames of several LiDAR sweeps (a rig's extrinsic).

A camera mounted rigidly on a LiDAR sees every sweep from the same pose in the sweep's own frame,
``cam_from_lidar``. Each (photo, sweep map) pair alone is a localization near a rough guess of it
(``localize`` with a ``Prior``), and alone a single sweep's map holds so little of its photo that a pose
a few degrees off may explain more than the true one (docs/measurements.md, sessions 42 and 55). The
extrinsic is the one pose that explains every photo at once, so the evidence of the frames adds up:

1. candidates: each frame localized alone near the guess (``register_undistorted`` with the prior: its
   answer and alternatives), the guess, and each frame's local optimum (``search.solve_locally``, as the
   search solves its vote peaks) from every start of a cover of the guess's bounds (rotations on a lattice
   of ``COVER_STEP_DEG`` within its ``sigma_rot_deg``, camera centres in cells a photo resolves);
2. the candidates are ranked by their scores summed over the frames, and the best distinct ones refined
   jointly: one pose, one GTSAM graph holding every frame's line-projection factor (``refine.fragments``
   of each frame re-associated each round, each frame's residuals weighted by their own noise), then scored
   again with occlusion by each map's surfaces (``pipeline.view_score``);
3. the answer is the refined pose of the highest summed score, claimed only when at least two frames are
   explained at it as a single photo's decision asks (``min_inliers`` matches, the floor of the line length
   its map covers, significance against chance), every distinct pose found scores below ``1 - margin`` of
   it or leaves unexplained what the answer explains beyond chance while explaining nothing beyond it
   that chance would not (the single photo's advantage test, each photo's chance combined by Fisher's
   rule: ``_rival``), and its covariance pins it closer than distinct poses lie (``pipeline.undetermined``).

The covariance fuses the frames' own: each frame's fit at the answer plus its map's floor
(``pipeline.with_map_floor``), combined as independent measurements of one pose (information summed),
scaled by how much more the frames' own optima disagree than those covariances allow (``_disagreement``),
plus the spread of the other refined poses that score within the margin without being distinct (law of
total covariance), each such basin weighted by the odds that the photos favour it over the answer: a
paired t-test of the photos' scores at either (``_odds``; as likely as the answer with fewer than three
photos, where the photos' own scatter cannot be measured). Single sweeps' summed scores can be rugged:
on three to five KITTI frames of one calibration the basins found lie 0.15-0.8 deg / 3-11 cm from the
truth, with others a degree or two away scoring within the margin, and the fit's covariance alone had
claimed a basin 1.4 deg off to a tenth of a degree (docs/measurements.md, session 55): such answers are
refused as undetermined. Over 21 photos, a basin every photo scores lower weighs nothing (session 56).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from .camera import Camera
from .config import LineDetectConfig, RegisterConfig
from .errors import InvalidInputError
from .geometry import camera_center, invert, line_coefficients, make_cam_from_world, rotation_error_deg
from .lines2d import detect
from .localization import map_view, seen_from_prior
from .map.linemap import LineMap
from .pipeline import (
    MapView,
    advantage_nfa,
    basin_spread,
    differs,
    explains_too_little,
    log10_nfa,
    register_undistorted,
    same_pose,
    undetermined,
    view_score,
    with_map_floor,
)
from .priors import Prior, admits_pose
from .refine import (
    Problem,
    fragments,
    inlier_sigma,
    line_problem,
    optimise,
    problem_covariance,
    refine_pose,
    residuals_px,
)
from .registration import Registration, check_segments
from .score import ImageLines, Score, coverable_length, image_lines, score_pose
from .search import solve_all
from .significance import SearchSpace, depth_of, log10_fisher
from .timing import StageTimer

__all__ = ["Calibration", "calibrate", "calibrate_segments"]

COVER_STEP_DEG = 2.5  # the rotation lattice of the cover: its covering radius 2.2 deg
COVER_PX = 70.0  # a cover cell's edge moves a point at the median depth in view this many pixels
MAX_STARTS = 2000  # a cover of more starts is thinned to its rotations at the guess's centre
CONTENDERS = 16  # the best distinct candidates by summed score, refined jointly


@dataclass(frozen=True)
class Calibration:
    """A camera pose in the frames of several maps (a camera-LiDAR extrinsic).

    cam_from_lidar: (4, 4) ``x_cam = R x_lidar + t`` (the guess when nothing near it explains the photos).
    covariance: (6, 6) (rotation rad, translation m), camera frame, as ``Registration.covariance``.
    score: the frames' scores at it, summed (px); frame_scores, frame_inliers, frame_rms_px: per frame;
        frame_matches: per frame (K, 2) ``(i2d, j3d)``, j3d a row of that frame's map; frame_offsets: (K, 2)
        where each photo alone settles, refined from the answer (degrees, metres from it; NaN: its fit is
        degenerate): a photo far from the others is the one to look at (a moving truck, a bad sweep).
    alternatives, alternative_scores: distinct poses found near the guess and their summed scores.
    singles: each frame localized alone near the guess (``Registration``; matches index its map).
    """

    success: bool
    reason: str = ""
    cam_from_lidar: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    score: float = 0.0
    frame_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    frame_rms_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_matches: tuple[np.ndarray, ...] = ()
    frame_offsets: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    alternative_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    singles: tuple[Registration, ...] = ()
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Returns a JSON-ready dict (the per-frame localizations as their own dicts)."""

        def finite(a: np.ndarray) -> list:
            return np.where(np.isfinite(a), a, np.nan).tolist()

        return {
            "success": self.success,
            "reason": self.reason,
            "cam_from_lidar": self.cam_from_lidar.tolist(),
            "covariance": None if not np.isfinite(self.covariance).all() else self.covariance.tolist(),
            "score": self.score,
            "frame_scores": finite(self.frame_scores),
            "frame_inliers": self.frame_inliers.tolist(),
            "frame_matches": [m.tolist() for m in self.frame_matches],
            "frame_rms_px": [None if not np.isfinite(x) else float(x) for x in self.frame_rms_px],
            "frame_offsets": [
                [None if not np.isfinite(x) else float(x) for x in row] for row in self.frame_offsets
            ],
            "alternatives": self.alternatives.tolist(),
            "alternative_scores": self.alternative_scores.tolist(),
            "singles": [s.to_dict() for s in self.singles],
            "timings": self.timings,
        }


@dataclass(frozen=True)
class _Frame:
    """One photo's side of the calibration: its lines, camera (undistorted), map view and score's image."""

    lines2d: np.ndarray
    camera: Camera
    view: MapView
    image: ImageLines
    rows: np.ndarray  # the map rows of the view's segments
    coeffs: np.ndarray  # (N, 3) the image segments' line coefficients


@dataclass(frozen=True)
class _Refined:
    """A pose refined over the frames: its frames' last matching tolerances (px, for ``_fused_covariance``)
    and each frame's occlusion-aware (Score, seen map parts) there, scored once for every test after."""

    pose: np.ndarray
    tolerance: list[float]
    seen: list[tuple[Score, np.ndarray]]

    @property
    def values(self) -> np.ndarray:
        """(K,) each frame's score."""
        return np.array([score.value for score, _ in self.seen])

    @property
    def value(self) -> float:
        """The frames' scores summed (in order, as a ranking compares them)."""
        return float(sum(score.value for score, _ in self.seen))


def calibrate(
    images: Sequence[np.ndarray],
    maps: Sequence[LineMap],
    camera: Camera | Sequence[Camera],
    guess: Prior,
    config: RegisterConfig | None = None,
    detect_config: LineDetectConfig | None = None,
) -> Calibration:
    """Returns the Calibration of photos ``images[k]`` taken from one pose in the frames of ``maps[k]``
    (each sweep's line map in its LiDAR's frame), near ``guess`` (a Prior with a whole pose:
    ``cam_from_world`` is the guessed cam_from_lidar, ``sigma_rot_deg`` and ``radius_m`` how far off it may
    be). ``camera``: one for every photo, or one per photo."""
    cameras = _cameras(camera, len(images))
    lines = [detect(image, cam, detect_config) for image, cam in zip(images, cameras, strict=True)]
    return _calibrate_undistorted(lines, maps, [c.undistorted() for c in cameras], guess, config)


def calibrate_segments(
    lines2d: Sequence[np.ndarray],
    maps: Sequence[LineMap],
    camera: Camera | Sequence[Camera],
    guess: Prior,
    config: RegisterConfig | None = None,
) -> Calibration:
    """``calibrate`` of precomputed (N, 4) segments per photo (distorted pixels if the camera has a
    distortion)."""
    cameras = _cameras(camera, len(lines2d))
    undistorted = []
    for k, (segments, cam) in enumerate(zip(lines2d, cameras, strict=True)):
        segments = check_segments(segments, f"lines2d[{k}]", 4)
        if cam.has_distortion:
            segments = cam.undistort_points(segments.reshape(-1, 2)).reshape(-1, 4)
        undistorted.append(segments)
    return _calibrate_undistorted(undistorted, maps, [c.undistorted() for c in cameras], guess, config)


def _cameras(camera: Camera | Sequence[Camera], count: int) -> list[Camera]:
    if isinstance(camera, Camera):
        return [camera] * count
    cameras = list(camera)
    if len(cameras) != count or not all(isinstance(c, Camera) for c in cameras):
        raise InvalidInputError(
            f"camera must be a Camera or one Camera per photo ({count}), got {len(cameras)}"
        )
    return cameras


def _check(lines2d: Sequence[np.ndarray], maps: Sequence[LineMap], guess: Prior) -> None:
    if len(lines2d) != len(maps):
        raise InvalidInputError(f"one map per photo: {len(lines2d)} photos, {len(maps)} maps")
    if len(maps) < 2:
        raise InvalidInputError(f"calibration needs at least 2 photos with their maps, got {len(maps)}")
    if not isinstance(guess, Prior) or guess.cam_from_world is None or guess.radius_m is None:
        raise InvalidInputError("guess must be a Prior with a whole pose (cam_from_world) and radius_m")


def _calibrate_undistorted(
    lines2d: Sequence[np.ndarray],
    maps: Sequence[LineMap],
    cameras: Sequence[Camera],
    guess: Prior,
    config: RegisterConfig | None,
) -> Calibration:
    _check(lines2d, maps, guess)
    config = config or RegisterConfig()
    timings: dict[str, float] = {}
    start = time.perf_counter()
    frames = _frames(lines2d, maps, cameras, guess, config)
    singles = [_alone(frame, guess, config) for frame in frames]
    timings["alone"] = time.perf_counter() - start
    start = time.perf_counter()
    candidates, rotations = _candidates(frames, singles, guess, config)
    everything = np.concatenate([f.view.segments for f in frames])
    ranked = sorted(candidates, key=lambda T: -_summed_unhidden(frames, T, config))
    contenders: list[np.ndarray] = []
    for T in ranked:
        if all(differs(T, other, everything, config.decide) for other in contenders):
            contenders.append(T)
        if len(contenders) == CONTENDERS:
            break
    refined: list[_Refined] = []
    for T in contenders:
        pose, tolerance = refine_jointly(frames, T, config)
        if not admits_pose(guess, pose) or any(same_pose(pose, other.pose) for other in refined):
            continue  # outside the guess's bounds, or a basin reached before
        refined.append(_Refined(pose, tolerance, _seen(frames, pose, config)))
    timings["joint"] = time.perf_counter() - start
    timings["total"] = timings["alone"] + timings["joint"]
    if not refined:
        reason = "every pose refined over the frames leaves the guess's bounds"
        guessed = np.asarray(guess.cam_from_world)
        return Calibration(False, reason, guessed, singles=tuple(singles), timings=timings)
    refined.sort(key=lambda r: -r.value)
    space = SearchSpace((2.0 * float(guess.radius_m or 0.0)) ** 3, rotations, COVER_STEP_DEG * np.sqrt(3) / 2)
    return replace(
        _decide(frames, refined, everything, space, config), singles=tuple(singles), timings=timings
    )


def _frames(
    lines2d: Sequence[np.ndarray],
    maps: Sequence[LineMap],
    cameras: Sequence[Camera],
    guess: Prior,
    config: RegisterConfig,
) -> list[_Frame]:
    """Returns each photo's _Frame: its lines, camera, the view of its map near the guess."""
    frames = []
    for segments, line_map, cam in zip(lines2d, maps, cameras, strict=True):
        rows = seen_from_prior(line_map, cam, guess, config)
        view = map_view(line_map, rows, config)
        image = image_lines(segments, cam, config.score)
        frames.append(_Frame(segments, cam, view, image, rows, line_coefficients(image.segments)))
    return frames


def _alone(frame: _Frame, guess: Prior, config: RegisterConfig) -> Registration:
    """Returns a frame's photo localized alone near the guess (its matches naming rows of its map)."""
    if len(frame.lines2d) < config.min_lines2d or len(frame.view.segments) < config.min_lines3d:
        return Registration(False, reason="too few lines in the photo or near the guess in its map")
    single = register_undistorted(frame.lines2d, frame.view, frame.camera, config, StageTimer(), guess)
    matches = np.c_[single.matches[:, 0], frame.rows[single.matches[:, 1]]].astype(np.int64)
    return replace(single, matches=matches)


def _candidates(
    frames: Sequence[_Frame], singles: Sequence[Registration], guess: Prior, config: RegisterConfig
) -> tuple[list[np.ndarray], int]:
    """Returns (the poses within the guess's bounds to rank by summed score, how many rotations they
    were searched about): the guess, each frame's own answer and alternatives, and each frame's local
    optimum (``search.solve_locally``, as the search solves its vote peaks) from every start of the cover."""
    candidates = [np.asarray(guess.cam_from_world)]
    for single in singles:
        if single.score > 0:
            candidates.append(single.cam_from_world)
        candidates += list(single.alternatives)
    starts, slack_deg = _cover(guess, frames, config)
    rotations = len({T[:3, :3].tobytes() for T, _ in starts}) + len(candidates)
    wide = replace(config.search, rotation_slack_deg=slack_deg)
    for f in frames:
        solved = solve_all(
            starts, f.image, f.view.segments, f.camera, wide, config.score, f.view.visible, f.view.chunks
        )
        candidates += [s[0] for s in solved if s is not None]
    return [T for T in candidates if admits_pose(guess, T)], rotations


def _decide(
    frames: Sequence[_Frame],
    refined: Sequence[_Refined],
    everything: np.ndarray,
    space: SearchSpace,
    config: RegisterConfig,
) -> Calibration:
    """Returns the Calibration of the best of the jointly refined (pose, frames' tolerances, summed
    score), best first: claimed when two frames are explained at it (``_unexplained``), no distinct pose scores
    within the margin without the best holding evidence it lacks (``_rival``), and its covariance with the
    spread of the non-distinct basins within the margin (each by its ``_odds``) pins it
    (``pipeline.undetermined``)."""
    dc = config.decide
    best = refined[0]
    pose, value, seen = best.pose, best.value, best.seen
    fit = _fused_covariance(frames, pose, best.tolerance, [part for _, part in seen], config)
    near = [r for r in refined[1:] if r.value >= (1.0 - dc.margin) * value]
    near = [r for r in near if not differs(r.pose, pose, everything, dc)]
    spread = basin_spread(pose, [r.pose for r in near], [_odds(best.values, r.values) for r in near])
    ratio, offsets = _disagreement(frames, pose, config)
    covariance = fit * ratio + spread
    distinct: list[_Refined] = []
    for r in refined[1:]:
        if differs(r.pose, pose, everything, dc) and all(
            differs(r.pose, other.pose, everything, dc) for other in distinct
        ):
            distinct.append(r)
    matches = [score.matches(dc.min_cover) for score, _ in seen]
    verdicts = [
        _unexplained(f, pose, sc, part, config, space) for f, (sc, part) in zip(frames, seen, strict=True)
    ]
    explained = sum(not v for v in verdicts)
    reason = ""
    if value <= 0:
        reason = "no pose near the guess explains the photos' lines"
    elif explained < 2:
        why = next(v for v in verdicts if v)
        reason = f"{explained} of {len(frames)} photos are explained at the best pose, a calibration needs two ({why})"
    elif rival := _rival(frames, best, distinct, config, space):
        reason = rival
    elif not np.isfinite(covariance).all():
        reason = "the photos' lines do not fix every degree of freedom of the pose (a degenerate fit)"
    else:
        reason = undetermined(covariance, pose, everything, dc)
    return Calibration(
        success=not reason,
        reason=reason,
        cam_from_lidar=pose,
        covariance=covariance,
        score=float(value),
        frame_scores=best.values,
        frame_inliers=np.array([len(m) for m in matches], dtype=np.int64),
        frame_rms_px=np.array([_rms(f, pose, config) for f in frames]),
        frame_offsets=offsets,
        frame_matches=tuple(
            np.c_[m[:, 0], f.rows[m[:, 1]]].astype(np.int64) for m, f in zip(matches, frames, strict=True)
        ),
        alternatives=np.array([r.pose for r in distinct[:8]]).reshape(-1, 4, 4),
        alternative_scores=np.array([r.value for r in distinct[:8]], dtype=np.float64),
    )


def _rival(
    frames: Sequence[_Frame],
    best: _Refined,
    distinct: Sequence[_Refined],
    config: RegisterConfig,
    space: SearchSpace,
) -> str:
    """Returns why a distinct pose makes the answer ambiguous ("" if none does): it scores within the margin
    of the best over the photos, unless what the best explains beyond it is more than chance and what it
    explains beyond the best is not (``_advantage``, the single photo's test with the photos' evidence
    combined): else each holds evidence the other lacks."""
    dc = config.decide
    pose, value = best.pose, best.value
    for rival in distinct:
        v, other = rival.value, rival.pose
        if v < (1.0 - dc.margin) * value:
            return ""
        over = _advantage(frames, pose, best.seen, rival.seen, config, space)
        back = _advantage(frames, other, rival.seen, best.seen, config, space)
        if over < dc.max_log10_nfa <= back:
            continue
        turn = rotation_error_deg(other[:3, :3], pose[:3, :3])
        shift = float(np.linalg.norm(camera_center(other) - camera_center(pose)))
        beyond = (
            f"what the best explains beyond it 10^{over:.1f} chance poses would"
            if over >= dc.max_log10_nfa
            else f"it explains lines the best does not (10^{back:.1f} chance poses would)"
        )
        return (
            f"ambiguous: a distinct pose ({turn:.1f} deg, {shift:.2f} m away) scores "
            f"{100 * v / value:.0f} % of the best over the {len(frames)} photos, and {beyond}"
        )
    return ""


def _advantage(
    frames: Sequence[_Frame],
    pose: np.ndarray,
    mine: Sequence[tuple[Score, np.ndarray]],
    theirs: Sequence[tuple[Score, np.ndarray]],
    config: RegisterConfig,
    space: SearchSpace,
) -> float:
    """Returns log10 of the number of false alarms of what ``pose`` explains beyond another pose over the
    photos (each photo's (Score, seen parts) at either): in each photo the chance of its matches among the
    image segments the other leaves unexplained (``pipeline.advantage_nfa``), the photos' chances combined
    (``log10_fisher``: independent photos), among as many poses as the finest photo tells apart in the
    space searched."""
    tails, tests = [], []
    for f, (score, parts), (other, _) in zip(frames, mine, theirs, strict=True):
        t = space.log10_tests(f.camera, depth_of(parts, pose), config.score.distance_px)
        tails.append(advantage_nfa(pose, score, parts, other, f.image, f.camera, config, space) - t)
        tests.append(t)
    return max(tests) + log10_fisher(tails)


def _summed_unhidden(frames: Sequence[_Frame], cam_from_lidar: np.ndarray, config: RegisterConfig) -> float:
    """Returns the frames' scores of one pose without occlusion, summed (a cheap ranking of candidates)."""
    return float(
        sum(
            score_pose(
                f.image,
                f.view.segments,
                f.camera,
                cam_from_lidar,
                config.score,
                f.view.visible,
                f.view.chunks,
            ).value
            for f in frames
        )
    )


def _seen(
    frames: Sequence[_Frame], cam_from_lidar: np.ndarray, config: RegisterConfig
) -> list[tuple[Score, np.ndarray]]:
    """Returns each frame's occlusion-aware (Score, seen map parts) of one pose (``pipeline.view_score``)."""
    return [view_score(f.view, f.image, f.camera, cam_from_lidar, config.score) for f in frames]


def _rms(frame: _Frame, pose: np.ndarray, config: RegisterConfig) -> float:
    """Returns a frame's rms px of its matched stretches at a pose (NaN: none)."""
    problem = _frame_problem(frame, pose, config.score.distance_px, 1.0, config)
    if problem is None:
        return float("nan")
    return float(np.sqrt(np.mean(np.square(residuals_px(problem, pose)))))


def _frame_problem(
    frame: _Frame, pose: np.ndarray, tolerance_px: float, sigma_px: float, config: RegisterConfig
) -> Problem | None:
    """Returns one frame's factor graph (its matched stretches at ``tolerance_px``, residuals of
    ``sigma_px``), or None when it has fewer than ``refine.min_matches`` stretches."""
    rc = config.refine
    scored = score_pose(
        frame.image, frame.view.segments, frame.camera, pose,
        replace(config.score, distance_px=tolerance_px), frame.view.visible,
    )  # fmt: skip
    pairs, points = fragments(frame.image, frame.view.segments, frame.camera, pose, scored, rc)
    if len(pairs) < rc.min_matches:
        return None
    return line_problem(frame.coeffs[pairs[:, 0]], points, frame.camera, rc, sigma_px)


def refine_jointly(
    frames: Sequence[_Frame], cam_from_lidar: np.ndarray, config: RegisterConfig
) -> tuple[np.ndarray, list[float]]:
    """Returns (the pose, each frame's last matching tolerance px, for ``_fused_covariance``) minimising
    every frame's line reprojection at once:
    ``refine.refine_pose``'s rounds (score at a shrinking tolerance, fit the matched stretches) with one
    factor per frame on one pose, each frame's residuals weighted by its own noise (``inlier_sigma``). The
    start pose when no frame has enough matches. (A start a degree or more off is
    first solved per frame by ``search.solve_locally``: least squares from a tolerance that wide settled
    in poor basins, KITTI frames 0.5 deg off the truth at a third of its summed score.)"""
    rc, sc = config.refine, config.score
    tolerance = [rc.start_factor * sc.distance_px] * len(frames)
    sigma = [1.0] * len(frames)
    pose = cam_from_lidar
    for _ in range(rc.max_rounds):
        problems = [_frame_problem(f, pose, tolerance[k], sigma[k], config) for k, f in enumerate(frames)]
        kept = [p for p in problems if p is not None]
        if not kept:
            return cam_from_lidar, tolerance
        graph = gtsam.NonlinearFactorGraph()
        for problem in kept:
            graph.push_back(problem.graph)
        try:
            moved = optimise(graph, pose, rc)
        except RuntimeError:  # gtsam: an indeterminant system
            break
        step = rotation_error_deg(moved[:3, :3], pose[:3, :3])
        shift = float(np.linalg.norm(camera_center(moved) - camera_center(pose)))
        pose = moved
        for k, item in enumerate(problems):
            if item is None:
                continue
            residuals = residuals_px(item, pose)
            sigma[k] = max(inlier_sigma(residuals, tolerance[k]), 0.3)
            tolerance[k] = float(np.clip(rc.outlier_sigmas * sigma[k], rc.min_outlier_px, tolerance[k]))
        if step < 1e-4 and shift < 1e-5:
            break
    return pose, tolerance


def _fused_covariance(
    frames: Sequence[_Frame],
    pose: np.ndarray,
    tolerance: Sequence[float],
    seen: Sequence[np.ndarray],
    config: RegisterConfig,
) -> np.ndarray:
    """Returns the covariance of one pose measured by each frame independently: each frame's own fit at
    ``pose`` (``refine.problem_covariance``, its stretches matched at its ``tolerance``) plus the floor of
    its map, of which it sees the (K, 6) ``seen``; their information summed."""
    information = np.zeros((6, 6))
    for frame, tol, parts in zip(frames, tolerance, seen, strict=True):
        problem = _frame_problem(frame, pose, tol, 1.0, config)
        if problem is None:
            continue
        fit = problem_covariance(problem, pose, config.refine)
        if not np.isfinite(fit).all():
            continue
        total = with_map_floor(fit, frame.view.accuracy_m, parts, pose)
        try:
            information += np.linalg.inv(total)
        except np.linalg.LinAlgError:
            continue
    try:
        covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.nan)
    return 0.5 * (covariance + covariance.T) if np.isfinite(covariance).all() else np.full((6, 6), np.nan)


def _disagreement(
    frames: Sequence[_Frame], pose: np.ndarray, config: RegisterConfig
) -> tuple[float, np.ndarray]:
    """Returns (how much more the frames disagree than their own covariances allow, >= 1; (K, 2) each
    frame's own optimum near ``pose`` as degrees and metres from it, NaN where its fit is degenerate): the
    first is the reduced chi-square of each frame's own optimum (``refine_pose`` from ``pose``, alone)
    about ``pose`` under that frame's covariance with its map's floor (the Birge ratio, by which a
    combination of inconsistent measurements scales its uncertainty). Single sweeps of one calibration
    settle a degree apart and each claims a tenth of one: the fused covariance alone put the joint answer 8
    sigma from KITTI's calibration."""
    here = gtsam.Pose3(invert(pose))
    chi2, dof = 0.0, 0
    offsets = np.full((len(frames), 2), np.nan)
    for k, f in enumerate(frames):
        alone = refine_pose(
            f.image, f.view.segments, f.camera, pose, config.refine, config.score, f.view.visible
        )
        if not np.isfinite(alone.covariance).all():
            continue
        T = alone.cam_from_world
        offsets[k] = (
            rotation_error_deg(T[:3, :3], pose[:3, :3]),
            np.linalg.norm(camera_center(T) - camera_center(pose)),
        )
        seen = view_score(f.view, f.image, f.camera, T, config.score)[1]
        own = with_map_floor(alone.covariance, f.view.accuracy_m, seen, T)
        xi = gtsam.Pose3.Logmap(here.between(gtsam.Pose3(invert(T))))
        try:
            chi2 += float(xi @ np.linalg.solve(own, xi))
        except np.linalg.LinAlgError:
            continue
        dof += 6
    return (max(chi2 / (dof - 6), 1.0) if dof > 6 else 1.0), offsets


def _cover(
    guess: Prior, frames: Sequence[_Frame], config: RegisterConfig
) -> tuple[list[tuple[np.ndarray, float]], float]:
    """Returns (the starts (pose, m its centre may be off), the degrees its rotation may be off) covering
    the guess's bounds: rotations on a lattice of ``COVER_STEP_DEG`` within ``sigma_rot_deg`` of the guess
    (a cubic lattice of rotation vectors: every rotation lies within ``step * sqrt(3) / 2`` of one; half a
    step more of slack), times camera centres at the middles of cells whose edge moves a point at the
    median depth in view ``COVER_PX`` pixels; thinned to the rotations at the guess's centre (the whole
    ball their size) when that makes more than ``MAX_STARTS``."""
    from scipy.spatial.transform import Rotation

    assert guess.cam_from_world is not None and guess.radius_m is not None
    T0, radius = guess.cam_from_world, float(guess.radius_m)
    sigma = float(guess.sigma_rot_deg or 0.0)
    n = int(np.floor(sigma / COVER_STEP_DEG))
    g = np.arange(-n, n + 1) * COVER_STEP_DEG
    w = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    w = w[np.linalg.norm(w, axis=1) <= sigma + 1e-9]
    turns = [Rotation.from_rotvec(np.radians(v)).as_matrix() @ T0[:3, :3] for v in w]
    focal = max(max(f.camera.fx, f.camera.fy) for f in frames)
    depth = float(np.median([depth_of(f.view.segments, T0) for f in frames]))
    cells = max(int(np.ceil(2 * radius / (COVER_PX * depth / focal))), 1)
    offsets = (np.arange(cells) + 0.5) * (2 * radius / cells) - radius
    shifts = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), -1).reshape(-1, 3)
    half = radius / cells * np.sqrt(3)
    shifts = shifts[np.linalg.norm(shifts, axis=1) <= radius + half]
    if len(turns) * len(shifts) > MAX_STARTS:
        shifts, half = np.zeros((1, 3)), radius
    slack_deg = COVER_STEP_DEG * (np.sqrt(3) / 2 + 0.5)
    centre = camera_center(T0)
    starts = [(make_cam_from_world(R, -R @ (centre + d)), float(half)) for R in turns for d in shifts]
    return starts, float(slack_deg)


def _odds(mine: np.ndarray, theirs: np.ndarray) -> float:
    """Returns the odds that another pose, not the answer, is the one the photos favour, from the (K,)
    photos' scores at each: their differences as K draws of how much the answer explains more (a paired
    t-test across the photos: what another draw of photos would say). 1 (as likely) with fewer than
    three photos or a pose scoring as much; 0 when every photo scores the answer the same amount higher."""
    d = np.asarray(mine, dtype=np.float64) - np.asarray(theirs, dtype=np.float64)
    k, total = len(d), float(d.sum())
    if k < 3 or total <= 0.0:
        return 1.0
    spread = float(np.std(d, ddof=1)) * np.sqrt(k)
    if spread <= 0.0:
        return 0.0
    from scipy.stats import t

    p = float(t.sf(total / spread, k - 1))
    return min(p / max(1.0 - p, 1e-300), 1.0)


def _unexplained(
    frame: _Frame,
    pose: np.ndarray,
    score: Score,
    seen: np.ndarray,
    config: RegisterConfig,
    space: SearchSpace,
) -> str:
    """Returns why a frame does not count as explained at a pose ("" if it does): as the single-photo
    decision asks (``pipeline.decide``), fewer than ``min_inliers`` matches, less than the floor of the
    image length its map covers there (``explains_too_little``), or no more than chance would match among
    the poses searched (``log10_nfa``)."""
    dc = config.decide
    matches = score.matches(dc.min_cover)
    if len(matches) < config.min_inliers:
        return f"{len(matches)} matches, fewer than {config.min_inliers}"

    def coverable() -> float:
        footprint = (
            None
            if frame.view.footprint is None
            else frame.view.footprint(frame.camera, pose, config.score.distance_px)
        )
        return coverable_length(frame.image, frame.camera, pose, seen, footprint, config.score)

    if short := explains_too_little(score.explained_length, frame.image, coverable, dc):
        return f"a photo {short}"
    distinct = len(np.unique(matches[:, 1]))
    nfa = log10_nfa(pose, distinct, seen, frame.image, frame.camera, config, space)
    if nfa >= dc.max_log10_nfa:
        return f"a photo's matches are what 10^{nfa:.1f} chance poses would match"
    return ""
