"""The ``linereg`` CLI end to end on a small demo scene, and its answers to bad input (issue 3)."""

import json
import os
import stat
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import save_box_map

from linereg import localize
from linereg.cli import main
from linereg.geometry import camera_center, pose_errors
from linereg.map.linemap import LineMap

NUM_IMAGES = 2


def write_ply(path, points: np.ndarray) -> None:
    """Writes (P, 3) points as a binary little-endian PLY with float32 x y z."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path.write_bytes(header.encode() + np.asarray(points, dtype="<f4").tobytes())


def run(capsys, *argv) -> tuple[int, str, str]:
    """Returns (exit code, stdout, stderr) of ``linereg ARGV``."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def leftovers(folder) -> list[str]:
    """Returns names of temp files an atomic write could leave behind in ``folder``."""
    return [p.name for p in folder.rglob("*") if p.name.startswith(".") or p.suffix in (".tmp", ".part")]


@pytest.fixture(scope="module")
def scene():
    """The demo scene as `linereg demo` makes it (a coarser scan gives a map too poor to localize in)."""
    from linereg.sim.demo_scene import make_demo_scene

    return make_demo_scene(seed=0, num_images=NUM_IMAGES)


@pytest.fixture(scope="module")
def files(scene, tmp_path_factory):
    """The scene on disk: cloud.ply, camera.json, image PNGs, and a map built by ``linereg map build``."""
    folder = tmp_path_factory.mktemp("cli")
    write_ply(folder / "cloud.ply", scene.cloud)
    (folder / "camera.json").write_text(json.dumps(scene.camera.to_dict()))
    images = []
    for k, image in enumerate(scene.images):
        images.append(folder / f"img{k}.png")
        assert cv2.imwrite(str(images[-1]), image)
    code = main(["map", "build", str(folder / "cloud.ply"), "-o", str(folder / "demo.npz")])
    assert code == 0
    return folder, images


def test_map_build_and_info(files, capsys):
    folder, _ = files
    assert (folder / "demo.npz").is_file() and not leftovers(folder)
    line_map = LineMap.load(folder / "demo.npz")
    assert line_map.metadata["name"] == "cloud" and len(line_map) > 100  # named after the cloud file
    code, out, err = run(capsys, "map", "info", "--json", folder / "demo.npz")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["name"] == "cloud" and summary["num_segments"] == len(line_map)
    assert len(summary["clusters"]) == len(line_map.clusters) >= 3  # a building: at least 3 directions
    assert sum(c["size"] for c in summary["clusters"]) + summary["unclustered"] == len(line_map)
    lo, hi = np.array(summary["bounds"])
    assert (lo <= line_map.segments.reshape(-1, 3).min(axis=0) + 1e-9).all()
    assert (hi >= line_map.segments.reshape(-1, 3).max(axis=0) - 1e-9).all()
    code, out, _ = run(capsys, "map", "info", folder / "demo.npz")
    assert code == 0
    assert out.startswith(f"map 'cloud' ({folder / 'demo.npz'})")
    assert f"segments: {len(line_map)} (total" in out and f"clusters: {len(line_map.clusters)} (" in out
    kind = line_map.metadata["profile"]["kind"]
    assert f"  cloud: {kind}, " in out and "density spread" in out  # the cloud's profile in words


