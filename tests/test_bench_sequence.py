"""``linereg bench sequence --seeds``: one walk per seed and every row's wrong claims summed over them."""

import argparse

import pytest

from linereg.bench import sequence
from linereg.errors import InvalidInputError


def _walk(wrong: dict[str, int], within: dict[str, float], ate: tuple[float, float]) -> dict:
    rows = {name: {"wrong": wrong[name], "within": within[name]} for name in wrong}
    rows["global"] |= {"frames": list(range(0, 320, 20))}  # every 20th frame only
    rows["per-frame"]["ate_m"], rows["smoothed"]["ate_m_same_frames"] = ate
    return {"rows": rows, "frames": 320}


def test_the_seeds_table_sums_each_rows_wrong_claims_and_frames_within(capsys):
    walks = [
        _walk(
            {"per-frame": 0, "smoothed": 0, "tracking": 0, "tracking-reach": 1, "global": 0},
            {"per-frame": 0.5, "smoothed": 0.75, "tracking": 0.5, "tracking-reach": 0.25, "global": 0.0625},
            (0.08, 0.04),
        ),
        _walk(
            {"per-frame": 0, "smoothed": 0, "tracking": 2, "tracking-reach": 110, "global": 1},
            {"per-frame": 0.5, "smoothed": 0.75, "tracking": 1.0, "tracking-reach": 0.125, "global": 0.125},
            (0.1, 0.06),
        ),
    ]
    walks[0]["rows"]["per-frame"]["covariance"] = {"claims": 160, "beyond_3sigma": 3, "nees_median": 4.0}
    walks[1]["rows"]["per-frame"]["covariance"] = {"claims": 150, "beyond_3sigma": 1, "nees_median": 6.0}
    sequence._print_seeds([0, 2], walks)
    header, _, _, tracking, reach, global_, beyond, ratios = capsys.readouterr().out.strip().splitlines()
    assert beyond.endswith("all walks: per-frame 4/310")  # rows without the check are left out
    assert "seeds 0 2" in header
    assert tracking.endswith("all:    2 /  480 of 640")
    assert reach.endswith("all:  111 /  120 of 640")
    assert global_.endswith("all:    1 /    3 of 32")  # 1 + 2 of the 16 + 16 global frames
    assert ratios.endswith("0.50  0.60")  # smoothed / per-frame ATE on the per-frame frames


def test_the_same_seed_twice_is_refused(tmp_path):
    parser = argparse.ArgumentParser()
    sequence.configure(parser)
    args = parser.parse_args(["--scene", "synthetic", "--seeds", "3", "3", "--out", str(tmp_path / "out")])
    with pytest.raises(InvalidInputError, match="--seeds"):
        sequence.run(args)


def test_the_at_truth_row_is_what_each_frames_lines_allow_from_its_ground_truth():
    """A frame rendered 3 degrees off its ground truth (a colour camera not registered to the pose) is
    refined to where its lines put it, outside ``--good-rot-deg`` for every row; a blank frame is not posed."""
    import numpy as np

    from linereg.camera import Camera
    from linereg.geometry import rotation_from_vector
    from linereg.map.linemap import LineMap
    from linereg.score import image_lines
    from linereg.sequence import SequenceConfig
    from linereg.sim.synthetic import look_at, project_visible

    camera = Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)
    rng = np.random.default_rng(0)
    directions = np.r_[np.tile(np.eye(3), (12, 1)), rng.normal(size=(8, 3))]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = rng.uniform(-1.5, 1.5, (len(directions), 3))
    lines3d = np.c_[starts, starts + rng.uniform(0.4, 1.2, (len(directions), 1)) * directions]
    angles = np.radians(2.0) * np.arange(3)
    truth = np.array([look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 0.8]), np.zeros(3)) for a in angles])
    seen = truth.copy()
    seen[1, :3, :3] = rotation_from_vector(np.radians([0.0, 3.0, 0.0])) @ truth[1, :3, :3]
    seen[1, :3, 3] = rotation_from_vector(np.radians([0.0, 3.0, 0.0])) @ truth[1, :3, 3]  # turned in place
    config = SequenceConfig()
    frames = [project_visible(lines3d, camera, T)[0] for T in seen]
    frames[2] = np.zeros((0, 4))
    images = [image_lines(f, camera, config.register.score) for f in frames]
    parser = argparse.ArgumentParser()
    sequence.configure(parser)
    args = parser.parse_args([])
    row = sequence._at_truth(images, LineMap.from_segments(lines3d), camera, truth, config, args)
    assert row["posed_mask"].tolist() == [True, True, False]
    assert row["within"] == pytest.approx(1 / 3)  # frame 0 of the three
    assert np.allclose(row["poses"][0], truth[0], atol=1e-6)
    assert np.allclose(row["poses"][1], seen[1], atol=1e-4)  # where its lines are, not its ground truth


