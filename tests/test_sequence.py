"""Sequences and tracking: exact recovery in one graph, odometry covariance growth, bridged frames, bad input,
trajectory errors as evo computes them."""

from __future__ import annotations

import itertools
from dataclasses import replace

import gtsam
import numpy as np
import pytest

from linereg import sequence
from linereg.camera import Camera
from linereg.errors import InvalidInputError
from linereg.geometry import check_rigid, invert, pose_errors
from linereg.graph import from_pose3, relative_pose, to_pose3
from linereg.map.linemap import LineMap
from linereg.priors import Prior
from linereg.registration import Registration
from linereg.score import image_lines
from linereg.sequence import FROM_NEIGHBOURS, GATED, SequenceConfig, frames_alone, localize_sequence
from linereg.sim.synthetic import decoy_scene, look_at, project_visible
from linereg.tracking import Tracker, TrackingConfig, innovation_distance

CAMERA = Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)
BLANK = np.zeros((0, 4))


def _scene(n_frames: int = 6, seed: int = 0):
    """Returns (LineMap, (K, 4, 4) truth, list of exact (N, 4) segments): a camera circling a box of lines.

    Seed 0 has no two map lines within a few pixels of each other in any view (seeds 2-4 do: a single
    frame's refinement then settles with a wrong pair, and no test of exactness can pass).
    """
    rng = np.random.default_rng(seed)
    directions = np.r_[np.tile(np.eye(3), (12, 1)), rng.normal(size=(8, 3))]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = rng.uniform(-1.5, 1.5, (len(directions), 3))
    lines3d = np.c_[starts, starts + rng.uniform(0.4, 1.2, (len(directions), 1)) * directions]
    angles = np.radians(2.0) * np.arange(n_frames)  # 0.14 m and 2 degrees per frame
    truth = np.array([look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 0.8]), np.zeros(3)) for a in angles])
    frames = [project_visible(lines3d, CAMERA, T)[0] for T in truth]
    return LineMap.from_segments(lines3d), truth, frames


@pytest.fixture(scope="module")
def scene():
    return _scene()


def _odometry(truth: np.ndarray, sigma: float = 1e-3):
    relative = [relative_pose(a, b) for a, b in itertools.pairwise(truth)]
    return relative, [np.eye(6) * sigma**2 for _ in relative]


def test_exact_odometry_and_exact_lines_recover_the_poses(scene):
    line_map, truth, frames = scene
    relative, covariances = _odometry(truth)
    start = truth[0].copy()
    start[:3, 3] += 0.05  # a rough start pose, refined by the graph
    results = localize_sequence(
        frames, line_map, CAMERA, relative, covariances, prior=Prior(cam_from_world=start, radius_m=0.5)
    )
    for r, T in zip(results, truth, strict=True):
        rot, pos, _ = pose_errors(r.cam_from_world, T)
        assert r.success, r.reason
        assert pos < 1e-6 and rot < 1e-5
        assert np.isfinite(r.covariance).all()


def test_odometry_alone_propagates_the_pose_with_the_right_covariance(scene):
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    covariances = [np.diag([1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 3e-3]) for _ in relative]
    blank_after = [frames[0], BLANK, BLANK, BLANK]
    results = localize_sequence(
        blank_after,
        line_map,
        CAMERA,
        relative[:3],
        covariances[:3],
        prior=Prior(cam_from_world=truth[0], radius_m=0.5),
    )
    assert results[0].success
    expected = results[0].covariance
    for k in range(1, 4):
        r = results[k]
        assert not r.success and r.reason.startswith(FROM_NEIGHBOURS)
        # right perturbation: xi_k = Ad(step^-1) xi_k-1 + noise (gtsam's between on world_T_cam)
        adjoint = gtsam.Pose3(relative[k - 1]).inverse().AdjointMap()
        expected = adjoint @ expected @ adjoint.T + covariances[k - 1]
        np.testing.assert_allclose(r.covariance, expected, rtol=1e-6, atol=1e-12)
        assert pose_errors(r.cam_from_world, truth[k])[1] < 1e-6
    assert np.trace(results[3].covariance) > np.trace(results[1].covariance) > np.trace(results[0].covariance)


