"""2D line detection: known edges on synthetic images, input kinds, bad input, merging, real photos."""

import json
import math
import pathlib

import cv2
import numpy as np
import pytest

import linereg
from linereg.config import LineDetectConfig
from linereg.errors import InvalidInputError
from linereg.lines2d import along_border, detect, frame_margins, lsd_segments, merge_collinear, to_gray8

DATA = pathlib.Path("/work/shared/data")
# a tilted quadrilateral: four long edges at various angles
QUAD = np.array([[120.3, 90.7], [505.2, 130.4], [470.8, 400.1], [150.6, 370.9]])


def quad_edges(quad: np.ndarray) -> np.ndarray:
    """Returns (4, 4) the true edges of a polygon."""
    return np.c_[quad, np.roll(quad, -1, axis=0)]


def polygon_image(quad, rng, shape=(480, 640), fg=70.0, bg=180.0, noise=2.0, supersample=4) -> np.ndarray:
    """Returns a (H, W) uint8 image of a filled polygon, anti-aliased by supersampling, with noise."""
    s = supersample
    big = np.full((shape[0] * s, shape[1] * s), bg, dtype=np.float32)
    pts = np.round(((quad + 0.5) * s - 0.5) * 16).astype(np.int32)  # pixel centres at integers
    cv2.fillPoly(big, [pts], fg, lineType=cv2.LINE_8, shift=4)
    img = cv2.resize(big, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    img += rng.normal(0.0, noise, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def matches_of(truth: np.ndarray, found: np.ndarray, dist_px=1.5, angle_deg=1.0) -> np.ndarray:
    """Returns (len(found),) bool: segments lying on the true segment's line (both endpoints, angle)."""
    p, q = truth[:2], truth[2:]
    d = (q - p) / np.linalg.norm(q - p)
    normal = np.array([-d[1], d[0]])
    ends = found.reshape(-1, 2, 2)
    dist = np.abs((ends - p) @ normal).max(axis=1)
    fd = found[:, 2:] - found[:, :2]
    cos = np.abs(fd @ d) / np.linalg.norm(fd, axis=1)
    return (dist <= dist_px) & (cos >= math.cos(math.radians(angle_deg)))


def assert_edges_found(found: np.ndarray, truths: np.ndarray, min_cover: float = 0.85) -> None:
    for truth in truths:
        on_line = found[matches_of(truth, found)]
        assert len(on_line) == 1, f"edge {truth} found as {len(on_line)} segments"
        length = np.linalg.norm(truth[2:] - truth[:2])
        assert np.linalg.norm(on_line[0, 2:] - on_line[0, :2]) >= min_cover * length


def test_polygon_edges_are_found_precisely(camera, rng):
    found = detect(polygon_image(QUAD, rng), camera)
    assert found.dtype == np.float64 and found.shape[1] == 4
    assert_edges_found(found, quad_edges(QUAD))


def test_fragments_are_merged_into_one_segment(camera, rng):
    img = polygon_image(QUAD, rng)
    # blobs of background across the top edge break it into pieces for LSD
    for t in (0.2, 0.4, 0.6, 0.8):
        centre = QUAD[0] + t * (QUAD[1] - QUAD[0])
        cv2.circle(img, tuple(round(float(c)) for c in centre), 3, 125, -1)
    raw = lsd_segments(img, LineDetectConfig())
    top = quad_edges(QUAD)[0]
    assert matches_of(top, raw, dist_px=2.0).sum() >= 3  # LSD alone sees fragments
    assert_edges_found(detect(img, camera), quad_edges(QUAD)[:1], min_cover=0.8)


@pytest.mark.parametrize(
    "convert",
    [
        lambda g: g,
        lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGR),
        lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGRA),
        lambda g: g[:, :, None],
        lambda g: g.astype(np.uint16) * 40 + 3000,  # 16-bit, only a narrow band of the range used
        lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGR).astype(np.uint16) * 257,
        lambda g: g.astype(np.float32) / 255.0,
        lambda g: g.astype(np.float64),
        lambda g: g.astype(np.float64) * 1000.0 - 5.0,  # arbitrary float range: stretched
    ],
    ids=["gray8", "bgr8", "bgra8", "hw1", "gray16", "bgr16", "float01", "float255", "float-any"],
)
def test_input_kinds_give_the_same_edges(camera, rng, convert):
    image = convert(polygon_image(QUAD, rng))
    assert_edges_found(detect(image, camera), quad_edges(QUAD))


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((240, 320), np.uint8),  # size differs from the camera
        np.zeros((480, 640), np.int32),
        np.zeros((480, 640), bool),
        np.zeros(640 * 480, np.uint8),
        np.zeros((480, 640, 2), np.uint8),
        np.full((480, 640), np.nan, np.float32),
        [[0, 1], [2, 3]],
    ],
    ids=["size", "int32", "bool", "1d", "2-channel", "nan", "list"],
)
def test_bad_input_names_image(camera, image):
    with pytest.raises(InvalidInputError, match="image"):
        detect(image, camera)


