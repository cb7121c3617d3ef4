"""Pose refinement (paper III-D): factor Jacobian, gtsam robust-kernel facts, recovery, outliers, covariance."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from linereg.config import RefineConfig, ScoreConfig
from linereg.errors import InvalidInputError
from linereg.geometry import camera_center, invert, line_coefficients, pose_errors, transform_points
from linereg.line_factor import LineProjection, line_factor, line_residuals
from linereg.refine import Refinement, _one_per_stretch, refine_pose, robust_noise
from linereg.score import image_lines
from linereg.sim.synthetic import paper_scene

Scalar = gtsam.noiseModel.mEstimator.Base.ReweightScheme.Scalar
Block = gtsam.noiseModel.mEstimator.Base.ReweightScheme.Block


def perturb(cam_from_world: np.ndarray, rng: np.random.Generator, angle_deg: float, fraction: float):
    """Returns the pose rotated by angle_deg about a random axis, its centre moved by fraction x distance."""
    axis = rng.normal(size=3)
    R = (
        gtsam.Rot3.Expmap(axis / np.linalg.norm(axis) * np.radians(angle_deg)).matrix()
        @ cam_from_world[:3, :3]
    )
    direction = rng.normal(size=3)
    c = camera_center(cam_from_world)
    c = c + direction / np.linalg.norm(direction) * fraction * np.linalg.norm(c)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, -R @ c
    return out


def scene_problem(seed: int, noise_px: float = 0.0):
    scene = paper_scene(np.random.default_rng(seed), 100, 0.3, 0.3, noise_px)
    m = scene.true_matches
    return scene, line_coefficients(scene.lines2d[m[:, 0]]), scene.lines3d[m[:, 1]]


def numerical_jacobian(cam_from_world, coeffs, segments, camera, min_depth_m=1e-3, h=1e-6):
    """Returns (2K, 6) central differences of line_residuals over gtsam's Pose3.retract (world_T_cam)."""
    pose = gtsam.Pose3(invert(cam_from_world))
    J = np.zeros((2 * len(coeffs), 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        plus = line_residuals(invert(pose.retract(d).matrix()), coeffs, segments, camera, min_depth_m)[0]
        minus = line_residuals(invert(pose.retract(-d).matrix()), coeffs, segments, camera, min_depth_m)[0]
        J[:, i] = (plus - minus) / (2 * h)
    return J


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobian_matches_central_differences(seed):
    scene, coeffs, segments = scene_problem(seed, noise_px=2.0)
    start = perturb(scene.cam_from_world, np.random.default_rng(seed), 3.0, 0.05)
    e, J = line_residuals(start, coeffs, segments, scene.camera)
    assert e.shape == (2 * len(coeffs),) and J.shape == (2 * len(coeffs), 6)
    Jn = numerical_jacobian(start, coeffs, segments, scene.camera)
    assert np.abs(J - Jn).max() <= 1e-6 * np.abs(J).max()


def test_residuals_are_signed_endpoint_distances(camera):
    # a 2D line y = 100 and a 3D segment 1 m in front, 0.1 m below the axis: both endpoints at y = 320 px
    coeffs = line_coefficients(np.array([[0.0, 100.0, 600.0, 100.0]]))
    segment = np.array([[-0.2, 0.1, 1.0, 0.3, 0.1, 1.0]])
    e, _ = line_residuals(np.eye(4), coeffs, segment, camera)
    np.testing.assert_allclose(np.abs(e), [220.0, 220.0])


def test_depth_clamp_keeps_points_behind_the_camera_finite(camera):
    coeffs = line_coefficients(np.array([[0.0, 100.0, 600.0, 100.0], [10.0, 0.0, 20.0, 400.0]]))
    segments = np.array([[-0.2, 0.1, -1.0, 0.3, 0.1, 2.0], [0.0, 0.0, 0.0, 0.1, 0.5, 3.0]])
    e, J = line_residuals(np.eye(4), coeffs, segments, camera, min_depth_m=0.01)
    assert np.isfinite(e).all() and np.isfinite(J).all()
    np.testing.assert_allclose(
        J, numerical_jacobian(np.eye(4), coeffs, segments, camera, 0.01), rtol=1e-6, atol=1e-3
    )


def test_custom_factor_wraps_line_residuals():
    scene, coeffs, segments = scene_problem(3, noise_px=1.0)
    projection = LineProjection.build(coeffs, segments, scene.camera)
    factor = line_factor(7, projection, gtsam.noiseModel.Isotropic.Sigma(2 * len(coeffs), 1.0))
    values = gtsam.Values()
    values.insert(7, gtsam.Pose3(invert(scene.cam_from_world)))
    A, b = factor.linearize(values).jacobian()
    e, J = line_residuals(scene.cam_from_world, coeffs, segments, scene.camera)
    np.testing.assert_allclose(A, J, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(b, -e, atol=1e-12)
    assert factor.error(values) == pytest.approx(0.5 * e @ e)


@pytest.mark.parametrize("scheme", [Scalar, Block])
def test_gtsam_reweight_schemes(scheme):
    """gtsam 4.3 fact: Scalar weights (and losses) each residual on its own; Block uses the block norm."""
    residuals, k = np.array([0.5, 10.0, -0.2, 30.0]), 1.0
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(k, scheme), gtsam.noiseModel.Isotropic.Sigma(4, 1.0)
    )

    def error(this, values, jacobians):
        if jacobians is not None:
            jacobians[0] = np.ones((4, 6))
        return residuals

    factor = gtsam.CustomFactor(noise, [0], error)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    A, b = factor.linearize(values).jacobian()
    if scheme == Scalar:
        sqrt_w = np.sqrt(np.minimum(1.0, k / np.abs(residuals)))
        loss = np.where(np.abs(residuals) <= k, 0.5 * residuals**2, k * np.abs(residuals) - 0.5 * k * k).sum()
    else:
        norm = np.linalg.norm(residuals)
        sqrt_w, loss = np.full(4, np.sqrt(k / norm)), k * norm - 0.5 * k * k
    np.testing.assert_allclose(A[:, 0], sqrt_w)
    np.testing.assert_allclose(b, -sqrt_w * residuals)
    assert factor.error(values) == pytest.approx(loss)


def optimise(scene, coeffs, segments, scheme) -> np.ndarray:
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(2.0, scheme),
        gtsam.noiseModel.Isotropic.Sigma(2 * len(coeffs), 1.0),
    )
    graph = gtsam.NonlinearFactorGraph()
    graph.add(line_factor(0, LineProjection.build(coeffs, segments, scene.camera), noise))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(invert(scene.cam_from_world)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return invert(result.atPose3(0).matrix())


def test_outlier_line_does_not_pull_the_pose_with_scalar_reweighting():
    scene, coeffs, segments = scene_problem(4)
    wrong = segments.copy()
    wrong[:2] = segments[[40, 50]]  # two gross outliers, tens to hundreds of px off
    scalar = pose_errors(optimise(scene, coeffs, wrong, Scalar), scene.cam_from_world)
    block = pose_errors(optimise(scene, coeffs, wrong, Block), scene.cam_from_world)
    assert scalar[0] < 0.05 and scalar[2] < 1e-3
    assert block[0] > 5 * scalar[0]  # Block = one weight for the whole image = least squares


def refine(scene, start, config: RefineConfig | None = None, lines3d=None, score: ScoreConfig | None = None):
    score = score or ScoreConfig(distance_px=5.0)  # the paper scenes' 2 px noise
    image = image_lines(scene.lines2d, scene.camera, score)
    lines3d = scene.lines3d if lines3d is None else lines3d
    return refine_pose(image, lines3d, scene.camera, start, config or RefineConfig(), score)


@pytest.mark.parametrize("seed", range(4))
def test_recovers_perturbed_pose_noise_free(seed):
    scene = paper_scene(np.random.default_rng(seed), 100, 0.3, 0.3, 0.0)
    start = perturb(scene.cam_from_world, np.random.default_rng(100 + seed), 0.3, 0.01)
    result = refine(scene, start)
    rot_deg, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
    assert isinstance(result, Refinement)
    # accidental pairs within the 2 px floor of re-association bias a noise-free fit by a few 0.01 deg
    assert rot_deg < 0.1 and rel < 1e-3
    assert 1 <= result.rounds <= RefineConfig().max_rounds
    # every true pair covers its image segment at the refined pose
    true = set(map(tuple, scene.true_matches))
    assert len(true & set(map(tuple, result.score.matches(0.5)))) >= 0.9 * len(true)


def test_accuracy_with_2px_noise_matches_the_covariance():
    rot, rel, chi2 = [], [], []
    for seed in range(10):
        scene = paper_scene(np.random.default_rng(seed), 100, 0.3, 0.3, 2.0)
        start = perturb(scene.cam_from_world, np.random.default_rng(100 + seed), 0.3, 0.01)
        result = refine(scene, start)
        r, _, t = pose_errors(result.cam_from_world, scene.cam_from_world)
        truth, estimate = (
            gtsam.Pose3(invert(scene.cam_from_world)),
            gtsam.Pose3(invert(result.cam_from_world)),
        )
        xi = gtsam.Pose3.Logmap(truth.between(estimate))  # body-frame error, (rotation, translation)
        rot.append(r)
        rel.append(t)
        chi2.append(xi @ np.linalg.solve(result.covariance, xi))
        assert 1.0 < result.rms_px < 3.0
    assert np.median(rot) < 0.4 and max(rot) < 1.0
    assert np.median(rel) < 0.003 and max(rel) < 0.008
    assert 1.0 < np.mean(chi2) < 20.0  # 6 for a calibrated covariance


def test_map_lines_on_no_image_line_do_not_pull():
    """Wrong map lines added near the true ones: the score's union keeps one pair per covered stretch."""
    scene = paper_scene(np.random.default_rng(5), 100, 0.3, 0.3, 1.0)
    rng = np.random.default_rng(6)
    decoys = scene.lines3d[rng.integers(0, len(scene.lines3d), 20)] + rng.normal(scale=0.05, size=(20, 6))
    start = perturb(scene.cam_from_world, rng, 0.3, 0.01)
    result = refine(scene, start, lines3d=np.r_[scene.lines3d, decoys])
    rot_deg, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
    assert rot_deg < 0.3 and rel < 0.003


def test_covariance_is_spd_and_shrinks_with_more_lines():
    scene = paper_scene(np.random.default_rng(7), 100, 0.3, 0.3, 2.0)
    traces = []
    for k in (12, 30, len(scene.true_matches)):
        keep = np.unique(scene.true_matches[:k, 1])
        result = refine(scene, scene.cam_from_world, lines3d=scene.lines3d[keep])
        cov = result.covariance
        np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=1e-15)
        assert np.linalg.eigvalsh(cov).min() > 0
        traces.append(np.trace(cov))
    assert traces[0] > traces[1] > traces[2]


@pytest.mark.parametrize("case", ["empty", "too_few", "parallel"])
def test_degenerate_input_returns_the_input_pose(case):
    scene = paper_scene(np.random.default_rng(9), 100, 0.3, 0.3, 1.0)
    j = scene.true_matches[:, 1]
    lines3d = {"empty": scene.lines3d[:0], "too_few": scene.lines3d[j[:3]], "parallel": None}[case]
    if case == "parallel":  # every map segment along one direction
        lines3d = scene.lines3d[j[:20]].copy()
        lines3d[:, 3:6] = lines3d[:, 0:3] + [0.0, 0.0, 0.5]
    start = perturb(scene.cam_from_world, np.random.default_rng(0), 0.3, 0.01)
    result = refine(scene, start, lines3d=lines3d.reshape(-1, 6))
    np.testing.assert_array_equal(result.cam_from_world, start)
    assert np.isnan(result.covariance).all() and result.covariance.shape == (6, 6)


def test_endpoints_behind_the_camera_do_not_blow_up():
    scene = paper_scene(np.random.default_rng(10), 100, 0.3, 0.3, 1.0)
    lines3d, m = scene.lines3d.copy(), scene.true_matches
    # extend five matched segments along their own line until the second endpoint is 1 m behind the camera
    z1 = transform_points(scene.cam_from_world, lines3d[m[:, 1], 0:3])[:, 2]
    z2 = transform_points(scene.cam_from_world, lines3d[m[:, 1], 3:6])[:, 2]
    pick = np.argsort(-np.abs(z2 - z1))[:5]
    j, s = m[pick, 1], (-1.0 - z1[pick]) / (z2 - z1)[pick]
    lines3d[j, 3:6] = lines3d[j, 0:3] + s[:, None] * (lines3d[j, 3:6] - lines3d[j, 0:3])
    start = perturb(scene.cam_from_world, np.random.default_rng(11), 0.3, 0.01)
    result = refine(scene, start, lines3d=lines3d)
    assert np.isfinite(result.cam_from_world).all() and np.isfinite(result.covariance).all()
    rot_deg, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
    assert rot_deg < 0.5 and rel < 0.005


@pytest.mark.parametrize("kernel", ["cauchy", "tukey", "none"])
def test_other_kernels_recover_the_pose(kernel):
    scene = paper_scene(np.random.default_rng(12), 100, 0.3, 0.3, 0.0)
    start = perturb(scene.cam_from_world, np.random.default_rng(13), 0.3, 0.01)
    result = refine(scene, start, RefineConfig(kernel=kernel, kernel_px=5.0))
    rot_deg, _, rel = pose_errors(result.cam_from_world, scene.cam_from_world)
    assert rot_deg < 0.05 and rel < 1e-3 and np.isfinite(result.covariance).all()


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "tukey"])
def test_a_kernel_weighs_a_residual_by_its_pixels_whatever_the_noise_level(kernel):
    # the sequence graph's line factors carry each frame's own noise level; the kernel's threshold stays in
    # pixels, as in the single-image refinement (sigma 1 px): the same residual gets the same weight
    config = RefineConfig(kernel=kernel, kernel_px=3.0)
    for residual_px in (1.0, 2.0, 4.0):
        weights = [robust_noise(2, s, config).robust().weight(residual_px / s) for s in (0.5, 1.0, 2.0)]
        assert weights == pytest.approx([weights[1]] * 3, rel=1e-9)
    tukey = RefineConfig(kernel="tukey", kernel_px=3.0)
    assert robust_noise(2, 2.0, tukey).robust().weight(4.0 / 2.0) == 0.0  # beyond 3 px: no pull at all
    assert isinstance(robust_noise(2, 2.0, RefineConfig(kernel="none")), gtsam.noiseModel.Isotropic)


