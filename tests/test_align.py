"""Window alignment: a window of frames turned about its newest centre comes back by its summed score; the
rotation measurement enters the graph in the right frame; a tracker coasting on drifting odometry is
turned back, without claiming the frames."""

from __future__ import annotations

import itertools
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from test_sequence import CAMERA, _scene

from linereg.align import WindowAlignment, align_window, rotation_prior, turned_about
from linereg.config import RegisterConfig
from linereg.geometry import camera_center, pose_errors
from linereg.graph import frame_key, relative_pose, to_pose3
from linereg.score import image_lines
from linereg.sim.synthetic import look_at
from linereg.tracking import Tracker, TrackingConfig

TURN = np.radians([0.8, -1.2, 0.6])  # a world-frame rotation vector, 1.6 deg


def test_a_turn_about_a_point_keeps_that_centre_and_undoes_itself():
    T = look_at(np.array([4.0, 1.0, 0.8]), np.zeros(3))
    centre = np.array([1.0, 2.0, 3.0])
    turned = turned_about(T, TURN, centre)
    assert pose_errors(turned, T)[0] == pytest.approx(np.degrees(np.linalg.norm(TURN)), rel=1e-9)
    same = turned_about(look_at(centre, np.zeros(3)), TURN, centre)
    assert np.allclose(camera_center(same), centre)
    assert np.allclose(turned_about(turned, -TURN, centre), T)


def test_a_turned_window_comes_back_by_its_summed_score():
    line_map, truth, frames = _scene(6)
    config = RegisterConfig()
    images = [image_lines(f, CAMERA, config.score) for f in frames]
    centre = camera_center(truth[-1])
    drifted = [turned_about(T, TURN, centre) for T in truth]
    resolution = config.score.distance_px / CAMERA.fx
    found = align_window(images, drifted, line_map.segments, CAMERA, np.radians(3.0), resolution, config)
    assert found is not None and found.value > found.at_zero
    back = turned_about(drifted[-1], found.rotation, found.centre)
    assert pose_errors(back, truth[-1])[0] < np.degrees(resolution)
    assert np.linalg.eigvalsh(found.covariance)[0] > 0
    blank = [image_lines(np.zeros((0, 4)), CAMERA, config.score)] * 2
    assert align_window(blank, truth[:2], line_map.segments, CAMERA, 0.05, resolution, config) is None


def test_the_rotation_prior_measures_the_turn_with_its_world_covariance():
    _, truth, _ = _scene(2)
    T = truth[0]
    # a turn with a known, anisotropic world-frame covariance
    found = WindowAlignment(TURN, camera_center(T), np.diag([1e-4, 4e-4, 9e-4]), 1.0, 0.0, 1)
    factor = rotation_prior(frame_key(0), T, found)
    values = gtsam.Values()
    values.insert(frame_key(0), to_pose3(turned_about(T, found.rotation, found.centre)))
    assert factor.error(values) == pytest.approx(0.0, abs=1e-12)
    values.update(frame_key(0), to_pose3(T))  # the untouched pose is the turn away: w^T C^-1 w / 2
    w = found.rotation
    assert factor.error(values) == pytest.approx(0.5 * w @ np.linalg.solve(found.covariance, w), rel=1e-6)


def test_a_tracker_coasting_on_turning_odometry_is_turned_back_without_claims():
    line_map, truth, frames = _scene(30)
    relative = [relative_pose(a, b) for a, b in itertools.pairwise(truth)]
    bias = gtsam.Rot3.Expmap(np.radians([0.0, 0.15, 0.0])).matrix()  # 0.15 deg of yaw per frame
    odometry = [np.r_[np.c_[bias @ T[:3, :3], T[:3, 3]], [[0, 0, 0, 1]]] for T in relative]
    # no frame can be fixed alone (min_inliers out of reach): the tracker coasts on odometry
    base = TrackingConfig()
    register = replace(base.sequence.register, min_inliers=10**6)
    sequence = replace(base.sequence, register=register, relocalize_every=10**6)
    errors = {}
    for frames_scored in (0, 6):
        tracker = Tracker(line_map, CAMERA, replace(base, sequence=sequence, align_frames=frames_scored))
        tracker.start_at(truth[0], sigma_rot_deg=0.1, sigma_pos_m=0.01)
        out = [tracker.step(frames[0])]
        out += [tracker.step(f, odometry[k]) for k, f in enumerate(frames[1:])]
        assert not any(r.success for r in out)
        errors[frames_scored] = pose_errors(out[-1].cam_from_world, truth[-1])[0]
        assert (tracker.alignments > 0) == (frames_scored > 0)
    assert errors[0] > 3.0  # 29 steps of 0.15 deg
    assert errors[6] < 0.5 * errors[0]