def test_a_dropped_frame_is_bridged_with_a_larger_covariance(scene):
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    dropped = [*frames[:2], BLANK, *frames[3:]]
    results = localize_sequence(
        dropped, line_map, CAMERA, relative, prior=Prior(cam_from_world=truth[0], radius_m=0.5)
    )
    assert [r.success for r in results] == [True, True, False, True, True, True]
    assert results[2].reason.startswith(FROM_NEIGHBOURS)
    rot, pos, _ = pose_errors(results[2].cam_from_world, truth[2])
    assert pos < 0.01 and rot < 0.2
    assert np.trace(results[2].covariance[3:, 3:]) > np.trace(results[1].covariance[3:, 3:])


def test_a_frame_after_a_loss_is_searched_for_not_refined_from_its_prediction(scene):
    # after a frame without a fix the prediction has drifted (here the odometry over the lost frame is off
    # by 0.3 m): the next frame is relocalized near it (the best-scoring pose there, against its rivals),
    # not refined into whatever basin the prediction lies in; the frame after a fix is refined (tracked)
    # (its covariance says so: 0.2 m; one claiming 1 mm would have the relocalized fix gated, not claimed)
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    relative[1] = relative[1].copy()
    relative[1][:3, 3] += [0.3, 0.0, 0.0]
    covariances = [np.eye(6) * 1e-6 for _ in relative]
    covariances[1] = np.eye(6) * 0.2**2
    dropped = [*frames[:2], BLANK, *frames[3:]]
    config = SequenceConfig()
    first = Prior(cam_from_world=truth[0], radius_m=0.5)
    results = localize_sequence(dropped, line_map, CAMERA, relative, covariances, config, first)
    images = [image_lines(f, CAMERA, config.register.score) for f in dropped]
    alone = frames_alone(
        dropped,
        images,
        line_map,
        CAMERA,
        relative,
        covariances,
        config,
        first,
    )
    assert "relocalize" in alone[3].timings and "track" not in alone[3].timings
    assert "track" in alone[4].timings
    for k in (3, 4, 5):
        assert alone[k].success and results[k].success, (k, alone[k].reason)
        rot, pos, _ = pose_errors(results[k].cam_from_world, truth[k])
        assert pos < 0.01 and rot < 0.2


def test_a_map_fitting_loosely_is_tracked_as_loosely_as_its_relocalized_fix_fits():
    # a map whose lines lie ~3.5 px off the photo's (each shifted 3 cm, as a fused RGB-D room's are): the
    # first frame's relocalization (decided against its rivals) fits that loosely, and so may the frames
    # tracked after it (sequence.fit_limit), where a fixed 2.5 px bar relocalized every frame
    line_map, truth, frames = _scene(6)
    offsets = np.random.default_rng(1).normal(size=(len(line_map.segments), 3)) * 0.03
    loose = LineMap.from_segments(line_map.segments + np.c_[offsets, offsets])
    relative, covariances = _odometry(truth)
    config = SequenceConfig()
    images = [image_lines(f, CAMERA, config.register.score) for f in frames]
    first = Prior(cam_from_world=truth[0], radius_m=0.3, sigma_rot_deg=2.0)
    alone = frames_alone(frames, images, loose, CAMERA, relative, covariances, config, first)
    assert alone[0].success and alone[0].rms_px > config.max_rms_px
    for k in range(1, len(frames)):
        assert alone[k].success and "relocalize" not in alone[k].timings, (k, alone[k].reason)
        rot, pos, _ = pose_errors(alone[k].cam_from_world, truth[k])
        assert pos < 0.15 and rot < 1.5  # the map's own error: its lines are 5 cm off, 4 m away
    bar = sequence.refine_from(images[1], loose, CAMERA, truth[1], 0.5, config)
    assert not bar.success and "loose" in bar.reason
    assert sequence.fit_limit(alone[0].rms_px, config) == config.loose_factor * alone[0].rms_px
    assert sequence.fit_limit(None, config) == sequence.fit_limit(1.0, config) == config.max_rms_px


