"""Negative evidence: map lines a pose predicts where the image shows none."""

import numpy as np
import pytest

from linereg import Camera
from linereg.evidence import _clip, empty_areas, unexplained_length
from linereg.geometry import make_cam_from_world

CAM = Camera(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)


def test_empty_areas_are_far_from_every_segment():
    lines2d = np.array([[100.0, 100.0, 200.0, 100.0]])
    empty = empty_areas(lines2d, CAM, radius_px=40.0)
    cell = empty.cell_px
    assert cell == pytest.approx(5.0)
    assert not empty.mask[int(100 / cell), int(150 / cell)]  # on the segment
    assert not empty.mask[int(130 / cell), int(150 / cell)]  # 30 px below it
    assert empty.mask[int(150 / cell), int(150 / cell)]  # 50 px below it
    assert empty.mask[int(400 / cell), int(600 / cell)]  # far corner


def test_no_segments_means_all_empty():
    empty = empty_areas(np.zeros((0, 4)), CAM, radius_px=40.0)
    assert empty.mask.all()


def test_clip_keeps_the_inside_part():
    segs = np.array([[-100.0, 240.0, 700.0, 240.0], [-10.0, -10.0, -5.0, -5.0], [10.0, 10.0, 20.0, 20.0]])
    clipped = _clip(segs, 640, 480)
    assert len(clipped) == 2  # the wholly outside one is gone
    np.testing.assert_allclose(clipped[0], [-0.5, 240.0, 639.5, 240.0])
    np.testing.assert_allclose(clipped[1], segs[2])


def test_unexplained_counts_only_predictions_in_empty_areas():
    # a camera at the origin looking down +z; a 3D segment imaged at y = 100 px... and one in the image's
    # empty top-left corner
    pose = make_cam_from_world(np.eye(3), np.zeros(3))
    z = 10.0
    on_line = np.array([[-2.0, -2.8, z, 2.0, -2.8, z]])  # v = 239.5 - 140 = 99.5
    in_void = np.array([[-5.5, -3.9, z, -4.5, -3.9, z]])  # (44.5, 44.5) to (94.5, 44.5): 50 px, far away
    lines2d = np.array([[100.0, 99.5, 540.0, 99.5]])
    empty = empty_areas(lines2d, CAM, radius_px=30.0)
    assert unexplained_length(on_line, CAM, pose, empty) == 0.0
    assert unexplained_length(in_void, CAM, pose, empty) == pytest.approx(50.0, abs=3.0)
    behind = in_void.copy()
    behind[:, [2, 5]] = -z  # behind the camera: predicts nothing
    assert unexplained_length(behind, CAM, pose, empty) == 0.0
