"""``localize_sequence``: many frames of one camera, with optional odometry, smoothed in ONE GTSAM graph.

1. Each frame alone (``alone``): refined from its prediction (odometry from the last fix, else constant
   velocity), a fix only if no distinct pose near it scores as well (``rival_test``); failing that,
   registered near the prediction (a ``Prior``); globally only for the first frame and frames after a
   loss without odometry. With odometry a fix must also lie near the odometry's prediction (``gated``,
   the tracker's innovation gate); a gated fix is not claimed but still starts the graph at its pose.
2. One graph over all frames: a line-projection factor per frame on its matched fragments (the
   refinement's vectorised factor and robust kernel in pixels, noise = the frame's own residual level) on
   the pose its lines give against the map, tied to the frame's pose by the map's accuracy (``map_floor``:
   a view's lines are off the world alike, so its pixels cannot place the camera closer than the map), a
   ``BetweenFactorPose3`` per odometry step with its covariance, and, only when asked
   (``smoothness``), a random-walk prior between consecutive frames. It starts each fixed frame at its
   fix and each frame between fixes where the pose graph of the fixes and the odometry puts it (the
   drift shared over the gap, not chained from one side). Re-association rounds: each frame's
   fragments are matched again at the smoothed poses until no frame's pairs change.
3. Marginal covariance per frame. A frame whose own lines do not fix it but which odometry ties to fixed
   frames keeps its smoothed pose with ``success=False, reason="from neighbours ..."`` and the larger
   covariance the graph gives it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cache, partial

import gtsam
import numpy as np

from .camera import Camera
from .config import LineDetectConfig, RegisterConfig, ScoreConfig
from .errors import InvalidInputError
from .geometry import camera_center, check_rigid, rotation_error_deg
from .graph import (
    LineFit,
    carry,
    check_covariance,
    chi2_quantile,
    frame_key,
    frame_lines,
    from_pose3,
    fuse,
    innovation_distance,
    line_fit,
    lines_key,
    next_tolerance,
    noise_px,
    odometry_factor,
    predict,
    relative_pose,
    step_covariance,
    to_pose3,
)
from .localization import localize_segments
from .map.linemap import LineMap
from .pipeline import (
    differs,
    explains_too_little,
    fine_config,
    map_floor,
    orbit_rivals,
    precise_config,
    precision_is_evidence,
    sharp_dismisses,
    sharper_reason,
    sharper_rival,
    turned_rival,
    with_map_floor,
)
from .priors import Prior
from .refine import refine_pose
from .registration import Registration
from .score import ImageLines, Score, coverable_length, image_lines, score_pose
from .significance import depth_of
from .threads import both

log = logging.getLogger(__name__)

FROM_NEIGHBOURS = "from neighbours"  # the reason of a frame posed by the graph, not by its own lines
AMBIGUOUS = "tracking: ambiguous"  # the reason of a fix refused for a rival (``rival_test``)
GATED = "tracking: off the prediction"  # the reason of a fix refused by the innovation gate (``gated``)


def _sequence_register() -> RegisterConfig:
    """Returns the registration's configuration for a sequence's frames: a single photo's, without the
    spread of the basins next to an answer (``DecideConfig.basin_turn_deg`` 0). A frame is a fix by the
    sequence's own tests (its prediction, the innovation gate, the graph's odometry); with the basins a
    single shot needs, the real kitchen's frames fixed alone fell from 22 to 15 and its smoothed graph from
    96.7 to 53.7 % of the frames within 10 cm / 2 deg, and a synthetic walk's relocalization with a top
    speed claimed a wrong pose (docs/measurements.md, session 56)."""
    base = RegisterConfig()
    return replace(base, decide=replace(base.decide, basin_turn_deg=0.0))


@dataclass(frozen=True)
class SequenceConfig:
    """Sequences and tracking: the per-frame checks, odometry defaults, the graph."""

    register: RegisterConfig = field(default_factory=_sequence_register)
    detect: LineDetectConfig = field(default_factory=LineDetectConfig)
    # odometry given without covariances: per step, rotation sigma per metre moved, translation sigma as a
    # share of the distance plus a floor (wheel and visual odometry drift by 1-3 % of the distance)
    odometry_rot_deg_per_m: float = 1.0
    odometry_pos_fraction: float = 0.03
    odometry_floor_m: float = 0.005
    # a frame refined from its prediction is a fix when it matches register.min_inliers image segments,
    # explains decide.min_explained_fraction of its lines the map covers and fits them within max_rms_px,
    # or within loose_factor x the rms of the last pose the global decision vetted (``fit_limit``) ...
    max_rms_px: float = 2.5
    loose_factor: float = 1.5
    # ... and moved less than the search radius from its prediction: relocalize_radius_m, plus 3 sigma of
    # the odometry since the last fix, at most max_relocalize_radius_m (also the Prior of a relocalization)
    relocalize_radius_m: float = 1.0
    max_relocalize_radius_m: float = 5.0
    relocalize_sigma_rot_deg: float = 5.0
    # innovation gate: with odometry, a fix is claimed only if its Mahalanobis distance to the predicted
    # pose (covariance: the last pose's carried along the odometry, plus the fix's own) is within this
    # chi-square(6) quantile (0: no gate). A wrong basin (a window period off, a pose orbited along a
    # facade) lies many sigmas from the prediction.
    gate_probability: float = 0.999
    # a frame after one without a fix is searched for near its prediction (relocalized): the first
    # relocalize_every frames of a loss each, then every n-th (each costs 0.1 s to seconds)
    relocalize_every: int = 5
    # without odometry after this many frames without a fix: global registration (no prior)
    global_after_frames: int = 10
    # without odometry, a random-walk prior between consecutive frames (never on unless asked)
    smoothness: bool = False
    smooth_sigma_rot_deg: float = 5.0
    smooth_sigma_pos_m: float = 0.3
    rounds: int = 4  # graph re-association rounds
    min_noise_px: float = 0.3  # a frame's line noise is its residual level, at least this
    max_iterations: int = 100  # Levenberg-Marquardt iterations per round


def localize_sequence(
    frames: Sequence[np.ndarray],
    line_map: LineMap,
    camera: Camera,
    relative_poses: Sequence[np.ndarray] | None = None,
    relative_covariances: Sequence[np.ndarray] | None = None,
    config: SequenceConfig | None = None,
    prior: Prior | None = None,
) -> list[Registration]:
    """Returns one Registration per frame, smoothed over the sequence.

    frames: images (H, W[, C]) of the camera's size or (N, 4) float64 segments (the camera's pixels).
    relative_poses: K - 1 (4, 4) measured ``cam_k_from_cam_k+1``; relative_covariances: their (6, 6)
    covariances (gtsam tangent of the relative pose: rotation rad, translation m, in camera k+1), default
    from ``config.odometry_*``. prior: what is known of the first frame's pose (a given start pose is
    ``Prior(cam_from_world=...)``: frame 0 is refined from it, and when frame 0's own lines do not fix it
    the next frames are predicted from it). Bad input raises InvalidInputError.
    """
    config = config or SequenceConfig()
    lines = [_lines(f, camera, config, k) for k, f in enumerate(frames)]
    relative, covariances = check_odometry(relative_poses, relative_covariances, len(lines), config)
    cam = camera.undistorted()
    images = [image_lines(s, cam, config.register.score) for s in lines]
    start = time.perf_counter()
    alone = frames_alone(lines, images, line_map, cam, relative, covariances, config, prior)
    log.info("sequence: %d of %d frames fixed alone", sum(r.success for r in alone), len(alone))
    if relative is None and config.smoothness:
        log.info("sequence: no odometry; a random-walk smoothness prior links consecutive frames")
    graph_start = time.perf_counter()
    out = smooth(
        images, line_map.segments, cam, alone, relative, covariances, config, line_map.accuracy_m,
        map_coverable(line_map, cam, config.register.score),
    )  # fmt: skip
    share = (time.perf_counter() - graph_start) / max(len(out), 1)
    log.debug("sequence: %.1f s alone, %.1f s graph", graph_start - start, share * len(out))
    return [replace(r, timings={**r.timings, "graph": share}) for r in out]


def _lines(frame: np.ndarray, camera: Camera, config: SequenceConfig, k: int) -> np.ndarray:
    try:
        return frame_lines(frame, camera, config.detect)
    except InvalidInputError as e:
        raise InvalidInputError(f"frame {k}: {e}") from None


def check_odometry(
    relative_poses: Sequence[np.ndarray] | None,
    relative_covariances: Sequence[np.ndarray] | None,
    num_frames: int,
    config: SequenceConfig,
) -> tuple[list[np.ndarray] | None, list[np.ndarray] | None]:
    """Returns validated (K - 1) relative poses and covariances (defaults filled in), or (None, None)."""
    if relative_poses is None:
        if relative_covariances is not None:
            raise InvalidInputError("relative_covariances given without relative_poses")
        return None, None
    if len(relative_poses) != num_frames - 1:
        raise InvalidInputError(
            f"{num_frames} frames need {num_frames - 1} relative poses, got {len(relative_poses)}"
        )
    relative = [check_rigid(T, f"relative_poses[{k}]") for k, T in enumerate(relative_poses)]
    if relative_covariances is None:
        c = config
        return relative, [
            step_covariance(T, c.odometry_rot_deg_per_m, c.odometry_pos_fraction, c.odometry_floor_m)
            for T in relative
        ]
    if len(relative_covariances) != len(relative):
        raise InvalidInputError(f"{len(relative)} relative poses but {len(relative_covariances)} covariances")
    return relative, [
        check_covariance(C, f"relative_covariances[{k}]") for k, C in enumerate(relative_covariances)
    ]


def refine_from(
    image: ImageLines,
    line_map: LineMap,
    camera: Camera,
    predicted: np.ndarray,
    radius_m: float,
    config: SequenceConfig,
    max_rms_px: float | None = None,
) -> Registration:
    """Returns the Registration of a frame refined from a predicted (4, 4) cam_from_world: ``success`` when
    it passes the fix checks (matches, explained share, rms within ``max_rms_px`` (None: the config's; see
    ``fit_limit``), within ``radius_m`` of the prediction)."""
    max_rms_px = config.max_rms_px if max_rms_px is None else max_rms_px
    rc = config.register
    start = time.perf_counter()
    centre = camera_center(predicted)
    visible = visible_mask(line_map, centre, radius_m)
    r = refine_pose(image, line_map.segments, camera, predicted, rc.refine, rc.score, visible)
    matches = r.score.matches(rc.decide.min_cover)
    explained = r.score.explained_length / max(image.total_length, 1e-9)
    moved = float(np.linalg.norm(camera_center(r.cam_from_world) - centre))
    reason = ""
    if len(matches) < rc.min_inliers:
        reason = f"tracking: {len(matches)} matched image segments (< {rc.min_inliers})"
    elif short := explains_too_little(
        r.score.explained_length,
        image,
        partial(map_coverable(line_map, camera, rc.score), image, r.cam_from_world),
        rc.decide,
    ):
        reason = f"tracking: the pose {short}"
    elif not np.isfinite(r.covariance).all() or not r.rms_px <= max_rms_px:
        reason = f"tracking: the fit is degenerate or loose (rms {r.rms_px:.1f} px > {max_rms_px:.1f})"
    elif moved > radius_m:
        reason = f"tracking: the pose moved {moved:.2f} m from its prediction (> {radius_m:.2f} m)"
    return Registration(
        success=not reason, reason=reason, cam_from_world=r.cam_from_world, matches=matches,
        num_inliers=len(matches), covariance=r.covariance, rms_px=r.rms_px, score=float(r.score.value),
        explained_fraction=float(explained), timings={"track": time.perf_counter() - start},
    )  # fmt: skip


def fit_limit(reference_px: float | None, config: SequenceConfig) -> float:
    """Returns the rms (px) a tracked fix may fit its lines with: ``max_rms_px``, or ``loose_factor`` x
    ``reference_px`` when that is more: the rms of the last pose the global decision vetted against its
    rivals (a relocalization; for the smoothed frames, the median fit of the frames fixed alone), None
    before there is one. How closely a map's lines fall on a photo's is the map's: a fused RGB-D room's lie
    a few pixels off (the 7-Scenes kitchen's decided poses and its truths alike refine to 4.5-5 px), a
    procedural scan's within one; a fixed bar held every tracked frame of the kitchen to the scan's.
    The batch's frames (``frames_alone``) each face the rival test; the live ``Tracker`` with odometry skips
    it for speed (its fixes are only moved along their valley) and keeps the fixed bar: with this limit its
    fixes on the kitchen, refined from a track 2-3 deg off, held the track there (9 frames claimed 0.3 m off,
    within 10 cm / 2 deg 53.7 -> 23.7 %)."""
    if reference_px is None or not np.isfinite(reference_px):
        return config.max_rms_px
    return max(config.max_rms_px, config.loose_factor * reference_px)


def rival_test(
    image: ImageLines,
    line_map: LineMap,
    camera: Camera,
    fix: Registration,
    config: SequenceConfig,
    max_rms_px: float | None = None,
) -> Registration:
    """Returns a fix (``refine_from``), or no fix (``success=False``, reason ``AMBIGUOUS`` ...) when a
    distinct pose scores above ``(1 - margin)`` of it, as in the global decision: the fix turned beyond
    ``distinct_angle_deg`` (``pipeline.turned_rival``: where the image's clutter lets a displaced copy of
    the map explain nearly as much, the alignment is chance) and the fix orbited round the point it looks
    at, solved locally (``pipeline.orbit_rivals``: a turn and a shift that compensate along a facade, where
    a refinement stops wherever its start lies). A rival is set aside where the fix is sharp and the rival
    is not, where that is evidence (``pipeline.sharp_dismisses``, ``pipeline.precision_is_evidence``).
    ~15 ms on 2 cores (18 on one). A refused fix leaves the frame to the search near its prediction
    (``relocalize``: search and decision). ``max_rms_px``: the bound of the fix's own refinement
    (``fit_limit``), which a fix moved along its valley keeps.

    A fix that passes is moved along its valley (``valley_move``). A refinement from a start a step off along
    the valley stops short (on the synthetic walks without odometry, fixes 0.3-0.4 m and 2-3 deg off the
    truth whose orbit one step over scored up to twice as much); at the score's own distance the valley is
    nearly flat (an orbit 0.3 m off the truth scored 14 % more than one 0.1 m off it: moving to the best
    there claimed more wrong frames, 13 against 8 over four walks), at the finer one the truth stands out
    where the map's lines are exact."""
    rc = config.register
    dc, segments, T0 = rc.decide, line_map.segments, fix.cam_from_world
    visible = visible_mask(line_map, camera_center(T0), config.relocalize_radius_m)
    orbits, turned = both(  # the turned rival's compiled loop runs beside the orbits' solves
        partial(orbit_rivals, T0, fix.matches, image, segments, camera, rc, visible),
        partial(turned_rival, T0, image, segments, camera, rc, visible),
    )
    rivals = sorted([turned, *((T, s.value) for T, s in orbits)], key=lambda r: -r[1])
    fine_value = _fine_scorer(image, line_map, camera, rc, visible)
    sharp = cache(partial(fine_value, T0))  # the fix's, asked for by the rivals

    scores = {id(T): s for T, s in orbits}
    depth = depth_of(segments[fix.matches[:, 1]], T0) if len(fix.matches) else 1.0

    def evidence(T: np.ndarray) -> bool:
        theirs = scores.get(id(T)) or score_pose(image, segments, camera, T, rc.score, visible)
        return precision_is_evidence(
            theirs.matches(dc.min_cover), fix.matches, line_map.accuracy_m, depth, camera, rc
        )

    @cache
    def sharpest() -> float:  # the fix's fine score at its own most precise fit (``_sharper_elsewhere``)
        at = refine_pose(image, segments, camera, T0, precise_config(rc).refine, rc.score, visible)
        return max(sharp(), fine_value(at.cam_from_world))

    def passed() -> Registration:
        for T, value in distinct:  # below the margin, a rival may still fit its lines clearly closer
            theirs, known = cache(partial(fine_value, T)), cache(partial(evidence, T))
            if sharper_rival(fix.score, value, sharp(), theirs, known, dc) and sharper_rival(
                fix.score, value, sharpest(), theirs, known, dc
            ):
                words = sharper_reason(T, T0, value, fix.score, theirs(), sharpest(), rc)
                return replace(fix, success=False, reason=f"{AMBIGUOUS}: {words}")
        return valley_move(image, line_map, camera, fix, config, max_rms_px, orbits, visible)

    distinct = [(T, v) for T, v in rivals if T is turned[0] or differs(T, T0, segments, dc)]
    for T, value in distinct:
        if value < (1.0 - dc.margin) * fix.score:
            return passed()
        if sharp_dismisses(fix.score, value, sharp(), partial(fine_value, T), partial(evidence, T), dc):
            continue
        turn = rotation_error_deg(T[:3, :3], T0[:3, :3])
        shift = float(np.linalg.norm(camera_center(T) - camera_center(T0)))
        share = 100 * value / fix.score if fix.score > 0 else float("inf")
        kind = "turned" if T is turned[0] else "orbited"
        reason = f"{AMBIGUOUS}: the fix {kind} {turn:.0f} deg ({shift:.2f} m) scores {share:.0f} % of it"
        return replace(fix, success=False, reason=reason)
    return passed()


def prediction_move(
    image: ImageLines,
    line_map: LineMap,
    camera: Camera,
    fix: Registration,
    predicted: np.ndarray,
    config: SequenceConfig,
) -> Registration:
    """Returns a tracked fix or, if more precise, the motion model's own answer: the (4, 4) ``predicted``
    pose refined associating at the fine distance (``precise_config``), when that is the same answer
    (``pipeline.differs`` says no), scores within the decision's margin of the fix and fits its lines
    closer at ``sharp_fraction`` of the score's distance than the fix does.

    The tracker refines a fix from its prediction associating at ``start_factor`` times the score's
    distance, which takes in the pairs of a neighbouring basin a turn and a shift away: on the synthetic
    walks, from a prediction on the truth, fixes slid 0.30-0.42 m / 1.8-3.4 deg along a facade's valley
    to a basin that scores more at 4 px and fits less closely, and were claimed (walk 3's frames 102 and
    292 without odometry). The fix's orbits (``valley_move``) did not reach the truth's basin; the
    prediction lies in it. Only a fix fitting within ``max_rms_px`` is moved (a loose map's fine scores
    reward the lines that happen to fit: ``valley_move``)."""
    if not fix.rms_px <= config.max_rms_px:
        return fix
    dc = config.register.decide
    visible = visible_mask(line_map, camera_center(fix.cam_from_world), config.relocalize_radius_m)

    def same_answer(moved: Registration) -> bool:
        T, T0 = moved.cam_from_world, fix.cam_from_world
        return not differs(T, T0, line_map.segments, dc) and moved.score >= (1.0 - dc.margin) * fix.score

    limit = fit_limit(fix.rms_px, config)
    return _sharpest_refined(image, line_map, camera, fix, [predicted], config, limit, visible, same_answer)


def valley_move(
    image: ImageLines,
    line_map: LineMap,
    camera: Camera,
    fix: Registration,
    config: SequenceConfig,
    max_rms_px: float | None = None,
    orbits: list[tuple[np.ndarray, Score]] | None = None,
    visible: np.ndarray | None = None,
) -> Registration:
    """Returns a fix moved along its valley to the most precise of its orbits that are the same answer
    (``pipeline.differs``) and score within the margin, or the fix itself. When some orbit's lines lie
    closer than the fix's at ``sharp_fraction`` of the score's distance, each orbit (one of those converging
    together) is refined associating at that distance (no finer than the refinement's ``min_outlier_px``),
    not at ``start_factor`` times the score's, which takes in the pairs of the fix's basin and slides back to
    it (walk 2's frame 116: from an orbit 0.07 m off the truth back to the fix 0.32 m off; at 2 px, 0.05 m
    off). The most precise refinement is the answer if it is more precise than the fix. An unrefined orbit's
    precision does not tell which (frame 27 of that walk: the orbits nearest the truth scored below the fix
    at the fine distance and above it once refined). Only a fix fitting its lines within ``max_rms_px`` (a
    map as tight as a procedural scan) is moved: on a looser one the fine distance picks the few lines that
    happen to fit (lines 3 cm off at random, 3.5 px rms: moves to 0.4-0.8 px rms over them, up to 3.2 deg
    off where the fix was 0.9 deg; the real kitchen's, 4.8 px rms: moves took the smoothed graph from 85 %
    of the frames within 10 cm / 2 deg to 49 %).

    orbits: ``pipeline.orbit_rivals`` of the fix, if known; visible: the map segments taking part
    (``visible_mask``; None: computed here). ``max_rms_px``: the fix's own refinement bound (``fit_limit``)."""
    if not fix.rms_px <= config.max_rms_px:  # a loose map's fine scores reward the lines that happen to fit
        return fix
    rc = config.register
    dc, segments, T0 = rc.decide, line_map.segments, fix.cam_from_world
    if visible is None:
        visible = visible_mask(line_map, camera_center(T0), config.relocalize_radius_m)
    if orbits is None:
        orbits = orbit_rivals(T0, fix.matches, image, segments, camera, rc, visible)
    fine_value = _fine_scorer(image, line_map, camera, rc, visible)
    same = [
        T for T, s in orbits if s.value >= (1.0 - dc.margin) * fix.score and not differs(T, T0, segments, dc)
    ]
    if not same:
        return fix
    mine = fine_value(T0)
    if max(fine_value(T) for T in same) <= mine:
        return fix
    starts = [T for i, T in enumerate(same) if not any(np.allclose(T, U, atol=1e-9) for U in same[:i])]
    return _sharpest_refined(image, line_map, camera, fix, starts, config, max_rms_px, visible, mine=mine)


def _fine_scorer(
    image: ImageLines, line_map: LineMap, camera: Camera, config: RegisterConfig, visible: np.ndarray | None
) -> Callable[[np.ndarray], float]:
    """Returns cam_from_world -> the pose's score at the fine distance (``fine_config``): how closely it
    fits the lines (the map segments ``visible``, None: all)."""
    fine = fine_config(config)
    return lambda T: score_pose(image, line_map.segments, camera, T, fine, visible).value


def _sharpest_refined(
    image: ImageLines,
    line_map: LineMap,
    camera: Camera,
    fix: Registration,
    starts: Sequence[np.ndarray],
    config: SequenceConfig,
    max_rms_px: float | None,
    visible: np.ndarray | None,
    keep: Callable[[Registration], bool] | None = None,
    mine: float | None = None,
) -> Registration:
    """Returns the fix or, of the refinements from the (4, 4) ``starts`` associating at the fine distance
    (``precise_config``) that succeed and that ``keep`` admits, the one fitting the lines closest at the
    fine distance, when it fits them closer than the fix (whose fine score is ``mine``, if known): the end
    of ``valley_move`` and ``prediction_move``. The refinements' tracking time is added to the fix's."""
    fine_value = _fine_scorer(image, line_map, camera, config.register, visible)
    precise = replace(config, register=precise_config(config.register))
    moves = [
        refine_from(image, line_map, camera, T, config.relocalize_radius_m, precise, max_rms_px)
        for T in starts
    ]
    done = [(fine_value(m.cam_from_world), m) for m in moves if m.success and (keep is None or keep(m))]
    if not done:
        return fix
    value, moved = max(done, key=lambda r: r[0])
    if value <= (fine_value(fix.cam_from_world) if mine is None else mine):
        return fix
    track = fix.timings.get("track", 0.0) + sum(m.timings.get("track", 0.0) for m in moves)
    return replace(moved, timings={**fix.timings, "track": track})


def map_coverable(
    line_map: LineMap, camera: Camera, config: ScoreConfig
) -> Callable[[ImageLines, np.ndarray], float]:
    """Returns (image, cam_from_world) -> the image's line length the map could explain at that pose
    (``score.coverable_length``: near its visible parts or its surfaces; a map without surfaces, the whole
    image's), for ``pipeline.explains_too_little``."""

    def coverable(image: ImageLines, cam_from_world: np.ndarray) -> float:
        footprint = line_map.surface_footprint(camera, cam_from_world, config.distance_px)
        if footprint is None:
            return image.total_length
        # the segments potentially visible from the camera's cell (conservative: the same parts as the
        # whole map's, at the cost of what is near)
        centre = camera_center(cam_from_world)
        seen = line_map.potentially_visible(centre, centre)
        parts, _ = line_map.visible_parts(camera, cam_from_world, seen)
        return coverable_length(image, camera, cam_from_world, parts, footprint, config)

    return coverable


def visible_mask(line_map: LineMap, centre: np.ndarray, radius_m: float) -> np.ndarray | None:
    """Returns (M,) bool of the map segments that may be seen from within ``radius_m`` of a (3,) centre
    (the map's potentially-visible sets), or None when the map has no surfaces to hide anything."""
    if line_map.surfaces is None:
        return None
    mask = np.zeros(len(line_map.segments), dtype=bool)
    mask[line_map.potentially_visible(centre - radius_m, centre + radius_m)] = True
    return mask


def relocalize(
    lines2d: np.ndarray,
    line_map: LineMap,
    camera: Camera,
    predicted: np.ndarray | None,
    radius_m: float,
    config: SequenceConfig,
    image: ImageLines | None = None,
) -> Registration:
    """Returns the global Registration of undistorted (N, 4) segments, near ``predicted`` when given;
    ``image``: their ``image_lines`` if the caller has them (else made here for ``valley_move``)."""
    prior = None
    if predicted is not None:
        prior = Prior(
            cam_from_world=predicted, radius_m=radius_m, sigma_rot_deg=config.relocalize_sigma_rot_deg
        )
    found = localize_segments(lines2d, line_map, camera, config.register, prior)
    if not found.success:
        return found
    # the decision's answer is the refinement's from the search's pose, which stops wherever its basin lies
    # along a facade's valley, as a tracked fix does: moved as one is (``valley_move``)
    if image is None:
        image = image_lines(lines2d, camera, config.register.score)
    moved = valley_move(image, line_map, camera, found, config, fit_limit(found.rms_px, config))
    return found if moved is found else replace(moved, timings=found.timings)


def frames_alone(
    lines: list[np.ndarray],
    images: list[ImageLines],
    line_map: LineMap,
    camera: Camera,
    relative: list[np.ndarray] | None,
    covariances: list[np.ndarray] | None,
    config: SequenceConfig,
    prior: Prior | None = None,
) -> list[Registration]:
    """Returns each frame's own Registration: tracked from its prediction, else relocalized near it, else
    global (step 1 of the module docstring); a start pose given in ``prior`` that frame 0's own lines do not
    fix stands in for its fix, known to the prior's bounds. With odometry, a fix lying farther from the odometry's
    prediction than ``gate_probability`` allows (the tracker's innovation gate, on the last fix's covariance
    carried along the odometry) is not claimed: ``success=False``, its pose kept (``gated``)."""
    out: list[Registration] = []
    # where predictions start: the last frame fixed alone, or gated (its fix and its prediction combined)
    fix: tuple[int, np.ndarray] | None = None
    drift = 0.0  # 3 sigma of the odometry position since then
    carried: np.ndarray | None = None  # its covariance, carried along the odometry to the previous frame
    decided: float | None = None  # the rms of the last relocalization's fix: how loosely the map fits
    for k, image in enumerate(images):
        predicted, radius = _prediction(k, out, fix, relative, drift, config)
        if k == 0 and prior is not None and prior.cam_from_world is not None:
            predicted, radius = prior.cam_from_world, prior.radius_m or config.relocalize_radius_m
        lost = k - (fix[0] if fix else -1) - 1  # frames since the last fix
        every = config.relocalize_every
        untried = (
            f"not searched: {lost} frames since the last fix (a loss is searched for in its first {every} "
            f"frames, then every {every}th)"
        )
        result = Registration(success=False, reason=untried)
        # a refinement finds the nearest basin, right only while the prediction is (the last frame's fix
        # plus one step); after frames without a fix the frame is searched for near its prediction
        # (relocalize: the best-scoring pose there, against its rivals)
        follows = k == 0 or (fix is not None and fix[0] == k - 1)  # a fix, or a gated fix (``gated``)
        if follows and predicted is not None and len(lines[k]) >= config.register.min_lines2d:
            limit = fit_limit(decided, config)
            result = refine_from(image, line_map, camera, predicted, radius, config, limit)
            if result.success:
                result = rival_test(image, line_map, camera, result, config, limit)
        if not result.success and (lost < config.relocalize_every or lost % config.relocalize_every == 0):
            start = time.perf_counter()
            reloc = relocalize(lines[k], line_map, camera, predicted, radius, config, image)
            timings = {**reloc.timings, "relocalize": time.perf_counter() - start}
            if reloc.success:
                decided = reloc.rms_px
            if reloc.success or predicted is None:
                result = replace(reloc, timings=timings)
            else:  # the refinement's pose (gated or not) stays; a frame not refined says why the search failed
                why = reloc.reason if result.reason == untried else result.reason
                result = replace(result, reason=why, timings=timings | result.timings)
        base, covariance = result.cam_from_world, result.covariance
        if result.success and predicted is not None and carried is not None and relative is not None:
            assert covariances is not None
            result, base, covariance = gated(
                result, predicted, carried, relative[k - 1], covariances[k - 1], config
            )
        out.append(result)
        if result.success or result.reason.startswith(GATED):  # the next frame's prediction starts here
            fix, drift, carried = (k, base), 0.0, covariance
        elif k == 0 and predicted is not None and prior is not None:
            # a given start pose (the only prediction frame 0 has) that its own lines did not fix (a blank
            # wall, a rival as good): the next frames are predicted from it, as from a fix known to within
            # the prior's radius (3 sigma) and rotation sigma, not searched for in the whole map
            rot = np.radians(prior.sigma_rot_deg or config.relocalize_sigma_rot_deg)
            fix, drift = (0, predicted), radius
            carried = np.diag([rot**2] * 3 + [(radius / 3.0) ** 2] * 3)
        elif relative is not None and covariances is not None:
            if k < len(relative):
                drift += 3.0 * float(np.sqrt(np.trace(covariances[k][3:, 3:])))
            if carried is not None:  # the last fix's covariance carried on to this frame
                carried = carry(carried, relative[k - 1], covariances[k - 1])
    return out


def gated(
    fix: Registration,
    predicted: np.ndarray,
    previous_covariance: np.ndarray,
    step: np.ndarray,
    step_covariance: np.ndarray,
    config: SequenceConfig,
) -> tuple[Registration, np.ndarray, np.ndarray]:
    """Returns (the fix, or the fix not claimed; the (4, 4) pose and (6, 6) covariance the next frame's
    prediction starts from). The fix is not claimed (``success=False``, reason ``GATED``) when its pose lies
    farther from the odometry's ``predicted`` (4, 4) than ``gate_probability`` of the predicted distribution
    allows (``graph.innovation_distance``: the previous frame's covariance carried through ``step`` with its
    covariance, plus the fix's own); the next frame then starts from the fix and the prediction combined
    (``graph.fuse``, as the tracker's graph combines them), so a slip of the odometry strands nothing."""
    d2 = innovation_distance(
        predicted, fix.cam_from_world, previous_covariance, step, step_covariance, fix.covariance
    )
    limit = chi2_quantile(config.gate_probability, 6) if config.gate_probability else np.inf
    if d2 <= limit:
        return fix, fix.cam_from_world, fix.covariance
    reason = (
        f"{GATED}: its fix is {np.sqrt(d2):.1f} sigma from the odometry's prediction "
        f"(gate {np.sqrt(limit):.1f} sigma)"
    )
    base, covariance = fuse(
        predicted, carry(previous_covariance, step, step_covariance), fix.cam_from_world, fix.covariance
    )
    return replace(fix, success=False, reason=reason), base, covariance


def _prediction(
    k: int,
    done: list[Registration],
    fix: tuple[int, np.ndarray] | None,
    relative: list[np.ndarray] | None,
    drift: float,
    config: SequenceConfig,
) -> tuple[np.ndarray | None, float]:
    """Returns (predicted (4, 4) pose of frame k or None for a global search, search radius m)."""
    if fix is None:
        return None, config.max_relocalize_radius_m
    j, pose = fix
    if relative is not None:  # odometry from the last fix
        for i in range(j, k):
            pose = predict(pose, relative[i])
        return pose, min(config.relocalize_radius_m + drift, config.max_relocalize_radius_m)
    gap = k - j
    if gap > config.global_after_frames:
        return None, config.max_relocalize_radius_m
    if j >= 1 and done[j - 1].success:  # constant velocity
        step = relative_pose(done[j - 1].cam_from_world, pose)
        for _ in range(gap):
            pose = predict(pose, step)
    return pose, min(config.relocalize_radius_m * gap, config.max_relocalize_radius_m)


def smooth(
    images: list[ImageLines],
    lines3d: np.ndarray,
    camera: Camera,
    alone: list[Registration],
    relative: list[np.ndarray] | None,
    covariances: list[np.ndarray] | None,
    config: SequenceConfig,
    accuracy_m: float = 0.0,
    coverable: Callable[[ImageLines, np.ndarray], float] | None = None,
) -> list[Registration]:
    """Returns the frames' Registrations after the graph (steps 2 and 3 of the module docstring);
    ``accuracy_m``: how well the map places its lines (``LineMap.accuracy_m``; 0: exactly): in the graph it
    ties each frame's pose to the pose of its lines (``_ties``), and it is added to each frame's reported
    covariance (``pipeline.with_map_floor``: the graph treats the frames' map errors as independent, but
    frames seeing the same lines share them); ``coverable``: (image, cam_from_world) -> the image's
    line length the map could explain there (``map_coverable``; None: the whole image's)."""
    links = _links(len(images), relative, covariances, config)
    poses = _initial(alone, links, config)
    rc = config.register
    # a fix starts at its own refinement's tolerance; a frame placed by odometry needs a wider capture
    tolerance = {k: _start_tolerance(alone[k], rc) for k in poses}
    sigma = {k: alone[k].rms_px if np.isfinite(alone[k].rms_px) else 1.0 for k in poses}
    previous: dict[int, np.ndarray] = {}
    graph, fits = gtsam.NonlinearFactorGraph(), dict[int, LineFit]()
    # a frame's line factor holds the pose its lines give against the map, tied to the frame's by the map's
    # accuracy: 298 -> 320 of walk 0's 320 frames within 10 cm / 2 deg, smoothed ATE 0.64 -> 0.49 of
    # per-frame's (docs/measurements.md, session 50)
    tied = accuracy_m > 0
    for _ in range(config.rounds):
        fits = dict[int, LineFit]()
        for k, pose in poses.items():
            fit = line_fit(
                lines_key(k) if tied else frame_key(k),
                images[k],
                lines3d,
                camera,
                pose,
                tolerance[k],
                max(sigma[k], config.min_noise_px),
                rc,
            )
            if fit is not None:
                fits[k] = fit
        if all(k in previous and _same(fits[k].pairs, previous[k]) for k in fits) and len(fits) == len(
            previous
        ):
            break
        ties = _ties(fits, lines3d, poses, accuracy_m) if tied else {}
        graph, members = _graph(poses, fits, links, ties=ties)
        poses = {**poses, **_optimise(graph, members, poses, config, ties)}
        for k, fit in fits.items():
            r = fit.residuals(poses[k])
            tolerance[k], sigma[k] = next_tolerance(r, rc), noise_px(r, rc, config.min_noise_px)
        previous = {k: f.pairs for k, f in fits.items()}
    ties = _ties(fits, lines3d, poses, accuracy_m) if tied else {}
    graph, members = _graph(poses, fits, links, ties=ties)
    covariances_out = _marginals(graph, members, poses, ties)
    # each fitted frame's rms at its smoothed pose; how loosely this map's lines fit: the frames fixed alone
    rms = {k: _fit_rms(fits[k], poses[k]) for k in fits}
    fitted = [value for k, value in rms.items() if _fitted(alone[k])]
    limit = fit_limit(float(np.median(fitted)) if fitted else None, config)
    return [
        _result(
            k,
            alone[k],
            images[k],
            lines3d,
            camera,
            poses,
            covariances_out,
            rms.get(k, float("nan")),
            links,
            relative is not None,
            config,
            limit,
            accuracy_m,
            coverable,
        )
        for k in range(len(images))
    ]


def _fit_rms(fit: LineFit, cam_from_world: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(fit.residuals(cam_from_world)))))


