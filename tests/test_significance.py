"""The a-contrario test (``significance.py``): the chance model, the tail, and what the decision does with it."""

import math

import numpy as np
from scipy.stats import binom

import linereg
from linereg.config import RegisterConfig
from linereg.pipeline import log10_nfa
from linereg.score import image_lines, score_projected
from linereg.significance import SearchSpace, chance_probabilities, log10_tail
from linereg.sim.synthetic import paper_scene


def test_the_tail_of_equal_draws_is_the_binomial_tail():
    for n, p, k in [(30, 0.05, 6), (200, 0.02, 15), (50, 0.3, 40), (10, 0.5, 0)]:
        expected = math.log10(binom.sf(k - 1, n, p)) if k > 0 else 0.0
        assert abs(log10_tail(np.full(n, p), k) - expected) < 1e-9 * max(1.0, abs(expected))


def test_the_tail_of_unequal_draws_matches_enumeration(rng):
    p = rng.uniform(0.0, 0.6, 12)
    outcomes = (np.arange(2**12)[:, None] >> np.arange(12)) & 1
    weight = np.prod(np.where(outcomes == 1, p, 1.0 - p), axis=1)
    for k in (1, 4, 9, 12):
        expected = math.log10(weight[outcomes.sum(axis=1) >= k].sum())
        assert abs(log10_tail(p, k) - expected) < 1e-9 * max(1.0, abs(expected))
    assert log10_tail(p, 13) == -math.inf


def test_chance_probabilities_match_random_placements(camera, rng):
    """The model against simulation: a map segment dropped at uniformly random places in the image explains
    one of the image's segments as often as predicted, for image segments longer and shorter than it,
    parallel and at angles (a short image segment's angle tolerance is wider: the score's pair test)."""
    sc = RegisterConfig().score
    corners = np.array([[100.0, 100.0], [400.0, 120.0], [150.0, 350.0], [450.0, 330.0]])
    cases = [  # map segment length, image segment lengths, their angles to it (deg)
        (67.0, [40.0, 90.0, 150.0, 20.0], [0.0, 1.5, -2.5, 0.0]),
        (67.0, [100.0, 100.0, 100.0, 100.0], [3.0, 3.0, -3.0, -3.0]),
        (25.0, [30.0, 30.0, 60.0, 60.0], [8.0, -10.0, 6.0, -12.0]),
    ]
    for length, lengths, turns in cases:
        angles = 0.45 + np.radians(turns)
        ends = corners + np.array(lengths)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        image = image_lines(np.c_[corners, ends], camera, sc)
        template = np.array([[0.0, 0.0, length * np.cos(0.45), length * np.sin(0.45)]])
        q = chance_probabilities(image, template, sc.distance_px, sc.angle_deg, 0.5)[0]
        trials, hits = 12000, 0
        for _ in range(trials):
            corner = rng.uniform([0.0, 0.0], [camera.width, camera.height])
            score = score_projected(image, template + np.tile(corner, 2), np.arange(1), sc)
            hits += (score.explained >= 0.5 * image.lengths).any()
        sigma = math.sqrt(q * (1.0 - q) / trials)
        assert abs(hits / trials - q) <= 4.0 * sigma, (length, turns, q, hits / trials)


def test_the_truth_is_significant_and_a_wrong_pose_is_not(rng):
    scene = paper_scene(rng, 50, 0.3, 0.3, 1.0)
    config = RegisterConfig()
    image = image_lines(scene.lines2d, scene.camera, config.score)
    space = SearchSpace(volume_m3=50.0**3, rotations=20, rotation_tolerance_deg=8.0)
    truth = log10_nfa(scene.cam_from_world, 30, scene.lines3d, image, scene.camera, config, space)
    chance = log10_nfa(scene.cam_from_world, 5, scene.lines3d, image, scene.camera, config, space)
    assert truth < -5.0 < 0.0 < chance


def test_more_searched_space_needs_more_evidence(camera):
    small = SearchSpace(volume_m3=1.0, rotations=1, rotation_tolerance_deg=8.0)
    large = SearchSpace(volume_m3=1000.0, rotations=10, rotation_tolerance_deg=8.0)
    a, b = small.log10_tests(camera, 5.0, 4.0), large.log10_tests(camera, 5.0, 4.0)
    assert abs((b - a) - 4.0) < 1e-9  # 1000 x the volume and 10 x the rotations
    assert small.log10_tests(camera, 50.0, 4.0) < a  # far scenes: coarser steps tell fewer centres apart


def test_unrelated_images_are_never_an_answer(rng):
    """Image segments that have nothing to do with the map: whatever the search finds is chance."""
    for seed in range(3):
        scene = paper_scene(np.random.default_rng([7, seed]), 40, 0.0, 0.0, 1.0)
        noise = rng.uniform([0, 0, 0, 0], [640, 480, 640, 480], (40, 4))
        reg = linereg.register(noise, scene.lines3d, scene.camera)
        assert not reg.success, reg


def test_fishers_combination_is_the_chi_square_tail_of_the_photos_p_values():
    """Independent photos' chances combined (``log10_fisher``): exactly the tail of -2 sum(ln p) under a
    chi-square of 2K degrees of freedom; a photo holding no evidence (p = 1) only dilutes the rest."""
    from scipy.stats import chi2

    from linereg.significance import log10_fisher

    for log10_p in ([-3.0], [-3.0, 0.0], [-2.0, -2.0, -2.0], [-0.5] * 10, [-50.0, -40.0]):
        ln = np.array(log10_p) * math.log(10.0)
        expected = chi2.logsf(-2.0 * ln.sum(), 2 * len(ln)) / math.log(10.0)
        assert math.isclose(log10_fisher(log10_p), expected, rel_tol=1e-9, abs_tol=1e-9)
    assert log10_fisher([]) == 0.0 and log10_fisher([0.0, 0.0]) == 0.0
    assert log10_fisher([-4.0]) < log10_fisher([-4.0, 0.0]) < 0.0
    assert log10_fisher([-math.inf, -1.0]) == -math.inf
