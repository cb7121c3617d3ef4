"""The overlay PNG of ``linereg localize --overlay`` / ``linereg demo``: legend and caption, readable at 640x480."""

import numpy as np
import pytest

from linereg.camera import Camera
from linereg.geometry import make_cam_from_world
from linereg.overlay import GREEN, GREY, RED, draw_overlay, overlay_caption
from linereg.registration import Registration

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
PHOTO = np.full((480, 640), 200, np.uint8)  # dimmed to 120 by the overlay; shaded boxes to 36


@pytest.fixture
def scene():
    """A square 5 m ahead, its four edges as map lines (the last two matched) and as 2D lines."""
    cam_from_world = make_cam_from_world(np.eye(3), np.array([0.0, 0.0, 5.0]))
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    lines3d = np.array([np.r_[corners[k], corners[(k + 1) % 4]] for k in range(4)])
    pixels = 500.0 * corners[:, :2] / 5.0 + [319.5, 239.5]
    lines2d = np.array([np.r_[pixels[k], pixels[(k + 1) % 4]] for k in range(4)]) + 3.0
    return cam_from_world, lines2d, lines3d


def near(picture: np.ndarray, color, tolerance: int = 12) -> np.ndarray:
    """Returns the (H, W) mask of pixels within ``tolerance`` of a BGR colour."""
    return (np.abs(picture.astype(int) - np.array(color)) <= tolerance).all(axis=2)


def legend_box(picture: np.ndarray) -> tuple[int, int, int, int]:
    """Returns (x0, y0, x1, y1) of the shaded legend box in the bottom-left quarter."""
    h, w = picture.shape[:2]
    quarter = picture[h // 2 :, : w // 2]
    ys, xs = np.nonzero(near(quarter, (36, 36, 36), 2))
    return xs.min(), h // 2 + ys.min(), xs.max(), h // 2 + ys.max()


def test_success_has_a_legend_of_the_three_colours_and_the_numbers(scene):
    cam_from_world, lines2d, lines3d = scene
    matches = np.array([[2, 2], [3, 3]])
    reg = Registration(True, cam_from_world=cam_from_world, matches=matches, num_inliers=42,
                       score=400.0, explained_fraction=0.5, runner_up_score=200.0, timings={"total": 0.25})  # fmt: skip
    picture = draw_overlay(PHOTO, CAMERA, lines2d, lines3d, reg)
    assert picture.shape == (480, 640, 3) and picture.dtype == np.uint8
    x0, y0, x1, y1 = legend_box(picture)
    assert x1 - x0 < 0.4 * 640 and y1 - y0 < 0.3 * 480  # small, and in a corner
    legend = picture[y0 : y1 + 1, x0 : x1 + 1]
    for color in (RED, GREEN, GREY):
        assert near(legend, color).sum() >= 10, color  # a sample line of each colour
    assert (legend > 200).all(axis=2).sum() > 100  # white text beside them
    assert near(picture[y1 + 5 :, :], RED).sum() == 0  # nothing but the photo below the box
    assert overlay_caption(reg) == "localized | 42 inliers, 50 % explained, ambiguity 0.50, 250 ms"


def test_caption_band_is_one_readable_line(scene):
    _, lines2d, lines3d = scene
    reason = "ambiguous: another pose explains the image as well " * 4
    reg = Registration(False, reason=reason, num_inliers=12, score=80.0, runner_up_score=80.0)
    picture = draw_overlay(PHOTO, CAMERA, lines2d, lines3d, reg)
    band = int(np.argmax(np.percentile(picture[:, :, 1], 10, axis=1) > 60))  # the first row below the band
    assert 14 <= band <= 40, band
    assert (picture[:band, :] > 200).all(axis=2).sum() > 200  # the text
    caption = overlay_caption(reg)
    assert caption.startswith(
        "not localized | 12 inliers, 0 % explained, ambiguity 1.00 | ambiguous: another pose"
    )


def test_failure_legend_lists_only_what_is_drawn(scene):
    _, lines2d, lines3d = scene
    reg = Registration(False, reason="too few segments")
    picture = draw_overlay(PHOTO, CAMERA, lines2d, lines3d, reg)
    x0, y0, x1, y1 = legend_box(picture)
    legend = picture[y0 : y1 + 1, x0 : x1 + 1]
    assert near(legend, RED).sum() >= 10
    assert near(legend, GREEN).sum() == 0 and near(picture[60:400], GREY, 6).sum() == 0  # no pose, no map
    assert y1 - y0 < 0.1 * 480  # one row


def test_a_caption_can_be_given(scene):
    cam_from_world, lines2d, lines3d = scene
    reg = Registration(True, cam_from_world=cam_from_world)
    default = draw_overlay(PHOTO, CAMERA, lines2d, lines3d, reg)
    titled = draw_overlay(PHOTO, CAMERA, lines2d, lines3d, reg, caption="ground truth")
    assert (default[:30] != titled[:30]).any() and (default[100:] == titled[100:]).all()
