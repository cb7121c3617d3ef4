"""The score's penalty: map length predicted in empty image areas, with and without shifts."""

import numpy as np
import pytest

from linereg.camera import Camera
from linereg.config import ScoreConfig
from linereg.score import _length_in_cells, image_lines, score_projected, shifted_values, summed_area


def sampled_in_cells(segments: np.ndarray, mask: np.ndarray, cell: float) -> float:
    """Every segment sampled every half cell, in plain Python: what the penalty is defined as."""
    total = 0.0
    h, w = mask.shape
    for x0, y0, x1, y1 in segments:
        length = float(np.hypot(x1 - x0, y1 - y0))
        count = max(int(np.ceil(length / (0.5 * cell))), 1)
        for s in range(count):
            t = (s + 0.5) / count
            c, r = int((x0 + t * (x1 - x0) + 0.5) / cell), int((y0 + t * (y1 - y0) + 0.5) / cell)
            if 0 <= r < h and 0 <= c < w and mask[r, c]:
                total += length / count
    return total


def test_the_penalty_samples_every_segment_that_reaches_an_empty_cell():
    rng = np.random.default_rng(3)
    mask = rng.random((30, 40)) < 0.03  # a few scattered empty cells, as beside a cluttered image
    mask[0, 0] = mask[-1, -1] = True  # and at the borders, where truncated indices land
    segments = np.concatenate(
        [
            rng.uniform(-50.0, 370.0, (400, 4)),  # across and beyond a 320 x 240 image
            rng.uniform(0.0, 320.0, (100, 4)),  # inside it
            rng.uniform(-9.0, 2.0, (50, 4)),  # tiny ones at the corner
        ]
    )
    got = _length_in_cells(np.ascontiguousarray(segments), mask, 8.0, summed_area(mask))
    want = sampled_in_cells(segments, mask, 8.0)
    assert want > 0
    assert abs(got - want) <= 1e-9 * want


def test_shifted_scores_of_a_sparse_image_are_the_scores_of_the_shifted_projections():
    # a sparse image leaves most of itself empty: shifts move map segments into and out of empty cells
    camera = Camera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    rng = np.random.default_rng(7)
    lines2d = rng.uniform([0, 0, 0, 0], [640, 480, 640, 480], (12, 4))
    projected = np.concatenate([lines2d[:8] + rng.normal(0.0, 2.0, (8, 4)), rng.uniform(0, 640, (30, 4))])
    config = ScoreConfig()
    image = image_lines(lines2d, camera, config)
    assert 0.1 < image.empty.mean() < 0.9
    shifts = np.concatenate([[[0.0, 0.0]], rng.uniform(-80.0, 80.0, (40, 2))])
    values = shifted_values(image, projected, shifts, config)
    rows = np.arange(len(projected))
    for shift, value in zip(shifts, values, strict=True):
        expected = score_projected(image, projected + np.tile(shift, 2), rows, config)
        assert abs(value - expected.value) <= 1e-9 * max(abs(expected.value), 1.0)
        moved = projected + np.tile(shift, 2)
        assert abs(expected.unexplained - sampled_in_cells(moved, image.empty, image.cell_px)) <= 1e-6


def test_the_coverable_length_is_the_line_length_near_surfaces_or_seen_map_lines():
    """A line counts where the map's surfaces or its projected visible lines come within the score's
    distance of it; a map without surfaces covers the whole image."""
    from linereg.score import coverable_length

    camera = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    config = ScoreConfig()
    lines = np.array([[20.0, 100, 300, 100], [340, 300, 620, 300], [400, 50, 600, 50]])
    image = image_lines(lines, camera, config)
    cell = config.distance_px
    surfaces = np.zeros((int(np.ceil(480 / cell)), int(np.ceil(640 / cell))), bool)
    surfaces[:, : int(320 / cell)] = True  # the left half of the image
    # a map line 10 m ahead projecting 2 px below the second image line
    z, y = 10.0, (302.0 - camera.cy) / camera.fy * 10.0
    part = np.array([[(340 - camera.cx) / camera.fx * z, y, z, (620 - camera.cx) / camera.fx * z, y, z]])
    eye = np.eye(4)
    got = coverable_length(image, camera, eye, part, surfaces, config)
    assert abs(got - 560.0) <= 2 * cell  # the first two lines, to a cell at their ends
    assert coverable_length(image, camera, eye, np.zeros((0, 6)), surfaces, config) == pytest.approx(
        280.0, abs=2 * cell
    )
    assert coverable_length(image, camera, eye, part, None, config) == image.total_length
