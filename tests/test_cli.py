"""The ``linereg`` CLI end to end on a small demo scene, and its answers to bad input (issue 3)."""

import json
import math

import cv2
import numpy as np
import pytest

from linereg.cli import main
from linereg.geometry import camera_center, pose_errors

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
    code, out, err = run(capsys, "map", "info", folder / "demo.npz")
    assert code == 0
    assert "segments" in (out + err).lower()


def test_localize_writes_json_tum_and_overlays(scene, files, capsys, tmp_path):
    folder, images = files
    out, tum, overlay = tmp_path / "poses.json", tmp_path / "traj.tum", tmp_path / "overlay"
    code, _, err = run(
        capsys, "localize", "--map", folder / "demo.npz", "--camera", folder / "camera.json", *images,
        "--out", out, "--tum", tum, "--overlay", overlay,
    )  # fmt: skip
    assert code == 0, err
    poses = json.loads(out.read_text())
    assert len(poses) == NUM_IMAGES
    ok = []
    for path, truth in zip(images, scene.cam_from_world, strict=True):
        record = poses[str(path)]
        assert {"success", "reason", "cam_from_world", "num_inliers", "covariance", "timings"} <= set(record)
        if record["success"]:
            rot, pos, _ = pose_errors(np.array(record["cam_from_world"]), truth)
            assert rot < 2.0 and pos < 0.5, (path.name, rot, pos)
            assert record["num_inliers"] >= 6 and "total" in record["timings"]
            ok.append((path, np.array(record["cam_from_world"])))
    assert ok, f"no image localized: {[r['reason'] for r in poses.values()]}"
    lines = [line.split() for line in tum.read_text().splitlines() if line and not line.startswith("#")]
    assert len(lines) == len(ok)
    for fields, (_path, cam_from_world) in zip(lines, ok, strict=True):
        assert len(fields) == 8
        position, quat = np.array(fields[1:4], float), np.array(fields[4:8], float)
        assert np.allclose(position, camera_center(cam_from_world), atol=1e-5)
        assert math.isclose(np.linalg.norm(quat), 1.0, abs_tol=1e-5)
    for path in images:
        picture = cv2.imread(str(overlay / f"{path.stem}.png"))
        assert picture is not None and picture.shape == (scene.camera.height, scene.camera.width, 3)
    assert not leftovers(tmp_path)


def test_demo_smoke(scene, capsys, tmp_path, monkeypatch):
    import linereg.sim.demo_scene

    # the small scene of this module instead of a fresh 1 M-point one: this checks the command, not the scene
    monkeypatch.setattr(linereg.sim.demo_scene, "make_demo_scene", lambda seed, num_images: scene)
    code, out, err = run(capsys, "demo", "--images", NUM_IMAGES, "--out", tmp_path)
    assert code == 0, err
    assert "localized" in out and len(list(tmp_path.glob("*.png"))) == NUM_IMAGES


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
    from linereg.map.linemap import LineMap
    from linereg.sim.views import street_camera

    folder = tmp_path_factory.mktemp("small")
    corners = np.array([[x, y, z] for x in (0, 4) for y in (0, 3) for z in (0, 2)], float)
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    LineMap.from_segments(np.array([np.r_[corners[i], corners[j]] for i, j in pairs])).save(
        folder / "small.npz"
    )
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