def _fitted(alone: Registration) -> bool:
    """Returns True for a frame whose own lines fixed it: claimed, or gated (the graph weighs a fix against
    the odometry, as the tracker's does)."""
    return alone.success or alone.reason.startswith(GATED)


def _start_tolerance(alone: Registration, rc: RegisterConfig) -> float:
    if not _fitted(alone) or not np.isfinite(alone.rms_px):
        return rc.score.distance_px
    rf = rc.refine
    return float(np.clip(rf.outlier_sigmas * alone.rms_px, rf.min_outlier_px, rc.score.distance_px))


_Link = tuple[int, np.ndarray, np.ndarray]  # (k, cam_k_from_cam_k+1, (6, 6) covariance)


def _links(
    n: int, relative: list[np.ndarray] | None, covariances: list[np.ndarray] | None, config: SequenceConfig
) -> list[_Link]:
    """Returns the odometry links (or, when asked and there is no odometry, the random-walk prior)."""
    if relative is not None and covariances is not None:
        return [(k, relative[k], covariances[k]) for k in range(n - 1)]
    if not config.smoothness:
        return []
    walk = np.diag([np.radians(config.smooth_sigma_rot_deg) ** 2] * 3 + [config.smooth_sigma_pos_m**2] * 3)
    return [(k, np.eye(4), walk) for k in range(n - 1)]