def test_localize_writes_json_tum_and_overlays(scene, files, capsys, tmp_path):
    """The command's contract: a record per image, a TUM row per success, an overlay per image, never a wrong
    pose claimed that the record does not show. Whether the demo photos localize is the benchmark's business
    (``bench demo``) and ``test_demo_photos_never_claim_a_wrong_pose``'s."""
    from evo.tools import file_interface

    folder, images = files
    # TUM-style names (the capture time): the TUM file's timestamps
    stamps = [1305031102.175304, 1305031102.211214]
    named = [tmp_path / f"{stamp:.6f}.png" for stamp in stamps]
    for src, dst in zip(images, named, strict=True):
        dst.write_bytes(src.read_bytes())
    out, tum, overlay = tmp_path / "poses.json", tmp_path / "traj.tum", tmp_path / "overlay"
    code, _, err = run(
        capsys, "localize", "--map", folder / "demo.npz", "--camera", folder / "camera.json", *named,
        "--out", out, "--tum", tum, "--overlay", overlay,
    )  # fmt: skip
    assert code == 0, err
    poses = json.loads(out.read_text())
    assert sorted(poses) == sorted(map(str, named))
    done = [path for path in named if poses[str(path)]["success"]]
    assert f"localized {len(done)}/{NUM_IMAGES} images" in err
    for path, stamp in zip(named, stamps, strict=True):
        record = poses[str(path)]
        assert {"success", "reason", "cam_from_world", "num_inliers", "covariance", "timings"} <= set(record)
        assert record["timestamp"] == stamp and record["timings"]["total"] > 0
        if record["success"]:
            assert record["num_inliers"] >= 6 and np.isfinite(record["cam_from_world"]).all()
        else:
            assert record["reason"]
    # the TUM file as evo reads it: the successes' times, and positions = the camera centres
    if done:
        trajectory = file_interface.read_tum_trajectory_file(str(tum))
        np.testing.assert_allclose(trajectory.timestamps, [float(p.stem) for p in done], rtol=0, atol=1e-6)
        for position, world_from_cam, path in zip(
            trajectory.positions_xyz, trajectory.poses_se3, done, strict=True
        ):
            cam_from_world = np.array(poses[str(path)]["cam_from_world"])
            np.testing.assert_allclose(position, camera_center(cam_from_world), atol=1e-6)
            np.testing.assert_allclose(world_from_cam @ cam_from_world, np.eye(4), atol=1e-6)
    for path in named:
        picture = cv2.imread(str(overlay / f"{path.stem}.png"))
        assert picture is not None and picture.shape == (scene.camera.height, scene.camera.width, 3)
    assert not leftovers(tmp_path)
    mode = 0o666 & ~current_umask()
    for written in (out, *([tum] if done else []), *overlay.iterdir()):
        assert stat.S_IMODE(written.stat().st_mode) == mode, written


def test_demo_photos_never_claim_a_wrong_pose(scene, files):
    folder, _ = files
    line_map = LineMap.load(folder / "demo.npz")
    for image, truth in zip(scene.images, scene.cam_from_world, strict=True):
        reg = localize(image, line_map, scene.camera)
        if reg.success:
            rot, pos, _ = pose_errors(reg.cam_from_world, truth)
            assert rot < 2.0 and pos < 0.5, (rot, pos)


