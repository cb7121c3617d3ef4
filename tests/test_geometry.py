"""The conventions of linereg.geometry: poses named by direction, round trips, gtsam's exponential map."""

import gtsam
import numpy as np
import pytest

from linereg.geometry import (
    axis_angle_deg,
    camera_center,
    invert,
    make_cam_from_world,
    nearest_rotation,
    pose_errors,
    rotation_error_deg,
    rotation_from_vector,
    transform_points,
)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_cam_from_world(rotation_from_vector(rng.normal(size=3)), rng.normal(scale=5.0, size=3))


@pytest.mark.parametrize("seed", range(5))
def test_invert_round_trips_and_composes_to_identity(seed):
    T = random_pose(np.random.default_rng(seed))
    np.testing.assert_allclose(invert(invert(T)), T, atol=1e-12)
    np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_make_cam_from_world_maps_world_points_into_the_camera(seed):
    rng = np.random.default_rng(seed)
    R, t = rotation_from_vector(rng.normal(size=3)), rng.normal(size=3)
    T = make_cam_from_world(R, t)
    points = rng.normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(T, points), points @ R.T + t, atol=1e-12)
    assert T.shape == (4, 4) and np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("seed", range(5))
def test_camera_center_maps_to_the_camera_origin(seed):
    T = random_pose(np.random.default_rng(seed))
    c = camera_center(T)
    np.testing.assert_allclose(transform_points(T, c[None])[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(c, invert(T)[:3, 3], atol=1e-12)  # world_from_cam's translation


@pytest.mark.parametrize("seed", range(5))
def test_rotation_from_vector_is_gtsams_expmap(seed):
    omega = np.random.default_rng(seed).normal(size=3)
    np.testing.assert_allclose(rotation_from_vector(omega), gtsam.Rot3.Expmap(omega).matrix(), atol=1e-12)
    np.testing.assert_allclose(
        gtsam.Rot3.Logmap(gtsam.Rot3(rotation_from_vector(omega))), _wrapped(omega), atol=1e-9
    )


def _wrapped(omega: np.ndarray) -> np.ndarray:
    """Returns the rotation vector of the same rotation with angle in [0, pi]."""
    angle = np.linalg.norm(omega)
    k = angle // (2 * np.pi)
    angle_w = angle - 2 * np.pi * k
    axis = omega / angle
    return axis * angle_w if angle_w <= np.pi else -axis * (2 * np.pi - angle_w)


def test_rotation_from_vector_of_zero_is_identity():
    assert np.array_equal(rotation_from_vector(np.zeros(3)), np.eye(3))


@pytest.mark.parametrize("angle_deg", [1e-9, 1e-6, 1e-3, 1.0, 90.0, 179.0])
def test_rotation_error_resolves_small_and_large_angles(angle_deg):
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    R = rotation_from_vector(np.radians(angle_deg) * axis)
    R0 = rotation_from_vector(np.array([0.3, -0.2, 0.1]))
    assert rotation_error_deg(R0, R0 @ R) == pytest.approx(angle_deg, rel=1e-6)
    assert rotation_error_deg(R0, R0) == 0.0


def test_axis_angle_is_sign_free_and_resolves_small_angles():
    a = np.array([1.0, 0.0, 0.0])
    b = np.array([np.cos(1e-8), np.sin(1e-8), 0.0])
    assert axis_angle_deg(a, b) == pytest.approx(np.degrees(1e-8), rel=1e-6)
    assert axis_angle_deg(a, -b) == pytest.approx(np.degrees(1e-8), rel=1e-6)
    assert axis_angle_deg(a, np.array([0.0, 0.0, 2.0])) == pytest.approx(90.0)


def test_nearest_rotation_is_proper_and_fixes_rotations():
    rng = np.random.default_rng(3)
    R = rotation_from_vector(rng.normal(size=3))
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)
    Q = nearest_rotation(rng.normal(size=(3, 3)))
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)


def test_pose_errors_measure_rotation_position_and_relative_translation():
    T = random_pose(np.random.default_rng(4))
    shift = make_cam_from_world(np.eye(3), [0.3, 0.0, 0.4])  # moves the camera by 0.5 m in its own frame
    rot, pos, rel = pose_errors(shift @ T, T)
    assert rot == pytest.approx(0.0, abs=1e-9) and pos == pytest.approx(0.5)
    assert rel == pytest.approx(0.5 / np.linalg.norm(T[:3, 3]))
