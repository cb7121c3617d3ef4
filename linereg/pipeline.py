"""``register``: the paper's section III from segments to a refined pose, and the decision — a composer.

III-B  vanishing directions (image) and parallel clusters (map) -> rotation candidates (eq. 2, Algorithm 1);
III-C  for all candidates at once, camera centres from the rays of matched corners (``search.py``, which
       replaces the paper's random 3-pair hypotheses: every point correspondence votes), each best voxel
       solved locally and scored without correspondences (``score.py``);
III-D  GTSAM refinement of the best distinct poses on matched fragments (eq. "costs", ``refine.py``);
then   the decision: a pose is an answer only when no distinct pose comes close, and the basins next to it
       that explain the image as well do not spread it as far as distinct poses lie (``decide``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cache, partial
from typing import TypeVar

import gtsam
import numpy as np

from .camera import Camera
from .chunks import Chunks
from .config import DecideConfig, RegisterConfig, ScoreConfig
from .copies import copy_starts
from .directions import DirectionClusters
from .errors import InvalidInputError
from .geometry import (
    camera_center,
    invert,
    make_cam_from_world,
    orbited,
    rotation_error_deg,
    rotation_from_vector,
)
from .parallel import parallel_clusters
from .points import Points, image_points, map_gap_m, map_points
from .priors import Prior, admits, admits_pose, search_region
from .refine import Refinement, refine_pose
from .registration import Registration, check_segments
from .rotation import refine_candidates, rotation_candidates, single_direction_candidates
from .score import (
    ImageLines,
    Score,
    coverable_length,
    image_lines,
    project_clipped,
    score_pose,
    shifted_values,
)
from .search import Found, MapSignatures, map_signatures, screen, search, solve_all, solve_locally
from .significance import SearchSpace, chance_probabilities, depth_of, log10_tail
from .threads import map_threads
from .timing import StageTimer
from .vanishing import vanishing_directions

log = logging.getLogger(__name__)
_Item = TypeVar("_Item")


# how the reasons begin when nothing found explains the image: no pose at all, or a best pose matching too
# few image segments or explaining too little of its lines to be an answer (``decide``)
NOTHING_FOUND = "no pose explains any image line"
UNEXPLAINED = "the best pose"


def register(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    config: RegisterConfig | None = None,
    prior: Prior | None = None,
) -> Registration:
    """Returns the Registration of an image's 2D segments against a map's 3D segments.

    lines2d: (N, 4) float64 pixels as measured in the image (distorted if ``camera.dist`` is set).
    lines3d: (M, 6) float64 world metres. No pose found -> ``success=False`` with a reason; malformed
    input -> ``InvalidInputError`` naming the argument. prior: what is known of the pose (``Prior``).
    """
    config = config or RegisterConfig()
    if not isinstance(camera, Camera):
        raise InvalidInputError(f"camera must be a linereg.Camera, got {type(camera).__name__}")
    lines2d = check_segments(lines2d, "lines2d", 4, config.min_lines2d)
    lines3d = check_segments(lines3d, "lines3d", 6, config.min_lines3d)
    if camera.has_distortion:  # the pipeline works on undistorted pixels of the same K
        lines2d = camera.undistort_points(lines2d.reshape(-1, 2)).reshape(-1, 4)
        camera = camera.undistorted()
    timer = StageTimer()
    return register_undistorted(lines2d, segments_view(lines3d, config, timer), camera, config, timer, prior)


def segments_view(lines3d: np.ndarray, config: RegisterConfig, timer: StageTimer | None = None) -> MapView:
    """Returns the MapView of validated (M, 6) bare segments (no surfaces): their direction clusters, corner
    points and signatures (timed as ``parallel_3d`` and ``map_points``)."""
    timer = timer or StageTimer()
    with timer("parallel_3d"):
        clusters = parallel_clusters(lines3d, config.parallel)
    with timer("map_points"):
        points = map_points(lines3d, config.points, map_gap_m(lines3d, config.points))
        signatures = map_signatures(points, clusters.labels, clusters.directions)
    return MapView(lines3d, clusters, points, signatures)


@dataclass(frozen=True)
class MapView:
    """The part of a map a query sees: (M, 6) segments, their clusters, corner points and signatures, and
    (M,) bool ``visible`` (None: no surfaces to hide anything); ``parts``: the map's occlusion test, (camera,
    cam_from_world) -> ((K, 6) visible pieces of the segments, (K,) the row of each), None without
    surfaces (``LineMap.visible_parts``)."""

    segments: np.ndarray
    clusters: DirectionClusters
    points: Points
    signatures: MapSignatures
    visible: np.ndarray | None = None
    parts: Callable[[Camera, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    accuracy_m: float = 0.0  # how well the map places its lines (``LineMap.accuracy_m``; 0: exact)
    # (camera, cam_from_world, cell_px) -> the cells whose ray meets the map's surfaces
    # (``LineMap.surface_footprint``), None without surfaces
    footprint: Callable[[Camera, np.ndarray, float], np.ndarray | None] | None = None
    # the segments' chunks (``chunks.Chunks``; None: none, a small map): what a pose's projection passes
    # over first, the same result sooner
    chunks: Chunks | None = None


def register_undistorted(
    lines2d: np.ndarray,
    view: MapView,
    camera: Camera,
    config: RegisterConfig,
    timer: StageTimer | None = None,
    prior: Prior | None = None,
) -> Registration:
    """Returns the Registration of validated, undistorted segments against a prepared map view."""
    timer = timer or StageTimer()
    # III-B: vanishing directions of the image (Rother 2002, multiple RANSAC on interpretation planes)
    with timer("vanishing"):
        vds = vanishing_directions(lines2d, camera, config.vanishing)
    # III-B, eq. (2): rotation candidates from VD <-> parallel-cluster pairings and signs (Algorithm 1); one
    # matched direction leaves an angle about it, its angles scored against the other directions; a prior
    # keeps those it admits
    with timer("rotation"):
        candidates = rotation_candidates(vds, view.clusters, config.rotation, partial(admits, prior))
        if config.rotation.refit:
            candidates = refine_candidates(candidates, vds, view.clusters, lines2d, camera)
        rotations = [c.R for c in candidates]
        singles = partial(single_direction_candidates, vds, view.clusters, lines2d, camera, config.rotation)
        paired = bool(rotations)
        if not paired:
            rotations = singles()
        if prior is not None and prior.cam_from_world is not None:
            rotations.append(prior.cam_from_world[:3, :3])
        rotations = [R for R in rotations if admits(prior, R)]
    if not rotations:
        reason = f"no rotation candidate ({len(vds)} vanishing directions, {len(view.clusters)} 3D clusters)"
        if prior is not None and (prior.gravity is not None or prior.cam_from_world is not None):
            reason += " agrees with the prior"
        return Registration(success=False, reason=reason, timings=timer.finish())
    image = image_lines(lines2d, camera, config.score)
    # the map's margins cut to a prior's ball: the same box twice is searched once
    regions: list[tuple[np.ndarray, np.ndarray]] = []
    for margin in config.search.region_margins:
        lo, hi = search_region(view.segments, prior, margin)
        if not any(np.array_equal(lo, a) and np.array_equal(hi, b) for a, b in regions):
            regions.append((lo, hi))
    points = image_points(lines2d, config.points)
    result, found = _search_and_decide(
        image, points, view, camera, config, timer, prior, rotations, regions, []
    )
    if not paired or not result.reason.startswith((NOTHING_FOUND, UNEXPLAINED)):
        return result
    # no pose under the paired rotations explains the image (too few matches, too little of its lines; not
    # a pose that explains much but not uniquely or not beyond chance): the second direction may be a chance
    # alignment of clutter (on the paper's scenes with 30-60 % outlier segments a VD of random segments
    # outscored a true one, and every paired rotation was 50-90 deg off), so each strong direction alone,
    # its angle searched with a bound (``single_direction_candidates``), adds rotations, and the decision
    # weighs every pose found. (Tried after every unanswered photo, or after every photo whose rotations no
    # third direction confirms, they took the shared real photos from 1.27 s to 1.9-2.3 s median and
    # answered none more.)
    with timer("rotation"):
        more = [
            R
            for R in singles()
            if admits(prior, R)
            and all(rotation_error_deg(R, Q) > config.rotation.dedupe_angle_deg for Q in rotations)
        ]
    if not more:
        return result
    return _search_and_decide(
        image, points, view, camera, config, timer, prior, rotations + more, regions, found, len(rotations)
    )[0]


def _search_and_decide(
    image: ImageLines,
    image_pts: Points,
    view: MapView,
    camera: Camera,
    config: RegisterConfig,
    timer: StageTimer,
    prior: Prior | None,
    rotations: list[np.ndarray],
    regions: list[tuple[np.ndarray, np.ndarray]],
    before: list[Found],
    searched: int = 0,
) -> tuple[Registration, list[Found]]:
    """Returns (the Registration, the poses found) of a search over ``rotations[searched:]`` (III-C; the
    image side ``image`` and ``image_pts`` made once by the caller) with
    the poses ``before`` found under the first ``searched``, refined (III-D) and decided over all of them."""
    # III-C: camera centres from the rays of matched corners, the best solved locally and scored (near the
    # map on a fine grid, farther out on a coarser one: a photo of a small mapped object is taken from afar)
    with timer("search"):
        found, _ = search(
            image,
            image_pts,
            view.segments,
            view.points,
            view.signatures,
            camera,
            rotations[searched:],
            regions,
            config.search,
            config.score,
            view.visible,
            None if view.parts is None else lambda T: view_score(view, image, camera, T, config.score)[0],
            view.chunks,
        )
    # a prior is a bound: poses the local solves or the refinement carry out of it are neither answers nor
    # rivals (``priors.admits_pose``)
    found = [
        replace(f, rotation=f.rotation + searched) for f in found if admits_pose(prior, f.cam_from_world)
    ]
    found = sorted(before + found, key=lambda f: -f.score.value)
    if not found:
        reason = NOTHING_FOUND + (" within the prior" if prior is not None else "")
        return Registration(success=False, reason=reason, timings=timer.finish()), found
    # III-D: GTSAM refinement of the best distinct poses on their matched fragments
    with timer("refine"):
        contenders = _distinct(found, _found_pose, view.segments, config.decide)[: config.decide.contenders]
        refined, slides = [], []
        for f in contenders:
            at_start = start_score(f.cam_from_world, image, view, camera, config)
            fit = refine_pose(
                image, view.segments, camera, f.cam_from_world, config.refine, config.score, view.visible
            )
            refined.append(no_worse(f.cam_from_world, fit, image, view, camera, config, at_start))
            # how far the refinement slid its start along a flat score: the decision's to weigh
            slides.append(slid(f.cam_from_world, refined[-1], at_start, view, config))
        admitted = [k for k, r in enumerate(refined) if admits_pose(prior, r.cam_from_world)]
        refined, slides = [refined[k] for k in admitted], [slides[k] for k in admitted]
    if not refined:
        reason = "every pose refined leaves the prior's bounds"
        return Registration(success=False, reason=reason, timings=timer.finish()), found
    # copies of what the best pose sees elsewhere in the map: rivals the search need not have solved
    with timer("copies"):
        seen, rivals = with_copies(refined, found, view, image, camera, config, rotations, regions)
    space = SearchSpace.of(regions, len(rotations), config)
    return decide(refined, seen, rivals, view, image, camera, config, timer, space, slides), found


def decide(
    refined: list[Refinement],
    seen: list[tuple[Score, np.ndarray]],
    found: list[Found],
    view: MapView,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
    timer: StageTimer,
    space: SearchSpace,
    slides: Sequence[tuple[float, float] | None] | None = None,
) -> Registration:
    """Returns the Registration of the best refined pose (``seen``: the ``view_score`` of each), with
    ``success`` only when it has enough matches,
    explains ``min_explained_fraction`` of the image lines the map covers at it (``explains_too_little``),
    more than chance would give any of the poses the search
    examined (``space``: ``significance.py``), and every distinct pose either scores below ``(1 - margin)``
    of it or leaves unexplained image lines that the best explains beyond chance while explaining none
    beyond the best that chance would not (``advantage_nfa`` both ways): the
    other poses found (with the copies of what the best sees elsewhere in the map and the best orbited
    round what it looks at: ``with_copies``) and the best pose itself turned by small angles
    (``turned_rivals``), which the search need not have visited. A rival that the refinement takes back to
    the best (``in_basin``) is the same answer; one that falls below the margin at ``sharp_fraction`` of the
    score's distance, where the best keeps ``sharp_keep`` of its score, is a less precise fit, where that
    is evidence (``precision_is_evidence``: the same map lines, or a map more accurate than that distance);
    and never when its refinement slid it to a distinct pose along a flat score (``slides``: ``slid`` of
    each refined pose, None: not known). Last, its covariance (the fit's, with the map's floor) takes in
    the spread of the basins next to it that the rival tests would not set aside (``near_basins``,
    ``basin_spread``), and it is refused when that reaches distinct poses (``undetermined``)."""
    dc = config.decide
    lines3d = view.segments
    with timer("decide"):
        # the contenders and their rivals scored with what the map's surfaces hide from each: a pose behind a
        # wall, explaining the image with lines it could not see, loses them (the search scores without)
        order = sorted(range(len(refined)), key=lambda k: -seen[k][0].value)
        order = _sharpest_first(order, refined, seen, view, image, camera, config)
        best = replace(refined[order[0]], score=seen[order[0]][0])
        # (pose, (its occlusion-aware Score, the segments it sees)): kept for the advantage test below
        scored: list[tuple[np.ndarray, tuple[Score, np.ndarray]]] = [
            (refined[k].cam_from_world, seen[k]) for k in order[1:]
        ]
        scored += [
            (f.cam_from_world, view_score(view, image, camera, f.cam_from_world, config.score))
            for f in found
            # a pose's score never exceeds the image length it explains: one that cannot come near the best
            # is no rival, seen or hidden
            if f.score.explained_length >= (1.0 - dc.margin) * best.score.value
        ]
        scored = [(T, sc) for T, sc in scored if differs(T, best.cam_from_world, lines3d, dc)]
        # (pose, value, its (Score, seen) or None): the turned rival is scored below when it is needed
        rivals: list[tuple[np.ndarray, float, tuple[Score, np.ndarray] | None]] = [
            (T, sc[0].value, sc) for T, sc in scored
        ]
        turned = turned_rival(best.cam_from_world, image, seen[order[0]][1], camera, config)
        rivals.append((*turned, None))
        matches = best.score.matches(dc.min_cover)
        distinct = len(np.unique(matches[:, 1]))  # chance events are per map segment (significance.py)
        nfa = log10_nfa(best.cam_from_world, distinct, seen[order[0]][1], image, camera, config, space)
    rivals.sort(key=lambda p: -p[1])
    alternatives = _distinct(rivals, lambda rival: rival[0], lines3d, dc)[:8]

    def coverable() -> float:  # the image's line length the map could explain at the best pose
        T = best.cam_from_world
        footprint = None if view.footprint is None else view.footprint(camera, T, config.score.distance_px)
        return coverable_length(image, camera, T, seen[order[0]][1], footprint, config.score)

    runner_up = max((s for _, s, _ in alternatives), default=0.0)
    explained = best.score.explained_length / max(image.total_length, 1e-9)
    reason = ""
    if best.score.value <= 0:
        reason = f"{UNEXPLAINED} explains none of the image's lines"
    elif len(matches) < config.min_inliers:
        reason = f"{UNEXPLAINED} matches {len(matches)} image segments, fewer than {config.min_inliers}"
    elif short := explains_too_little(best.score.explained_length, image, coverable, dc):
        reason = f"{UNEXPLAINED} {short}"
    elif nfa >= dc.max_log10_nfa:
        reason = (
            f"not significant: the best pose matches {len(matches)} of {len(image.segments)} image segments "
            f"to {distinct} map segments, as 10^{nfa:.1f} chance poses among those searched would"
        )
    else:
        sharp: float | None = None  # the best's ``fine_value``, when a rival needs it
        depth = depth_of(lines3d[matches[:, 1]], best.cam_from_world)
        for T, value, known in alternatives:
            if value < (1.0 - dc.margin) * best.score.value:
                break  # (sorted: the rest are below it too)
            # where the best's lines lie closer than the score's distance, a rival is judged at that precision
            # (two scores: tested before the refinement below)
            if sharp is None:
                sharp = fine_value(view, image, camera, best.cam_from_world, config)
            refined_T = cache(partial(refined_pose, view, image, camera, T, config))  # once, if needed
            rival_sharp = partial(refined_fine_value, view, image, camera, T, refined_T, config)
            # its occlusion-aware (Score, seen): for the precision test if it needs it, else the advantage test
            their = cache(lambda T=T, known=known: known or view_score(view, image, camera, T, config.score))

            def evidence(their: Callable[[], tuple[Score, np.ndarray]] = their) -> bool:
                theirs = their()[0].matches(dc.min_cover)
                return precision_is_evidence(theirs, matches, view.accuracy_m, depth, camera, config)

            if sharp_dismisses(best.score.value, value, sharp, rival_sharp, evidence, dc):
                continue
            # a pose that the refinement takes back to the best is the best answer less well placed, not
            # another one (a turn and a shift that compensate along the lines' depth keep the score); a
            # turn of the whole projection is tested as a turn (the turn test's point is that it need not dip)
            if T is not turned[0] and in_basin(
                best.cam_from_world, T, image, view, camera, config, refined_T()
            ):
                continue
            # a rival within the margin: the best pose is still the answer if what it explains beyond the
            # rival is more than chance (the image segments the rival leaves unexplained), and what the
            # rival explains beyond the best is not: else each holds evidence the other lacks (on a
            # cluttered real map a wrong pose's chance matches pass the first test, the truth's the second)
            theirs, theirs_seen = their()
            over = advantage_nfa(
                best.cam_from_world, best.score, seen[order[0]][1], theirs, image, camera, config, space
            )
            back = advantage_nfa(T, theirs, theirs_seen, best.score, image, camera, config, space)
            if over >= dc.max_log10_nfa or back < dc.max_log10_nfa:
                turn = rotation_error_deg(T[:3, :3], best.cam_from_world[:3, :3])
                shift = float(np.linalg.norm(camera_center(T) - camera_center(best.cam_from_world)))
                beyond = (
                    f"what the best explains beyond it 10^{over:.1f} chance poses would"
                    if over >= dc.max_log10_nfa
                    else f"it explains lines the best does not (10^{back:.1f} chance poses would)"
                )
                reason = (
                    f"ambiguous: a distinct pose ({turn:.0f} deg, {shift:.1f} m away) scores "
                    f"{100 * value / best.score.value:.0f} % of the best, and {beyond}"
                )
                break
        if not reason:
            sharp = fine_value(view, image, camera, best.cam_from_world, config) if sharp is None else sharp
            reason = _sharper_elsewhere(
                best, sharp, matches, depth, alternatives, view, image, camera, config
            )
    covariance = with_map_floor(best.covariance, view.accuracy_m, seen[order[0]][1], best.cam_from_world)
    if not reason and slides is not None and (moved := slides[order[0]]) is not None:
        reason = f"ambiguous: the refinement slid the pose {moved[0]:.1f} deg / {moved[1]:.2f} m along a flat score"
    if not reason and dc.basin_turn_deg > 0:
        with timer("decide"):
            near = near_basins(best, seen[order[0]][1], image, view, camera, config, space)
        covariance = covariance + basin_spread(best.cam_from_world, near)
    if not reason:
        reason = undetermined(covariance, best.cam_from_world, lines3d, dc)
    return Registration(
        success=not reason,
        reason=reason,
        cam_from_world=best.cam_from_world,
        matches=matches,
        num_inliers=len(matches),
        covariance=covariance,
        rms_px=best.rms_px,
        score=float(best.score.value),
        explained_fraction=float(explained),
        log10_nfa=float(nfa),
        runner_up_score=float(max(runner_up, 0.0)),
        alternatives=np.array([T for T, _, _ in alternatives]).reshape(-1, 4, 4),
        alternative_scores=np.array([s for _, s, _ in alternatives], dtype=np.float64),
        timings=timer.finish(),
    )


def explains_too_little(
    explained_px: float, image: ImageLines, coverable: Callable[[], float], dc: DecideConfig
) -> str:
    """Returns why a pose explaining ``explained_px`` of the image's line length explains too little ("" if
    it does not): less than ``min_explained_fraction`` of the line length lying where the map could explain
    it at that pose (``coverable()``, ``score.coverable_length``; asked for only when the pose explains less
    than that share of the whole image). The floor is the map's to reach: a single LiDAR sweep covers the
    lower half of a street photo, and a pose explaining 15 % of the whole image would explain 20-30 % of
    what the sweep covers (the true poses of the shared sweeps: 50-70 % of the photos' line length
    coverable), a bar a fused room, covering nearly all of its photos, is not held to."""
    total = image.total_length
    floor = dc.min_explained_fraction
    if explained_px >= floor * total:
        return ""
    room = max(coverable(), explained_px)
    if explained_px >= floor * room:
        return ""

    def percent(part: float, whole: float) -> int:  # rounded down: 14.6 % is not shown as the floor's 15 %
        return int(np.floor(100.0 * part / max(whole, 1e-9) + 1e-9))

    share = f"{percent(explained_px, total)} % of the image's lines"
    if room < total:
        share += f", {percent(explained_px, room)} % of the {percent(room, total)} % the map covers"
    return f"explains {share} (< {100 * floor:.0f} %)"


def near_basins(
    answer: Refinement,
    seen: np.ndarray,
    image: ImageLines,
    view: MapView,
    camera: Camera,
    config: RegisterConfig,
    space: SearchSpace,
) -> list[np.ndarray]:
    """Returns the other basins of the score next to the ``answer`` (its pose refined, its occlusion-aware
    Score, seeing the (K, 6) map parts ``seen``): solved (``solve_locally``) from it turned by
    ``basin_turn_deg`` each way about each camera axis, refined twice as it was (once when the first
    round is back at the answer, ``same_pose``), kept when they are neither the answer nor distinct from
    it (``differs``) and a distinct pose there would be a rival too: they score
    within the margin, and neither the precision test (``sharp_dismisses``) nor the advantage test (what
    the answer explains beyond one significant, the reverse not: ``advantage_nfa``) sets them aside, as
    they set a distinct rival aside. Poses the decision calls one answer that the fit's curvature at it
    does not see: a rugged score along the valley where a turn and a shift compensate."""
    dc = config.decide
    best, value = answer.cam_from_world, answer.score.value
    turn = dc.basin_turn_deg
    search = replace(config.search, rotation_slack_deg=1.5 * turn)
    centre = camera_center(best)
    turns = [rotation_from_vector(np.radians(sign * turn) * axis) for axis in np.eye(3) for sign in (-1, 1)]
    starts = [make_cam_from_world(R @ best[:3, :3], -(R @ best[:3, :3]) @ centre) for R in turns]

    def basin(start: np.ndarray) -> np.ndarray | None:
        q = solve_locally(
            image, view.segments, camera, start, 0.0, search, config.score, view.visible, view.chunks
        )
        if q is None:
            return None
        once = refined_pose(view, image, camera, q[0], config)
        if same_pose(once, best):  # back in the answer's basin: a second round starts where the answer is
            return once
        return refined_pose(view, image, camera, once, config)

    found: list[np.ndarray] = []
    mine = answer.score.matches(dc.min_cover)
    depth = depth_of(view.segments[mine[:, 1]], best) if len(mine) else 1.0
    sharp = cache(lambda: fine_value(view, image, camera, best, config))
    for T in [T for T in map_threads(basin, starts, config.search.max_threads) if T is not None]:
        if same_pose(T, best) or any(same_pose(T, other) for other in found):
            continue
        if differs(T, best, view.segments, dc):
            continue
        theirs, theirs_seen = view_score(view, image, camera, T, config.score)
        if theirs.value < (1.0 - dc.margin) * value:
            continue

        def evidence(theirs: Score = theirs) -> bool:
            return precision_is_evidence(
                theirs.matches(dc.min_cover), mine, view.accuracy_m, depth, camera, config
            )

        fine = partial(fine_value, view, image, camera, T, config)
        if sharp_dismisses(value, theirs.value, sharp(), fine, evidence, dc):
            continue
        over = advantage_nfa(best, answer.score, seen, theirs, image, camera, config, space)
        back = advantage_nfa(T, theirs, theirs_seen, answer.score, image, camera, config, space)
        if not over < dc.max_log10_nfa <= back:
            found.append(T)
    return found


def same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Returns True if two refined poses are one basin reached twice (within 0.01 deg and 1 mm)."""
    close = float(np.linalg.norm(camera_center(a) - camera_center(b))) < 1e-3
    return close and rotation_error_deg(a[:3, :3], b[:3, :3]) < 0.01


