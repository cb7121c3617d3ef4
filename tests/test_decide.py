"""The decision (``pipeline.decide``): an answer must beat every distinct pose, including the best pose
turned by small angles (``turned_rival``), whose scores come from ``score.shifted_values``."""

from dataclasses import replace

import numpy as np
import pytest

import linereg
from linereg.camera import Camera
from linereg.config import RegisterConfig
from linereg.geometry import (
    camera_center,
    make_cam_from_world,
    orbited,
    rotation_error_deg,
    rotation_from_vector,
)
from linereg.localization import map_view
from linereg.pipeline import fine_value, in_basin, no_worse, slid, turned_rival, view_score
from linereg.refine import Refinement, refine_pose
from linereg.score import (
    image_lines,
    project_clipped,
    project_segments,
    score_pose,
    score_projected,
    shifted_values,
)
from linereg.significance import SearchSpace
from linereg.sim.synthetic import decoy_scene, look_at, paper_scene, project_visible


def test_shifted_values_are_the_scores_of_the_shifted_projections(rng):
    scene = paper_scene(rng, 100, 0.3, 0.3, 2.0)
    config = RegisterConfig().score
    image = image_lines(scene.lines2d, scene.camera, config)
    projected, rows = project_clipped(scene.lines3d, scene.camera, scene.cam_from_world, config.min_depth_m)
    shifts = rng.uniform(-60.0, 60.0, (12, 2))
    shifts[0] = 0.0
    values = shifted_values(image, projected, shifts, config)
    for shift, value in zip(shifts, values, strict=True):
        expected = score_projected(image, projected + np.tile(shift, 2), rows, config).value
        assert abs(value - expected) < 1e-6 * max(abs(expected), 1.0)
    truth = score_pose(image, scene.lines3d, scene.camera, scene.cam_from_world, config).value
    assert abs(values[0] - truth) < 1e-6 * truth


def wall_grid(spacing_m: float, size_m: float = 8.0) -> np.ndarray:
    """Returns (M, 6) the lines of a square grid on the wall y = 10 (x, z in [-size/2, size/2])."""
    ticks = np.arange(-size_m / 2, size_m / 2 + 1e-9, spacing_m)
    half = size_m / 2
    vertical = [[x, 10.0, -half, x, 10.0, half] for x in ticks]
    horizontal = [[-half, 10.0, z, half, 10.0, z] for z in ticks]
    return np.array(vertical + horizontal, dtype=np.float64)


def test_a_periodic_wall_has_a_turned_rival_as_good_as_the_truth(camera):
    """Seen square on, a grid of lines 0.25 m apart repeats every 20 px: the pose turned by one period
    explains the image as well as the truth, so no pose of it is an answer."""
    lines3d = wall_grid(0.25)
    truth = look_at(np.array([0.3, 0.0, 0.1]), np.array([0.3, 10.0, 0.1]))
    lines2d, _ = project_clipped(lines3d, camera, truth, 0.05)
    config = RegisterConfig()
    image = image_lines(lines2d, camera, config.score)
    score = score_pose(image, lines3d, camera, truth, config.score).value
    pose, rival = turned_rival(truth, image, lines3d, camera, config)
    assert rival >= 0.85 * score
    assert rotation_error_deg(pose[:3, :3], truth[:3, :3]) > config.decide.distinct_angle_deg


def test_a_true_alignment_drops_off_when_turned(rng):
    scene = paper_scene(rng, 100, 0.3, 0.3, 2.0)
    config = RegisterConfig()
    image = image_lines(scene.lines2d, scene.camera, config.score)
    score = score_pose(image, scene.lines3d, scene.camera, scene.cam_from_world, config.score).value
    pose, rival = turned_rival(scene.cam_from_world, image, scene.lines3d, scene.camera, config)
    assert rival < (1.0 - config.decide.margin) * score  # the truth stays an answer
    turn = rotation_error_deg(pose[:3, :3], scene.cam_from_world[:3, :3])
    reach = np.degrees(np.arctan(config.decide.turn_reach_fraction * np.hypot(640, 480) / 800.0))
    assert config.decide.distinct_angle_deg < turn <= reach * np.sqrt(2) + 1e-6