def test_distorted_image_gives_undistorted_segments(rng):
    from linereg.sim.render import _distort

    camera = linereg.Camera(600.0, 600.0, 320.0, 240.0, 640, 480, dist=(-0.25, 0.08, 0.0, 0.0))
    image = _distort(polygon_image(QUAD, rng).astype(np.float32), camera)
    found = detect(np.clip(image, 0, 255).astype(np.uint8), camera)
    for truth in quad_edges(QUAD):  # straight again after undistortion, a little less precise
        assert matches_of(truth, found, dist_px=2.0, angle_deg=1.5).any()


def test_merge_collinear_rules():
    cfg = LineDetectConfig()
    chain = np.array([[10.0 + 30 * k, 50.0, 35.0 + 30 * k, 50.2] for k in range(6)])  # gaps of 5 px
    merged = merge_collinear(chain[np.random.default_rng(0).permutation(6)], 16.0, cfg)
    assert merged.shape == (1, 4)
    assert np.allclose(sorted([merged[0, 0], merged[0, 2]]), [10.0, 185.0], atol=0.5)
    parallel = np.array([[0.0, 0.0, 100.0, 0.0], [110.0, 5.0, 200.0, 5.0]])  # offset 5 px: two lines
    assert len(merge_collinear(parallel, 16.0, cfg)) == 2
    far = np.array([[0.0, 0.0, 100.0, 0.0], [140.0, 0.0, 200.0, 0.0]])  # gap 40 px > 16 px
    assert len(merge_collinear(far, 16.0, cfg)) == 2
    crossing = np.array([[0.0, 0.0, 100.0, 0.0], [50.0, -50.0, 50.0, 50.0]])
    assert len(merge_collinear(crossing, 16.0, cfg)) == 2
    flipped = np.array([[0.0, 0.0, 100.0, 0.0], [150.0, 0.3, 105.0, 0.3]])  # opposite polarity still merges
    assert len(merge_collinear(flipped, 16.0, cfg)) == 1
    assert merge_collinear(np.zeros((0, 4)), 16.0, cfg).shape == (0, 4)


def test_opencv4_shaped_output_is_accepted(monkeypatch):
    class Old:
        def detect(self, image):
            return (np.array([[[1.0, 2.0, 30.0, 2.0]]], dtype=np.float32), None, None, None)

    monkeypatch.setattr(cv2, "createLineSegmentDetector", lambda *a: Old())
    assert lsd_segments(np.zeros((100, 100), np.uint8), LineDetectConfig()).shape == (1, 4)


@pytest.mark.skipif(not (DATA / "home_kinect").is_dir(), reason="shared data absent")
@pytest.mark.parametrize("folder", ["home_kinect", "kitti_obj_000002"])
def test_real_photos(folder):
    meta = json.loads((DATA / folder / "cameras.json").read_text())
    entry = (meta if isinstance(meta, list) else meta.get("images", meta.get("cameras", [meta])))[0]
    camera = linereg.Camera.from_dict(entry)
    image = cv2.imread(str(DATA / folder / entry["file"]), cv2.IMREAD_UNCHANGED)
    found = detect(image, camera)
    diagonal = math.hypot(camera.width, camera.height)
    assert len(found) >= 50 and np.isfinite(found).all()
    assert (np.linalg.norm(found[:, 2:] - found[:, :2], axis=1) >= 0.025 * diagonal).all()