def basin_spread(
    best: np.ndarray, others: Sequence[np.ndarray], odds: Sequence[float] | None = None
) -> np.ndarray:
    """Returns the (6, 6) second moment about ``best`` of it and ``others``, each other pose weighted by its
    ``odds`` against the best (None: all 1, as likely; gtsam's tangent of world_T_cam, rotation first, as
    the covariance): what the answer cannot tell apart adds to its uncertainty (the law of total
    covariance)."""
    if not others:
        return np.zeros((6, 6))
    w = np.ones(len(others)) if odds is None else np.asarray(odds, dtype=np.float64)
    here = gtsam.Pose3(invert(best))
    xi = np.array([gtsam.Pose3.Logmap(here.between(gtsam.Pose3(invert(T)))) for T in others])
    return np.asarray((xi * w[:, None]).T @ xi / (1.0 + w.sum()))


def undetermined(
    covariance: np.ndarray, cam_from_world: np.ndarray, lines3d: np.ndarray, dc: DecideConfig
) -> str:
    """Returns why a pose with this (6, 6) covariance (rotation rad, translation m) is not determined ("" if
    it is): its 3-sigma spread reaches a distinct pose (``differs``: ``distinct_angle_deg``, or
    ``distinct_fraction`` of the depth of the (M, 6) map seen from it). The data then hold distinct poses
    alike, found or not: a small wall patch seen square-on is pinned only up to an orbit round it, and
    the rivals along that valley may be dismissed as less precise or as the same basin."""
    rotation_deg = 3.0 * np.degrees(np.sqrt(max(np.linalg.eigvalsh(covariance[:3, :3]).max(), 0.0)))
    position_m = 3.0 * np.sqrt(max(np.linalg.eigvalsh(covariance[3:, 3:]).max(), 0.0))
    reach_m = dc.distinct_fraction * depth_of(lines3d, cam_from_world)
    if rotation_deg <= dc.distinct_angle_deg and position_m <= reach_m:
        return ""
    return (
        f"ambiguous: the pose is determined to {rotation_deg:.1f} deg / {position_m:.2f} m (3 sigma), as far "
        f"as distinct poses lie ({dc.distinct_angle_deg:.1f} deg / {reach_m:.2f} m)"
    )


