"""Camera-LiDAR calibration over several frames (``linereg.calibrate``): one pose in every sweep's frame."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from linereg import Prior, calibrate, calibrate_segments
from linereg.bench.honesty import nees
from linereg.errors import InvalidInputError
from linereg.geometry import invert, make_cam_from_world, pose_errors
from linereg.map.linemap import LineMap
from linereg.sim.rig import moved_map, rig_maps

PHOTOS = (0, 2, 3)


@pytest.fixture(scope="module")
def rig():
    """Three demo photos, taken from a rig whose camera sits 2-3 deg and 0.4 m off its LiDAR, and each
    stop's map in its LiDAR's frame."""
    from linereg.sim.demo_scene import make_demo_scene

    scene = make_demo_scene(seed=0, num_images=max(PHOTOS) + 1)
    extrinsic = make_cam_from_world(
        Rotation.from_rotvec(np.radians([1.0, -2.0, 2.0])).as_matrix(), [0.1, -0.2, 0.3]
    )
    poses = [scene.cam_from_world[k] for k in PHOTOS]
    maps = rig_maps(LineMap.build(scene.cloud), poses, extrinsic)
    return scene, [scene.images[k] for k in PHOTOS], maps, extrinsic


def test_a_moved_map_is_seen_from_the_moved_pose_as_before(rig):
    scene, _, maps, extrinsic = rig
    world = moved_map(maps[0], invert(invert(extrinsic) @ scene.cam_from_world[PHOTOS[0]]))
    base = LineMap.build(scene.cloud)
    assert np.allclose(world.segments, base.segments, atol=1e-9)
    assert np.allclose(world.clusters.directions, base.clusters.directions, atol=1e-12)
    assert len(world.surfaces) == len(base.surfaces)


def test_the_extrinsic_is_found_from_a_rough_guess(rig):
    scene, images, maps, extrinsic = rig
    turn = Rotation.from_rotvec(np.radians([3.0, 2.0, -1.5])).as_matrix()
    guess = make_cam_from_world(turn @ extrinsic[:3, :3], extrinsic[:3, 3] + [0.25, -0.2, 0.2])
    result = calibrate(
        images, maps, scene.camera, Prior(cam_from_world=guess, sigma_rot_deg=5.0, radius_m=0.5)
    )
    assert result.success, result.reason
    rotation, position, _ = pose_errors(result.cam_from_lidar, extrinsic)
    assert rotation < 0.3 and position < 0.08
    assert nees(result.cam_from_lidar, extrinsic, result.covariance) < 20.1  # within its own 3 sigma
    assert len(result.singles) == len(images) and result.frame_inliers.shape == (len(images),)
    assert (result.frame_inliers >= 10).all() and np.isfinite(result.frame_rms_px).all()
    assert result.frame_offsets.shape == (len(images), 2) and np.nanmax(result.frame_offsets[:, 0]) < 1.0
    assert result.score == pytest.approx(float(result.frame_scores.sum()))
    for single, matches, line_map in zip(result.singles, result.frame_matches, maps, strict=True):
        assert matches[:, 1].max() < len(line_map) and single.matches[:, 1].max(initial=0) < len(line_map)
    json.dumps(result.to_dict())  # every field serialisable


def test_bad_input_is_refused_by_name(rig):
    scene, images, maps, extrinsic = rig
    guess = Prior(cam_from_world=extrinsic, sigma_rot_deg=5.0, radius_m=0.5)
    with pytest.raises(InvalidInputError, match="one map per photo"):
        calibrate(images, maps[:2], scene.camera, guess)
    with pytest.raises(InvalidInputError, match="at least 2 photos"):
        calibrate(images[:1], maps[:1], scene.camera, guess)
    with pytest.raises(InvalidInputError, match="whole pose"):
        calibrate(images, maps, scene.camera, Prior(position=extrinsic[:3, 3], radius_m=1.0))
    with pytest.raises(InvalidInputError, match="one Camera per photo"):
        calibrate(images, maps, [scene.camera], guess)
    good = np.random.default_rng(0).uniform(0, 400, (30, 4))
    with pytest.raises(InvalidInputError, match=r"lines2d\[1\]"):
        calibrate_segments([good, good[:, :3], good], maps, scene.camera, guess)


def test_the_command_line_writes_the_extrinsic_and_overlays(rig, tmp_path, capsys):
    import cv2

    from linereg.cli import main

    scene, images, maps, extrinsic = rig
    frames = []
    for k, (image, line_map) in enumerate(zip(images, maps, strict=True)):
        assert cv2.imwrite(str(tmp_path / f"photo{k}.png"), image)
        line_map.save(tmp_path / f"sweep{k}.linemap")
        frames += ["--frame", str(tmp_path / f"photo{k}.png"), str(tmp_path / f"sweep{k}.linemap")]
    (tmp_path / "camera.json").write_text(json.dumps(scene.camera.to_dict()))
    guess = make_cam_from_world(
        Rotation.from_rotvec(np.radians([-2.0, 1.0, 2.5])).as_matrix() @ extrinsic[:3, :3],
        extrinsic[:3, 3] + [-0.2, 0.1, 0.25],
    )
    (tmp_path / "guess.json").write_text(json.dumps({"cam_from_lidar": guess.tolist()}))
    common = ["--camera", str(tmp_path / "camera.json"), "--guess", str(tmp_path / "guess.json")]
    out = tmp_path / "extrinsic.json"
    code = main(["calibrate", *frames, *common, "--out", str(out), "--overlay", str(tmp_path / "ov")])
    out_text = capsys.readouterr().out
    assert code == 0, out_text
    assert "calibrated" in out_text and "photo0.png" in out_text and "alone: deg off" in out_text
    record = json.loads(out.read_text())
    assert record["success"] and len(record["frames"]) == len(images)
    rotation, position, _ = pose_errors(np.array(record["cam_from_lidar"]), extrinsic)
    assert rotation < 0.3 and position < 0.08
    assert sorted(p.name for p in (tmp_path / "ov").iterdir()) == [
        f"photo{k}.png" for k in range(len(images))
    ]
    assert main(["calibrate", *frames[:3], *common, "--out", str(out)]) == 2  # one frame: refused by name
    assert "two or more photos" in capsys.readouterr().err
    missing = ["--frame", str(tmp_path / "nope.png"), str(tmp_path / "sweep0.linemap")]
    assert main(["calibrate", *frames[:3], *missing, *common, "--out", str(out)]) == 2
    assert "nope.png" in capsys.readouterr().err


def test_the_benchmark_calibrates_a_synthetic_rig(tmp_path, capsys):
    from linereg.cli import main

    code = main(
        ["bench", "calibrate", "--seeds", "0", "--photos", "2", "--guesses", "1", "--out", str(tmp_path)]
    )
    assert code == 0
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert len(rows) == 1 and rows[0]["rig"] == "demo seed 0" and rows[0]["photos"] == 2
    assert not rows[0]["wrong"]  # claimed only if right
    assert "synthetic: " in capsys.readouterr().out


def test_a_distinct_rival_is_dismissed_only_when_the_best_holds_evidence_it_lacks(rig):
    """A distinct pose scoring within the margin makes the answer ambiguous unless what the answer explains
    beyond it, over the photos, is more than chance and what it explains beyond the answer is not
    (``calibration._rival``): turned 3 deg about the optical axis it explains none of the lines the truth
    misses (turned about the vertical, the facades' window columns line up again: that is evidence), so it
    is dismissed; a twin explaining exactly the same lines is not."""
    from dataclasses import replace

    from linereg.calibration import COVER_STEP_DEG, _frames, _Refined, _rival, _seen
    from linereg.config import RegisterConfig
    from linereg.lines2d import detect
    from linereg.significance import SearchSpace

    scene, images, maps, extrinsic = rig
    config = RegisterConfig()
    guess = Prior(cam_from_world=extrinsic, sigma_rot_deg=5.0, radius_m=0.5)
    cam = scene.camera.undistorted()
    frames = _frames([detect(im, scene.camera) for im in images], maps, [cam] * len(images), guess, config)
    space = SearchSpace(1.0, 27, COVER_STEP_DEG * np.sqrt(3) / 2)

    def refined(pose: np.ndarray) -> _Refined:
        return _Refined(pose, [], _seen(frames, pose, config))

    best = refined(extrinsic)
    turned = refined(make_cam_from_world(Rotation.from_rotvec(np.radians([0, 0, 3.0])).as_matrix() @ extrinsic[:3, :3], extrinsic[:3, 3]))  # fmt: skip
    within = replace(config, decide=replace(config.decide, margin=1.0))  # every rival within the margin
    assert _rival(frames, best, [turned], within, space) == ""
    twin = _rival(frames, best, [refined(extrinsic.copy())], within, space)
    assert twin.startswith("ambiguous: a distinct pose") and "chance poses would" in twin
    assert turned.value < (1.0 - config.decide.margin) * best.value  # below the margin: not a rival
    assert _rival(frames, best, [turned], config, space) == ""


def test_a_near_basin_counts_in_the_spread_by_its_odds_across_the_photos():
    """The spread of the basins the answer cannot tell apart weighs each by the odds that the photos favour
    it (``calibration._odds``, a paired t-test of the photos' scores): a basin every photo scores lower
    weighs nothing, one the photos disagree on weighs its odds, and with fewer than three photos (no
    spread to measure) every basin counts as likely as the answer."""
    from scipy.stats import t

    from linereg.calibration import _odds
    from linereg.pipeline import basin_spread as _spread

    mine = np.array([100.0, 120.0, 90.0, 110.0])
    assert _odds(mine, mine - 10.0) == 0.0  # every photo 10 px lower: certainly worse
    assert _odds(mine, mine) == 1.0 and _odds(mine[:2], mine[:2] - 50.0) == 1.0
    mixed = mine - np.array([30.0, -20.0, 25.0, -15.0])  # lower by 20 px in all, the photos disagree
    d = mine - mixed
    p = t.sf(d.mean() / (d.std(ddof=1) / 2.0), 3)
    assert _odds(mine, mixed) == pytest.approx(p / (1 - p)) and 0.0 < _odds(mine, mixed) < 1.0
    best = np.eye(4)
    other = make_cam_from_world(Rotation.from_rotvec([0.0, 0.02, 0.0]).as_matrix(), [0.1, 0.0, 0.0])
    assert np.allclose(_spread(best, [other], [0.0]), 0.0)
    full, half = _spread(best, [other], [1.0]), _spread(best, [other], [0.5])
    assert np.allclose(half, full * (0.5 / 1.5) / (1.0 / 2.0))