def test_a_fix_far_from_the_odometrys_prediction_is_not_claimed_alone(scene):
    line_map, truth, frames = scene
    relative, covariances = _odometry(truth)
    relative[1] = relative[1].copy()
    relative[1][:3, 3] += [0.0, 0.0, 0.1]  # odometry 10 cm off on one step, its covariance says 1 mm
    config = SequenceConfig()
    images = [image_lines(f, CAMERA, config.register.score) for f in frames]
    first = Prior(cam_from_world=truth[0], radius_m=0.5)
    for probability in (config.gate_probability, 0.0):
        gate = replace(config, gate_probability=probability)
        alone = frames_alone(frames, images, line_map, CAMERA, relative, covariances, gate, first)
        assert alone[1].success and alone[2].success == (probability == 0.0)
        if probability:
            assert (
                alone[2].reason.startswith(GATED)
                and "sigma from the odometry's prediction" in alone[2].reason
            )
        # the gated fix and its prediction combined start the next frame: tracking goes on, claimed
        for k in (2, 3, 4, 5):
            rot, pos, _ = pose_errors(alone[k].cam_from_world, truth[k])
            assert pos < 1e-3 and rot < 0.05, (k, alone[k].reason)
        assert all(alone[k].success for k in (3, 4, 5)), [r.reason for r in alone]


def test_sequence_bad_input_names_the_frame(scene):
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    bad = frames[1].copy()
    bad[0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="frame 1"):
        localize_sequence([frames[0], bad], line_map, CAMERA)
    skewed = relative[0].copy()
    skewed[:3, :3] *= 1.1
    with pytest.raises(InvalidInputError, match="not rigid"):
        localize_sequence(frames[:2], line_map, CAMERA, [skewed])
    # odometry written to six digits is a rigid motion (the nearest rotation is taken)
    written = check_rigid(np.round(relative[0], 6), "relative_poses[0]")
    np.testing.assert_allclose(written[:3, :3] @ written[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(written, relative[0], atol=1e-5)
    with pytest.raises(InvalidInputError, match="relative poses"):
        localize_sequence(frames[:3], line_map, CAMERA, relative[:1])


def test_tracker_tracks_coasts_and_recovers(scene):
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    tracker = Tracker(line_map, CAMERA)
    tracker.start_at(truth[0])
    events = []
    for k, frame in enumerate(frames):
        r = tracker.step(BLANK if k == 2 else frame, relative[k - 1] if k else None, timestamp=0.1 * k)
        events.append(tracker.event)
        assert pose_errors(r.cam_from_world, truth[k])[1] < 0.01
        assert r.success == (k != 2)
    assert events == ["tracked", "tracked", "predicted", "tracked", "tracked", "tracked"]


def test_innovation_distance_is_the_mahalanobis_distance_of_the_fix_from_its_prediction():
    predicted = look_at(np.array([4.0, 0.0, 0.8]), np.zeros(3))
    nudge = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.03, 0.0, 0.0))  # 3 cm along the camera's x
    fixed = from_pose3(to_pose3(predicted).compose(nudge))
    step = np.eye(4)
    step[:3, 3] = [0.0, 0.0, 0.5]
    q = np.diag([1e-6] * 3 + [0.01**2] * 3)
    unknown = np.full((6, 6), np.nan)
    assert innovation_distance(predicted, predicted, unknown, step, q, unknown) == pytest.approx(0.0)
    assert innovation_distance(predicted, fixed, unknown, step, q, unknown) == pytest.approx(9.0, rel=1e-6)
    # the previous pose's and the fix's own uncertainty widen the gate: 3 cm over sqrt(3) cm
    previous = np.diag([0.0] * 3 + [0.01**2] * 3)  # a pure translation step carries it unchanged
    d2 = innovation_distance(predicted, fixed, previous, step, q, previous)
    assert d2 == pytest.approx(3.0, rel=1e-6)


