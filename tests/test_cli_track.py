"""``linereg track`` on drawn frames of a small line scene: a folder or a video in, TUM and JSON out; bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from test_sequence import CAMERA, _scene

from linereg import io
from linereg.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Returns (folder of PNG frames, map, camera JSON, odometry TUM): the lines drawn black on grey."""
    root = tmp_path_factory.mktemp("track")
    line_map, truth, frames = _scene(5)
    (root / "frames").mkdir()
    for k, segments in enumerate(frames):
        image = np.full((CAMERA.height, CAMERA.width), 200, np.uint8)
        for x1, y1, x2, y2 in segments:
            cv2.line(image, (round(x1), round(y1)), (round(x2), round(y2)), 20, 2, cv2.LINE_AA)
        cv2.imwrite(str(root / "frames" / f"{k}.png"), image)
    line_map.save(root / "scene.linemap")
    (root / "camera.json").write_text(json.dumps(CAMERA.to_dict()))
    io.write_tum(root / "odometry.tum", [float(k) for k in range(len(truth))], truth)
    return root


@pytest.mark.parametrize("smooth", [False, True])
def test_track_writes_tum_and_records(files, tmp_path, capsys, smooth):
    argv = ["track", "--map", files / "scene.linemap", "--camera", files / "camera.json", files / "frames"]
    argv += [
        "--odometry",
        files / "odometry.tum",
        "--tum",
        tmp_path / "out.tum",
        "--out",
        tmp_path / "out.json",
    ]
    code = main([str(a) for a in argv] + (["--smooth"] if smooth else []))
    assert code == 0, capsys.readouterr().err
    records = json.loads((tmp_path / "out.json").read_text())
    assert [r["timestamp"] for r in records] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert (tmp_path / "out.tum").is_file()
    assert "frames:" in capsys.readouterr().err


def test_track_reads_a_video(files, tmp_path, capsys):
    video = tmp_path / "walk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (CAMERA.width, CAMERA.height))
    for k in range(3):
        writer.write(cv2.cvtColor(cv2.imread(str(files / "frames" / f"{k}.png")), cv2.COLOR_BGR2RGB))
    writer.release()
    argv = ["track", "--map", files / "scene.linemap", "--camera", files / "camera.json", video]
    code = main([str(a) for a in [*argv, "--tum", tmp_path / "out.tum", "--out", tmp_path / "out.json"]])
    assert code == 0, capsys.readouterr().err
    records = json.loads((tmp_path / "out.json").read_text())
    assert [r["timestamp"] for r in records] == pytest.approx([0.0, 0.1, 0.2])


def test_track_bad_odometry_is_one_line(files, tmp_path, capsys):
    bad = tmp_path / "bad.tum"
    bad.write_text("0 1 2 3\n")
    argv = ["track", "--map", files / "scene.linemap", "--camera", files / "camera.json", files / "frames"]
    code = main([str(a) for a in [*argv, "--odometry", bad, "--tum", tmp_path / "out.tum"]])
    err = capsys.readouterr().err
    assert code == 2 and "8 finite numbers" in err and "Traceback" not in err


def test_track_takes_a_top_speed_and_refuses_a_bad_one(files, tmp_path, capsys):
    argv = ["track", "--map", files / "scene.linemap", "--camera", files / "camera.json", files / "frames"]
    argv += ["--tum", tmp_path / "out.tum"]
    assert main([str(a) for a in [*argv, "--max-speed", "2.5"]]) == 0, capsys.readouterr().err
    assert (tmp_path / "out.tum").is_file()
    assert main([str(a) for a in [*argv[:-1], tmp_path / "other.tum", "--max-speed", "-1"]]) != 0
    assert "--max-speed" in capsys.readouterr().err
    assert not (tmp_path / "other.tum").exists()


@pytest.mark.parametrize("smooth", [False, True])
def test_track_starts_from_a_given_pose(files, tmp_path, capsys, smooth):
    """``--start``: the first frame is tracked from a pose prior (given as world_from_cam, as a robot's
    dock pose is written); a position alone is refused, naming the option."""
    from linereg.geometry import invert, pose_errors

    _, truth, _ = _scene(5)
    start = {"world_from_cam": invert(truth[0]).tolist(), "sigma_rot_deg": 1.0, "radius_m": 0.15}
    (tmp_path / "start.json").write_text(json.dumps(start))
    argv = ["track", "--map", files / "scene.linemap", "--camera", files / "camera.json", files / "frames"]
    argv += [
        "--tum",
        tmp_path / "out.tum",
        "--out",
        tmp_path / "out.json",
        "--start",
        tmp_path / "start.json",
    ]
    code = main([str(a) for a in argv] + (["--smooth"] if smooth else []))
    assert code == 0, capsys.readouterr().err
    records = json.loads((tmp_path / "out.json").read_text())
    assert records[0]["success"], records[0]["reason"]
    rot, pos, _ = pose_errors(np.array(records[0]["cam_from_world"]), truth[0])
    assert rot < 0.5 and pos < 0.05, (rot, pos)
    (tmp_path / "where.json").write_text(json.dumps({"position": [0, 0, 0], "radius_m": 1}))
    code = main([str(a) for a in [*argv[:-1], tmp_path / "where.json"]])
    err = capsys.readouterr().err
    assert code != 0 and "--start" in err and "pose" in err and "Traceback" not in err