def test_picture_border_and_flat_frame_give_no_segments(camera, rng):
    img = polygon_image(QUAD, rng)
    framed = img.copy()
    framed[:, :6], framed[:, -7:], framed[:5], framed[-5:] = 255, 255, 255, 255  # a Kinect-like frame
    np.testing.assert_array_equal(frame_margins(framed), [6, 5, 7, 5])
    np.testing.assert_array_equal(frame_margins(img), [0, 0, 0, 0])
    for picture in (framed, img):
        found = detect(picture, camera)
        assert_edges_found(found, quad_edges(QUAD))
        assert len(found) == 4  # the frame's inner edges and the picture's end are no lines
    # a segment along the border but across it (or far from it) is kept
    cfg = LineDetectConfig()
    segments = np.array([[1.0, 10.0, 1.5, 300.0], [1.0, 10.0, 60.0, 300.0], [100.0, 477.5, 500.0, 478.0]])
    np.testing.assert_array_equal(along_border(segments, (480, 640), np.zeros(4), cfg), [True, False, True])


@pytest.mark.parametrize("threads", [1, 2, 3, 4])
def test_parallel_bands_find_each_edge_once(camera, rng, threads):
    # the top and bottom edges cross every band boundary: their pieces must be joined again
    found = detect(polygon_image(QUAD, rng), camera, LineDetectConfig(lsd_bands=threads))
    assert_edges_found(found, quad_edges(QUAD))
    assert len(found) == 4


def test_bands_keep_short_segments_near_a_cut(camera, rng):
    img = polygon_image(QUAD, rng)
    cv2.rectangle(img, (300, 200), (340, 230), 20, -1)  # a small box straddling the cut at x = 320
    one = detect(img, camera, LineDetectConfig(lsd_bands=1))
    two = detect(img, camera, LineDetectConfig(lsd_bands=2))
    assert len(one) == len(two) == 8
    for truth in one:  # the same segments, within a pixel
        assert matches_of(truth, two, dist_px=1.0).sum() == 1


def test_16bit_stretch_keeps_dead_pixels_dark_and_hot_ones_bright(rng):
    img = (polygon_image(QUAD, rng).astype(np.uint16) * 40 + 3000).astype(np.uint16)
    img[5, 5], img[6, 6] = 0, 65535
    gray = to_gray8(img)
    assert gray.dtype == np.uint8 and gray[5, 5] == 0 and gray[6, 6] == 255
    assert gray.max() == 255 and gray.min() == 0 and np.percentile(gray, 50) > 100  # the picture's range used


def test_bands_see_the_same_subsampled_pixels_away_from_the_cut(rng):
    img = polygon_image(QUAD, rng)
    one = lsd_segments(img, LineDetectConfig(lsd_bands=1))
    two = lsd_segments(img, LineDetectConfig(lsd_bands=2))
    # the right edge (x ~ 470-505) is in the second band (starting near x = 300), far from the cut
    right_one = one[np.minimum(one[:, 0], one[:, 2]) > 400]
    right_two = two[np.minimum(two[:, 0], two[:, 2]) > 400]
    assert len(right_one) >= 1
    np.testing.assert_allclose(np.sort(right_one, axis=0), np.sort(right_two, axis=0), atol=1e-4)


def test_segments_do_not_depend_on_opencv_threads(camera, rng):
    # service workers hold OpenCV to one thread: they must see the segments an interactive run sees
    img = polygon_image(QUAD, rng)
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        serial = detect(img, camera)
        cv2.setNumThreads(2)
        threaded = detect(img, camera)
    finally:
        cv2.setNumThreads(before)
    np.testing.assert_array_equal(serial, threaded)
