"""Corners and free ends (``points.py``): the candidate pairs of the corner test are cut to those whose ends
lie close enough to make a corner, and the corners are those of every end pair within the widest reach."""

import numpy as np

from linereg.config import PointsConfig
from linereg.points import _corners, _near_end_pairs, image_points, map_gap_m, map_points


def every_pair_within(ends: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The plain rule: segment pairs a < b with an end of each within ``radius``, in increasing a n + b."""
    n = len(ends)
    points = ends.reshape(2 * n, -1)
    dist = np.linalg.norm(points[:, None] - points[None], axis=2)
    i, j = np.nonzero(dist <= radius)
    a, b = i // 2, j // 2
    keep = a < b
    key = np.unique(a[keep] * n + b[keep])
    return key // n, key % n


def test_the_cut_pairs_make_the_same_corners_as_every_pair_within_the_widest_reach(rng):
    """On random segments in 2D and 3D (short and long, a lattice of window-like edges beside a few long
    ones), the corners found from ``_near_end_pairs`` are those found from every end pair within the
    widest reach, in the same order; the cut leaves out pairs (it does cut)."""
    config = PointsConfig()
    cut = 0
    for trial in range(60):
        dim = 2 if trial % 2 else 3
        n = int(rng.integers(20, 300))
        start = rng.uniform(0.0, 20.0, (n, dim))
        length = np.where(rng.uniform(size=n) < 0.05, rng.uniform(5.0, 30.0, n), rng.uniform(0.2, 1.5, n))
        direction = rng.normal(size=(n, dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        ends = np.stack([start, start + length[:, None] * direction], axis=1)
        gap = 0.3
        unit = direction
        reach = gap + config.gap_fraction * length
        a, b = _near_end_pairs(ends, reach, config.line_gap)
        want_a, want_b = every_pair_within(ends, float(reach.max()))
        assert np.isin(a * n + b, want_a * n + want_b).all()  # a subset of the plain rule's pairs
        cut += len(want_a) - len(a)
        got = _corners(ends, unit, length, a, b, gap, config)
        want = _corners(ends, unit, length, want_a, want_b, gap, config)
        np.testing.assert_array_equal(a[got[0]], want_a[want[0]])
        np.testing.assert_array_equal(b[got[0]], want_b[want[0]])
        for g, w in zip(got[1:], want[1:], strict=True):
            np.testing.assert_array_equal(g[got[0]], w[want[0]])
    assert cut > 0


def test_points_of_segments_meeting_at_a_corner_and_free_ends():
    """Two segments meeting at right angles make one corner (weight 2) and two free ends; the image
    version does the same in pixels."""
    config = PointsConfig()
    segments = np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], [0.02, 0.0, 0.0, 0.02, 1.0, 0.0]])
    points = map_points(segments, config, map_gap_m(segments, config))
    assert len(points.positions) == 3 and sorted(points.weight) == [1.0, 1.0, config.corner_weight]
    pixels = image_points(np.array([[0.0, 0.0, 100.0, 0.0], [2.0, 0.0, 2.0, 100.0]]), config)
    assert len(pixels.positions) == 3
