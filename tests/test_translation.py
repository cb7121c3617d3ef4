"""Translation per rotation candidate (paper III-C): known answers on synthetic scenes, bad input."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from linereg.config import MatchConfig, TranslationConfig
from linereg.directions import DirectionClusters
from linereg.geometry import make_cam_from_world
from linereg.matching import match_matrix, match_segments, project_segments
from linereg.parallel import parallel_clusters
from linereg.sim.synthetic import paper_scene
from linereg.translation import estimate_translation, screen_translation
from linereg.translation_inliers import pair_inliers, pair_matches
from linereg.translation_pairs import compatible_pairs
from linereg.translation_search import _corner_ends, pair_hypotheses

MATCH = MatchConfig()


def _scene(seed, **kw):
    scene = paper_scene(np.random.default_rng(seed), **kw)
    return scene, parallel_clusters(scene.lines3d)


def _rel_error(t, scene):
    t_gt = scene.cam_from_world[:3, 3]
    return np.linalg.norm(t - t_gt) / np.linalg.norm(t_gt)


@pytest.mark.parametrize("seed", range(6))
def test_search_recovers_t_at_true_rotation(seed):
    scene, clusters = _scene(seed, outlier3d_fraction=0.3, outlier2d_fraction=0.3)
    R = scene.cam_from_world[:3, :3]
    h = estimate_translation(
        scene.lines2d, scene.lines3d, scene.camera, R, clusters, TranslationConfig(), MATCH
    )
    assert _rel_error(h.t, scene) < 0.01
    assert h.num_inliers == len(h.matches) >= 0.8 * len(scene.true_matches)
    assert h.matches.dtype == np.int64 and h.matches.shape[1] == 2
    truth = {tuple(m) for m in scene.true_matches.tolist()}
    assert np.mean([tuple(m) in truth for m in h.matches.tolist()]) > 0.8
    assert 0 <= h.runner_up_inliers < h.num_inliers


def test_search_survives_heavy_outliers():
    scene, clusters = _scene(3, outlier3d_fraction=0.6, outlier2d_fraction=0.6)
    R = scene.cam_from_world[:3, :3]
    h = estimate_translation(
        scene.lines2d, scene.lines3d, scene.camera, R, clusters, TranslationConfig(), MATCH
    )
    assert _rel_error(h.t, scene) < 0.02


def test_ransac_recovers_t_on_an_easy_scene():
    scene, clusters = _scene(0, num_lines=30, outlier3d_fraction=0.0, outlier2d_fraction=0.0, noise_px=1.0)
    R = scene.cam_from_world[:3, :3]
    config = TranslationConfig(method="ransac", ransac_iterations=3000)
    h = estimate_translation(scene.lines2d, scene.lines3d, scene.camera, R, clusters, config, MATCH)
    assert _rel_error(h.t, scene) < 0.1
    assert h.num_inliers >= 0.5 * len(scene.true_matches)


def test_wrong_rotation_gets_fewer_inliers():
    scene, clusters = _scene(1)
    R = scene.cam_from_world[:3, :3]
    wrong = Rotation.from_rotvec(np.radians(15.0) * np.array([0.6, -0.8, 0.0])).as_matrix() @ R
    args = (scene.lines2d, scene.lines3d, scene.camera)
    right = estimate_translation(*args, R, clusters, TranslationConfig(), MATCH)
    bad = estimate_translation(*args, wrong, clusters, TranslationConfig(), MATCH)
    assert bad.num_inliers < 0.5 * right.num_inliers


def test_pair_hypothesis_is_exact_without_noise():
    scene = _scene(2, outlier3d_fraction=0.0, outlier2d_fraction=0.0, noise_px=0.0)[0]
    R, t = scene.cam_from_world[:3, :3], scene.cam_from_world[:3, 3]
    exact = 0
    for i, j in scene.true_matches[:10]:
        lines2d, lines3d = scene.lines2d[[i]], scene.lines3d[[j]]
        pairs = compatible_pairs(lines2d, lines3d, scene.camera, R, _no_clusters(1), 1.0)
        T, depth = pair_hypotheses(lines2d, scene.camera, pairs, 0.0)
        if len(T):  # a segment clipped by the image border gives no hypothesis
            np.testing.assert_allclose(T[0], t, atol=1e-9)
            assert depth[0] > 0
            exact += 1
    assert exact >= 5


def test_pair_inliers_is_a_lower_bound_of_match_segments():
    scene, clusters = _scene(4)
    R, t = scene.cam_from_world[:3, :3], scene.cam_from_world[:3, 3]
    pairs = compatible_pairs(scene.lines2d, scene.lines3d, scene.camera, R, clusters, 6.0)
    T = t + np.random.default_rng(0).normal(scale=0.02, size=(5, 3))
    counts = pair_inliers(scene.lines2d, scene.camera, pairs, T, MATCH)
    for t_k, c in zip(T, counts, strict=True):
        exact = len(
            match_segments(scene.lines2d, scene.lines3d, scene.camera, make_cam_from_world(R, t_k), MATCH)
        )
        assert c <= exact and c >= 0.9 * exact


def test_match_segments_equals_dense_argmin():
    scene, _ = _scene(5)
    rng = np.random.default_rng(1)
    for _ in range(5):
        T = scene.cam_from_world.copy()
        T[:3, 3] += rng.normal(scale=0.03, size=3)
        projected, visible = project_segments(scene.lines3d, scene.camera, T, MATCH.min_depth_m)
        inlier, dist = match_matrix(scene.lines2d, projected, MATCH)
        dist = np.where(inlier & visible[None, :], dist, np.inf)
        rows = np.flatnonzero(np.isfinite(dist.min(axis=1)))
        expected = np.c_[rows, dist[rows].argmin(axis=1)]
        np.testing.assert_array_equal(
            match_segments(scene.lines2d, scene.lines3d, scene.camera, T, MATCH), expected
        )


def _no_clusters(m):
    return DirectionClusters(np.zeros((0, 3)), np.full(m, -1, dtype=np.int64), np.zeros(0))


@pytest.mark.parametrize("method", ["search", "ransac"])
def test_degenerate_inputs_return_zero_inliers(camera, method):
    config = TranslationConfig(method=method, ransac_iterations=50)
    R = np.eye(3)
    lines3d = np.array([[0.0, 0.0, 5.0, 1.0, 0.0, 5.0], [0.0, 1.0, 5.0, 1.0, 1.0, 5.0]])
    vertical = np.array([[100.0, 100.0, 100.0, 300.0], [200.0, 100.0, 200.0, 300.0]])  # no x-direction line
    clusters = DirectionClusters(np.array([[1.0, 0.0, 0.0]]), np.zeros(2, dtype=np.int64), np.array([2.0]))
    for lines2d, lines3d_, cl in [
        (vertical, lines3d, clusters),  # no compatible pair
        (np.zeros((0, 4)), lines3d, clusters),  # nothing seen
        (vertical, np.zeros((0, 6)), _no_clusters(0)),  # empty map
    ]:
        h = estimate_translation(lines2d, lines3d_, camera, R, cl, config, MATCH)
        assert h.num_inliers == 0 and h.matches.shape == (0, 2) and h.t.shape == (3,)


def test_single_cluster_does_not_raise():
    scene, clusters = _scene(6)
    one = DirectionClusters(
        clusters.directions[:1], np.where(clusters.labels == 0, 0, -1), clusters.support[:1]
    )
    only = np.flatnonzero(one.labels == 0)
    R = scene.cam_from_world[:3, :3]
    for method in ("search", "ransac"):
        config = TranslationConfig(method=method, ransac_iterations=200)
        h = estimate_translation(
            scene.lines2d,
            scene.lines3d[only],
            scene.camera,
            R,
            DirectionClusters(one.directions, np.zeros(len(only), dtype=np.int64), one.support),
            config,
            MATCH,
        )
        assert h.num_inliers == len(h.matches) and h.t.shape == (3,)


def test_bearing_prefilter_finds_the_same_inliers_as_the_plane_prefilter():
    scene, clusters = _scene(7, num_lines=150)
    R, t = scene.cam_from_world[:3, :3], scene.cam_from_world[:3, 3]
    pairs = compatible_pairs(scene.lines2d, scene.lines3d, scene.camera, R, clusters, 6.0)
    many = dataclasses.replace(pairs, direct=False)  # as on a big map
    T = t + np.random.default_rng(2).normal(scale=0.01, size=(4, 3))
    direct = set(
        zip(*(a.tolist() for a in pair_matches(scene.lines2d, scene.camera, pairs, T, MATCH)), strict=True)
    )
    near = set(
        zip(*(a.tolist() for a in pair_matches(scene.lines2d, scene.camera, many, T, MATCH)), strict=True)
    )
    assert near <= direct and len(near) >= 0.95 * len(direct) > 0


def test_search_works_without_clusters():
    scene = _scene(0)[0]
    R = scene.cam_from_world[:3, :3]
    h = estimate_translation(
        scene.lines2d,
        scene.lines3d,
        scene.camera,
        R,
        _no_clusters(len(scene.lines3d)),
        TranslationConfig(),
        MATCH,
    )
    assert _rel_error(h.t, scene) < 0.01  # every 3D segment is then its own direction group


def test_corner_ends_counts_shared_endpoints():
    lines2d = np.array([[0.0, 0.0, 100.0, 0.0], [101.0, 1.0, 100.0, 80.0], [300.0, 300.0, 350.0, 300.0]])
    np.testing.assert_array_equal(_corner_ends(lines2d, 4.0), [1, 1, 0])
    assert _corner_ends(np.array([[0.0, 0.0, 2.0, 0.0]]), 4.0)[0] == 0  # its own ends are not a corner


def test_screening_prefers_the_true_rotation_and_never_counts_more_than_the_full_search():
    scene, clusters = _scene(4, outlier3d_fraction=0.3, outlier2d_fraction=0.3)
    R = scene.cam_from_world[:3, :3]
    wrong = Rotation.from_rotvec(np.radians(90.0) * np.array([0.0, 1.0, 0.0])).as_matrix() @ R
    args = (scene.lines2d, scene.lines3d, scene.camera)
    config = TranslationConfig()
    right = screen_translation(*args, R, clusters, config, MATCH)
    assert right > 2 * screen_translation(*args, wrong, clusters, config, MATCH)
    assert right <= estimate_translation(*args, R, clusters, config, MATCH).num_inliers
    empty = DirectionClusters(np.zeros((0, 3)), np.full(len(scene.lines3d), -1), np.zeros(0))
    assert (
        screen_translation(scene.lines2d[:2], scene.lines3d[:2], scene.camera, R, empty, config, MATCH) == 0
    )