def _initial(alone: list[Registration], links: list[_Link], config: SequenceConfig) -> dict[int, np.ndarray]:
    """Returns the initial pose of every frame the graph can reach: its own fix (claimed or gated); a frame
    between fixes, where the pose graph of the fixes (each a prior with its covariance) and the odometry
    puts it, the drift shared over the gap; a frame the graph cannot place, chained along the links from
    the nearest fix before it, else back from the nearest one after it."""
    fixed = {k: r.cam_from_world for k, r in enumerate(alone) if _fitted(r)}
    poses = dict(fixed)
    step = {k: T for k, T, _ in links}
    for k in range(1, len(alone)):
        if k not in poses and k - 1 in poses and k - 1 in step:
            poses[k] = predict(poses[k - 1], step[k - 1])
    for k in range(len(alone) - 2, -1, -1):
        if k not in poses and k + 1 in poses and k in step:
            poses[k] = step[k] @ poses[k + 1]  # cam_k_from_cam_k+1 @ cam_k+1_from_world
    bridged = _pose_graph(poses, {k: alone[k].covariance for k in fixed}, links, config)
    return dict(sorted((poses | {k: T for k, T in bridged.items() if k not in fixed}).items()))


def _pose_graph(
    poses: dict[int, np.ndarray],
    covariances: dict[int, np.ndarray],
    links: list[_Link],
    config: SequenceConfig,
) -> dict[int, np.ndarray]:
    """Returns the poses of the pose graph started at ``poses``: a prior per fix with its (6, 6) covariance
    (fixes without a usable one are left out), a ``BetweenFactorPose3`` per odometry link; {} when no fix
    has a usable covariance or the graph cannot be solved."""
    anchors = {
        k: gtsam.PriorFactorPose3(frame_key(k), to_pose3(poses[k]), gtsam.noiseModel.Gaussian.Covariance(C))
        for k, C in covariances.items()
        if np.all(np.isfinite(C)) and np.all(np.linalg.eigvalsh(0.5 * (C + C.T)) > 0)
    }
    if not anchors:
        return {}
    graph, members = _graph(poses, {}, links, anchors)
    return _optimise(graph, members, poses, config)


