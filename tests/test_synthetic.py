import numpy as np
import pytest

from linereg.config import ScoreConfig
from linereg.errors import InvalidInputError
from linereg.geometry import camera_center, line_coefficients, segment_lengths, transform_points
from linereg.score import image_lines, project_segments, score_pose
from linereg.sim.synthetic import Scene, clip_to_image, look_at, paper_camera, paper_scene


def endpoint_distances(scene: Scene) -> np.ndarray:
    """Returns (K, 2) pixel distances of each true 2D segment's endpoints to its 3D line's projection."""
    i, j = scene.true_matches.T
    projected, visible = project_segments(scene.lines3d[j], scene.camera, scene.cam_from_world, 1e-3)
    assert visible.all()
    H = line_coefficients(projected)
    ends = scene.lines2d[i].reshape(-1, 2, 2)
    return np.abs(np.einsum("kpc,kc->kp", ends, H[:, :2]) + H[:, 2:3])


def test_paper_scene_shapes_and_dtypes(rng):
    scene = paper_scene(rng)
    assert scene.lines2d.shape[1] == 4 and scene.lines2d.dtype == np.float64
    assert scene.lines3d.shape == (100, 6) and scene.lines3d.dtype == np.float64
    assert scene.cam_from_world.shape == (4, 4)
    assert scene.true_matches.dtype == np.int64 and scene.true_matches.shape[1] == 2
    assert np.all(np.diff(scene.true_matches[:, 0]) > 0)  # sorted, one row per 2D segment
    assert np.all(np.abs(scene.lines3d) <= 1.0 + 1e-9)
    assert np.all(segment_lengths(scene.lines3d) > 0.39)
    R = scene.cam_from_world[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    assert 3.0 <= np.linalg.norm(camera_center(scene.cam_from_world)) <= 5.0


@pytest.mark.parametrize("seed", range(5))
def test_paper_scene_true_matches_reproject(seed):
    noise = 2.0
    scene = paper_scene(np.random.default_rng(seed), noise_px=noise)
    assert endpoint_distances(scene).max() < 5 * noise
    # the score's pair test finds nearly all true pairs at the true pose (short, noisy segments may tilt past
    # its tolerance): 2 px noise against 4 px
    image = image_lines(scene.lines2d, scene.camera, ScoreConfig(distance_px=5.0))
    score = score_pose(image, scene.lines3d, scene.camera, scene.cam_from_world, ScoreConfig(distance_px=5.0))
    found = {tuple(p) for p in score.pairs.tolist()}
    assert np.mean([tuple(p) in found for p in scene.true_matches.tolist()]) > 0.9


def test_paper_scene_noise_free_is_exact(rng):
    scene = paper_scene(rng, noise_px=0.0)
    assert endpoint_distances(scene).max() < 1e-6


@pytest.mark.parametrize(("f3", "f2"), [(0.0, 0.0), (0.3, 0.3), (0.5, 0.6)])
def test_paper_scene_outlier_fractions(f3, f2):
    scene = paper_scene(np.random.default_rng(7), num_lines=120, outlier3d_fraction=f3, outlier2d_fraction=f2)
    n2d, k = len(scene.lines2d), len(scene.true_matches)
    assert abs((n2d - k) / n2d - f2) <= 1.0 / n2d
    assert len(np.unique(scene.true_matches[:, 1])) == k  # one 2D segment per imaged map line
    assert k <= round(120 * (1 - f3))
    assert k >= 0.6 * round(120 * (1 - f3))  # few are lost to clipping / shortness


def test_paper_scene_outliers_inside_image(rng):
    scene = paper_scene(rng, noise_px=0.0, outlier2d_fraction=0.5)
    assert np.all(scene.lines2d[:, [0, 2]] >= -1e-9) and np.all(scene.lines2d[:, [0, 2]] <= 639 + 1e-9)
    assert np.all(scene.lines2d[:, [1, 3]] >= -1e-9) and np.all(scene.lines2d[:, [1, 3]] <= 479 + 1e-9)
    assert np.all(segment_lengths(scene.lines2d) >= 20.0 - 1e-9)


def test_paper_scene_has_two_parallel_families(rng):
    scene = paper_scene(rng, num_lines=100)
    d = scene.lines3d[:, 3:] - scene.lines3d[:, :3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.abs(d @ d.T)
    family = (cos > 1 - 1e-9).sum(axis=1)
    assert (family == 40).sum() == 80 and (family == 1).sum() == 20
    first, second = d[family == 40][[0, -1]]
    assert abs(first @ second) <= 0.5 + 1e-9  # families at least 60 degrees apart


def test_paper_scene_is_deterministic():
    a = paper_scene(np.random.default_rng(3))
    b = paper_scene(np.random.default_rng(3))
    for name in ("lines2d", "lines3d", "cam_from_world", "true_matches"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = paper_scene(np.random.default_rng(4))
    assert not np.array_equal(a.lines3d, c.lines3d)


def test_paper_scene_custom_camera(rng):
    from linereg.camera import Camera

    cam = Camera(fx=500.0, fy=500.0, cx=400.0, cy=300.0, width=800, height=600)
    scene = paper_scene(rng, camera=cam, noise_px=0.0)
    assert scene.camera is cam
    assert endpoint_distances(scene).max() < 1e-6


def test_paper_scene_bad_input(rng):
    with pytest.raises(InvalidInputError):
        paper_scene(rng, outlier2d_fraction=1.0)
    with pytest.raises(InvalidInputError):
        paper_scene(rng, num_lines=0)
    with pytest.raises(ValueError):
        paper_scene(rng, outlier3d_fraction=-0.1)


def test_look_at_points_axis_at_target():
    T = look_at(np.array([4.0, 1.0, 2.0]), np.zeros(3), roll_rad=0.7)
    p = transform_points(T, np.zeros((1, 3)))[0]
    np.testing.assert_allclose(p[:2], 0.0, atol=1e-12)
    assert p[2] > 0
    # roll 0: world up projects upwards in the image (negative y)
    T0 = look_at(np.array([5.0, 0.0, 0.0]), np.zeros(3))
    assert transform_points(T0, np.array([[0.0, 0.0, 1.0]]))[0, 1] < 0


def test_clip_to_image():
    cam = paper_camera()
    seg = np.array([[-100.0, 240.0, 700.0, 240.0], [-10.0, -10.0, -5.0, -5.0], [10.0, 10.0, 20.0, 30.0]])
    out, keep = clip_to_image(seg, cam)
    assert keep.tolist() == [True, False, True]
    np.testing.assert_allclose(out[0], [0.0, 240.0, 639.0, 240.0])
    np.testing.assert_allclose(out[2], seg[2])
