import numpy as np
import pytest

from linereg.config import ParallelConfig
from linereg.errors import InvalidInputError
from linereg.geometry import axis_angle_deg
from linereg.parallel import diverse_order, parallel_clusters, tolerance_rad


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def segments_along(
    rng, directions, counts, jitter_deg=0.0, length_m=(0.5, 2.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((M, 6) segments, (M,) true direction index) along ``directions`` (each tilted by up to
    ``jitter_deg``, with a random endpoint order), centres in [-5, 5]^3."""
    segs, labels = [], []
    for k, (d, n) in enumerate(zip(unit(directions), counts, strict=True)):
        tilt = rng.normal(size=(n, 3))
        tilt -= (tilt @ d)[:, None] * d  # perpendicular perturbation of about jitter_deg
        dirs = unit(d + np.radians(jitter_deg) * tilt / np.sqrt(2))
        dirs *= rng.choice([-1.0, 1.0], size=(n, 1))  # a 3D segment's endpoint order means nothing
        c = rng.uniform(-5, 5, (n, 3))
        half = rng.uniform(*length_m, (n, 1)) / 2
        segs.append(np.c_[c - half * dirs, c + half * dirs])
        labels += [k] * n
    return np.vstack(segs), np.array(labels)


def random_segments(rng, n) -> np.ndarray:
    c = rng.uniform(-5, 5, (n, 3))
    d = unit(rng.normal(size=(n, 3)))
    return np.c_[c - 0.5 * d, c + 0.5 * d]


def angle_deg(a, b) -> float:
    return axis_angle_deg(a, b)


DIRECTIONS = unit([[1.0, 0.2, 0.0], [-0.2, 1.0, 0.1], [0.0, -0.1, 1.0]])


def test_recovers_directions_and_memberships(rng):
    lines3d, truth = segments_along(rng, DIRECTIONS, [300, 200, 100], jitter_deg=0.2)
    lines3d = np.vstack([lines3d, random_segments(rng, 150)])
    clusters = parallel_clusters(lines3d)
    assert len(clusters) == 3
    for k, d in enumerate(DIRECTIONS):  # strongest first: the counts decide, the lengths are alike
        assert angle_deg(clusters.directions[k], d) < 0.1
        np.testing.assert_array_equal(clusters.labels[: len(truth)][truth == k], k)
    # random outliers join a cluster only when they happen to lie within their tolerance of it
    outliers = lines3d[len(truth) :]
    joined = clusters.labels[len(truth) :] >= 0
    d_out = unit(outliers[:, 3:] - outliers[:, :3])
    tolerance = tolerance_rad(np.linalg.norm(outliers[:, 3:] - outliers[:, :3], axis=1), ParallelConfig())
    close = np.max(np.abs(d_out @ clusters.directions.T), axis=1) >= np.cos(tolerance)
    np.testing.assert_array_equal(joined, close)


def test_tolerance_grows_for_short_segments():
    config = ParallelConfig(parallel_angle_deg=1.0, noise_m=0.02, max_angle_deg=8.0)
    tol = np.degrees(tolerance_rad(np.array([100.0, 2.0, 0.5, 0.01]), config))
    assert tol[0] == pytest.approx(1.0, abs=0.01)  # long: the paper's 1 degree
    assert tol[1] == pytest.approx(np.hypot(1.0, np.degrees(2 * np.sqrt(2) * 0.02 / 2.0)))
    assert tol[3] == pytest.approx(8.0)  # capped
    assert np.all(np.diff(tol) >= 0)
    fixed = tolerance_rad(np.array([0.1, 10.0]), ParallelConfig(noise_m=0.0))
    np.testing.assert_allclose(np.degrees(fixed), 1.0)


def test_short_noisy_segments_still_cluster(rng):
    # real maps (RGB-D, LiDAR): 0.3-0.8 m segments 2-3 degrees off their direction; 1 degree finds nothing
    lines3d, truth = segments_along(rng, DIRECTIONS, [60, 40, 30], jitter_deg=2.5, length_m=(0.3, 0.8))
    lines3d = np.vstack([lines3d, random_segments(rng, 60)])
    clusters = parallel_clusters(lines3d)
    assert len(clusters) == 3
    for k, d in enumerate(DIRECTIONS):
        assert angle_deg(clusters.directions[k], d) < 1.0
        assert np.mean(clusters.labels[: len(truth)][truth == k] == k) > 0.8
    strict = parallel_clusters(lines3d, ParallelConfig(noise_m=0.0))
    assert strict.support.sum() < 0.5 * clusters.support.sum()


def test_support_order_and_conventions(rng):
    lines3d, _ = segments_along(rng, DIRECTIONS, [50, 80, 20])
    clusters = parallel_clusters(lines3d)
    lengths = np.linalg.norm(lines3d[:, 3:] - lines3d[:, :3], axis=1)
    assert np.all(np.diff(clusters.support) <= 0)
    for k in range(len(clusters)):
        assert clusters.support[k] == pytest.approx(lengths[clusters.members(k)].sum())
    np.testing.assert_allclose(np.linalg.norm(clusters.directions, axis=1), 1.0)
    assert np.all(clusters.directions[:, 2] >= 0)
    assert angle_deg(clusters.directions[0], DIRECTIONS[1]) < 1e-5  # noise-free: exact
    assert clusters.labels.dtype == np.int64


def test_top_k_and_min_lines(rng):
    lines3d, _ = segments_along(rng, unit([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]]), [40, 30, 20, 2])
    assert len(parallel_clusters(lines3d)) == 3  # top_k = 3
    clusters = parallel_clusters(lines3d, ParallelConfig(top_k=5))
    assert len(clusters) == 3  # the pair along (1, 1, 1) is below min_lines
    assert np.all(clusters.labels[-2:] == -1)


def test_near_duplicate_directions_merge(rng):
    # two sets 1.5 degrees apart: RANSAC (1 deg) finds them apart, merging (3 deg) joins them
    d2 = unit(DIRECTIONS[0] + np.tan(np.radians(1.5)) * unit(np.cross(DIRECTIONS[0], [0, 0, 1])))
    lines3d, _ = segments_along(rng, np.array([DIRECTIONS[0], d2]), [60, 40])
    clusters = parallel_clusters(lines3d)
    assert len(clusters) == 1
    assert np.all(clusters.labels == 0)
    # without the noise slack (1 degree for every segment) and without merging, they stay apart
    apart = parallel_clusters(lines3d, ParallelConfig(merge_angle_deg=1.0, noise_m=0.0))
    assert len(apart) == 2


def test_deterministic_and_fast_on_many_segments(rng):
    lines3d, truth = segments_along(rng, DIRECTIONS, [3500, 3000, 2000], jitter_deg=0.3)
    lines3d = np.vstack([lines3d, random_segments(rng, 2000)])
    a, b = parallel_clusters(lines3d), parallel_clusters(lines3d)
    np.testing.assert_array_equal(a.labels, b.labels)
    for k, d in enumerate(DIRECTIONS):
        assert angle_deg(a.directions[k], d) < 0.05
        assert np.mean(a.labels[: len(truth)][truth == k] == k) > 0.99


def test_degenerate_inputs():
    empty = parallel_clusters(np.zeros((0, 6)))
    assert len(empty) == 0 and empty.labels.shape == (0,) and empty.directions.shape == (0, 3)
    zero = parallel_clusters(np.zeros((5, 6)))  # zero-length segments have no direction
    assert len(zero) == 0 and np.all(zero.labels == -1)
    one_family = parallel_clusters(np.c_[np.zeros((4, 3)), np.tile([0.0, 0.0, -1.0], (4, 1))])
    assert len(one_family) == 1 and np.allclose(one_family.directions[0], [0, 0, 1])


@pytest.mark.parametrize("bad", [np.zeros((3, 4)), np.zeros(6), [[0.0, 0.0, 0.0, np.inf, 1.0, 1.0]]])
def test_bad_input(bad):
    with pytest.raises(InvalidInputError):
        parallel_clusters(bad)


def test_near_parallel_clusters_do_not_push_out_a_distinct_direction(rng):
    # a street map: long ground contours along x and along a direction 20 degrees off it outweigh the short
    # vertical edges; the vertical is kept among the top 3 because it adds what the others cannot
    x, diagonal, cross, up = unit([[1, 0, 0], [np.cos(0.35), np.sin(0.35), 0], [0, 1, 0], [0, 0, 1]])
    lines3d, _ = segments_along(rng, [x, diagonal, cross, up], [60, 40, 40, 40], length_m=(1.5, 2.5))
    shorter_up = np.abs(lines3d[:, 5] - lines3d[:, 2]) > 1.0  # the vertical segments: make them short
    mid = 0.5 * (lines3d[shorter_up, :3] + lines3d[shorter_up, 3:])
    half = np.array([0.0, 0.0, 0.5])
    lines3d[shorter_up] = np.c_[mid - half, mid + half]
    clusters = parallel_clusters(lines3d)
    assert len(clusters) == 3
    assert min(angle_deg(d, up) for d in clusters.directions) < 1.0
    assert np.all(np.diff(clusters.support) <= 0)  # still strongest first


def test_diverse_order():
    directions = unit([[1, 0, 0], [1, 0.05, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_array_equal(diverse_order(directions, np.array([10.0, 9.0, 5.0, 4.0]), 3), [0, 2, 3])
    np.testing.assert_array_equal(diverse_order(directions, np.array([10.0, 9.0, 5.0, 4.0]), 9), [0, 2, 3, 1])
    assert len(diverse_order(np.zeros((0, 3)), np.zeros(0), 3)) == 0


def test_scoring_on_a_small_sample_finds_the_same_directions(rng):
    # hypotheses are scored on ``score_sample`` random segments; a small sample still ranks the true ones
    lines3d, _ = segments_along(rng, DIRECTIONS, [600, 400, 200], jitter_deg=0.2)
    sampled = parallel_clusters(lines3d, ParallelConfig(score_sample=100))
    assert len(sampled) == 3
    for k, d in enumerate(DIRECTIONS):
        assert angle_deg(sampled.directions[k], d) < 0.1
