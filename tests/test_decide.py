"""The decision (``pipeline.decide``): an answer must beat every distinct pose, including the best pose
turned by small angles (``turned_rival``), whose scores come from ``score.shifted_values``."""

import numpy as np

import linereg
from linereg.config import RegisterConfig
from linereg.geometry import rotation_error_deg
from linereg.pipeline import turned_rival
from linereg.score import image_lines, project_clipped, score_pose, score_projected, shifted_values
from linereg.sim.synthetic import look_at, paper_scene


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
