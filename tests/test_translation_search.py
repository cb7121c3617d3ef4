"""Translation search internals (paper III-C): the fast paths equal their plain definitions."""

import numpy as np
import pytest

from linereg.config import MatchConfig
from linereg.directions import DirectionClusters
from linereg.sim.synthetic import paper_scene
from linereg.translation_inliers import _near_loose
from linereg.translation_pairs import Pairs, compatible_pairs
from linereg.translation_search import _fullest_cells, vote_cells


def _reference_fullest(T, key, top):
    """The plain definition: np.unique counts, stable ranking by count (ties: key order), bincount means."""
    cells, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    best = np.argsort(-count, kind="stable")[:top]
    sums = np.stack([np.bincount(inverse, weights=T[:, k], minlength=len(cells)) for k in range(3)], 1)
    return sums[best] / count[best, None], count[best]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("top", [1, 4, 32])
def test_fullest_cells_equals_unique_counts(seed, top):
    rng = np.random.default_rng(seed)
    # a few full cells among many single votes, with ties, as the search makes them
    key = np.r_[
        rng.integers(0, 1 << 60, 3000), np.repeat(rng.integers(0, 1 << 60, 40), rng.integers(1, 9, 40))
    ]
    key = rng.permutation(key)
    T = rng.normal(size=(len(key), 3))
    mean, count = _fullest_cells(T, key, top)
    ref_mean, ref_count = _reference_fullest(T, key, top)
    np.testing.assert_array_equal(count, ref_count)
    np.testing.assert_array_equal(mean, ref_mean)  # same sums in the same order: bit for bit


def test_fullest_cells_with_few_votes_or_cells():
    T = np.arange(12.0).reshape(4, 3)
    for key in (np.array([5, 5, 5, 5]), np.array([3, 1, 2, 1]), np.array([7])):
        mean, count = _fullest_cells(T[: len(key)], key, 8)
        ref_mean, ref_count = _reference_fullest(T[: len(key)], key, 8)
        np.testing.assert_array_equal(count, ref_count)
        np.testing.assert_array_equal(mean, ref_mean)


def test_vote_cells_finds_the_true_translation_among_noise():
    rng = np.random.default_rng(0)
    t = np.array([0.5, -1.0, 8.0])
    T = np.r_[t + rng.normal(scale=0.01, size=(50, 3)), rng.uniform(-20, 20, size=(2000, 3))]
    best = vote_cells(T, np.eye(3), cell=0.2, top=4)
    assert len(best) >= 1 and np.linalg.norm(best[0] - t) < 0.05


def test_near_loose_equals_the_angle_test():
    scene = paper_scene(np.random.default_rng(3))
    R, t = scene.cam_from_world[:3, :3], scene.cam_from_world[:3, 3]
    none = DirectionClusters(np.zeros((0, 3)), np.full(len(scene.lines3d), -1, dtype=np.int64), np.zeros(0))
    pairs = compatible_pairs(scene.lines2d, scene.lines3d, scene.camera, R, none, 6.0)
    T = t + np.random.default_rng(1).normal(scale=0.05, size=(6, 3))
    h, i, j = _near_loose(pairs, T, MatchConfig().distance_px)
    # the definition: the 3D midpoint's angle from i's bearing, seen along the direction, within the tolerance
    loose = np.flatnonzero(pairs.combo_g >= pairs.num_clusters)
    side, bearing, turn = pairs.combo_normal[loose], pairs.combo_bearing[loose], pairs.combo_turn[loose]
    x = pairs.point[pairs.loose[1]][None] + T[:, None]
    phi = np.arctan2(np.einsum("hck,ck->hc", x, side), np.einsum("hck,ck->hc", x, bearing))
    ref_h, ref_c = np.nonzero(np.abs(phi) <= 1.5 * MatchConfig().distance_px * turn)
    np.testing.assert_array_equal(h, ref_h)
    np.testing.assert_array_equal(j, pairs.loose[1][ref_c])
    np.testing.assert_array_equal(i, pairs.loose[0][ref_c])
    assert len(h) > 0


def test_pairs_expand_in_pair_order():
    scene = paper_scene(np.random.default_rng(5))
    R = scene.cam_from_world[:3, :3]
    none = DirectionClusters(np.zeros((0, 3)), np.full(len(scene.lines3d), -1, dtype=np.int64), np.zeros(0))
    pairs: Pairs = compatible_pairs(scene.lines2d, scene.lines3d, scene.camera, R, none, 6.0)
    some = np.arange(0, len(pairs.combo_i), 3)
    combo, j = pairs.expand(some)
    assert pairs.size == len(pairs.i) == pairs.counts().sum()
    keep = np.isin(np.repeat(np.arange(len(pairs.combo_i)), pairs.counts()), some)
    np.testing.assert_array_equal(j, pairs.j[keep])
    np.testing.assert_array_equal(pairs.combo_i[combo], pairs.i[keep])