def in_basin(
    best: np.ndarray,
    other: np.ndarray,
    image: ImageLines,
    view: MapView,
    camera: Camera,
    config: RegisterConfig,
    back: np.ndarray | None = None,
) -> bool:
    """Returns True if refining the pose ``other`` (``refined_pose``; ``back``: that refinement, when
    already made) ends where the pose ``best`` is, not distinct from it (``differs``): one answer, found
    twice."""
    back = refined_pose(view, image, camera, other, config) if back is None else back
    return not differs(back, best, view.segments, config.decide)


def refined_pose(
    view: MapView, image: ImageLines, camera: Camera, cam_from_world: np.ndarray, config: RegisterConfig
) -> np.ndarray:
    """Returns the (4, 4) pose a rival refines to (``refine_pose``, as the best was refined)."""
    return refine_pose(
        image, view.segments, camera, cam_from_world, config.refine, config.score, view.visible
    ).cam_from_world


def fine_value(
    view: MapView, image: ImageLines, camera: Camera, cam_from_world: np.ndarray, config: RegisterConfig
) -> float:
    """Returns a pose's occlusion-aware score at ``sharp_fraction`` of the score's distance (the image's
    candidate pairs, listed for the full distance, hold those of a smaller one)."""
    return view_score(view, image, camera, cam_from_world, fine_config(config))[0].value