def test_unknown_kernel_is_rejected():
    scene = paper_scene(np.random.default_rng(14), 30, 0.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match="kernel"):
        refine(scene, scene.cam_from_world, RefineConfig(kernel="gauss"))  # type: ignore[arg-type]


def test_each_image_stretch_keeps_its_longest_cover_and_the_fragments_beside_it():
    # the rule, written plainly: longest first per image segment, a cover overlapping a taken one of its
    # segment by more than half its own length is dropped, covers shorter than the minimum never taken
    rng = np.random.default_rng(11)
    i = rng.integers(0, 12, 400)
    lo = rng.uniform(0.0, 80.0, 400).round(0)  # whole pixels: ties of start and length happen
    cover = np.c_[lo, lo + rng.uniform(1.0, 60.0, 400).round(0)]
    want = cover[:, 1] - cover[:, 0] >= 5.0
    taken: dict[int, list[tuple[float, float]]] = {}
    for k in np.lexsort((-(cover[:, 1] - cover[:, 0]), i)):
        if want[k]:
            spans = taken.setdefault(int(i[k]), [])
            if any(
                min(cover[k, 1], b) - max(cover[k, 0], a) > 0.5 * (cover[k, 1] - cover[k, 0])
                for a, b in spans
            ):
                want[k] = False
            else:
                spans.append((cover[k, 0], cover[k, 1]))
    got = _one_per_stretch(i, cover, 5.0)
    assert np.array_equal(got, want)
    assert 0 < got.sum() < (cover[:, 1] - cover[:, 0] >= 5.0).sum()  # some dropped for overlaps
    assert _one_per_stretch(np.zeros(0, np.int64), np.zeros((0, 2)), 5.0).shape == (0,)


