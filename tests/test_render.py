"""Rendered building photos: edges where Building.edges project, exact z-buffer, determinism, demo scene."""

import numpy as np
import pytest

import linereg
from linereg.geometry import invert
from linereg.lines2d import detect
from linereg.sim.building import make_building
from linereg.sim.demo_scene import make_demo_scene
from linereg.sim.render import RenderConfig, rasterize, render_image, scaled_camera, visible_edge_lengths
from linereg.sim.scanner import ScanConfig
from linereg.sim.views import camera_poses, project_building, street_camera


@pytest.fixture(scope="module")
def scene():
    building = make_building(np.random.default_rng(0))
    pose = camera_poses(building, np.random.default_rng(1), 1)[0]
    return building, pose


def on_line_fraction(truths: np.ndarray, found: np.ndarray, dist_px: float = 2.0) -> float:
    """Returns the fraction of true segments covered >= 50 % by found segments lying on their line."""
    hits = 0
    for t in truths:
        p, d = t[:2], t[2:] - t[:2]
        length = np.linalg.norm(d)
        d /= length
        n = np.array([-d[1], d[0]])
        ends = found.reshape(-1, 2, 2) - p
        near = np.abs(ends @ n).max(axis=1) <= dist_px
        along = np.sort(ends[near] @ d, axis=1).clip(0.0, length)
        hits += (along[:, 1] - along[:, 0]).sum() >= 0.5 * length
    return hits / len(truths)


def test_render_shape_and_determinism(scene):
    building, pose = scene
    camera = street_camera()
    a = render_image(building, pose, camera, np.random.default_rng(5))
    b = render_image(building, pose, camera, np.random.default_rng(5))
    assert a.shape == (480, 640, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert a.std() > 10  # not a blank frame


def test_detected_lines_lie_on_projected_building_edges(scene):
    building, pose = scene
    camera = street_camera()
    truth, _ = project_building(building, camera, pose)
    long = truth[np.linalg.norm(truth[:, 2:] - truth[:, :2], axis=1) >= 60.0]
    assert len(long) >= 10
    found = detect(render_image(building, pose, camera, np.random.default_rng(2)), camera)
    assert on_line_fraction(long, found) >= 0.6


def test_distorted_render_round_trips_through_detect(scene):
    building, pose = scene
    camera = linereg.Camera(600.0, 600.0, 320.0, 240.0, 640, 480, dist=(-0.2, 0.05, 0.0, 0.0))
    truth, _ = project_building(building, camera.undistorted(), pose)
    long = truth[np.linalg.norm(truth[:, 2:] - truth[:, :2], axis=1) >= 60.0]
    found = detect(render_image(building, pose, camera, np.random.default_rng(2)), camera)
    assert on_line_fraction(long, found, dist_px=2.5) >= 0.5


def test_rasterized_depth_lies_on_the_visible_face(scene):
    building, pose = scene
    camera = street_camera()
    face_id, inv_depth = rasterize(building, pose, camera)
    v, u = np.nonzero(face_id >= 0)
    pick = np.random.default_rng(0).choice(len(u), 3000, replace=False)
    u, v, f = u[pick], v[pick], face_id[v[pick], u[pick]]
    rays = np.c_[(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(len(u))]
    points = (rays / inv_depth[v, u][:, None]) @ invert(pose)[:3, :3].T + invert(pose)[:3, 3]
    normals, corner = building.normals[f], building.faces[f, 0]
    assert np.abs(np.einsum("pk,pk->p", points - corner, normals)).max() < 1e-6
    centre = invert(pose)[:3, 3]
    assert (np.einsum("pk,pk->p", centre - corner, normals) > 0).all()  # only faces turned to the camera


def test_demo_scene_is_deterministic_and_complete():
    cfg = ScanConfig(angular_step_deg=1.5)
    a = make_demo_scene(seed=3, num_images=1, scan_config=cfg)
    b = make_demo_scene(seed=3, num_images=1, scan_config=cfg)
    assert a.images.shape == (1, 480, 480 * 4 // 3, 3) and a.cam_from_world.shape == (1, 4, 4)
    assert a.cloud.shape[1] == 3 and len(a.cloud) > 10_000 and 3 <= len(a.scanner_positions) <= 5
    assert np.array_equal(a.cloud, b.cloud) and np.array_equal(a.images, b.images)
    assert np.array_equal(a.cam_from_world, b.cam_from_world)


def test_zbuffer_edge_visibility_agrees_with_ray_casting(scene):
    building, pose = scene
    camera = street_camera()
    face_id, inv_depth = rasterize(building, pose, scaled_camera(camera, 0.5))
    lengths = visible_edge_lengths(building, pose, camera, face_id, inv_depth)
    assert lengths.shape == (len(building.edges),) and (lengths >= 0).all()
    truth, idx = project_building(building, camera, pose)
    cast = np.zeros(len(building.edges))
    np.add.at(cast, idx, np.linalg.norm(truth[:, 2:] - truth[:, :2], axis=1))
    long = cast >= 40.0
    assert (lengths[long] >= 0.7 * cast[long]).mean() > 0.9  # visible edges are seen
    assert (lengths[cast == 0] < 20.0).mean() > 0.95  # hidden or out of view ones are not


def test_shade_is_lifted_by_the_tone_curve(scene):
    building, pose = scene
    camera = street_camera()
    linear = render_image(building, pose, camera, np.random.default_rng(5), RenderConfig(gamma=1.0))
    photo = render_image(building, pose, camera, np.random.default_rng(5))
    assert np.median(photo) > np.median(linear) and photo.max() >= linear.max() - 2


def test_demo_poses_show_more_than_a_wall():
    from linereg.sim.demo_scene import _distinctive, demo_poses

    building = make_building(np.random.default_rng(2))
    camera = street_camera()
    poses = demo_poses(building, np.random.default_rng(3), 3, camera)
    again = demo_poses(building, np.random.default_rng(3), 3, camera)
    assert np.array_equal(np.array(poses), np.array(again))
    for pose in poses:
        face_id, inv_depth = rasterize(building, pose, scaled_camera(camera, 0.5))
        lengths = visible_edge_lengths(building, pose, camera, face_id, inv_depth)
        assert (lengths >= 20.0).sum() >= 60 and _distinctive(building, face_id, lengths, camera)