def _graph(
    poses: dict[int, np.ndarray],
    fits: dict[int, LineFit],
    links: list[_Link],
    anchors: Mapping[int, gtsam.NonlinearFactor] | None = None,
    ties: Mapping[int, np.ndarray] | None = None,
) -> tuple[gtsam.NonlinearFactorGraph, list[int]]:
    """Returns the graph and its frames: the connected groups of frames holding at least one line factor
    or one of the ``anchors`` (frame -> a factor on that frame alone; a group without either has nothing
    fixing it in the world). ``ties``: frame -> the (6, 6) covariance between its pose and the pose its
    line factor holds (``lines_key``; a frame without one has its line factor on its own pose)."""
    parent = {k: k for k in poses}

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    used = [(k, T, C) for k, T, C in links if k in poses and k + 1 in poses]
    for k, _, _ in used:
        parent[root(k)] = root(k + 1)
    anchors = anchors or {}
    anchored = {root(k) for k in (*fits, *anchors)}
    members = [k for k in poses if root(k) in anchored]
    keep = set(members)
    graph = gtsam.NonlinearFactorGraph()
    for k in members:
        if k in fits:
            graph.add(fits[k].factor)
        if ties and k in ties:
            noise = gtsam.noiseModel.Gaussian.Covariance(ties[k])
            graph.add(gtsam.BetweenFactorPose3(frame_key(k), lines_key(k), gtsam.Pose3(), noise))
        if k in anchors:
            graph.add(anchors[k])
    for k, T, C in used:
        if k in keep:
            graph.add(odometry_factor(k, T, C))
    return graph, members


