"""Copies of what a pose sees elsewhere in the map (``copies.py``): found from the map alone."""

import numpy as np
from test_decide import facade_copies

import linereg
from linereg.config import RegisterConfig
from linereg.copies import copy_starts
from linereg.geometry import camera_center, rotation_error_deg
from linereg.localization import map_view
from linereg.score import image_lines, project_clipped, score_pose
from linereg.sim.synthetic import look_at

CAMERA = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)


def starts_of(segments: np.ndarray, pose: np.ndarray, rotations: list[np.ndarray], regions=None) -> list:
    """Returns ``copy_starts`` of a pose matching every map segment it sees (the map without surfaces)."""
    config = RegisterConfig()
    view = map_view(linereg.LineMap.from_segments(segments), None, config)
    lines2d, _ = project_clipped(segments, CAMERA, pose, 0.05)
    score = score_pose(image_lines(lines2d, CAMERA, config.score), segments, CAMERA, pose, config.score)
    matched = np.zeros(len(segments), dtype=bool)
    matched[score.matches(0.5)[:, 1]] = True
    return copy_starts(
        pose, matched, view.points, view.signatures, segments, CAMERA, rotations,
        config.search.arm_angle_deg, config.decide, regions,
    )  # fmt: skip


def test_a_facade_repeated_along_the_street_gives_its_copy_and_not_the_pose_itself():
    """The same facade pattern 20 m along: the camera 20 m along is where every matched corner agrees."""
    segments, _ = facade_copies()
    pose = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    starts = starts_of(segments, pose, [])
    assert starts, "no copy found"
    T, size, share = starts[0]
    assert share > 0.9
    assert rotation_error_deg(T[:3, :3], pose[:3, :3]) < 1e-9
    assert np.linalg.norm(camera_center(T) - [2.0, 20.0, 1.5]) <= size
    assert all(np.linalg.norm(camera_center(T) - [2.0, 0.0, 1.5]) > size for T, size, _ in starts)