def test_tracker_does_not_claim_a_fix_many_sigmas_from_its_prediction(scene):
    line_map, truth, frames = scene
    relative, _ = _odometry(truth)
    lying = relative[0].copy()
    lying[:3, 3] += [0.0, 0.0, 0.1]  # odometry 10 cm off, its covariance says ~1 cm: the fix disagrees
    for probability, claimed in ((SequenceConfig().gate_probability, False), (0.0, True)):
        config = TrackingConfig()
        config = replace(config, sequence=replace(config.sequence, gate_probability=probability))
        tracker = Tracker(line_map, CAMERA, config)
        tracker.start_at(truth[0], sigma_rot_deg=0.1, sigma_pos_m=0.005)
        assert tracker.step(frames[0]).success
        r = tracker.step(frames[1], lying)
        assert tracker.event == "tracked" and r.success == claimed
        if not claimed:
            assert r.reason.startswith(FROM_NEIGHBOURS) and "sigma from the prediction" in r.reason
        r = tracker.step(frames[2], relative[1])  # the graph took the fix in: tracking goes on
        assert r.success and pose_errors(r.cam_from_world, truth[2])[1] < 0.05


def test_tracker_bad_input_leaves_the_session_alive(scene):
    line_map, truth, frames = scene
    tracker = Tracker(line_map, CAMERA)
    tracker.start_at(truth[0])
    assert tracker.step(frames[0]).success
    with pytest.raises(InvalidInputError, match="camera is 640x480"):
        tracker.step(np.zeros((100, 100), np.uint8))
    with pytest.raises(InvalidInputError, match="not rigid"):
        tracker.step(frames[1], relative_pose=np.full((4, 4), 2.0))
    with pytest.raises(InvalidInputError, match="NaN"):
        tracker.step(np.full((3, 4), np.nan))
    with pytest.raises(InvalidInputError, match="relative_pose"):
        tracker.step(frames[1], relative_pose=np.eye(4) * np.nan)
    r = tracker.step(frames[1], relative_pose(truth[0], truth[1]))
    assert r.success and tracker.event == "tracked"
    assert pose_errors(r.cam_from_world, truth[1])[1] < 0.01


def test_trajectory_errors_match_evo(tmp_path):
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.tools import file_interface

    from linereg import io
    from linereg.bench.trajectory import ape, rpe

    _, truth, _ = _scene(12)
    rng = np.random.default_rng(0)
    est = []
    for T in truth:
        world_from_cam = invert(T)
        world_from_cam[:3, 3] += rng.normal(0, 0.05, 3)
        world_from_cam[:3, :3] = gtsam.Rot3.Expmap(rng.normal(0, 0.02, 3)).matrix() @ world_from_cam[:3, :3]
        est.append(invert(world_from_cam))
    times = np.arange(len(truth)) * 0.1
    io.write_tum(tmp_path / "ref.tum", times.tolist(), truth)
    io.write_tum(tmp_path / "est.tum", times.tolist(), est)
    ref_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "ref.tum"))
    est_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    rmse = evo_metrics.StatisticsType.rmse
    for ours, metric in (
        (ape(np.array(est), truth)[0].rmse, evo_metrics.APE(evo_metrics.PoseRelation.translation_part)),
        (rpe(np.array(est), truth)[0].rmse, evo_metrics.RPE(evo_metrics.PoseRelation.translation_part)),
        (rpe(np.array(est), truth)[1].rmse, evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg)),
    ):
        metric.process_data((ref_traj, est_traj))
        assert ours == pytest.approx(metric.get_statistic(rmse), rel=1e-6)


def test_without_odometry_frames_stand_alone_unless_smoothness_is_asked(scene):
    line_map, truth, frames = scene
    dropped = [*frames[:2], BLANK, *frames[3:]]
    start = Prior(cam_from_world=truth[0], radius_m=0.5)
    alone = localize_sequence(dropped, line_map, CAMERA, prior=start)
    assert not alone[2].success and not alone[2].reason.startswith(FROM_NEIGHBOURS)
    assert all(r.success for k, r in enumerate(alone) if k != 2)
    smoothed = localize_sequence(
        dropped, line_map, CAMERA, config=SequenceConfig(smoothness=True), prior=start
    )
    assert smoothed[2].reason.startswith(FROM_NEIGHBOURS)
    assert pose_errors(smoothed[2].cam_from_world, truth[2])[1] < 0.3