def _ties(
    fits: dict[int, LineFit], lines3d: np.ndarray, poses: dict[int, np.ndarray], accuracy_m: float
) -> dict[int, np.ndarray]:
    """Returns frame -> the (6, 6) covariance tying its pose to the pose its lines give: ``map_floor`` of a
    map placing its lines to ``accuracy_m``, at the median depth of the lines the frame matched."""
    return {k: map_floor(accuracy_m, depth_of(lines3d[f.pairs[:, 1]], poses[k])) for k, f in fits.items()}


def _values(
    members: list[int], poses: dict[int, np.ndarray], ties: Mapping[int, np.ndarray] | None
) -> gtsam.Values:
    """Returns the graph's initial values: each frame's pose, and the pose of its lines where tied."""
    values = gtsam.Values()
    for k in members:
        values.insert(frame_key(k), to_pose3(poses[k]))
        if ties and k in ties:
            values.insert(lines_key(k), to_pose3(poses[k]))
    return values


def _optimise(
    graph: gtsam.NonlinearFactorGraph,
    members: list[int],
    poses: dict[int, np.ndarray],
    config: SequenceConfig,
    ties: Mapping[int, np.ndarray] | None = None,
) -> dict[int, np.ndarray]:
    """Returns the optimised poses of the graph's frames (Levenberg-Marquardt; the input on failure)."""
    values = _values(members, poses, ties)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.register.refine.relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as e:  # indeterminant system
        log.warning("sequence graph: %s", e)
        return {}
    return {k: from_pose3(result.atPose3(frame_key(k))) for k in members}