def test_localize_searches_within_priors(scene, files, capsys, tmp_path):
    """``--prior``: a TUM file of rough poses (each truth turned 1.5 deg and moved 0.2 m) with --prior-sigma,
    and per-image JSON position priors that leave the truth out: every record names the prior it was
    searched within, and no pose is claimed outside it."""
    from scipy.spatial.transform import Rotation

    from linereg.io import write_tum

    folder, images = files
    rough = []
    for k, truth in enumerate(scene.cam_from_world):
        turn = Rotation.from_rotvec(np.radians(1.5) * np.array([0.6, 0.8, 0.0])).as_matrix()
        T = truth.copy()
        T[:3, :3] = turn @ truth[:3, :3]
        T[:3, 3] = -T[:3, :3] @ (camera_center(truth) + np.array([0.2 * (-1) ** k, 0.0, 0.0]))
        rough.append(T)
    write_tum(tmp_path / "rough.tum", [0.0, 1.0], rough)  # the images' stems are not numbers: 0, 1
    base = ["localize", "--map", folder / "demo.npz", "--camera", folder / "camera.json", *images]
    code, _, err = run(capsys, *base, "--out", tmp_path / "a.json", "--prior", tmp_path / "rough.tum",
                       "--prior-sigma", 5, 0.5)  # fmt: skip
    assert code == 0, err
    records = json.loads((tmp_path / "a.json").read_text())
    for k, path in enumerate(images):
        record = records[str(path)]
        np.testing.assert_allclose(record["prior"]["cam_from_world"], rough[k], atol=1e-6)
        assert (record["prior"]["sigma_rot_deg"], record["prior"]["radius_m"]) == (5.0, 0.5)
        if record["success"]:
            rot, pos, _ = pose_errors(np.array(record["cam_from_world"]), scene.cam_from_world[k])
            assert rot < 2.0 and pos < 0.5, (rot, pos)
    # 30 m off the truth within 5 m: the truth is outside, and nothing outside is an answer
    away = {
        path.name: {"position": (camera_center(T) + np.array([30.0, 0.0, 0.0])).tolist(), "radius_m": 5.0}
        for path, T in zip(images, scene.cam_from_world, strict=True)
    }
    (tmp_path / "away.json").write_text(json.dumps(away))
    code, _, err = run(capsys, *base, "--out", tmp_path / "b.json", "--prior", tmp_path / "away.json")
    assert code == 0, err
    for path, record in json.loads((tmp_path / "b.json").read_text()).items():
        assert record["prior"]["position"] == away[Path(path).name]["position"]
        if record["success"]:
            centre = camera_center(np.array(record["cam_from_world"]))
            assert np.linalg.norm(centre - record["prior"]["position"]) <= 5.0 + 1e-9


def current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_demo_smoke(scene, capsys, tmp_path, monkeypatch):
    import linereg.sim.demo_scene

    # the small scene of this module instead of a fresh 1 M-point one: this checks the command, not the scene
    monkeypatch.setattr(linereg.sim.demo_scene, "make_demo_scene", lambda seed, num_images: scene)
    code, out, err = run(capsys, "demo", "--images", NUM_IMAGES, "--out", tmp_path)
    assert code == 0, err
    assert "localized" in out and len(list(tmp_path.glob("*.png"))) == NUM_IMAGES


def test_bench_demo_with_a_rough_prior(scene, capsys, tmp_path, monkeypatch):
    """``bench demo --prior ROT POS``: each photo searched near a rough guess of its pose (the calibration
    case), recorded in results.json; never a wrong pose claimed."""
    import linereg.sim.demo_scene

    monkeypatch.setattr(linereg.sim.demo_scene, "make_demo_scene", lambda seed, num_images: scene)
    argv = ["bench", "demo", "--images", NUM_IMAGES, "--out", tmp_path]
    code, out, err = run(capsys, *argv, "--prior", 5, 0.5)
    assert code == 0, err
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["options"]["prior"] == {"rotation_deg": 5.0, "position_m": 0.5}
    assert len(results["seeds"][0]["images"]) == NUM_IMAGES
    assert results["summary"]["stats"]["wrong_claimed"] == 0 and "localized:" in out
    # every claim's error measured in its reported sigmas (``bench/honesty.py``)
    claims = [r for r in results["seeds"][0]["images"] if r["reported"]]
    assert results["summary"]["covariance"]["claims"] == len(claims) and "covariance:" in out
    assert all(r["nees"] >= 0 for r in claims)
    code, _, err = run(capsys, *argv, "--prior", -1, 0.5)
    assert_user_error(code, err, "--prior")


# --- bad input: a clear message naming the file, exit code != 0, no traceback, nothing half-written ---


def assert_user_error(code: int, err: str, name: str) -> None:
    assert code != 0
    assert name in err, err
    assert "Traceback" not in err