def test_reported_covariances_include_the_maps_accuracy(scene):
    # a map placing its lines to 5 cm: in the graph each frame's lines are tied to its pose by that much
    # (the six frames pool it through the odometry), and the reported covariance adds it once more (frames
    # seeing the same lines share the map's error); the tracker's innovation gate keeps the marginals alone
    line_map, truth, frames = scene
    scanned = LineMap.from_segments(line_map.segments, profile={"spacing_m": 0.05})
    relative, covariances = _odometry(truth)
    prior = Prior(cam_from_world=truth[0], radius_m=0.5)
    exact = localize_sequence(frames, line_map, CAMERA, relative, covariances, prior=prior)
    floored = localize_sequence(frames, scanned, CAMERA, relative, covariances, prior=prior)
    for a, b, T in zip(exact, floored, truth, strict=True):
        assert a.success and b.success
        assert pose_errors(b.cam_from_world, T)[1] < 1e-6  # exact lines: the tie costs nothing
        added = np.diag(b.covariance - a.covariance)[3:]
        assert np.all(added > 0.05**2 * (1 + 1 / 12)) and np.all(added < 0.05**2 * 2), added
    trackers = [Tracker(m, CAMERA) for m in (line_map, scanned)]
    for t in trackers:
        t.start_at(truth[0])
    for k in range(1, len(frames)):
        a, b = (t.step(frames[k], relative[k - 1]) for t in trackers)
        assert a.success and b.success
        np.testing.assert_allclose(np.diag(b.covariance - a.covariance)[3:], 0.05**2, rtol=1e-6)


def test_frames_between_fixes_start_where_the_fixes_and_the_odometry_put_them():
    # odometry that overshoots 1 cm a step: chained forward from the first fix, the frame before the
    # second fix would start 9 cm off; the pose graph of the two fixes and the odometry shares the drift
    # over the gap (a constant overshoot cancels: every frame starts at its true pose)
    truth = np.array(
        [look_at(np.array([0.1 * k, -5.0, 1.0]), np.array([0.1 * k, 0.0, 1.0])) for k in range(11)]
    )
    relative = [relative_pose(a, b) for a, b in itertools.pairwise(truth)]
    world_step = np.array([0.01, 0.0, 0.0])  # the overshoot, in the world
    for k, T in enumerate(relative):
        T[:3, 3] -= truth[k][:3, :3] @ world_step  # cam_k_from_cam_k+1 moves c_k+1 by +world_step
    covariances = [np.eye(6) * 1e-4 for _ in relative]
    fix = np.eye(6) * 1e-8
    alone = [
        Registration(
            success=k in (0, 10), cam_from_world=truth[k] if k in (0, 10) else np.eye(4), covariance=fix
        )
        for k in range(11)
    ]
    links = sequence._links(11, relative, covariances, SequenceConfig())
    chained = sequence.predict(truth[0], relative[0])
    for k in range(1, 9):
        chained = sequence.predict(chained, relative[k])
    assert pose_errors(chained, truth[9])[1] == pytest.approx(0.09, abs=1e-6)
    start = sequence._initial(alone, links, SequenceConfig())
    assert sorted(start) == list(range(11))
    for k, T in start.items():
        rot, pos, _ = pose_errors(T, truth[k])
        assert pos < 1e-3 and rot < 1e-2, k


def test_tracker_does_not_claim_a_track_whose_fixes_keep_landing_off_its_predictions():
    # odometry overshooting 3.5 cm every step (its covariance says ~1 cm): each fix alone passes the
    # innovation gate, but five in a row lie farther from their predictions than the gate over five allows,
    # and from then on the track is not claimed; with the window test off every frame is
    line_map, truth, frames = _scene(12)
    relative, _ = _odometry(truth)
    claims = {}
    for window in (TrackingConfig().consistency_window, 0):
        tracker = Tracker(line_map, CAMERA, TrackingConfig(consistency_window=window))
        tracker.start_at(truth[0], sigma_rot_deg=0.1, sigma_pos_m=0.005)
        assert tracker.step(frames[0]).success
        results = []
        for k in range(1, len(frames)):
            lying = relative[k - 1].copy()
            lying[:3, 3] += [0.0, 0.0, 0.035]
            results.append(tracker.step(frames[k], lying))
        assert all(r.success or "track disagrees" in r.reason for r in results)
        claims[window] = [r.success for r in results]
    assert all(claims[0])
    assert all(claims[5][:3]) and not any(claims[5][6:])


