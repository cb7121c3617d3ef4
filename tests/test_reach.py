"""What a prior leaves of the map (``map.reach``): the bounds really bound, against brute force on random
cameras the prior allows, and a rough pose prior keeps what the camera sees far beyond its ball."""

import numpy as np
from scipy.spatial.transform import Rotation

import linereg
from linereg.geometry import camera_center, pose_errors
from linereg.map.reach import in_cone, projected_length_bound, seen_from
from linereg.score import project_clipped
from linereg.sim.synthetic import look_at

CAMERA = linereg.Camera(fx=600.0, fy=550.0, cx=300.0, cy=250.0, width=640, height=480)


def _pixels_inside(segment: np.ndarray, cam_from_world: np.ndarray, samples: int = 300) -> float:
    """Returns the pixel length of a world segment's projection that lies inside the image (sampled)."""
    t = np.linspace(0.0, 1.0, samples)[:, None]
    x = (segment[:3] + t * (segment[3:] - segment[:3])) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    front = x[:, 2] > 1e-6
    z = np.where(front, x[:, 2], 1.0)
    u, v = CAMERA.fx * x[:, 0] / z + CAMERA.cx, CAMERA.fy * x[:, 1] / z + CAMERA.cy
    inside = front & (u >= -0.5) & (u <= CAMERA.width - 0.5) & (v >= -0.5) & (v <= CAMERA.height - 0.5)
    both = inside[1:] & inside[:-1]
    return float(np.hypot(np.diff(u), np.diff(v))[both].sum())


def _allowed_poses(rng, centre, radius, base, turn_rad, n):
    """Yields n random poses with centres in the ball and rotations within ``turn_rad`` of ``base``'s."""
    for _ in range(n):
        offset = rng.normal(size=3)
        offset *= radius * rng.uniform() ** (1 / 3) / np.linalg.norm(offset)
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * turn_rad * rng.uniform()).as_matrix()
        R = turn @ base[:3, :3]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ (centre + offset)
        yield T


def test_no_allowed_pose_sees_more_than_the_bounds_allow():
    rng = np.random.default_rng(3)
    segments = rng.uniform(-15.0, 15.0, (1500, 6))
    centre, radius, turn = np.array([1.0, -2.0, 0.5]), 2.0, np.radians(12.0)
    base = look_at(centre, centre + np.array([8.0, 3.0, 1.0]))
    bound = projected_length_bound(segments, centre - radius, centre + radius, CAMERA)
    kept = seen_from(segments, CAMERA, centre, radius, 4.0, base, turn)
    assert 0 < kept.sum() < len(segments)  # the test culls something, keeps something
    for T in _allowed_poses(rng, centre, radius, base, turn, 25):
        for j in rng.choice(len(segments), 150, replace=False):
            seen = _pixels_inside(segments[j], T)
            assert seen <= bound[j] * (1 + 1e-9)
            assert kept[j] or seen < 4.0


def test_a_segment_meets_the_cone_exactly_when_a_point_of_it_lies_inside():
    rng = np.random.default_rng(4)
    segments = rng.uniform(-5.0, 5.0, (3000, 6))
    apex, axis, half = np.array([0.3, -0.2, 0.1]), np.array([0.0, 0.6, 0.8]), np.radians(25.0)
    t = np.linspace(0.0, 1.0, 2001)[None, :, None]
    points = segments[:, None, :3] + t * (segments[:, None, 3:] - segments[:, None, :3]) - apex
    angle = np.arccos(np.clip(points @ axis / np.linalg.norm(points, axis=2), -1.0, 1.0))
    sampled = (angle <= half).any(axis=1)
    exact = in_cone(segments, apex, axis, half)
    assert np.all(exact[sampled])  # never misses a segment with a point inside
    # a segment the samples miss but the test keeps grazes the cone between two samples
    grazing = exact & ~sampled
    assert grazing.sum() <= 3 and np.all(angle[grazing].min(axis=1) <= half + np.radians(0.2))
    assert in_cone(segments, apex, axis, np.radians(95.0)).all()


def test_a_rough_pose_prior_keeps_what_the_camera_sees_far_beyond_its_ball():
    """A street: facades 6 m either side running 60 m ahead, posts every 5 m; a rough guess 3 deg / 0.3 m
    off with a 0.5 m ball. The camera sees 40 m ahead, far beyond the ball."""
    lines = []
    for y in (-6.0, 6.0):
        for x in np.arange(0.0, 60.0, 5.0):
            lines += [[x, y, 0.0, x, y, 3.0 + 0.1 * x], [x, y, 1.0, x + 4.0, y, 1.0]]
        lines += [[0.0, y, 0.0, 60.0, y, 0.0], [0.0, y, 6.0, 60.0, y, 6.0]]
    lines += [[x, -1.0, 0.0, x, 1.0, 0.0] for x in np.arange(2.0, 40.0, 3.0)]
    lines3d = np.array(lines, dtype=np.float64)
    line_map = linereg.LineMap.from_segments(lines3d)
    truth = look_at(np.array([-5.0, 0.5, 1.6]), np.array([20.0, 0.0, 1.0]))
    lines2d, _ = project_clipped(lines3d, CAMERA, truth, 0.05, None)
    assert len(lines2d) > 30
    turn = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, 0.8, 0.0])).as_matrix()
    guess = truth.copy()
    guess[:3, :3] = turn @ truth[:3, :3]
    guess[:3, 3] = -guess[:3, :3] @ (camera_center(truth) + np.array([0.2, -0.2, 0.1]))
    prior = linereg.Prior(cam_from_world=guess, sigma_rot_deg=3.0, radius_m=0.5)
    kept = seen_from(lines3d, CAMERA, prior.position, 0.5, 2.0, guess, np.radians(10.0))
    far = np.linalg.norm(lines3d[:, :3] - camera_center(truth), axis=1) > 10 * 0.5
    assert kept[far].sum() > 20  # the old ball-and-reach culling (radius + 10 radii) kept none of these
    result = linereg.localize_segments(lines2d, line_map, CAMERA, prior=prior)
    assert result.success, result.reason
    rotation_deg, position_m, _ = pose_errors(result.cam_from_world, truth)
    assert rotation_deg < 0.1 and position_m < 0.01
