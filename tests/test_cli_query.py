"""``linereg query`` against a throwaway service (fake engine, zenoh on loopback): what a new user hits."""

import json
import socket
import time

import cv2
import numpy as np
import pytest

from linereg.cli import main
from service import Service, ServiceConfig
from service.fake import expected_pose
from service.loadgen import CAMERA


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture(scope="module")
def endpoint():
    endpoint = free_endpoint()
    config = ServiceConfig(
        loader="service.fake:load_fake_engine", loader_args=("", "fake"), listen=(endpoint,), workers=1
    )
    with Service(config):
        yield endpoint


@pytest.fixture
def images(tmp_path):
    """Three photos of the camera's size, as the fake engine answers them: {path: expected pose}."""
    rng = np.random.default_rng(7)
    out = {}
    for name in ("a.png", "b.jpg", "c.bmp"):  # PNG and JPEG sent as they are, BMP decoded and sent as PNG
        pixels = rng.integers(0, 256, size=(CAMERA.height, CAMERA.width), dtype=np.uint8)
        assert cv2.imwrite(str(tmp_path / name), pixels)
        out[tmp_path / name] = expected_pose(cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED))
    (tmp_path / "camera.json").write_text(json.dumps(CAMERA.to_dict()))
    return out


def query(capsys, *argv) -> tuple[int, list[dict], str]:
    """Returns (exit code, the JSON lines on stdout, stderr) of ``linereg query ARGV``."""
    code = main(["query", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, [json.loads(line) for line in out.splitlines()], err


def assert_answered(records: list[dict], images: dict) -> None:
    by_image = {r["image"]: r for r in records}
    for path, pose in images.items():
        assert by_image[str(path)]["success"], by_image[str(path)]
        np.testing.assert_allclose(by_image[str(path)]["cam_from_world"], pose)


def test_query_answers_every_image(endpoint, images, tmp_path, capsys):
    code, records, err = query(capsys, "--connect", endpoint, "--camera", tmp_path / "camera.json", *images)
    assert code == 0, err
    assert [r["image"] for r in records] == [str(p) for p in images]
    assert_answered(records, images)
    assert "3/3 images answered" in err


def test_nobody_listening_is_one_line(tmp_path, images, capsys):
    unused = free_endpoint()
    code, records, err = query(capsys, "--connect", unused, "--camera", tmp_path / "camera.json", *images)
    assert code == 2 and not records
    assert err.startswith(f"linereg query: error: cannot connect to {unused}") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err


def test_a_map_nobody_serves_is_said_at_once(endpoint, images, tmp_path, capsys):
    start = time.monotonic()
    argv = ["--connect", endpoint, "--map", "nope", "--camera", tmp_path / "camera.json", *images]
    code, records, err = query(capsys, *argv, "--timeout", 10)
    assert time.monotonic() - start < 2.0  # not the 10 s timeout
    assert code == 2 and not records
    assert "no service for map 'nope'" in err and "fake" in err and len(err.strip().splitlines()) == 1


def test_an_invalid_map_name_is_a_user_error(endpoint, images, tmp_path, capsys):
    argv = ["--connect", endpoint, "--map", "site/*", "--camera", tmp_path / "camera.json", *images]
    code, _, err = query(capsys, *argv)
    assert code == 2 and "--map 'site/*'" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("name", "content", "problem"),
    [
        ("corrupt.png", b"\x89PNG\r\n\x1a\n truncated", "cannot read image"),
        ("empty.png", b"", "empty file"),
        ("small.png", "small", "160x120"),
    ],
)
def test_a_bad_image_among_several_is_named_and_the_rest_answered(
    endpoint, images, tmp_path, capsys, name, content, problem
):
    bad = tmp_path / name
    if content == "small":
        assert cv2.imwrite(str(bad), np.zeros((120, 160), np.uint8))
    else:
        bad.write_bytes(content)
    paths = list(images)
    argv = ["--connect", endpoint, "--camera", tmp_path / "camera.json", paths[0], bad, *paths[1:]]
    code, records, err = query(capsys, *argv)
    assert code == 2 and "Traceback" not in err
    assert [r["image"] for r in records] == [str(p) for p in (paths[0], bad, *paths[1:])]
    assert records[1]["error"] and problem in records[1]["message"]
    assert_answered(records, images)
    assert "3/4 images answered" in err
    assert f"linereg query: error: {bad}: " in err and problem in err


def test_per_image_camera_files_as_for_localize(endpoint, images, tmp_path, capsys):
    listed = tmp_path / "cameras.json"  # the shared/data layout: {"images": [{file, fx, ...}, ...]}
    listed.write_text(json.dumps({"images": [CAMERA.to_dict() | {"file": p.name} for p in images]}))
    code, records, err = query(capsys, "--connect", endpoint, "--camera", listed, *images)
    assert code == 0, err
    assert_answered(records, images)
    keyed = tmp_path / "by_stem.json"
    keyed.write_text(json.dumps({p.stem: CAMERA.to_dict() for p in images}))
    code, records, err = query(capsys, "--connect", endpoint, "--camera", keyed, *images)
    assert code == 0, err
    assert_answered(records, images)
    keyed.write_text(json.dumps({"a": CAMERA.to_dict()}))
    code, records, err = query(capsys, "--connect", endpoint, "--camera", keyed, *images)
    assert code == 2 and "by_stem.json: no camera for image b.jpg" in err and not records


def test_colmap_cameras_txt(endpoint, images, tmp_path, capsys):
    c = CAMERA  # COLMAP puts the centre of the top-left pixel at (0.5, 0.5)
    line = f"1 PINHOLE {c.width} {c.height} {c.fx} {c.fy} {c.cx + 0.5} {c.cy + 0.5}\n"
    (tmp_path / "cameras.txt").write_text("# Camera list\n" + line)
    code, records, err = query(capsys, "--connect", endpoint, "--camera", tmp_path / "cameras.txt", *images)
    assert code == 0, err
    assert_answered(records, images)


def test_missing_images_are_said_before_anything_is_sent(endpoint, images, tmp_path, capsys):
    argv = ["--connect", endpoint, "--camera", tmp_path / "camera.json", *images, tmp_path / "typo.png"]
    code, records, err = query(capsys, *argv)
    assert code == 2 and not records and f"image file(s) not found: {tmp_path / 'typo.png'}" in err


def test_priors_are_sent_and_recorded(endpoint, images, tmp_path, capsys):
    """``--prior``: each image's prior (per image from JSON) goes with its query and into its record; an
    image the file names no prior for is said before anything is sent."""
    priors = {p.name: {"position": [float(k), 2.0, 1.5], "radius_m": 10.0} for k, p in enumerate(images)}
    (tmp_path / "priors.json").write_text(json.dumps(priors))
    argv = ["--connect", endpoint, "--camera", tmp_path / "camera.json", *images]
    code, records, err = query(capsys, *argv, "--prior", tmp_path / "priors.json")
    assert code == 0, err
    assert_answered(records, images)
    for record in records:
        assert record["prior"] == priors[record["image"].rsplit("/", 1)[-1]]
    del priors["b.jpg"]
    (tmp_path / "priors.json").write_text(json.dumps(priors))
    code, records, err = query(capsys, *argv, "--prior", tmp_path / "priors.json")
    assert code != 0 and not records
    assert "b.jpg" in err and "priors.json" in err and "Traceback" not in err