CORRUPT_PLY = (
    b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nend_header\n\x00\x01"
)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("missing.ply", None),
        ("corrupt.ply", CORRUPT_PLY),
        ("garbage.ply", b"\x89PNG not a cloud at all"),
        ("cloud.foo", b"1 2 3\n"),
        ("empty.xyz", b""),
        ("empty.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n"),
    ],
)  # fmt: skip
def test_map_build_rejects_bad_clouds(tmp_path, capsys, name, content):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    code, _, err = run(capsys, "map", "build", tmp_path / name, "-o", tmp_path / "out.npz")
    assert_user_error(code, err, name)
    assert not (tmp_path / "out.npz").exists() and not leftovers(tmp_path)


def test_map_info_rejects_a_corrupt_map(tmp_path, capsys):
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    code, _, err = run(capsys, "map", "info", tmp_path / "bad.npz")
    assert_user_error(code, err, "bad.npz")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A small map (the edges of a box), a 640x480 camera file and a valid image, for the bad-input cases."""
    from linereg.sim.views import street_camera

    folder = tmp_path_factory.mktemp("small")
    save_box_map(folder / "small.npz")
    (folder / "camera.json").write_text(json.dumps(street_camera().to_dict()))
    assert cv2.imwrite(str(folder / "ok.png"), np.full((480, 640), 100, np.uint8))
    return folder


def localize_args(small, tmp_path, images, camera=None, line_map=None):
    return [
        "localize", "--map", line_map or small / "small.npz", "--camera", camera or small / "camera.json",
        *images, "--out", tmp_path / "poses.json",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("missing.png", None),
        ("corrupt.png", b"\x89PNG\r\n\x1a\n truncated"),
        ("image.xyz", b"1 2 3\n"),
    ],
)
def test_localize_rejects_bad_image_files(small, tmp_path, capsys, name, content):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    code, _, err = run(capsys, *localize_args(small, tmp_path, [tmp_path / name]))
    assert_user_error(code, err, name)
    assert not leftovers(tmp_path)


def test_localize_rejects_an_image_of_another_size(small, tmp_path, capsys):
    assert cv2.imwrite(str(tmp_path / "small.png"), np.full((120, 160, 3), 128, np.uint8))
    code, _, err = run(capsys, *localize_args(small, tmp_path, [tmp_path / "small.png"]))
    assert_user_error(code, err, "small.png")
    assert "160" in err and not leftovers(tmp_path)


@pytest.mark.parametrize(
    ("name", "text", "problem"),
    [
        ("no_fy.json", json.dumps({"fx": 600, "cx": 320, "cy": 240, "width": 640, "height": 480}), "fy"),
        ("broken.json", '{"fx": 600,', "JSON"),
        ("camera.yaml", "fx: 600\n", ""),
    ],
)
def test_localize_rejects_bad_camera_files(small, tmp_path, capsys, name, text, problem):
    (tmp_path / name).write_text(text)
    code, _, err = run(capsys, *localize_args(small, tmp_path, [small / "ok.png"], camera=tmp_path / name))
    assert_user_error(code, err, name)
    assert problem in err
    assert not (tmp_path / "poses.json").exists() and not leftovers(tmp_path)


@pytest.mark.parametrize(
    ("name", "text", "extra", "problem"),
    [
        ("some.json", json.dumps({"other.png": {"position": [0, 0, 0], "radius_m": 5}}), [], "ok.png"),
        ("typo.json", json.dumps({"position": [0, 0, 0], "radus_m": 5}), [], "radus_m"),
        ("rough.tum", "0 1 2 3 0 0 0 1\n", [], "--prior-sigma"),
        ("far.tum", "7 1 2 3 0 0 0 1\n", ["--prior-sigma", "5", "0.5"], "no pose within"),
        ("site.json", json.dumps({"position": [0, 0, 0], "radius_m": 5}), ["--prior-sigma", "-1", "1"], "positive"),
    ],
)  # fmt: skip
def test_localize_rejects_priors_that_do_not_fit(small, tmp_path, capsys, name, text, extra, problem):
    """A prior file that names no prior for an image, mistypes a key, or a TUM file without its sigma: said
    before anything is localized, naming the file."""
    (tmp_path / name).write_text(text)
    argv = localize_args(small, tmp_path, [small / "ok.png"])
    code, _, err = run(capsys, *argv, "--prior", tmp_path / name, *extra)
    assert_user_error(code, err, problem)
    assert not (tmp_path / "poses.json").exists() and not leftovers(tmp_path)
    code, _, err = run(capsys, *argv, "--prior-sigma", "5", "0.5")
    assert_user_error(code, err, "--prior")


def test_localize_rejects_a_corrupt_map(small, tmp_path, capsys):
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    argv = localize_args(small, tmp_path, [small / "ok.png"], line_map=tmp_path / "bad.npz")
    code, _, err = run(capsys, *argv)
    assert_user_error(code, err, "bad.npz")
    assert not (tmp_path / "poses.json").exists() and not leftovers(tmp_path)


def test_localize_of_a_featureless_image_is_a_failed_record_not_an_error(small, tmp_path, capsys):
    code, _, err = run(capsys, *localize_args(small, tmp_path, [small / "ok.png"]))
    assert code == 0, err
    record = json.loads((tmp_path / "poses.json").read_text())[str(small / "ok.png")]
    assert record["success"] is False and record["reason"]
    assert record["timestamp"] == 0.0  # not a number in the file name: the image's place in the batch


def test_tum_timestamps_from_numeric_stems_else_positions():
    from linereg.cli.localize import tum_timestamps

    assert tum_timestamps([Path("a/1305031102.175304.png"), Path("b/12.jpg")]) == [1305031102.175304, 12.0]
    assert tum_timestamps([Path("img7.png"), Path("3.png")]) == [0.0, 1.0]  # one rule for the batch
    assert tum_timestamps([Path("a/5.png"), Path("b/5.png")]) == [0.0, 1.0]  # equal stems would collide


# --- arguments checked before any work; what a file is when it is not what was expected (issue 8) ---


@pytest.fixture
def no_work(monkeypatch):
    """Fails the test if localize starts its workers (loads the map)."""
    import linereg.cli.localize

    def started(*args):
        raise AssertionError("the work started before the arguments were checked")

    monkeypatch.setattr(linereg.cli.localize, "_init_worker", started)


@pytest.mark.parametrize("flag", ["--out", "--tum", "--overlay"])
def test_localize_refuses_unwritable_outputs_before_any_work(small, tmp_path, capsys, no_work, flag):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file.txt").write_text("keep me")
    target = tmp_path / ("file.txt" if flag == "--overlay" else "folder")
    argv = [*localize_args(small, tmp_path, [small / "ok.png"]), flag, target]  # the last --out counts
    code, _, err = run(capsys, *argv)
    assert code == 2 and "Traceback" not in err
    assert f"error: {flag} {target}: " in err and len(err.strip().splitlines()) == 1, err
    assert (tmp_path / "file.txt").read_text() == "keep me" and not (tmp_path / "poses.json").exists()


def test_localize_refuses_an_output_under_a_file(small, tmp_path, capsys, no_work):
    (tmp_path / "file.txt").write_text("")
    argv = [*localize_args(small, tmp_path, [small / "ok.png"]), "--out", tmp_path / "file.txt" / "p.json"]
    code, _, err = run(capsys, *argv)
    assert code == 2 and "--out" in err and "is a file, not a directory" in err


def test_map_build_refuses_a_directory_output_before_reading(tmp_path, capsys, monkeypatch):
    import linereg.io

    monkeypatch.setattr(linereg.io, "read_cloud", lambda path: pytest.fail("read before the check"))
    (tmp_path / "out").mkdir()
    write_ply(tmp_path / "c.ply", np.zeros((10, 3)))
    code, _, err = run(capsys, "map", "build", tmp_path / "c.ply", "-o", tmp_path / "out")
    assert code == 2 and f"--output {tmp_path / 'out'}: is a directory" in err


def test_map_build_of_an_empty_ply_says_empty(tmp_path, capsys):
    (tmp_path / "zero.ply").write_bytes(b"")
    code, _, err = run(capsys, "map", "build", tmp_path / "zero.ply", "-o", tmp_path / "out.linemap")
    assert code == 2 and f"{tmp_path / 'zero.ply'}: empty file" in err and "magic" not in err


def test_a_directory_as_map_is_named_a_directory(small, tmp_path, capsys):
    (tmp_path / "maps").mkdir()
    code, _, err = run(capsys, "map", "info", tmp_path / "maps")
    assert code == 2 and f"{tmp_path / 'maps'}: is a directory" in err
    argv = localize_args(small, tmp_path, [small / "ok.png"], line_map=tmp_path / "maps")
    code, _, err = run(capsys, *argv)
    assert code == 2 and f"{tmp_path / 'maps'}: is a directory" in err
    assert not (tmp_path / "poses.json").exists()


@pytest.mark.parametrize("workers", [1, 2])
def test_random_bytes_as_map_are_not_a_linereg_map(small, tmp_path, capsys, workers):
    (tmp_path / "noise.linemap").write_bytes(np.random.default_rng(1).bytes(2000))
    code, _, err = run(capsys, "map", "info", tmp_path / "noise.linemap")
    assert code == 2 and "noise.linemap: not a linereg map file" in err and "pickle" not in err
    argv = localize_args(small, tmp_path, [small / "ok.png"], line_map=tmp_path / "noise.linemap")
    code, _, err = run(capsys, *argv, "--workers", workers)
    assert code == 2 and "noise.linemap: not a linereg map file" in err and "Traceback" not in err


def test_a_truncated_map_is_one_line_with_worker_processes(small, tmp_path, capsys):
    data = (small / "small.npz").read_bytes()
    (tmp_path / "cut.linemap").write_bytes(data[: len(data) // 2])
    argv = localize_args(small, tmp_path, [small / "ok.png"] * 2, line_map=tmp_path / "cut.linemap")
    code, _, err = run(capsys, *argv, "--workers", 2)
    assert code == 2 and "cut.linemap: corrupt or truncated" in err and "Traceback" not in err


def test_api_localize_and_service_give_the_same_answer(scene, files, capsys, tmp_path):
    """One image, one map, one default configuration: the Python API, ``linereg localize`` and
    ``linereg serve`` + ``linereg query`` answer alike (the wire carries what Registration holds)."""
    import socket

    from service import Service, ServiceConfig

    folder, images = files
    image, camera_file, map_file = images[0], folder / "camera.json", folder / "demo.npz"
    api = localize(cv2.imread(str(image), cv2.IMREAD_UNCHANGED), LineMap.load(map_file), scene.camera)
    out = tmp_path / "poses.json"
    code, _, err = run(capsys, "localize", "--map", map_file, "--camera", camera_file, image, "--out", out)
    assert code == 0, err
    cli = json.loads(out.read_text())[str(image)]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    config = ServiceConfig(
        loader="service.engine:load_map_engine", loader_args=(str(map_file), "demo", None),
        listen=(endpoint,), workers=1,
    )  # fmt: skip
    with Service(config):
        code, stdout, err = run(
            capsys, "query", "--connect", endpoint, "--map", "demo", "--camera", camera_file, image,
            "--timeout", 120,
        )  # fmt: skip
    assert code == 0, err
    served = json.loads(stdout.splitlines()[0])
    for record in (cli, served):
        assert record["success"] == api.success and record["reason"] == api.reason
        np.testing.assert_allclose(record["cam_from_world"], api.cam_from_world, atol=1e-6)
        assert record["score"] == pytest.approx(api.score, rel=1e-6)
        assert record["ambiguity"] == pytest.approx(api.ambiguity, rel=1e-6)
        assert len(record["alternatives"]) == len(api.alternatives)