def refined_fine_value(
    view: MapView,
    image: ImageLines,
    camera: Camera,
    cam_from_world: np.ndarray,
    back: Callable[[], np.ndarray],
    config: RegisterConfig,
) -> float:
    """Returns the better ``fine_value`` of a rival and of ``back()``, its refinement (``refined_pose``): a
    rival is judged at its own best fit. The copies and the search's poses come from a few Gauss-Newton
    steps on pairs taken at a loose tolerance; unrefined, a 180-degree twin scoring 126 % of the best lay a
    pixel off its lines and was dismissed as less precise (seed 2's synthetic walk, frame 280: the best,
    the twin of the truth, was claimed)."""
    return max(fine_value(view, image, camera, T, config) for T in (cam_from_world, back()))


def precise_config(config: RegisterConfig) -> RegisterConfig:
    """Returns the configuration whose refinement associates first at ``sharp_fraction`` of the score's
    distance (no finer than the refinement's ``min_outlier_px``), not at ``start_factor`` times it: from a
    pose in a valley's basin the wider association takes in the basin's pairs and stays there."""
    fine_px = config.decide.sharp_fraction * config.score.distance_px
    first = max(fine_px, config.refine.min_outlier_px) / config.score.distance_px
    return replace(config, refine=replace(config.refine, start_factor=first))


