import numpy as np
import pytest

from linereg.bench.baselines import BaselineConfig, dlt_lines, ransac3, ransac6
from linereg.bench.oracle import pnl_known_correspondences
from linereg.errors import InvalidInputError
from linereg.geometry import pose_errors
from linereg.score import project_segments
from linereg.sim.synthetic import look_at, paper_scene


def general_scene(rng, camera, num_lines, noise_px=0.0):
    """Returns (lines2d, lines3d, cam_from_world): random directions (general position), all imaged."""
    cam_from_world = look_at(np.array([0.5, -4.0, 1.0]), np.zeros(3), roll_rad=0.3)
    lines3d = np.zeros((0, 6))
    while len(lines3d) < num_lines:
        cand = rng.uniform(-1.0, 1.0, size=(1, 6))
        seg, _ = project_segments(cand, camera, cam_from_world, 1e-3)
        inside = (seg[:, 0::2].min() > 0) & (seg[:, 0::2].max() < camera.width)
        inside &= (seg[:, 1::2].min() > 0) & (seg[:, 1::2].max() < camera.height)
        if inside and np.linalg.norm(seg[0, 2:] - seg[0, :2]) > 40.0:
            lines3d = np.r_[lines3d, cand]
    lines2d, _ = project_segments(lines3d, camera, cam_from_world, 1e-3)
    return lines2d + rng.normal(scale=noise_px, size=lines2d.shape), lines3d, cam_from_world


@pytest.mark.parametrize("num_lines", [6, 7, 20])
def test_dlt_lines_exact_on_noise_free_correspondences(camera, rng, num_lines):
    lines2d, lines3d, truth = general_scene(rng, camera, num_lines)
    estimate = dlt_lines(lines2d, lines3d, camera)
    assert np.allclose(estimate, truth, atol=1e-7)  # a 6-line DLT's condition number reaches ~1e6


def test_dlt_lines_is_invariant_to_world_offset_and_endpoint_order(camera, rng):
    # Hartley normalisation: a map far from the origin is as well conditioned as one around it
    lines2d, lines3d, truth = general_scene(rng, camera, 8)
    offset = np.array([1e4, -2e4, 300.0])
    shifted = truth.copy()
    shifted[:3, 3] -= truth[:3, :3] @ offset
    swapped = np.c_[lines2d[:, 2:4], lines2d[:, 0:2]]
    estimate = dlt_lines(swapped, lines3d + np.tile(offset, 2), camera)
    assert np.allclose(estimate[:3, :3], shifted[:3, :3], atol=1e-8)
    assert np.allclose(estimate[:3, 3], shifted[:3, 3], atol=1e-4 * np.linalg.norm(shifted[:3, 3]))


def test_dlt_lines_degrades_gracefully_with_noise(camera, rng):
    lines2d, lines3d, truth = general_scene(rng, camera, 60, noise_px=1.0)
    rot_deg, _, rel = pose_errors(dlt_lines(lines2d, lines3d, camera), truth)
    assert rot_deg < 2.0 and rel < 0.05


def test_dlt_lines_rejects_bad_input(camera, rng):
    lines2d, lines3d, _ = general_scene(rng, camera, 6)
    with pytest.raises(InvalidInputError, match="lines2d"):
        dlt_lines(lines2d[:5], lines3d[:5], camera)
    with pytest.raises(InvalidInputError, match="row by row"):
        dlt_lines(lines2d, np.r_[lines3d, lines3d[:1]], camera)
    with pytest.raises(InvalidInputError, match="lines3d"):
        dlt_lines(lines2d, lines3d[:, :4], camera)


def test_ransac6_succeeds_on_easy_scene(camera, rng):
    # A blind 6-pair sample is all-correct with probability 1/6! here (about (1/20)^6 with 20 lines, which
    # is why the paper's baseline fails on realistic scenes): the easy scene is 6 noise-free lines.
    lines2d, lines3d, truth = general_scene(rng, camera, 6)
    order = rng.permutation(6)
    result = ransac6(lines2d[order], lines3d, camera, baseline=BaselineConfig(max_iterations=5000, seed=3))
    assert result.success, result.reason
    rot_deg, _, rel = pose_errors(result.cam_from_world, truth)
    assert rot_deg < 0.01 and rel < 1e-3
    assert result.num_inliers == 6
    assert np.array_equal(np.sort(result.matches, axis=0)[:, 1], np.sort(order))
    assert {"ransac6", "total"} <= set(result.timings)


def test_ransac6_fails_with_a_reason_within_its_budget(rng):
    scene = paper_scene(rng, 20, 0.3, 0.3, 2.0)
    result = ransac6(scene.lines2d, scene.lines3d, scene.camera, baseline=BaselineConfig(max_iterations=50))
    assert not result.success and "ransac6" in result.reason
    assert np.array_equal(result.cam_from_world, np.eye(4))


def test_ransac6_too_few_lines_is_an_input_error(camera, rng):
    lines2d, lines3d, _ = general_scene(rng, camera, 6)
    with pytest.raises(InvalidInputError, match="at least 6"):
        ransac6(lines2d[:4], lines3d, camera)
    with pytest.raises(InvalidInputError):
        ransac6(lines2d[:, :3], lines3d, camera)


@pytest.mark.parametrize("seed", range(3))
def test_ransac3_registers_an_easy_paper_scene(seed):
    """The paper's own translation stage (random 3-pair RANSAC per rotation candidate): exact on 20 noise-free
    lines without outliers, where a random triple of compatible pairs is right often enough."""
    scene = paper_scene(np.random.default_rng(seed), 20, 0.0, 0.0, 0.0)
    result = ransac3(scene.lines2d, scene.lines3d, scene.camera, baseline=BaselineConfig(max_iterations=3000))
    assert result.success, result.reason
    rot_deg, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
    assert rot_deg < 0.01 and rel < 1e-3 and result.num_inliers == 20


@pytest.mark.parametrize("noise_px", [0.0, 2.0])
def test_oracle_matches_ground_truth(noise_px):
    scene = paper_scene(np.random.default_rng(7), 50, 0.3, 0.3, noise_px)
    estimate = pnl_known_correspondences(scene.lines2d, scene.lines3d, scene.true_matches, scene.camera)
    rot_deg, _, rel = pose_errors(estimate, scene.cam_from_world)
    if noise_px == 0.0:  # PoseLib's CameraPose is world -> camera: exactly our cam_from_world
        assert np.allclose(estimate, scene.cam_from_world, atol=1e-7)
    else:
        assert rot_deg < 1.0 and rel < 0.02


def test_oracle_rejects_bad_matches(camera):
    scene = paper_scene(np.random.default_rng(8), 20, 0.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match="at least 3"):
        pnl_known_correspondences(scene.lines2d, scene.lines3d, scene.true_matches[:2], scene.camera)
    bad = scene.true_matches.copy()
    bad[0, 1] = len(scene.lines3d)
    with pytest.raises(InvalidInputError, match="outside"):
        pnl_known_correspondences(scene.lines2d, scene.lines3d, bad, scene.camera)