def test_a_given_start_pose_carries_the_frames_after_a_start_frame_without_lines(scene):
    """Frame 0 shows nothing (a blank wall) but its pose is given (``prior``): frame 1 is refined from that
    pose moved by the odometry ("track"), not searched for in the whole map, and frame 0 is posed by its
    neighbours."""
    line_map, truth, frames = scene
    relative, covariances = _odometry(truth)
    blank_first = [BLANK, *frames[1:]]
    config = SequenceConfig()
    first = Prior(cam_from_world=truth[0], radius_m=0.3, sigma_rot_deg=2.0)
    images = [image_lines(f, CAMERA, config.register.score) for f in blank_first]
    alone = frames_alone(blank_first, images, line_map, CAMERA, relative, covariances, config, first)
    assert not alone[0].success
    assert "track" in alone[1].timings and "relocalize" not in alone[1].timings
    assert all(r.success for r in alone[1:]), [r.reason for r in alone]
    results = localize_sequence(blank_first, line_map, CAMERA, relative, covariances, config, first)
    assert results[0].reason.startswith(FROM_NEIGHBOURS)
    for r, T in zip(results, truth, strict=True):
        rot, pos, _ = pose_errors(r.cam_from_world, T)
        assert pos < 0.01 and rot < 0.2


def test_a_fix_pulled_off_its_lines_by_decoy_edges_is_moved_back_along_its_valley():
    """Half the image's lines have a second edge 3 px beside them, longer (a frame's other side): the
    refinement, associating first at 2.5 x the score's distance, takes the decoys and settles off the truth.
    The rival test's valley move refines the orbits associating at the fine distance and returns the truth."""
    from linereg.pipeline import fine_config
    from linereg.score import score_pose

    lines3d, truth, lines2d = decoy_scene(CAMERA)
    config = SequenceConfig()
    image = image_lines(lines2d, CAMERA, config.register.score)
    line_map = LineMap.from_segments(lines3d)
    fix = sequence.refine_from(image, line_map, CAMERA, truth, 1.0, config)
    assert fix.success and pose_errors(fix.cam_from_world, truth)[0] > 0.1  # pulled off by the decoys
    moved = sequence.rival_test(image, line_map, CAMERA, fix, config)
    rot, pos, _ = pose_errors(moved.cam_from_world, truth)
    assert moved.success and rot < 1e-3 and pos < 1e-4
    fine = fine_config(config.register)
    sharper = score_pose(image, lines3d, CAMERA, moved.cam_from_world, fine).value
    assert sharper > score_pose(image, lines3d, CAMERA, fix.cam_from_world, fine).value


def test_a_fix_pulled_off_by_decoy_edges_is_moved_to_its_prediction_refined_finely():
    """The tracker's prediction move (``sequence.prediction_move``): the decoy scene's fix, pulled off the
    truth, is replaced by the prediction (here the truth) refined at the fine distance, which fits the lines
    closer; a prediction that is another answer (3 m away), or a fix on a loose map (rms above
    ``max_rms_px``), leaves the fix as it is."""
    from dataclasses import replace

    from linereg.geometry import make_cam_from_world

    lines3d, truth, lines2d = decoy_scene(CAMERA)
    config = SequenceConfig()
    image = image_lines(lines2d, CAMERA, config.register.score)
    line_map = LineMap.from_segments(lines3d)
    fix = sequence.refine_from(image, line_map, CAMERA, truth, 1.0, config)
    assert fix.success and pose_errors(fix.cam_from_world, truth)[0] > 0.1
    moved = sequence.prediction_move(image, line_map, CAMERA, fix, truth, config)
    rot, pos, _ = pose_errors(moved.cam_from_world, truth)
    assert moved.success and rot < 1e-3 and pos < 1e-4
    R, c = truth[:3, :3], -truth[:3, :3].T @ truth[:3, 3]
    elsewhere = make_cam_from_world(R, -R @ (c + np.array([3.0, 0.0, 0.0])))
    assert sequence.prediction_move(image, line_map, CAMERA, fix, elsewhere, config) is fix
    loose = replace(fix, rms_px=config.max_rms_px + 0.5)
    assert sequence.prediction_move(image, line_map, CAMERA, loose, truth, config) is loose