def test_inlier_sigma_is_the_inliers_noise_among_outliers_spread_over_the_window():
    from linereg.refine import inlier_sigma

    rng = np.random.default_rng(0)
    mixed = np.r_[rng.normal(0.0, 1.3, 700), rng.uniform(-10.0, 10.0, 300)]  # pairs covered within 10 px
    mad = 1.4826 * np.median(np.abs(mixed))
    assert abs(inlier_sigma(mixed, 10.0) - 1.3) < 0.15 and mad > 1.9  # the MAD is the outliers'
    clean = rng.normal(0.0, 2.0, 1000)
    assert abs(inlier_sigma(clean[np.abs(clean) <= 10.0], 10.0) - 2.0) < 0.2  # no outliers: the noise
    assert inlier_sigma(np.array([0.5, -1.0, 12.0]), 10.0) == pytest.approx(1.4826 * 0.75)  # few: the MAD
    assert inlier_sigma(np.array([11.0]), 10.0) == 10.0  # none within the window


def _clutter_beside(scene, share: float, rng: np.random.Generator) -> np.ndarray:
    """Returns image segments parallel to ``share`` of the true ones, 2-9 px beside them (texture edges)."""
    true2d = scene.lines2d[scene.true_matches[:, 0]]
    picked = true2d[rng.random(len(true2d)) < share]
    d = picked[:, 2:] - picked[:, :2]
    normal = np.c_[-d[:, 1], d[:, 0]] / np.linalg.norm(d, axis=1)[:, None]
    offset = rng.uniform(2.0, 9.0, len(picked))[:, None] * normal
    return picked + np.c_[offset, offset]