def _sequence_set(folder, frames: int) -> None:
    """Writes a set folder: a box room's cloud.ply (ASCII PLY) and a sequence of ``frames`` grey frames."""
    import json

    import cv2
    import numpy as np

    g = np.arange(0.0, 2.0001, 0.05)
    a, b = np.meshgrid(g, g)
    faces = []
    for axis in range(3):
        for side in (0.0, 2.0):
            p = np.zeros((a.size, 3))
            p[:, axis] = side
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a.ravel(), b.ravel()
            faces.append(p)
    points = np.unique(np.round(np.vstack(faces), 6), axis=0)
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
    header += "property float z\nend_header\n"
    folder.mkdir(parents=True)
    (folder / "cloud.ply").write_text(
        header + "\n".join(" ".join(f"{v:.6f}" for v in p) for p in points) + "\n"
    )
    (folder / "sequence").mkdir()
    entries = []
    for k in range(frames):
        cv2.imwrite(str(folder / "sequence" / f"f{k}.png"), np.full((48, 64), 128, np.uint8))
        pose = np.eye(4)
        pose[:3, 3] = [-1.0 - 0.01 * k, -1.0, -0.2]  # inside the room, looking along +z
        entries.append({"file": f"f{k}.png", "timestamp": 0.1 * k, "T_cam_from_world": pose.tolist()})
    camera = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0}
    camera["distortion"] = {"model": "none", "coeffs": []}
    meta = {"camera": camera, "rate_hz": 10, "frames": entries}
    (folder / "sequence" / "frames.json").write_text(json.dumps(meta))


def test_real_sequences_are_the_set_folders_with_a_frames_json_each_read_with_its_map(tmp_path):
    _sequence_set(tmp_path / "room_b", 3)
    _sequence_set(tmp_path / "room_a", 2)
    (tmp_path / "no_sequence").mkdir()
    assert sequence.real_sequences(tmp_path) == ["room_a", "room_b"]
    assert sequence.real_sequences(tmp_path / "absent") == []
    problem = sequence.real_problem(tmp_path / "room_b")
    assert problem["name"] == "room_b" and len(problem["frames"]) == 3
    assert problem["truth"].shape == (3, 4, 4) and len(problem["relative"]) == 2
    assert problem["camera"].fx == 50.0 and len(problem["line_map"]) > 0
    assert problem["times"].tolist() == [0.0, 0.1, 0.2] and not problem["blank"].any()


def test_an_unknown_scene_is_refused_naming_the_sets_found(tmp_path):
    _sequence_set(tmp_path / "data" / "room_a", 2)
    parser = argparse.ArgumentParser()
    sequence.configure(parser)
    args = parser.parse_args(
        ["--scene", "kitchen", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "o")]
    )
    with pytest.raises(InvalidInputError, match=r"--scene kitchen: .*found: room_a"):
        sequence.run(args)


def test_a_real_sequence_is_evaluated_once_per_odometry_draw(tmp_path, monkeypatch, capsys):
    import json

    import numpy as np

    _sequence_set(tmp_path / "data" / "room_a", 3)
    problem = sequence.real_problem(tmp_path / "data" / "room_a")
    again = sequence.with_odometry(problem, 0)
    other = sequence.with_odometry(problem, 1)
    assert all(np.array_equal(a, b) for a, b in zip(problem["relative"], again["relative"], strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(problem["relative"], other["relative"], strict=True))
    assert other["frames"] is problem["frames"] and other["truth"] is problem["truth"]
    drawn = []

    def evaluate(p, args, out):  # the rows themselves are the walks' tests' business
        drawn.append((out.name, p["relative"][0]))
        return {"rows": {"smoothed": {"within": 0.5 * len(drawn), "wrong": 0}}}

    monkeypatch.setattr(sequence, "evaluate", evaluate)
    parser = argparse.ArgumentParser()
    sequence.configure(parser)
    out = tmp_path / "o"
    argv = ["--scene", "room_a", "--data", str(tmp_path / "data"), "--out", str(out)]
    sequence.run(parser.parse_args([*argv, "--odometry-seeds", "0", "1"]))
    assert [name for name, _ in drawn] == ["room_a-odometry0", "room_a-odometry1"]
    assert np.array_equal(drawn[0][1], problem["relative"][0])
    assert np.array_equal(drawn[1][1], other["relative"][0])
    assert "smoothed" in capsys.readouterr().out
    assert set(json.loads((out / "results.json").read_text())) == {"room_a-odometry0", "room_a-odometry1"}
    with pytest.raises(InvalidInputError, match="--odometry-seeds must differ"):
        sequence.run(parser.parse_args([*argv, "--odometry-seeds", "2", "2"]))
