"""Real scenes of ../shared/data (skipped when absent): the loaders read them with the right conventions."""

import json

import numpy as np
import pytest

from linereg.bench.real import default_data_dir, read_scene, scene_folders
from linereg.geometry import project_points, transform_points

DATA = default_data_dir()
FOLDERS = scene_folders(DATA)
pytestmark = pytest.mark.skipif(not FOLDERS, reason=f"no real data in {DATA}")


@pytest.mark.parametrize("folder", FOLDERS, ids=lambda f: f.name)
def test_scene_images_match_their_cameras_and_poses(folder):
    from linereg import io

    items = read_scene(folder)
    assert len(items) == len(json.loads((folder / "cameras.json").read_text())["images"]) > 0
    for item in items:
        image = io.read_image(item.image_path)
        assert image.shape[:2] == (item.camera.height, item.camera.width)
        R = item.cam_from_world[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
        assert item.cloud_path.is_file()


@pytest.mark.parametrize("folder", FOLDERS, ids=lambda f: f.name)
def test_cloud_seen_through_the_true_pose_fills_the_image(folder):
    """The convention check: with the ground truth, many map points land in front of the camera, in the image."""
    from linereg import io

    meta = json.loads((folder / "cameras.json").read_text())
    item = read_scene(folder)[0]
    points = io.read_cloud(folder / "cloud.ply")
    assert points.shape == (meta["n_points"], 3) and np.isfinite(points).all()
    cam = transform_points(item.cam_from_world, points)
    front = cam[cam[:, 2] > 0.1]
    uv = project_points(item.camera, front)
    inside = (
        (uv[:, 0] >= 0) & (uv[:, 0] < item.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < item.camera.height)
    )
    assert inside.sum() > min(10_000, 0.1 * len(points))  # a sweep cropped to the view, or a 360 one
    # the points cover the image broadly (KITTI's Velodyne: the lower part only)
    cells = np.unique((uv[inside] // 40).astype(int), axis=0)
    assert len(cells) > 0.3 * (item.camera.width // 40) * (item.camera.height // 40)


def test_kitti_frame_runs_through_map_and_localization():
    """The whole path on a real LiDAR scan: a map, then a Registration (no pose accuracy asserted: the
    pipeline does not localize this sparse single sweep yet; see ``linereg bench real``)."""
    from linereg.bench.real import build_map, localize_one

    folder = DATA / "kitti_obj_000002"
    if folder not in FOLDERS:
        pytest.skip("kitti_obj_000002 not in the data folder")
    item = read_scene(folder)[0]
    line_map, record = build_map(item.cloud_path)
    assert record["num_segments"] > 100
    result, _ = localize_one(item, line_map, (5.0, 0.3))
    assert result["num_lines2d"] > 50 and result["gt_inliers"] > 0
    assert result["success"] or result["reason"]