def _marginals(
    graph: gtsam.NonlinearFactorGraph,
    members: list[int],
    poses: dict[int, np.ndarray],
    ties: Mapping[int, np.ndarray] | None = None,
) -> dict[int, np.ndarray]:
    """Returns (6, 6) marginal covariances (body frame, rotation first) of the graph's frames."""
    values = _values(members, poses, ties)
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as e:
        log.warning("sequence marginals: %s", e)
        return {}
    return {k: marginals.marginalCovariance(frame_key(k)) for k in members}


def _result(
    k: int,
    alone: Registration,
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    poses: dict[int, np.ndarray],
    covariances: dict[int, np.ndarray],
    rms: float,
    links: list[_Link],
    odometry: bool,
    config: SequenceConfig,
    max_rms_px: float,
    accuracy_m: float = 0.0,
    coverable: Callable[[ImageLines, np.ndarray], float] | None = None,
) -> Registration:
    """Returns frame k's Registration at its smoothed pose: a fix of its own lines (its line factor's rms
    ``rms`` px within ``max_rms_px``; NaN: the frame has none), or from neighbours; its covariance: the
    graph's marginal plus what the map's ``accuracy_m`` adds."""
    if k not in covariances:
        return alone
    rc = config.register
    pose = poses[k]
    score = score_pose(image, lines3d, camera, pose, rc.score)
    matches = score.matches(rc.decide.min_cover)
    explained = score.explained_length / max(image.total_length, 1e-9)
    linked = alone.success or (odometry and any(j in (k, k - 1) for j, _, _ in links))
    room = partial(coverable, image, pose) if coverable is not None else lambda: image.total_length
    enough = not explains_too_little(score.explained_length, image, room, rc.decide)
    own = len(matches) >= rc.min_inliers and enough and rms <= max_rms_px  # False for NaN: no line factor
    reason = ""
    if not (own and linked):
        reason = f"{FROM_NEIGHBOURS}: the frame's own lines match {len(matches)} image segments ({100 * explained:.0f} % explained)"
    return replace(
        alone, success=not reason, reason=reason, cam_from_world=pose, matches=matches, num_inliers=len(matches),
        covariance=with_map_floor(covariances[k], accuracy_m, lines3d[matches[:, 1]], pose), rms_px=rms, score=float(score.value), explained_fraction=float(explained),
    )  # fmt: skip


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.shape != b.shape:
        return False
    return bool(np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])]))