def test_the_covers_tighten_to_the_inliers_noise_and_let_the_wide_rounds_clutter_go(monkeypatch):
    """From the exact pose, a first round covering at 10 px takes in edges beside the true lines; the MAD of
    those pairs is the clutter's and kept later rounds as wide (``noise_model="mad"``), the mixture's sigma
    is the true lines' and lets the clutter go: the refinement stays nearer the pose."""
    import linereg.refine as refine_module

    score = ScoreConfig(distance_px=4.0)
    errors: dict[str, list[float]] = {"mad": [], "mixture": []}
    last: dict[str, list[float]] = {"mad": [], "mixture": []}
    threshold = refine_module._threshold_px
    for seed in range(4):
        scene = paper_scene(np.random.default_rng(seed), 100, 0.3, 0.3, 0.7)
        clutter = _clutter_beside(scene, 0.6, np.random.default_rng(seed + 50))
        image = image_lines(np.r_[scene.lines2d, clutter], scene.camera, score)
        for model in errors:
            tolerances: list[float] = []

            def recording(problem, pose, config, ceiling, tolerances=tolerances):
                tolerances.append(threshold(problem, pose, config, ceiling))
                return tolerances[-1]

            monkeypatch.setattr(refine_module, "_threshold_px", recording)
            config = RefineConfig(noise_model=model)
            result = refine_pose(image, scene.lines3d, scene.camera, scene.cam_from_world, config, score)
            errors[model].append(pose_errors(result.cam_from_world, scene.cam_from_world)[0])
            last[model].append(tolerances[-1])
    assert np.mean(errors["mixture"]) < 0.7 * np.mean(errors["mad"])
    assert np.median(last["mixture"]) < 3.5 < np.median(last["mad"])


def test_an_unknown_noise_model_is_refused():
    scene = paper_scene(np.random.default_rng(0), 30, 0.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match="noise_model"):
        refine(scene, scene.cam_from_world, RefineConfig(noise_model="median"))  # type: ignore[arg-type]