def test_a_building_turned_half_round_gives_the_twin_under_the_turned_rotation():
    """A facade and its copy turned 180 degrees about a vertical axis (a building's back): under the
    rotation candidate of the twin, the camera centre is the pose's own turned about that axis."""
    segments, _ = facade_copies()
    pattern = segments[: len(segments) // 2]
    turn = np.diag([-1.0, -1.0, 1.0])  # 180 degrees about z
    twin = np.c_[pattern[:, :3] @ turn.T, pattern[:, 3:] @ turn.T] + [60.0, 5.0, 0.0, 60.0, 5.0, 0.0]
    both = np.r_[pattern, twin]
    pose = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    R_twin = pose[:3, :3] @ turn.T
    starts = starts_of(both, pose, [pose[:3, :3], R_twin])
    expected = turn @ np.array([2.0, 0.0, 1.5]) + [60.0, 5.0, 0.0]
    near = [s for s in starts if np.linalg.norm(camera_center(s[0]) - expected) <= s[1]]
    assert near, [camera_center(s[0]) for s in starts]
    T, _, share = near[0]
    assert share > 0.9 and rotation_error_deg(T[:3, :3], R_twin) < 1e-6


def test_a_lone_facade_has_no_copy():
    segments, _ = facade_copies()
    pattern = segments[: len(segments) // 2]
    pose = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    assert starts_of(pattern, pose, [pose[:3, :3]]) == []


def test_copies_outside_the_regions_searched_are_not_counted():
    """Three copies of the facade 20 m apart: a region round the second finds it alone, one round neither
    finds none (a prior's ball; on a large map the corners beyond the regions' reach are not even paired)."""
    segments, _ = facade_copies()
    pattern = segments[: len(segments) // 2]
    three = np.concatenate([pattern + np.tile([0.0, y, 0.0], 2) for y in (0.0, 20.0, 40.0)])
    pose = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    everywhere = starts_of(three, pose, [])
    assert sorted(round(float(camera_center(T)[1])) for T, _, _ in everywhere) == [20, 40]
    second = [(np.array([0.0, 15.0, 0.0]), np.array([4.0, 25.0, 3.0]))]
    (T, size, _), *others = starts_of(three, pose, [], second)
    assert not others and np.linalg.norm(camera_center(T) - [2.0, 20.0, 1.5]) <= size
    neither = [(np.array([0.0, 25.0, 0.0]), np.array([4.0, 35.0, 3.0]))]
    assert starts_of(three, pose, [], neither) == []


def test_every_copy_is_returned_and_the_rivals_solved_are_the_best_scoring():
    """Five copies of the facade 20 m apart share every corner alike; four have lines above them that the
    photo does not show (predicted where the image has none: 87 % of the score). ``copy_starts`` returns all five
    (not the first few by corner share: a lattice's bay shifts share nearly all corners, and the truth
    may share fewer), and ``copy_rivals`` solves the one explaining the photo best even when it may solve
    only one."""
    from dataclasses import replace

    from linereg.pipeline import copy_rivals

    segments, _ = facade_copies()
    pattern = segments[: len(segments) // 2]
    copies = [pattern + np.tile([0.0, y, 0.0], 2) for y in (0.0, 20.0, 40.0, 60.0, 80.0, 100.0)]
    clutter = np.array([[19.5, -4.0, 6.0 + 0.4 * i, 19.5, 4.0, 6.0 + 0.4 * i] for i in range(3)])  # above it
    cluttered = [c for y in (20.0, 40.0, 80.0, 100.0) for c in clutter + np.tile([0.0, y, 0.0], 2)]
    segments = np.r_[np.concatenate(copies), cluttered]
    pose = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    starts = starts_of(segments, pose, [])
    assert sorted(round(float(camera_center(T)[1])) for T, _, _ in starts) == [20, 40, 60, 80, 100]
    config = RegisterConfig()
    config = replace(config, decide=replace(config.decide, copies=1, orbit_deg=()))
    view = map_view(linereg.LineMap.from_segments(segments), None, config)
    lines2d, _ = project_clipped(pattern, CAMERA, pose, 0.05)
    image = image_lines(lines2d, CAMERA, config.score)
    score = score_pose(image, segments, CAMERA, pose, config.score)
    regions = [(np.array([-5.0, -10.0, 0.0]), np.array([10.0, 110.0, 3.0]))]
    (T, _), *rest = copy_rivals(pose, score, view, image, CAMERA, config, [pose[:3, :3]], regions)
    assert not rest
    assert np.linalg.norm(camera_center(T) - [2.0, 60.0, 1.5]) < 0.1


def test_agreements_count_exactly_what_reaches_the_share():
    """The voxels a copy's share cannot reach are skipped by a bound: what is left is exactly what counting
    every voxel gives, for any share (a voxel is only ever set aside by a better one)."""
    from linereg.copies import _agreements

    rng = np.random.default_rng(4)
    for trial in range(6):
        k = rng.integers(0, 40, 3000)
        clumps = rng.uniform(-20, 20, (5, 3))
        centres = np.where(
            (rng.random(3000) < 0.5)[:, None],
            clumps[rng.integers(0, 5, 3000)] + rng.normal(0, 0.3, (3000, 3)),
            rng.uniform(-30, 30, (3000, 3)),
        )
        weight = rng.uniform(0.5, 2.0, 40)
        total = float(weight.sum())
        every = _agreements(centres, k, weight, total, 1.0, 0.0, None)
        for share in (0.05, 0.2, 0.5):
            kept = _agreements(centres, k, weight, total, 1.0, share, None)
            expected = [(c, s) for c, s in every if s >= share]
            assert len(kept) == len(expected), (trial, share)
            for (c, s), (c_all, s_all) in zip(kept, expected, strict=True):
                np.testing.assert_array_equal(c, c_all)
                assert s == s_all
    assert any(s >= 0.2 for _, s in every)  # the clumps hold copies the bound must keep


def test_the_agreements_bound_keeps_what_numpy_sums_keep():
    """``copies._bound_kept`` (the compiled bound of ``_agreements``) keeps exactly the votes that summing
    each hashed voxel's weights with ``np.bincount`` and comparing keeps: the same floats, the same order."""
    from linereg.copies import _bound_kept

    rng = np.random.default_rng(11)
    for pairs, span in ((1, 3), (40, 2), (3000, 30), (20000, 400)):
        cell = rng.integers(0, span**3, pairs).astype(np.int64)
        offsets = (np.indices((2, 2, 2)).reshape(3, 8).T * [span * span, span, 1]).sum(axis=1)
        weight = rng.uniform(0.1, 3.0, pairs)
        cells = (cell[:, None] + offsets[None]).reshape(-1)
        for bins in (1, 7, max(16 * pairs, 1)):
            bound = np.bincount(cells % bins, weights=np.repeat(weight, 8))
            for threshold in (0.0, float(np.median(bound[cells % bins])), float(bound.max()), np.inf):
                expected = np.flatnonzero(bound[cells % bins] >= threshold)
                np.testing.assert_array_equal(_bound_kept(cell, offsets, weight, bins, threshold), expected)


def test_first_of_each_is_numpys_unique_with_first_indices():
    """``copies._first_of_each`` (the agreements' once-per-voxel count) gives what ``np.unique(...,
    return_index=True)`` gives: the distinct values sorted, each with the index of its first occurrence."""
    from linereg.copies import _first_of_each

    rng = np.random.default_rng(7)
    for size, high in ((1, 5), (50, 3), (5000, 400), (20000, 10**12)):
        values = rng.integers(0, high, size, dtype=np.int64)
        distinct, first = _first_of_each(values)
        expected, expected_first = np.unique(values, return_index=True)
        np.testing.assert_array_equal(distinct, expected)
        np.testing.assert_array_equal(first, expected_first)