def fine_config(config: RegisterConfig) -> ScoreConfig:
    """Returns the score's configuration at ``sharp_fraction`` of its distance (the sharpness test's)."""
    return replace(config.score, distance_px=config.decide.sharp_fraction * config.score.distance_px)


def map_floor(accuracy_m: float, depth_m: float) -> np.ndarray:
    """Returns the (6, 6) covariance (rotation rad, translation m) a pose inherits from its map's own
    accuracy: a pose is known relative to the map's lines, which are ``accuracy_m`` off the world, all
    alike along a facade (one frame's residuals cannot show it): ``accuracy_m`` in each translation axis
    and ``accuracy_m / depth_m`` in each rotation axis (a shift of the lines seen at that depth). On the
    demo courtyard (4.5 cm spacing) it brings the median chi-square of right fixes' true errors from 43.6
    to 3.7 (6 degrees of freedom: 5.3 expected; docs/measurements.md)."""
    rotation = (accuracy_m / max(depth_m, 1e-9)) ** 2
    return np.diag([rotation] * 3 + [accuracy_m**2] * 3)


def with_map_floor(
    covariance: np.ndarray, accuracy_m: float, seen: np.ndarray, cam_from_world: np.ndarray
) -> np.ndarray:
    """Returns a pose's (6, 6) covariance plus ``map_floor`` of a map placing its lines to ``accuracy_m``,
    at the median depth of the (K, 6) world segments the pose sees (none: no rotation term)."""
    if accuracy_m <= 0:
        return covariance
    depth = depth_of(seen, cam_from_world) if len(seen) else np.inf
    return covariance + map_floor(accuracy_m, depth)


def log10_nfa(
    cam_from_world: np.ndarray,
    matched: int,
    seen: np.ndarray,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
    space: SearchSpace,
    among: np.ndarray | None = None,
) -> float:
    """Returns log10 of the number of false alarms of a pose whose matches use ``matched`` of the (K, 6) map
    segments it sees: how many of the poses in ``space`` would match as many by chance
    (``significance.py``); ``among``: (N,) bool, the image segments the matches were counted in (None:
    all)."""
    sc = config.score
    projected, _ = project_clipped(seen, camera, cam_from_world, sc.min_depth_m)
    p = chance_probabilities(image, projected, sc.distance_px, sc.angle_deg, config.decide.min_cover, among)
    tests = space.log10_tests(camera, depth_of(seen, cam_from_world), sc.distance_px)
    return tests + log10_tail(p, matched)


def advantage_nfa(
    pose: np.ndarray,
    score: Score,
    seen: np.ndarray,
    other: Score,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
    space: SearchSpace,
) -> float:
    """Returns log10 of the number of false alarms of what the (4, 4) ``pose`` (its ``score``, seeing the
    (K, 6) map segments ``seen``) explains beyond another pose (its Score ``other``): its matches among the
    image segments the other matches none of, counted per map segment and judged against chance among
    those image segments alone.

    Two poses explaining nearly the same share of the image (a window lattice shifted by a bay, a
    courtyard's 180-degree twin) differ only where one explains lines the other does not: the building's
    corner, a door. Below 0 (fewer than one chance pose among those searched would match those lines as
    well) the difference is evidence, whatever the ratio of the scores; a symmetric twin, whose own matches
    are the best's, leaves none (docs/measurements.md)."""
    min_cover = config.decide.min_cover
    theirs = other.matches(min_cover)[:, 0]
    mine = score.matches(min_cover)
    own = mine[~np.isin(mine[:, 0], theirs)]
    among = np.ones(len(image.segments), dtype=bool)
    among[theirs] = False
    return log10_nfa(pose, len(np.unique(own[:, 1])), seen, image, camera, config, space, among)


def view_score(
    view: MapView, image: ImageLines, camera: Camera, cam_from_world: np.ndarray, config: ScoreConfig
) -> tuple[Score, np.ndarray]:
    """Returns (the Score of a pose, its pairs naming rows of ``view.segments``; the (K, 6) map segments
    it sees) with occlusion by the map's surfaces where the view has them (``view.parts``), else with
    ``view.visible``."""
    if view.parts is None:
        seen = view.segments if view.visible is None else view.segments[view.visible]
        return score_pose(
            image, view.segments, camera, cam_from_world, config, view.visible, view.chunks
        ), seen
    parts, rows = view.parts(camera, cam_from_world)
    score = score_pose(image, parts, camera, cam_from_world, config)
    pairs = np.c_[score.pairs[:, 0], rows[score.pairs[:, 1]]] if len(score.pairs) else score.pairs
    return replace(score, pairs=pairs.astype(np.int64).reshape(-1, 2)), parts


