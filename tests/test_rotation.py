import numpy as np
import pytest

from linereg.config import RegisterConfig, RotationConfig
from linereg.directions import DirectionClusters
from linereg.geometry import make_cam_from_world, nearest_rotation, project_points, rotation_error_deg
from linereg.rotation import (
    RotationCandidate,
    _nearest_rotations,
    rotation_candidates,
    rotation_candidates_from_segments,
)


def rotation_about(axis, angle_deg: float) -> np.ndarray:
    """Returns the (3, 3) rotation by ``angle_deg`` about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


R_TRUE = rotation_about([1.0, 2.0, 0.5], 40.0)


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def clusters(directions, support=None) -> DirectionClusters:
    """Returns DirectionClusters of the given directions, support descending in the given order."""
    directions = unit(directions).reshape(-1, 3)
    support = np.arange(len(directions), 0, -1.0) if support is None else np.asarray(support, float)
    return DirectionClusters(directions, np.zeros(0, dtype=np.int64), support)


def vds_of(world_directions, R=R_TRUE) -> DirectionClusters:
    """Returns the exact vanishing directions of world directions under R, with the z >= 0 convention."""
    v = unit(world_directions) @ R.T
    return clusters(np.where(v[:, 2:3] < 0, -v, v))


def best_error(candidates: list[RotationCandidate], R=R_TRUE) -> float:
    return min(rotation_error_deg(c.R, R) for c in candidates)


def assert_proper(candidates: list[RotationCandidate]) -> None:
    for c in candidates:
        np.testing.assert_allclose(c.R @ c.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(c.R) == pytest.approx(1.0)


PERPENDICULAR = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
AT_60_DEG = [[1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0]]
GENERIC_3 = [[1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0], [0.3, -0.2, 1.0]]  # 60, 74, 98 deg apart


def test_two_perpendicular_pairs_give_the_papers_eight():
    candidates = rotation_candidates(vds_of(PERPENDICULAR), clusters(PERPENDICULAR))
    assert len(candidates) == 8  # 2 assignments x 4 signs (paper, Algorithm 1)
    assert best_error(candidates) < 1e-6
    assert_proper(candidates)
    assert {c.pairs[0][1] for c in candidates} == {0, 1}  # both assignments of VD 0
    assert all(len(c.pairs) == 2 for c in candidates)


def test_two_generic_pairs_keep_only_angle_consistent_signs():
    # flipping one 3D sign turns 60 deg into 120: such a pairing cannot be a rotation, so 4 of the 8 remain
    V, D = vds_of(AT_60_DEG), clusters(AT_60_DEG)
    candidates = rotation_candidates(V, D)
    assert len(candidates) == 4
    assert best_error(candidates) < 1e-6
    assert_proper(candidates)
    for c in candidates:
        (i, a, s1), (j, b, s2) = c.pairs
        cos_3d = s1 * s2 * D.directions[a] @ D.directions[b]
        assert V.directions[i] @ V.directions[j] == pytest.approx(cos_3d)


def test_each_candidate_maps_its_pairs():
    V, D = vds_of(AT_60_DEG), clusters(AT_60_DEG)
    for c in rotation_candidates(V, D):
        for i, a, s in c.pairs:
            assert V.directions[i] @ (c.R @ (s * D.directions[a])) == pytest.approx(1.0)
        assert c.residual_deg < 1e-6


def test_a_third_pair_validates():
    candidates = rotation_candidates(vds_of(GENERIC_3), clusters(GENERIC_3))
    # of 4 per VD pair, only the true rotation maps the third direction: it comes first, with three pairs;
    # the unconfirmed follow, at most ``max_unconfirmed`` of them
    assert rotation_error_deg(candidates[0].R, R_TRUE) < 1e-6
    assert len(candidates[0].pairs) == 3
    assert 1 < len(candidates) <= 1 + RotationConfig().max_unconfirmed
    assert all(len(c.pairs) == 2 for c in candidates[1:])
    strict = rotation_candidates(vds_of(GENERIC_3), clusters(GENERIC_3), RotationConfig(max_unconfirmed=0))
    assert len(strict) == 1 and len(strict[0].pairs) == 3
    # with the third direction on one side only there is nothing to validate against
    assert len(rotation_candidates(vds_of(GENERIC_3[:2]), clusters(GENERIC_3))) > 1


def test_a_spurious_confirmation_does_not_drop_the_truth():
    # the image's third VD is no map direction under the truth (clutter, a noisy VD) but happens to be the
    # third direction under a wrong pairing of the first two: that one is confirmed, the truth must follow
    two = rotation_candidates(vds_of(GENERIC_3[:2]), clusters(GENERIC_3[:2]))
    wrong = next(c.R for c in two if rotation_error_deg(c.R, R_TRUE) > 30.0)
    v2 = wrong @ unit(GENERIC_3[2])
    V = np.vstack([vds_of(GENERIC_3[:2]).directions, v2 if v2[2] >= 0 else -v2])
    candidates = rotation_candidates(clusters(V), clusters(GENERIC_3))
    assert rotation_error_deg(candidates[0].R, wrong) < 1e-6 and len(candidates[0].pairs) == 3
    assert best_error(candidates) < 1e-6
    assert (
        best_error(rotation_candidates(clusters(V), clusters(GENERIC_3), RotationConfig(max_unconfirmed=0)))
        > 30
    )


def test_manhattan_gives_the_cube_symmetries():
    axes = np.eye(3)
    candidates = rotation_candidates(vds_of(axes), clusters(axes), RotationConfig(max_candidates=100))
    assert len(candidates) == 24  # every proper symmetry of the cube explains three orthogonal VDs
    assert best_error(candidates) < 1e-6
    assert_proper(candidates)
    Rs = np.array([c.R for c in candidates])
    for n in range(len(Rs)):  # deduplicated: pairwise distinct (90 deg apart at least)
        others = np.delete(Rs, n, axis=0)
        assert min(rotation_error_deg(Rs[n], R) for R in others) > 89.0
    assert len(rotation_candidates(vds_of(axes), clusters(axes), RotationConfig(max_candidates=5))) == 5


def test_image_without_the_maps_second_direction():
    # the map's three strongest directions; the image shows the first and third only (a facade hidden)
    candidates = rotation_candidates(vds_of([GENERIC_3[0], GENERIC_3[2]]), clusters(GENERIC_3))
    assert best_error(candidates) < 1e-6


def test_order_follows_image_support():
    # VD 0 strongest: candidates pairing it (with either cluster: the angles decide) come first
    axes = np.eye(3)
    V = clusters(vds_of(axes).directions, support=[10.0, 5.0, 1.0])
    candidates = rotation_candidates(V, clusters(axes[:2]))
    scores = [c.score for c in candidates]
    assert scores == sorted(scores, reverse=True)
    assert [v for v, _, _ in candidates[0].pairs] == [0, 1]


def test_the_maps_weakest_cluster_as_the_images_strongest_vd():
    # a LiDAR street: the map's vertical edges are few (ground contours dominate) while the image's vertical
    # VD is its strongest; ranking by the product of supports pairs strongest with strongest and cuts the truth
    axes = np.eye(3)  # x street, y cross, z vertical
    V = clusters(vds_of([axes[2], axes[0]]).directions, support=[50.0, 30.0])
    D = clusters([axes[0], axes[2], axes[1]], support=[166.7, 49.0, 38.0])
    config = RotationConfig(max_candidates=8)
    assert best_error(rotation_candidates(V, D, config)) < 1e-6
    product = rotation_candidates(V, D, RotationConfig(max_candidates=8, ranking="product"))
    assert best_error(product) > 80.0


def test_noisy_directions_within_tolerance():
    rng = np.random.default_rng(5)
    V = vds_of(GENERIC_3)
    noisy = unit(V.directions + np.radians(0.5) * rng.normal(size=(3, 3)) / np.sqrt(3))
    candidates = rotation_candidates(clusters(noisy), clusters(GENERIC_3))
    assert len(candidates[0].pairs) == 3 and rotation_error_deg(candidates[0].R, R_TRUE) < 1.0
    assert_proper(candidates)


def test_degenerate_inputs_give_no_candidates():
    one = clusters([[1.0, 0.0, 0.0]])
    two = clusters(PERPENDICULAR)
    assert rotation_candidates(one, two) == []
    assert rotation_candidates(two, one) == []
    assert rotation_candidates(clusters(np.zeros((0, 3))), two) == []
    parallel = clusters([[1.0, 0.0, 0.0], [-1.0, 0.02, 0.0]])  # 1 deg from antiparallel
    assert rotation_candidates(parallel, two) == []
    assert rotation_candidates(vds_of(PERPENDICULAR), parallel) == []
    # 90 deg apart in the image, 60 deg in the map: no rotation relates them
    assert rotation_candidates(vds_of(PERPENDICULAR), clusters(AT_60_DEG)) == []


def test_batched_procrustes_matches_geometry():
    rng = np.random.default_rng(11)
    M = rng.normal(size=(50, 3, 3))
    M[:10] = -np.abs(M[:10])  # some with negative determinants: must still give rotations
    R = _nearest_rotations(M.copy())
    for n in range(len(M)):
        np.testing.assert_allclose(R[n], nearest_rotation(M[n]), atol=1e-10)
        assert np.linalg.det(R[n]) == pytest.approx(1.0)


def scene_segments(rng, camera, directions, per_direction, noise_px):
    """Returns ((N, 4) image, (M, 6) map) segments along world ``directions`` seen under R_TRUE."""
    t = np.array([0.1, -0.2, 4.0])
    lines3d = []
    for d in unit(directions):
        c = rng.uniform(-1, 1, (per_direction, 3))
        half = rng.uniform(0.5, 1.0, (per_direction, 1))
        lines3d.append(np.c_[c - half * d, c + half * d])
    lines3d = np.vstack(lines3d)
    T = make_cam_from_world(R_TRUE, t)
    ends = lines3d.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    lines2d = project_points(camera, ends).reshape(-1, 4) + rng.normal(0, noise_px, (len(lines3d), 4))
    return lines2d, lines3d


def test_from_segments_noise_free(camera, rng):
    lines2d, lines3d = scene_segments(rng, camera, GENERIC_3, per_direction=30, noise_px=0.0)
    candidates, vds, found = rotation_candidates_from_segments(lines2d, lines3d, camera)
    assert len(vds) == 3 and len(found) == 3
    assert len(candidates[0].pairs) == 3 and rotation_error_deg(candidates[0].R, R_TRUE) < 0.2
    assert all(len(c.pairs) == 2 for c in candidates[1:])  # the truth alone is confirmed
    assert_proper(candidates)


def test_from_segments_with_noise_and_clutter(camera, rng):
    lines2d, lines3d = scene_segments(rng, camera, np.eye(3), per_direction=60, noise_px=2.0)
    clutter = rng.uniform([0, 0, 0, 0], [640, 480, 640, 480], (40, 4))
    candidates, _, _ = rotation_candidates_from_segments(np.vstack([lines2d, clutter]), lines3d, camera)
    assert len(candidates) == 24  # Manhattan: the cube symmetries, the true one among them
    assert best_error(candidates) < 1.0
    assert_proper(candidates)
    config = RegisterConfig.from_dict({"rotation": {"max_candidates": 8}})
    assert len(rotation_candidates_from_segments(lines2d, lines3d, camera, config)[0]) == 8


def test_paper_scenes():
    from linereg.sim import synthetic

    rng = np.random.default_rng(2)
    errors = []
    for _ in range(10):
        scene = synthetic.paper_scene(rng, num_lines=100)
        candidates, _, _ = rotation_candidates_from_segments(scene.lines2d, scene.lines3d, scene.camera)
        assert_proper(candidates)
        errors.append(best_error(candidates, scene.cam_from_world[:3, :3]) if candidates else 180.0)
    # 150 scenes: median 1.1 deg, 90 % within 3 deg, 97 % within the paper's 0.1 rad success bound
    assert np.median(errors) < 2.0 and sum(e < 5.7 for e in errors) >= 8, errors


def test_refine_candidates_pulls_an_off_rotation_onto_the_segments():
    from dataclasses import replace

    from linereg.rotation import refine_candidates
    from linereg.sim.building_scene import building_scene

    scene = building_scene(np.random.default_rng(3))
    candidates, vds, cl = rotation_candidates_from_segments(scene.lines2d, scene.lines3d, scene.camera)
    truth = scene.cam_from_world[:3, :3]
    best = min(candidates, key=lambda c: rotation_error_deg(c.R, truth))
    off = replace(best, R=rotation_about([0.3, 1.0, -0.4], 2.0) @ best.R)  # a VD error of 2 degrees
    (refit,) = refine_candidates([off], vds, cl, scene.lines2d, scene.camera)
    assert rotation_error_deg(refit.R, truth) < 0.5 * rotation_error_deg(off.R, truth)
    assert abs(np.linalg.det(refit.R) - 1.0) < 1e-9 and np.allclose(refit.R @ refit.R.T, np.eye(3))
    assert refit.pairs == off.pairs
    # nothing to fit on (labels of another size): candidates come back unchanged
    bare = DirectionClusters(vds.directions, np.zeros(0, dtype=np.int64), vds.support)
    assert refine_candidates([off], bare, cl, scene.lines2d, scene.camera)[0] is off


def one_direction_scene(rng, camera, noise_px):
    """Returns (image segments, the vanishing directions found on the first world direction alone, the map's
    clusters): 40 image lines along that direction, 6 along each of two others (too few for a VD)."""
    directions = unit(GENERIC_3)
    parts = [
        scene_segments(rng, camera, [d], n, noise_px) for d, n in zip(directions, (40, 6, 6), strict=True)
    ]
    lines2d = np.vstack([p[0] for p in parts])
    labels = np.r_[np.zeros(40, np.int64), np.full(12, -1)]
    v = unit(directions[0] @ R_TRUE.T)
    vds = DirectionClusters(v[None] * np.sign(v[2]), labels, np.array([1.0]))
    return lines2d, vds, clusters(directions)


@pytest.mark.parametrize("noise_px, tolerance_deg", [(0.0, 0.05), (1.0, 1.0)])
def test_one_vanishing_direction_leaves_an_angle_that_is_searched_not_sampled(
    camera, rng, noise_px, tolerance_deg
):
    from linereg.rotation import single_direction_candidates

    lines2d, vds, found = one_direction_scene(rng, camera, noise_px)
    rotations = single_direction_candidates(vds, found, lines2d, camera)
    assert 0 < len(rotations) <= RotationConfig().max_candidates
    errors = [rotation_error_deg(R, R_TRUE) for R in rotations]
    # the truth's angle about the matched direction is no multiple of any step: it is found, to the noise
    assert min(errors) < tolerance_deg, sorted(errors)[:3]
    for R in rotations:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # six segments of one other direction fix the angle as well as six of each
    keep = np.r_[np.arange(46)]
    subset = DirectionClusters(vds.directions, vds.labels[keep], vds.support)
    errors = [
        rotation_error_deg(R, R_TRUE)
        for R in single_direction_candidates(subset, found, lines2d[keep], camera)
    ]
    assert min(errors) < tolerance_deg


def test_free_angle_scores_bound_every_angle_between_grid_points():
    from linereg.rotation import free_angle_scores

    rng = np.random.default_rng(5)
    axis = unit([0.2, -0.1, 1.0])
    directions = unit(rng.normal(size=(3, 3)))
    normals = unit(rng.normal(size=(200, 3)))
    lengths = rng.uniform(10, 100, 200)
    angles, score = free_angle_scores(axis, normals, lengths, directions, 2.0)
    step = angles[1] - angles[0]
    # the exact score at fine angles never exceeds the larger grid neighbour's bound
    for t in rng.uniform(0, 2 * np.pi, 300):
        turned = directions @ rotation_about(axis, np.degrees(t)).T
        exact = lengths[(np.abs(normals @ turned.T) <= np.sin(np.radians(2.0))).any(axis=1)].sum()
        k = int(t // step) % len(angles)
        assert exact <= max(score[k], score[(k + 1) % len(angles)]) + 1e-9


def test_no_vanishing_direction_no_single_direction_candidates(camera):
    from linereg.rotation import single_direction_candidates

    empty = DirectionClusters(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0))
    lines = np.array([[10.0, 10, 100, 100]])
    assert single_direction_candidates(empty, clusters(PERPENDICULAR), lines, camera) == []
    assert single_direction_candidates(vds_of(PERPENDICULAR[:1]), empty, lines, camera) == []
