"""The public API's contract: shapes, types and the errors bad input gets (DESIGN.md, issue 2)."""

import numpy as np
import pytest

import linereg
from linereg.config import RegisterConfig


def test_camera_validates_and_names_the_argument():
    with pytest.raises(linereg.InvalidInputError, match="focal"):
        linereg.Camera(fx=0, fy=800, cx=320, cy=240, width=640, height=480)
    with pytest.raises(ValueError, match="cx"):
        linereg.Camera(fx=800, fy=800, cx=float("nan"), cy=240, width=640, height=480)
    with pytest.raises(linereg.InvalidInputError, match="width"):
        linereg.Camera(fx=800, fy=800, cx=320, cy=240, width=0, height=480)
    with pytest.raises(linereg.InvalidInputError, match="dist"):
        linereg.Camera(fx=800, fy=800, cx=320, cy=240, width=640, height=480, dist=(0.1,))


def test_camera_from_dict_names_missing_keys():
    with pytest.raises(linereg.InvalidInputError, match=r"cam\.json: missing key.*fy"):
        linereg.Camera.from_dict({"fx": 1, "cx": 1, "cy": 1, "width": 2, "height": 2}, source="cam.json")


@pytest.mark.parametrize(
    ("model", "accepted"),
    [
        ("none", True),
        ("opencv_radtan_k1k2p1p2", True),  # the names ../shared/data uses
        ("opencv_radtan_k1k2p1p2k3", True),
        ("OPENCV", True),
        ("opencv_fisheye", False),  # k1-k4 of another projection: taken for k1 k2 p1 p2 it was silently wrong
        ("Kannala-Brandt", False),
        ("equidistant", False),
        ("omni", False),
    ],
)
def test_a_camera_of_another_lens_model_is_refused_by_name(model, accepted):
    d = {"fx": 500, "fy": 500, "cx": 320, "cy": 240, "width": 640, "height": 480}
    d["distortion"] = {"model": model, "coeffs": [0.1, 0.01, 0.001, 0.0001]}
    if accepted:
        assert linereg.Camera.from_dict(d).dist == (0.1, 0.01, 0.001, 0.0001)
    else:
        with pytest.raises(linereg.InvalidInputError, match=f"cam.json: distortion model '{model}'"):
            linereg.Camera.from_dict(d, source="cam.json")


@pytest.mark.parametrize(
    ("lines2d", "lines3d", "match"),
    [
        (np.zeros((10, 3)), np.ones((10, 6)), "lines2d.*shape"),
        (np.full((10, 4), np.nan), np.ones((10, 6)), "lines2d.*NaN"),
        (np.random.default_rng(0).random((10, 4)), np.ones((10, 5)), "lines3d.*shape"),
        (
            np.random.default_rng(0).random((2, 4)),
            np.random.default_rng(0).random((10, 6)),
            "lines2d.*at least",
        ),
        ("not an array", np.ones((10, 6)), "lines2d"),
        # a unit gone wrong: squares of it overflow (the map's corner search crashed in scipy)
        (
            np.random.default_rng(0).random((10, 4)),
            np.r_[np.random.default_rng(0).random((9, 6)), [[1e200, 0, 0, 2e200, 0, 0]]],
            r"lines3d.*beyond.*\(row 9\)",
        ),
        (
            np.r_[np.random.default_rng(0).random((9, 4)), [[0, 0, 1e12, 5]]],
            np.random.default_rng(0).random((10, 6)),
            r"lines2d.*beyond.*\(row 9\)",
        ),
    ],
)
def test_register_rejects_malformed_input(camera, lines2d, lines3d, match):
    with pytest.raises(linereg.InvalidInputError, match=match):
        linereg.register(lines2d, lines3d, camera)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: linereg.Camera(fx=1e200, fy=1e200, cx=320, cy=240, width=640, height=480), "fx"),
        (lambda: linereg.Camera(fx=800, fy=800, cx=320, cy=240, width=10**12, height=480), "width"),
        (lambda: linereg.Prior(position=(1e200, 0.0, 0.0), radius_m=30.0), "prior position"),
    ],
)
def test_numbers_no_camera_or_place_can_have_are_refused_by_name(make, match):
    with pytest.raises(linereg.InvalidInputError, match=match):
        make()


def test_register_rejects_a_non_camera():
    rng = np.random.default_rng(0)
    with pytest.raises(linereg.InvalidInputError, match="camera"):
        linereg.register(rng.random((10, 4)), rng.random((10, 6)), {"fx": 800})


def test_config_from_dict_overrides_and_rejects_unknown_keys():
    config = RegisterConfig.from_dict({"score": {"distance_px": 3.0}, "min_inliers": 9})
    assert config.score.distance_px == 3.0 and config.min_inliers == 9
    with pytest.raises(linereg.InvalidInputError, match=r"config\.score\.nope"):
        RegisterConfig.from_dict({"score": {"nope": 1}})


@pytest.mark.parametrize("seed", range(5))
def test_lines_without_structure_fail_with_a_reason_not_an_exception(camera, seed):
    """Random 2D and 3D lines hold no pose: the answer is "not found" with a reason, never a claimed pose."""
    rng = np.random.default_rng(seed)
    lines2d = rng.uniform(0, 480, (40, 4))
    lines3d = rng.uniform(-1, 1, (40, 6)) + np.array([0, 0, 5, 0, 0, 5])
    result = linereg.register(lines2d, lines3d, camera)
    assert isinstance(result, linereg.Registration)
    assert not result.success and result.reason
    assert result.cam_from_world.shape == (4, 4) and result.matches.shape == (0, 2)


def test_a_map_too_small_to_pose_says_whether_the_map_or_the_prior_left_too_few(camera, rng):
    lines2d = rng.uniform(0, 480, (40, 4))
    tiny = linereg.LineMap.from_segments(np.array([[0.0, 0, 5, 1, 0, 5], [0, 0, 5, 0, 1, 5]]))
    result = linereg.localize_segments(lines2d, tiny, camera)
    assert not result.success and result.reason.startswith("the map has only 2 segments")
    far = linereg.Prior(position=np.array([1000.0, 0, 0]), radius_m=1.0)
    line_map = linereg.LineMap.from_segments(rng.uniform(-1, 1, (40, 6)) + np.array([0, 0, 5, 0, 0, 5]))
    result = linereg.localize_segments(lines2d, line_map, camera, prior=far)
    assert not result.success and result.reason.startswith("the prior leaves only")