def with_copies(
    refined: list[Refinement],
    found: list[Found],
    view: MapView,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
    rotations: Sequence[np.ndarray],
    regions: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[list[tuple[Score, np.ndarray]], list[Found]]:
    """Returns (the ``view_score`` of each refined pose, found) with the copies of the best refined pose
    (by that score) and its orbits among the found poses (``copy_rivals``): rivals only, never the answer
    (a copy taken as the best when it scored more claimed a demo photo's upside-down twin, the truth
    unsolved); copies under the ``rotations`` searched with camera centres in the ``regions`` searched
    (what a prior admits)."""
    seen = [view_score(view, image, camera, r.cam_from_world, config.score) for r in refined]
    k = int(np.argmax([v.value for v, _ in seen]))
    copies = copy_rivals(
        refined[k].cam_from_world, seen[k][0], view, image, camera, config, rotations, regions
    )
    return seen, found + [Found(T, score, -1) for T, score in copies]


def copy_rivals(
    cam_from_world: np.ndarray,
    score: Score,
    view: MapView,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
    rotations: Sequence[np.ndarray],
    regions: Sequence[tuple[np.ndarray, np.ndarray]],
) -> list[tuple[np.ndarray, Score]]:
    """Returns (pose, Score without occlusion) of the copies of what a pose (its occlusion-aware ``score``)
    matched elsewhere in the map under the (3, 3) ``rotations`` (``copies.py``) with camera centres inside
    one of the ``regions`` (boxes (low, high)), solved locally as the search solves its peaks: the rivals
    a symmetric or repeated map makes, found from the map; and the pose orbited by ``orbit_deg`` round the
    point it looks at, solved locally: the poses along the valley where a turn and a shift compensate.

    A window lattice makes many copies sharing nearly all the corners (each bay's shift), and the one that
    is the truth may share fewer (seed 2's synthetic walk, frame 280: the courtyard's 180-degree twin was
    claimed, the truth a copy sharing 93 % where five lattice shifts shared 96 %): every copy is scored
    where it stands, and the ``copies`` best by what the surfaces hide (the search's ``screen``) solved."""
    dc = config.decide
    matched = np.zeros(len(view.segments), dtype=bool)
    matched[score.matches(dc.min_cover)[:, 1]] = True
    starts = copy_starts(
        cam_from_world, matched, view.points, view.signatures, view.segments, camera, list(rotations),
        config.search.arm_angle_deg, dc, regions,
    )  # fmt: skip
    inside = [(T, size) for T, size, _ in starts if _in_regions(camera_center(T), regions)]

    def where_it_stands(start: tuple[np.ndarray, float]) -> Score:
        return score_pose(image, view.segments, camera, start[0], config.score, view.visible, view.chunks)

    scores = map_threads(where_it_stands, inside, config.search.max_threads)  # each copy's own
    standing = [(score, -1, T, size) for score, (T, size) in zip(scores, inside, strict=True)]
    seen = None if view.parts is None else lambda T: view_score(view, image, camera, T, config.score)[0]
    kept = screen(standing, replace(config.search, peaks=dc.copies), seen)
    orbits = _orbit_starts(cam_from_world, view.segments[matched], dc)
    starts_kept = [(T, size) for _, _, T, size in kept]
    starts_kept += [(T, size) for T, size, _ in orbits if _in_regions(camera_center(T), regions)]
    solved = solve_all(
        starts_kept, image, view.segments, camera, config.search, config.score, view.visible, view.chunks
    )
    return [s for s in solved if s is not None]


def orbit_rivals(
    cam_from_world: np.ndarray,
    matches: np.ndarray,
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    config: RegisterConfig,
    visible: np.ndarray | None = None,
) -> list[tuple[np.ndarray, Score]]:
    """Returns (pose, Score) of a pose orbited by each of ``orbit_deg`` round the point it looks at (the
    median depth of the (M, 6) map segments its (K, 2) ``matches`` (image row, map row) name), solved
    locally (``solve_locally``, ``visible``: (M,) bool or None): the poses along the valley where a turn and
    a shift compensate, as the decision's rivals (``copy_rivals``) hold them."""
    matched = lines3d[np.unique(matches[:, 1])]
    starts = [(T, size) for T, size, _ in _orbit_starts(cam_from_world, matched, config.decide)]
    solved = solve_all(starts, image, lines3d, camera, config.search, config.score, visible)
    return [s for s in solved if s is not None]


def precision_is_evidence(
    theirs: np.ndarray,
    mine: np.ndarray,
    accuracy_m: float,
    depth_m: float,
    camera: Camera,
    config: RegisterConfig,
) -> bool:
    """Returns True if a rival's fit at ``sharp_fraction`` of the score's distance can be compared with the
    best's (``sharp_dismisses``): most of the rival's (K, 2) matches (image segment, map segment) are the
    best's ``mine``, the same map lines placed otherwise (a turn, an orbit: the map's own errors are common
    to both fits); or the map places its lines (``accuracy_m``) closer than that distance resolves at the
    scene's ``depth_m``. A copy explaining the image with other lines of a map less accurate than that is
    only as precise as the map is there: on the demo scan's walk, a facade copy one lattice step from the
    truth held its lines closer than the truth did, and was claimed (seeds 1 and 3, 3.2-3.9 m off)."""
    fine_px = config.decide.sharp_fraction * config.score.distance_px
    if accuracy_m * max(camera.fx, camera.fy) < fine_px * depth_m:
        return True
    if not len(theirs):
        return False
    width = max(int(theirs[:, 1].max()), int(mine[:, 1].max(initial=0))) + 1
    shared = np.isin(theirs[:, 0] * width + theirs[:, 1], mine[:, 0] * width + mine[:, 1])
    return 2 * int(shared.sum()) > len(theirs)


def sharp_dismisses(
    best: float,
    rival: float,
    fine_best: float,
    fine_rival: Callable[[], float],
    evidence: Callable[[], bool],
    dc: DecideConfig,
) -> bool:
    """Returns True if a rival inside the margin is a less precise fit than the best: it scores less than
    the best (``rival`` < ``best``), at ``sharp_fraction`` of the score's distance the best (there
    ``fine_best``) keeps ``sharp_keep`` of its score, precision tells the two apart (``evidence()``:
    ``precision_is_evidence``) and the rival (there ``fine_rival()``) falls below ``(1 - margin)`` of it.
    The callables run only when the tests before them pass, cheapest first.

    A rival scoring at least the best at the score's own distance is never set aside so: the two scales then
    disagree on which pose is better, and that is an ambiguity, not a precision. (Where a simulated scan
    places edges a few cm off, a facade copy one lattice step from the truth held its lines closer than
    the truth did, and the truth, scoring 101 % of the copy, was dismissed: seed 3's synthetic walk.)"""
    if rival >= best or fine_best < dc.sharp_keep * best or not evidence():
        return False
    return fine_rival() < (1.0 - dc.margin) * fine_best


def sharper_rival(
    best: float,
    rival: float,
    fine_best: float,
    fine_rival: Callable[[], float],
    evidence: Callable[[], bool],
    dc: DecideConfig,
) -> bool:
    """Returns True if a distinct rival that scores below ``(1 - margin)`` of the best at the score's
    distance is a clearly more precise fit: at ``sharp_fraction`` of that distance (there the rival scores
    ``fine_rival()``, the best ``fine_best``) it keeps ``sharp_keep`` of its score (its lines lie that
    close: the map is accurate there) and the best falls below ``(1 - margin)`` of it, where precision
    tells the two apart (``evidence()``: ``precision_is_evidence``). The two scales then disagree on which
    pose is better: an ambiguity, as the mirror case is (``sharp_dismisses``). (On the synthetic walks a
    relocalization claimed a pose 5 deg / 0.53 m off that scored 120 % of one 0.22 m off at 4 px and 26 %
    of it at 1 px: the facade's lines lie within 1 px at the truth and within 4 at the claim.) A fine
    score never exceeds the score (the same penalty, less length explained), so a rival scoring no more
    than the best's fine score over ``(1 - margin)`` is not one; the callables run only past that test.
    A rival within the margin is judged there (``decide``, ``sharp_dismisses``), not here."""
    if rival >= (1.0 - dc.margin) * best or rival * (1.0 - dc.margin) <= fine_best:
        return False
    fine = fine_rival()
    return fine >= dc.sharp_keep * rival and fine_best < (1.0 - dc.margin) * fine and evidence()


def sharper_reason(
    rival: np.ndarray,
    best: np.ndarray,
    value: float,
    of: float,
    fine: float,
    fine_of: float,
    config: RegisterConfig,
) -> str:
    """Returns the words of an ambiguity found by ``sharper_rival``."""
    turn = rotation_error_deg(rival[:3, :3], best[:3, :3])
    shift = float(np.linalg.norm(camera_center(rival) - camera_center(best)))
    fine_px = config.decide.sharp_fraction * config.score.distance_px
    share = 100 * fine / fine_of if fine_of > 0 else float("inf")
    return (
        f"a distinct pose ({turn:.0f} deg, {shift:.2f} m away) scores {100 * value / of:.0f} % of the best, "
        f"but {share:.0f} % of it within {fine_px:g} px: its lines lie closer"
    )


def _sharper_elsewhere(
    best: Refinement,
    sharp: float,
    matches: np.ndarray,
    depth: float,
    alternatives: list[tuple[np.ndarray, float, tuple[Score, np.ndarray] | None]],
    view: MapView,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
) -> str:
    """Returns why the best (``sharp``: its ``fine_value``) is ambiguous for an alternative below the margin
    that fits its lines clearly closer (``sharper_rival``) than the best does even refined at the fine
    distance (a pose stopped in its basin's valley 0.35 deg off the truth of an exact facade kept 10 % of
    its score within 1 px, and a copy of the facade behind a wall seeing a fifth of the lines kept all of
    its), or ""."""
    dc = config.decide

    @cache
    def sharpest() -> float:  # judged at the best's own most precise fit: refined associating finely
        precise = precise_config(config).refine
        at = refine_pose(
            image, view.segments, camera, best.cam_from_world, precise, config.score, view.visible
        )
        return max(sharp, fine_value(view, image, camera, at.cam_from_world, config))

    for T, value, known in alternatives:
        # its occlusion-aware (Score, seen), for the precision test
        their = cache(lambda T=T, known=known: known or view_score(view, image, camera, T, config.score))
        fine = cache(partial(fine_value, view, image, camera, T, config))

        @cache
        def evidence(their: Callable[[], tuple[Score, np.ndarray]] = their) -> bool:
            theirs = their()[0].matches(dc.min_cover)
            return precision_is_evidence(theirs, matches, view.accuracy_m, depth, camera, config)

        if sharper_rival(best.score.value, value, sharp, fine, evidence, dc) and sharper_rival(
            best.score.value, value, sharpest(), fine, evidence, dc
        ):
            words = sharper_reason(
                T, best.cam_from_world, value, best.score.value, fine(), sharpest(), config
            )
            return f"ambiguous: {words}"
    return ""


def _sharpest_first(
    order: list[int],
    refined: list[Refinement],
    seen: list[tuple[Score, np.ndarray]],
    view: MapView,
    image: ImageLines,
    camera: Camera,
    config: RegisterConfig,
) -> list[int]:
    """Returns ``order`` (indices of ``refined``, best score first) led by the most precise of the refined
    poses that are the best's answer (not ``differs``) scoring within the margin of it: the one scoring
    most at ``sharp_fraction`` of the score's distance, if that is more than the best's there and keeps
    ``sharp_keep`` of its score (its lines lie that close: the map is accurate there). Along a facade's
    valley, where a turn and a shift compensate, the score's distance hardly tells the poses apart and the
    finer one does: on the synthetic walks a relocalization claimed a pose 1.8 deg / 0.30 m off that
    scored 100.4 % of a refined one 0.03 m off, and 37 % of it within 1 px."""
    dc = config.decide
    top = order[0]
    T0, v0 = refined[top].cam_from_world, seen[top][0].value
    same = [
        k
        for k in order[1:]
        if seen[k][0].value >= (1.0 - dc.margin) * v0
        and not differs(refined[k].cam_from_world, T0, view.segments, dc)
    ]
    if v0 <= 0 or not same:
        return order
    fine = {k: fine_value(view, image, camera, refined[k].cam_from_world, config) for k in [top, *same]}
    sharper = [k for k in same if fine[k] > fine[top] and fine[k] >= dc.sharp_keep * seen[k][0].value]
    if not sharper:
        return order
    lead = max(sharper, key=lambda k: fine[k])
    return [lead, *(k for k in order if k != lead)]


def _orbit_starts(
    cam_from_world: np.ndarray, matched: np.ndarray, dc: DecideConfig
) -> list[tuple[np.ndarray, float, float]]:
    """Returns (start cam_from_world, size_m, 0) of the pose orbited by each of ``orbit_deg`` up, down, left
    and right round the scene point at the median depth of the (K, 6) map segments it ``matched`` (1 m if
    none): a turn and a shift that compensate along the lines' depth, which the turned rival, turning about
    the camera centre, does not try."""
    depth_m = depth_of(matched, cam_from_world) if len(matched) else 1.0
    size = dc.distinct_fraction * depth_m
    turns = [
        np.radians(angle) * np.r_[axis, 0.0] for angle in dc.orbit_deg for axis in (*np.eye(2), *-np.eye(2))
    ]
    return [(orbited(cam_from_world, depth_m, rotation_from_vector(w)), size, 0.0) for w in turns]


def _in_regions(point: np.ndarray, regions: Sequence[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Returns True if a (3,) point lies in one of the boxes ((3,) low, (3,) high corner)."""
    return any(bool(np.all((lo <= point) & (point <= hi))) for lo, hi in regions)


def turned_rival(
    cam_from_world: np.ndarray,
    image: ImageLines,
    lines3d: np.ndarray,
    camera: Camera,
    config: RegisterConfig,
    visible: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Returns (pose, score) of the best-scoring turn of a pose by more than ``distinct_angle_deg``: the
    (M, 6) map ``lines3d`` (``visible`` (M,) bool or None) seen from ``cam_from_world`` turned about its
    centre.

    A small pan or tilt moves the projection across the image (a shift, exact at the principal point); the
    shifts tried run on a grid of ``distance_px * sqrt(2)`` (every line alignment falls within the score's
    distance of a grid point) out to ``turn_reach_fraction`` of the image diagonal. A true alignment drops
    off within a few pixels; a chance one, where the image's clutter would explain a displaced map about
    as well, does not -- the test holds whether or not the search found the true pose.
    """
    dc, sc = config.decide, config.score
    projected, _ = project_clipped(lines3d, camera, cam_from_world, sc.min_depth_m, visible)
    inner = np.tan(np.radians(dc.distinct_angle_deg)) * np.array([camera.fx, camera.fy])
    reach = max(dc.turn_reach_fraction * float(np.hypot(camera.width, camera.height)), 2.0 * inner.max())
    step = np.sqrt(2.0) * sc.distance_px
    grid = step * np.arange(-np.floor(reach / step), np.floor(reach / step) + 1)
    shifts = np.stack(np.meshgrid(grid, grid), axis=-1).reshape(-1, 2)
    shifts = shifts[np.hypot(*(shifts / inner).T) > 1.0]  # turned beyond the distinct angle
    values = shifted_values(image, projected, shifts, sc)
    k = int(np.argmax(values))
    return _turned(cam_from_world, shifts[k], camera), float(values[k])


def _turned(cam_from_world: np.ndarray, shift: np.ndarray, camera: Camera) -> np.ndarray:
    """Returns the pose turned about its centre so that the principal point's ray moves by (2,) pixels."""
    target = np.array([shift[0] / camera.fx, shift[1] / camera.fy, 1.0])
    axis = np.cross([0.0, 0.0, 1.0], target)  # length sin(angle) * |target|
    angle = float(np.arctan2(np.linalg.norm(axis), target[2]))
    turn = rotation_from_vector(axis / max(float(np.linalg.norm(axis)), 1e-300) * angle)
    out = cam_from_world.copy()
    out[:3, :3] = turn @ cam_from_world[:3, :3]
    out[:3, 3] = turn @ cam_from_world[:3, 3]
    return out


def _distinct(
    items: list[_Item], pose: Callable[[_Item], np.ndarray], lines3d: np.ndarray, dc: DecideConfig
) -> list[_Item]:
    """Returns the items (best first) whose ``pose(item)`` differs from that of every better one kept."""
    kept: list[_Item] = []
    for item in items:
        if all(differs(pose(item), pose(k), lines3d, dc) for k in kept):
            kept.append(item)
    return kept


def no_worse(
    start: np.ndarray,
    refined: Refinement,
    image: ImageLines,
    view: MapView,
    camera: Camera,
    config: RegisterConfig,
    before: Score | None = None,
) -> Refinement:
    """Returns the refinement of the (4, 4) pose ``start``, or ``start`` itself (with the refinement's
    covariance and rms) when the refinement lowers its score below ``(1 - margin)`` of the start's
    (``before``: its ``start_score``, None: scored here): the fit of matched fragments re-associates at a
    tolerance wider than the score's, and on real clutter wrong pairs can pull it off what the score found
    (18 of the 71 refinements of the shared real photos with a rough prior lost more than that). The score
    decides; a refinement that loses by the margin failed."""
    if before is None:
        before = start_score(start, image, view, camera, config)
    if before.value <= 0.0 or refined.score.value >= (1.0 - config.decide.margin) * before.value:
        return refined
    return replace(refined, cam_from_world=start, score=before)


def start_score(
    start: np.ndarray, image: ImageLines, view: MapView, camera: Camera, config: RegisterConfig
) -> Score:
    """Returns the Score of a (4, 4) pose to be refined, as ``refine_pose`` scores its result (the search's
    own score may be occlusion-aware): what ``no_worse`` and ``slid`` weigh the refinement against."""
    return score_pose(image, view.segments, camera, start, config.score, view.visible, view.chunks)


def slid(
    start: np.ndarray, refined: Refinement, before: Score, view: MapView, config: RegisterConfig
) -> tuple[float, float] | None:
    """Returns (degrees, metres) the refinement moved the (4, 4) pose ``start`` when it moved it to a
    distinct pose (``differs``) without raising its score (``before``: its ``start_score``) by ``margin``,
    else None. Such a move is a slide along a valley where a turn and a shift compensate: the image's lines
    do not fix the pose as far as distinct poses lie, whatever the fit's covariance says. On the rendered
    office subsampled to 10 % a search pose 1.7 deg / 0.16 m from the truth was refined to one 3.9 deg /
    0.31 m off (3 % lower, its 3-sigma 1.3 deg) and claimed. With slides refused it is not, the synthetic
    walks' trackers make no wrong claim (one before: walk 3 with a top speed, 0.31 m / 3 deg off), and no
    answer of the single-image benches changes (docs/measurements.md, session 52)."""
    if not differs(refined.cam_from_world, start, view.segments, config.decide):
        return None
    if before.value <= 0.0 or refined.score.value > (1.0 + config.decide.margin) * before.value:
        return None
    turn = rotation_error_deg(refined.cam_from_world[:3, :3], start[:3, :3])
    shift = float(np.linalg.norm(camera_center(refined.cam_from_world) - camera_center(start)))
    return turn, shift


def _found_pose(f: Found) -> np.ndarray:
    return f.cam_from_world


def differs(a: np.ndarray, b: np.ndarray, lines3d: np.ndarray, dc: DecideConfig) -> bool:
    """Returns True if two cam_from_world poses are distinct answers: rotations more than
    ``distinct_angle_deg`` apart, or camera centres farther apart than ``distinct_fraction`` of the median
    depth of the map seen from ``b``."""
    if rotation_error_deg(a[:3, :3], b[:3, :3]) > dc.distinct_angle_deg:
        return True
    scale = depth_of(lines3d, b)
    return float(np.linalg.norm(camera_center(a) - camera_center(b))) > dc.distinct_fraction * scale