def test_a_periodic_wall_is_never_a_success(camera):
    lines3d = wall_grid(0.25)
    truth = look_at(np.array([0.3, 0.0, 0.1]), np.array([0.3, 10.0, 0.1]))
    lines2d, _ = project_clipped(lines3d, camera, truth, 0.05)
    reg = linereg.register(lines2d, lines3d, camera)
    assert not reg.success and reg.reason


def facade_copies() -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Returns ((M, 6) segments, (vertices, triangles) surfaces): one facade pattern (lines of an uneven
    grid, window corners, ground lines leading to it) on a wall at x = 20 and the same pattern 20 m
    along it; a solid wall at x = 10 stands in front of the copy only, and the facade wall is 1 m thick."""
    rng = np.random.default_rng(0)
    ys = np.cumsum(rng.uniform(0.6, 1.6, 8)) - 5
    zs = np.cumsum(rng.uniform(0.4, 1.0, 5))
    segs = [[20, y, zs[0], 20, y, zs[-1]] for y in ys] + [[20, ys[0], z, 20, ys[-1], z] for z in zs]
    for k in range(6):
        y, z = ys[k] + 0.15, zs[k % 4] + 0.1
        segs += [[20, y, z, 20, y + 0.3, z], [20, y, z, 20, y, z + 0.2]]
    segs += [[8, y, 0, 20, y, 0] for y in ys[::2]] + [[x, ys[0], 0, x, ys[-1], 0] for x in (9.0, 12.5, 17.0)]
    pattern = np.array(segs, float)
    copy = pattern + np.array([0, 20.0, 0, 0, 20.0, 0])
    quads = [
        [(10, 10, -1), (10, 30, -1), (10, 30, 6), (10, 10, 6)],
        [(21, -10, -1), (21, 30, -1), (21, 30, 6), (21, -10, 6)],
    ]
    vertices = np.concatenate([np.asarray(q, float) for q in quads])
    triangles = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(len(quads))])
    return np.r_[pattern, copy], (vertices, triangles)


def test_the_decision_sees_what_the_surfaces_hide():
    """Two copies of a facade explain a photo equally well, but one is behind a wall from where it would
    have to be seen: with the map's surfaces the decision scores what each pose sees, and answers; without
    them the copies are a tie and the answer is ambiguous."""
    segments, surfaces = facade_copies()
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    lines2d, _ = project_clipped(segments, camera, truth, 0.05, None)
    seen = linereg.localize_segments(
        lines2d, linereg.LineMap.from_segments(segments, surfaces=surfaces), camera
    )
    assert seen.success, seen.reason
    assert rotation_error_deg(seen.cam_from_world[:3, :3], truth[:3, :3]) < 1.0
    centre = -seen.cam_from_world[:3, :3].T @ seen.cam_from_world[:3, 3]
    assert np.linalg.norm(centre - np.array([2.0, 0.0, 1.5])) < 0.3
    assert seen.matches[:, 1].max() < len(segments)  # matches name the map's segments, not visible pieces
    bare = linereg.localize_segments(lines2d, linereg.LineMap.from_segments(segments), camera)
    assert not bare.success and "ambiguous" in bare.reason


def door_facade(door_lines: int) -> np.ndarray:
    """Returns (M, 6) segments: an uneven grid on the wall x = 20, the same grid 20 m along it, and
    ``door_lines`` short slanted segments (a door's panels) on the first copy only."""
    rng = np.random.default_rng(0)
    ys = np.cumsum(rng.uniform(0.6, 1.6, 8)) - 5
    zs = np.cumsum(rng.uniform(0.4, 1.0, 5))
    grid = [[20, y, zs[0], 20, y, zs[-1]] for y in ys] + [[20, ys[0], z, 20, ys[-1], z] for z in zs]
    pattern = np.array(grid, float)
    door = []
    for _ in range(door_lines):
        angle = rng.uniform(0, 2 * np.pi)
        centre = np.array([20, 0.5 * (ys[3] + ys[4]) + rng.uniform(-0.6, 0.6), rng.uniform(zs[0], zs[-1])])
        half = np.array([0, np.cos(angle), np.sin(angle)]) * rng.uniform(0.2, 0.5)
        door.append(np.r_[centre - half, centre + half])
    return np.r_[pattern, pattern + np.array([0, 20.0, 0, 0, 20.0, 0]), np.reshape(door, (-1, 6))]


def test_a_rival_within_the_margin_loses_to_lines_it_cannot_explain():
    """The copy of a facade explains all of a photo of the original but its door: 92 % of the best score,
    inside the margin. The door's 8 segments, matched where the copy explains nothing, are more than chance
    would give any pose searched (``advantage_nfa``): an answer. With 4 they are not, and the grid alone is
    a tie: both ambiguous."""
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    for door_lines, answers in ((8, True), (4, False), (0, False)):
        segments = door_facade(door_lines)
        lines2d, _ = project_clipped(segments, camera, truth, 0.05, None)
        reg = linereg.localize_segments(lines2d, linereg.LineMap.from_segments(segments), camera)
        assert reg.success == answers, (door_lines, reg.reason)
        if answers:
            assert reg.runner_up_score >= (1.0 - RegisterConfig().decide.margin) * reg.score
            assert rotation_error_deg(reg.cam_from_world[:3, :3], truth[:3, :3]) < 0.5
            centre = -reg.cam_from_world[:3, :3].T @ reg.cam_from_world[:3, 3]
            assert np.linalg.norm(centre - np.array([2.0, 0.0, 1.5])) < 0.1
        else:
            assert reg.reason.startswith("ambiguous"), reg.reason


def test_two_poses_each_explaining_lines_the_other_cannot_are_ambiguous():
    """The facade and its copy each have a door of their own; the photo shows the original's grid and door
    and, where the copy's door would be seen from the copy, that door's lines too. Each pose explains the
    grid and one door: what either explains beyond the other is more than chance, so neither is the
    answer (``advantage_nfa`` both ways)."""
    panels = 12
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    shift = np.array([0, 20.0, 0, 0, 20.0, 0])
    segments = door_facade(panels)
    # the copy's door: the panels upside down and 0.4 m along (other slopes, other places)
    other_door = segments[-panels:].copy()
    middle = 0.5 * (segments[:-panels, [2, 5]].min() + segments[:-panels, [2, 5]].max())
    other_door[:, [2, 5]] = 2 * middle - other_door[:, [2, 5]]
    other_door[:, [1, 4]] += 0.4
    segments = np.r_[segments, other_door + shift]
    lines2d = np.r_[
        project_clipped(segments[:-panels], camera, truth, 0.05, None)[0],
        project_clipped(other_door, camera, truth, 0.05, None)[0],  # the copy's door, seen from the copy
    ]
    reg = linereg.localize_segments(lines2d, linereg.LineMap.from_segments(segments), camera)
    assert not reg.success
    assert reg.reason.startswith("ambiguous") and "explains lines the best does not" in reg.reason, reg.reason


def test_a_pose_the_refinement_takes_back_is_no_rival_and_a_copy_is():
    """Turned by 2.5 degrees about the middle of the wall it faces, 20 m ahead (so shifted by 0.9 m), the
    camera sees the wall's grid nearly where it was, and refining from there ends at the truth: the same
    answer (``in_basin``). The same camera looking at the facade's copy 20 m along it scores as well and
    refines to itself: another answer."""
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    segments = door_facade(0)
    lines2d, _ = project_clipped(segments, camera, truth, 0.05, None)
    config = RegisterConfig()
    view = map_view(linereg.LineMap.from_segments(segments), None, config)
    image = image_lines(lines2d, camera, config.score)
    pivot = np.array([20.0, 0.0, 1.5])
    turn = rotation_from_vector(np.radians([0.0, 0.0, 2.5]))  # about the vertical, through the pivot
    centre = pivot + turn @ (camera_center(truth) - pivot)
    R = truth[:3, :3] @ turn.T
    orbit = make_cam_from_world(R, -R @ centre)
    copy = truth.copy()
    copy[:3, 3] -= truth[:3, :3] @ np.array([0.0, 20.0, 0.0])  # the camera 20 m along y
    for other, expected in ((orbit, True), (copy, False)):
        value = score_pose(image, segments, camera, other, config.score).value
        assert value > 0.5 * score_pose(image, segments, camera, truth, config.score).value
        assert in_basin(truth, other, image, view, camera, config) == expected


def test_a_rival_as_good_at_the_scores_distance_falls_behind_where_the_best_is_sharp():
    """The camera 28 m from the window wall with a frame 8 m before it, orbited by 1 degree round the wall's
    middle (shifted 0.5 m): the frame's lines move by their parallax, ~2 px, within the score's 4 px, so
    it scores within the margin, but not within 1 px, where the true pose, whose lines are exact, keeps
    its score: the rule ``decide`` tells them apart by."""
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([-8.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    frame = [[12.0, y, 0.0, 12.0, y, 3.0] for y in (-3.0, -1.5, 1.5, 3.0)] + [
        [12.0, -3.0, 3.0, 12.0, 3.0, 3.0]
    ]
    segments = np.vstack([door_facade(0), frame])
    lines2d, _ = project_clipped(segments, camera, truth, 0.05, None)
    config = RegisterConfig()
    dc = config.decide
    view = map_view(linereg.LineMap.from_segments(segments), None, config)
    image = image_lines(lines2d, camera, config.score)
    pivot = np.array([20.0, 0.0, 1.5])
    turn = rotation_from_vector(np.radians([0.0, 0.0, 1.0]))
    centre = pivot + turn @ (camera_center(truth) - pivot)
    R = truth[:3, :3] @ turn.T
    orbit = make_cam_from_world(R, -R @ centre)
    best = view_score(view, image, camera, truth, config.score)[0].value
    rival = view_score(view, image, camera, orbit, config.score)[0].value
    assert rival >= (1.0 - dc.margin) * best
    sharp = fine_value(view, image, camera, truth, config)
    assert sharp >= dc.sharp_keep * best
    assert fine_value(view, image, camera, orbit, config) < (1.0 - dc.margin) * sharp


def test_a_pose_its_data_pin_only_to_an_orbit_is_not_an_answer():
    """A small patch of wall (12 lines, 1 m wide, seen square-on from 6 m) pins the camera only up to an
    orbit round it: with 1 px of noise the refinement, even from the true pose, ends 9 deg / 0.96 m off,
    and the orbits the decision tries along that valley are dismissed as the same basin or as less sharp.
    Its covariance says so: 3 sigma reaches distinct poses, so it is refused (``pipeline.undetermined``);
    exact lines, or a patch six times wider, pin the pose and are answered."""
    camera = linereg.Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)
    truth = look_at(np.zeros(3), np.array([0.0, 6.0, 0.0]))
    for half_m, noise_px, answered in ((0.5, 1.0, False), (0.5, 0.0, True), (3.0, 1.0, True)):
        rng = np.random.default_rng(1)
        a = rng.uniform(-half_m, half_m, (12, 2))
        b = a + rng.uniform(-0.6, 0.6, (12, 2)) * half_m
        lines3d = np.c_[a[:, 0], np.full(12, 6.0), a[:, 1], b[:, 0], np.full(12, 6.0), b[:, 1]]
        lines2d = project_visible(lines3d, camera, truth)[0]
        lines2d = lines2d + np.random.default_rng(0).normal(0.0, noise_px, lines2d.shape)
        prior = linereg.Prior(cam_from_world=truth, sigma_rot_deg=5.0, radius_m=1.0)
        result = linereg.localize_segments(
            lines2d, linereg.LineMap.from_segments(lines3d), camera, prior=prior
        )
        assert result.success == answered, result.reason
        if answered:
            assert rotation_error_deg(result.cam_from_world[:3, :3], truth[:3, :3]) < 1.0
        else:
            assert result.reason.startswith("ambiguous: the pose is determined to")


def test_a_rival_scoring_at_least_the_best_is_never_set_aside_as_less_precise():
    """The sharpness rule breaks ties below the best: a rival scoring less, where the best keeps its score at
    the finer distance and the rival does not, is a less precise fit; a rival scoring as much or more is an
    ambiguity whatever the finer distance says (the two scales disagree on which pose is better)."""
    dc = RegisterConfig().decide
    asked: list[bool] = []

    def fine_rival() -> float:
        asked.append(True)
        return 100.0

    assert linereg.pipeline.sharp_dismisses(1000.0, 900.0, 800.0, fine_rival, lambda: True, dc)
    assert not linereg.pipeline.sharp_dismisses(1000.0, 1000.0, 800.0, fine_rival, lambda: True, dc)
    assert not linereg.pipeline.sharp_dismisses(1000.0, 1200.0, 800.0, fine_rival, lambda: True, dc)
    assert len(asked) == 1  # the rival's finer score is computed only when it can decide
    # the best not sharp (it keeps less than sharp_keep of its score), or the rival as sharp: no dismissal
    assert not linereg.pipeline.sharp_dismisses(1000.0, 900.0, 400.0, fine_rival, lambda: True, dc)
    assert not linereg.pipeline.sharp_dismisses(1000.0, 900.0, 800.0, lambda: 790.0, lambda: True, dc)


def test_a_rival_below_the_margin_whose_lines_lie_clearly_closer_makes_the_best_ambiguous():
    """The mirror of the sharpness rule: a distinct rival scoring below the margin at the score's distance
    but keeping ``sharp_keep`` of its score at the finer one, where the best falls below the margin of it,
    is an ambiguity (the two scales disagree); not when it is within the margin (judged there), blurry
    itself, not clearly sharper, or not comparable (no evidence). Its finer score is asked for only when it
    can be sharper: a fine score never exceeds the score."""
    dc = RegisterConfig().decide
    asked: list[bool] = []

    def fine_rival(value: float):
        def fine() -> float:
            asked.append(True)
            return value

        return fine

    sharper = linereg.pipeline.sharper_rival
    assert sharper(1000.0, 800.0, 300.0, fine_rival(700.0), lambda: True, dc)
    assert not sharper(1000.0, 800.0, 300.0, fine_rival(700.0), lambda: False, dc)  # not comparable
    assert not sharper(1000.0, 900.0, 300.0, fine_rival(700.0), lambda: True, dc)  # within the margin
    assert not sharper(1000.0, 800.0, 300.0, fine_rival(350.0), lambda: True, dc)  # not clearly sharper
    assert not sharper(1000.0, 800.0, 300.0, fine_rival(390.0), lambda: True, dc)  # keeps < sharp_keep
    asked.clear()
    assert not sharper(1000.0, 300.0, 300.0, fine_rival(300.0), lambda: True, dc)  # cannot be sharper
    assert not asked


def test_the_decision_leads_with_the_most_precise_pose_of_its_answer():
    """Half the image's lines have a longer second edge 3 px beside them (a frame's other side): the
    refinement from the truth settles between them, a pose scoring as much as the truth at the score's
    distance. Both are the same answer, and among the contenders the decision leads with the truth, whose
    lines lie within the finer distance (``_sharpest_first``), whichever the score put first."""
    from linereg.pipeline import _sharpest_first

    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    lines3d, truth, lines2d = decoy_scene(camera)
    config = RegisterConfig()
    image = image_lines(lines2d, camera, config.score)
    view = map_view(linereg.LineMap.from_segments(lines3d), None, config)
    pulled = refine_pose(image, lines3d, camera, truth, config.refine, config.score)
    assert rotation_error_deg(pulled.cam_from_world[:3, :3], truth[:3, :3]) > 0.1
    refined = [pulled, replace(pulled, cam_from_world=truth)]
    seen = [view_score(view, image, camera, r.cam_from_world, config.score) for r in refined]
    # the score's distance hardly tells them apart: whichever it puts first, the truth leads
    assert abs(seen[0][0].value - seen[1][0].value) < 0.01 * seen[1][0].value
    assert _sharpest_first([0, 1], refined, seen, view, image, camera, config) == [1, 0]
    assert _sharpest_first([1, 0], refined, seen, view, image, camera, config) == [1, 0]


def test_precision_compares_fits_of_the_same_map_lines_or_of_an_accurate_map(camera):
    """A grid wall 10 m away (lines 1 m apart; each 8 m long, so a shifted view sees the same lines): the
    truth orbited by half a degree explains each image line with the same map line, a fit of the same
    lines; the truth shifted by one grid step explains them with the next map lines, a copy. With a map
    placing its lines to 5 cm (4 px at 10 m, beyond the finer distance's 1 px) the copy's precision is the
    map's there and no evidence; with an exact map it is."""
    lines3d = wall_grid(1.0)
    truth = look_at(np.array([0.3, 0.0, 0.1]), np.array([0.3, 10.0, 0.1]))
    lines2d, _ = project_clipped(lines3d, camera, truth, 0.05)
    config = RegisterConfig()
    image = image_lines(lines2d, camera, config.score)
    mine = score_pose(image, lines3d, camera, truth, config.score).matches(config.decide.min_cover)
    orbit = orbited(truth, 10.0, rotation_from_vector(np.radians([0.0, 0.5, 0.0])))
    shifted = look_at(np.array([1.3, 0.0, 0.1]), np.array([1.3, 10.0, 0.1]))
    copy = score_pose(image, lines3d, camera, shifted, config.score)
    assert (
        copy.value
        >= (1.0 - config.decide.margin) * score_pose(image, lines3d, camera, truth, config.score).value
    )

    def evidence(pose: np.ndarray, accuracy_m: float) -> bool:
        theirs = score_pose(image, lines3d, camera, pose, config.score).matches(config.decide.min_cover)
        return linereg.pipeline.precision_is_evidence(theirs, mine, accuracy_m, 10.0, camera, config)

    assert evidence(orbit, 0.05) and evidence(orbit, 0.0)
    assert not evidence(shifted, 0.05)
    assert evidence(shifted, 0.0) and evidence(shifted, 0.01)  # 0.8 px at 10 m: resolved


def test_the_explained_floor_counts_the_image_lines_the_map_covers():
    """A pose must explain ``min_explained_fraction`` of the image's line length lying where the map could
    explain it: a sweep covering half of a photo is not held to 15 % of the whole; what it covers is asked
    for only below that."""
    import pytest

    from linereg.config import DecideConfig
    from linereg.pipeline import explains_too_little

    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    image = image_lines(np.array([[0.0, 10, 600, 10], [0, 200, 400, 200]]), camera, RegisterConfig().score)
    total, dc = image.total_length, DecideConfig()

    def never() -> float:
        pytest.fail("the map's cover was asked for")

    assert explains_too_little(0.2 * total, image, never, dc) == ""
    assert explains_too_little(0.1 * total, image, lambda: 0.5 * total, dc) == ""  # 20 % of what it covers
    assert explains_too_little(0.1 * total, image, lambda: total, dc)  # a map covering all: 10 %
    reason = explains_too_little(0.05 * total, image, lambda: 0.5 * total, dc)
    assert reason == "explains 5 % of the image's lines, 10 % of the 50 % the map covers (< 15 %)"


def test_a_photo_whose_upper_half_the_map_does_not_hold_is_judged_on_what_the_map_covers():
    """A facade photo whose sky is full of lines (wires, branches) that no map line could explain: the best
    pose explains under 15 % of the whole image's line length but far more of what the map's surfaces
    cover, and is the answer; a map of the same segments without surfaces says nothing of what it
    covers, and the same pose explains too little."""
    segments, surfaces = facade_copies()
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    lines2d, _ = project_clipped(segments, camera, truth, 0.05, None)
    rng = np.random.default_rng(3)
    centres = rng.uniform([40.0, 35.0], [600.0, 75.0], (400, 2))  # above every surface's outline
    angles = rng.uniform(0.0, np.pi, 400)
    half = 30.0 * np.c_[np.cos(angles), np.sin(angles)]
    sky = np.c_[centres - half, centres + half]
    photo = np.r_[lines2d, sky]
    lengths = np.linalg.norm(photo[:, 2:] - photo[:, :2], axis=1)
    assert lengths[: len(lines2d)].sum() < 0.15 * lengths.sum()
    # the calibration case: a rough guess of the pose (about 2 deg and 0.3 m off)
    guess = truth @ make_cam_from_world(rotation_from_vector(np.radians([1.2, -1.0, 1.2])), [0.2, -0.1, 0.2])
    prior = linereg.Prior(cam_from_world=guess, sigma_rot_deg=3.0, radius_m=0.5)
    mapped = linereg.LineMap.from_segments(segments, surfaces=surfaces)
    seen = linereg.localize_segments(photo, mapped, camera, prior=prior)
    assert seen.success, seen.reason
    assert seen.explained_fraction < 0.15
    assert rotation_error_deg(seen.cam_from_world[:3, :3], truth[:3, :3]) < 1.0
    assert np.linalg.norm(camera_center(seen.cam_from_world) - camera_center(truth)) < 0.3
    bare = linereg.localize_segments(photo, linereg.LineMap.from_segments(segments), camera, prior=prior)
    assert not bare.success and "of the image's lines (< 15 %)" in bare.reason


def test_a_refinement_that_loses_the_score_keeps_the_pose_the_score_found(rng):
    """A refinement is kept when it scores within the margin of its start (here it improves a start 0.3 deg
    off); one that loses more (a fit pulled by wrong pairs, here a pose 3 deg off put in its place) gives
    way to the start, with the refinement's covariance."""
    scene = paper_scene(rng, 100, 0.3, 0.3, 2.0)
    config = RegisterConfig()
    view = map_view(linereg.LineMap.from_segments(scene.lines3d), None, config)
    image = image_lines(scene.lines2d, scene.camera, config.score)
    start = scene.cam_from_world.copy()
    start[:3, :3] = rotation_from_vector(np.radians([0.3, 0.0, 0.0])) @ start[:3, :3]
    refined = refine_pose(image, scene.lines3d, scene.camera, start, config.refine, config.score)
    kept = no_worse(start, refined, image, view, scene.camera, config)
    assert kept is refined
    pulled = scene.cam_from_world.copy()
    pulled[:3, :3] = rotation_from_vector(np.radians([0.0, 3.0, 0.0])) @ pulled[:3, :3]
    lost = type(refined)(pulled, score_pose(image, scene.lines3d, scene.camera, pulled, config.score),
                         refined.covariance, refined.rms_px, refined.rounds)  # fmt: skip
    assert lost.score.value < (1.0 - config.decide.margin) * refined.score.value
    back = no_worse(start, lost, image, view, scene.camera, config)
    assert np.array_equal(back.cam_from_world, start) and back.covariance is refined.covariance
    assert back.score.value == score_pose(image, scene.lines3d, scene.camera, start, config.score).value
    away = scene.cam_from_world.copy()  # a start explaining nothing has nothing to lose
    away[2, 3] -= 1e4  # every map line behind the camera
    assert score_pose(image, scene.lines3d, scene.camera, away, config.score).value <= 0
    assert no_worse(away, lost, image, view, scene.camera, config) is lost


def test_a_refinement_that_slides_along_a_valley_is_no_answer():
    """``slid``: a facade seen head-on 20 m away keeps its projection within a few pixels when the camera
    turns 2.5 deg and moves the 0.87 m that compensates, so a refinement making that move hardly changes the
    score: it slid along a valley, a distinct pose the lines do not tell from the start. A small move, or a
    move that gains more than the margin (a start 2 m off brought home), is no slide."""
    rows, cols = np.meshgrid(np.arange(-6.0, 7.0, 1.5), np.arange(-9.0, 10.0, 1.5), indexing="ij")
    z = 20.0
    horizontal = np.c_[cols.ravel() - 0.6, rows.ravel(), np.full(rows.size, z),
                       cols.ravel() + 0.6, rows.ravel(), np.full(rows.size, z)]  # fmt: skip
    vertical = np.c_[cols.ravel(), rows.ravel() - 0.6, np.full(rows.size, z),
                     cols.ravel(), rows.ravel() + 0.6, np.full(rows.size, z)]  # fmt: skip
    lines3d = np.r_[horizontal, vertical]
    camera = Camera(fx=500, fy=500, cx=320, cy=240, width=640, height=480)
    truth = np.eye(4)  # at the origin, looking along +z
    config = RegisterConfig()
    lines2d, _ = project_segments(lines3d, camera, truth, config.score.min_depth_m)
    image = image_lines(lines2d, camera, config.score)
    view = map_view(linereg.LineMap.from_segments(lines3d), None, config)

    def refinement(T: np.ndarray) -> Refinement:
        return Refinement(T, score_pose(image, lines3d, camera, T, config.score), np.eye(6), 0.5, 1)

    turn = np.radians(2.5)
    centre = np.array([z * np.tan(turn), 0.0, 0.0])  # looks at the same facade point
    R = rotation_from_vector([0.0, turn, 0.0])  # its axis R^T z turned towards -x
    valley = make_cam_from_world(R, -R @ centre)
    assert (
        score_pose(image, lines3d, camera, valley, config.score).value > 0.85 * refinement(truth).score.value
    )
    at_truth = refinement(truth).score
    moved = slid(truth, refinement(valley), at_truth, view, config)
    assert moved is not None
    assert moved[0] == pytest.approx(2.5, abs=1e-6) and moved[1] == pytest.approx(centre[0], abs=1e-6)
    near = make_cam_from_world(rotation_from_vector([0.0, -np.radians(0.5), 0.0]), np.zeros(3))
    assert slid(truth, refinement(near), at_truth, view, config) is None  # not a distinct pose
    away = make_cam_from_world(np.eye(3), [-2.0, 0.0, 0.0])  # a start 2 m off, refined home
    assert slid(away, refinement(truth), refinement(away).score, view, config) is None


def test_a_basin_next_to_the_answer_that_scores_as_well_widens_its_covariance():
    """A map holding every line twice, the copy turned 1.5 deg about the camera's vertical (a ghost: seen
    from the true centre turned by 1.5 deg, it projects where the lines do). The two poses are one answer to
    the decision (not 2 deg apart) and the fit at either is sharp, so without more the answer is claimed
    to a fraction of a degree. Solved from the answer turned by 1 deg each way (``near_basins``), the
    ghost's basin is found; it scores as well and holds the same evidence, so its spread enters the
    covariance and the answer is refused as undetermined. Without the ghost nothing is added."""
    from linereg.config import DecideConfig
    from linereg.pipeline import near_basins

    camera = linereg.Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)
    truth = look_at(np.zeros(3), np.array([0.0, 10.0, 0.0]))
    rng = np.random.default_rng(2)
    a = rng.uniform(-4.0, 4.0, (40, 2))
    b = a + rng.uniform(-1.5, 1.5, (40, 2))
    depth = rng.uniform(9.0, 14.0, (40, 1))
    lines3d = np.c_[a[:, :1], depth, a[:, 1:], b[:, :1], depth + rng.uniform(-1, 1, (40, 1)), b[:, 1:]]
    lines2d = project_visible(lines3d, camera, truth)[0]
    turn = rotation_from_vector(
        np.radians([0.0, 0.0, 1.5])
    )  # about the world's vertical (z), the centre at 0
    ghost = np.c_[lines3d[:, :3] @ turn.T, lines3d[:, 3:] @ turn.T]
    prior = linereg.Prior(cam_from_world=truth, sigma_rot_deg=5.0, radius_m=0.5)
    for segments, answered in ((lines3d, True), (np.concatenate([lines3d, ghost]), False)):
        line_map = linereg.LineMap.from_segments(segments)
        for basin_turn, expected in ((0.0, True), (1.0, answered)):
            config = RegisterConfig(decide=DecideConfig(basin_turn_deg=basin_turn))
            result = linereg.localize_segments(lines2d, line_map, camera, prior=prior, config=config)
            assert result.success == expected, (len(segments), basin_turn, result.reason)
            if not expected:
                assert result.reason.startswith("ambiguous: the pose is determined to")
    config = RegisterConfig()
    view = map_view(linereg.LineMap.from_segments(np.concatenate([lines3d, ghost])), None, config)
    image = image_lines(lines2d, camera, config.score)
    best = refine_pose(image, view.segments, camera, truth, config.refine, config.score)
    score, seen = view_score(view, image, camera, best.cam_from_world, config.score)
    space = SearchSpace(1.0, 4, 2.0)
    found = near_basins(replace(best, score=score), seen, image, view, camera, config, space)
    assert len(found) >= 1
    assert min(rotation_error_deg(T[:3, :3], best.cam_from_world[:3, :3]) for T in found) > 1.0
