"""linereg.io: cloud formats round trip, images, camera files, atomic JSON / TUM writers, bad inputs."""

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from linereg import io
from linereg.camera import Camera
from linereg.errors import FileFormatError, InvalidInputError
from linereg.geometry import camera_center, make_cam_from_world

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def cloud(rng):
    return rng.uniform(-10, 10, size=(500, 3)).round(3)


def _write_open3d(path, points):
    from linereg._open3d import open3d

    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    assert o3d.io.write_point_cloud(str(path), pcd)


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_open3d_formats(tmp_path, cloud, suffix):
    path = tmp_path / f"c{suffix}"
    _write_open3d(path, cloud)
    np.testing.assert_allclose(io.read_cloud(path), cloud, atol=1e-4)  # pye57 may store float32


def test_text_formats(tmp_path, cloud):
    np.savetxt(tmp_path / "c.xyz", np.c_[cloud, np.ones(len(cloud))], header="x y z intensity")
    np.testing.assert_allclose(io.read_cloud(tmp_path / "c.xyz"), cloud)
    np.savetxt(tmp_path / "c.txt", cloud, delimiter=",")
    np.testing.assert_allclose(io.read_cloud(tmp_path / "c.txt"), cloud)
    big = cloud + 5e6  # georeferenced: full float64 precision
    np.savetxt(tmp_path / "g.xyz", big, fmt="%.4f")
    np.testing.assert_allclose(io.read_cloud(tmp_path / "g.xyz"), big, rtol=0, atol=1e-4)


def test_las(tmp_path, cloud):
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = cloud.min(axis=0)
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud[:, 0], cloud[:, 1], cloud[:, 2]
    las.write(tmp_path / "c.las")
    np.testing.assert_allclose(io.read_cloud(tmp_path / "c.las"), cloud, atol=1e-3)


def test_laz_needs_backend_or_reads(tmp_path, cloud):
    import laspy

    if laspy.LazBackend.detect_available():
        pytest.skip("a LAZ backend is installed")
    (tmp_path / "c.laz").write_bytes(b"LASF" + bytes(400))
    with pytest.raises(FileFormatError, match="lazrs"):
        io.read_cloud(tmp_path / "c.laz")


def test_e57_scans_merged_with_poses(tmp_path, cloud):
    import pye57

    path = tmp_path / "c.e57"
    e57 = pye57.E57(str(path), mode="w")
    half = len(cloud) // 2
    for part, shift in ((cloud[:half], np.zeros(3)), (cloud[half:], np.array([100.0, 0, 0]))):
        local = part - shift  # stored in the scanner frame; the pose moves it back
        data = {f"cartesian{a}": local[:, i].copy() for i, a in enumerate("XYZ")}
        e57.write_scan_raw(data, rotation=np.array([1.0, 0, 0, 0]), translation=shift)
    e57.close()
    np.testing.assert_allclose(io.read_cloud(path), cloud, atol=1e-4)  # pye57 may store float32


def test_bad_clouds(tmp_path):
    with pytest.raises(FileFormatError, match=r"missing\.ply.*no such file"):
        io.read_cloud(tmp_path / "missing.ply")
    (tmp_path / "c.obj").write_text("v 0 0 0\n")
    with pytest.raises(FileFormatError, match="unsupported"):
        io.read_cloud(tmp_path / "c.obj")
    (tmp_path / "empty.xyz").write_text("# nothing\n")
    with pytest.raises(FileFormatError, match="empty"):
        io.read_cloud(tmp_path / "empty.xyz")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat garbage\n\x00\x01")
    with pytest.raises(FileFormatError, match=r"bad\.ply"):
        io.read_cloud(tmp_path / "bad.ply")
    (tmp_path / "bad.las").write_bytes(b"not a las file at all")
    with pytest.raises(FileFormatError, match=r"bad\.las"):
        io.read_cloud(tmp_path / "bad.las")
    (tmp_path / "bad.txt").write_text("1 2\n3 4\n")
    with pytest.raises(FileFormatError, match=r"bad\.txt"):
        io.read_cloud(tmp_path / "bad.txt")
    (tmp_path / "bad.e57").write_bytes(b"\x00" * 100)
    with pytest.raises(FileFormatError, match=r"bad\.e57"):
        io.read_cloud(tmp_path / "bad.e57")


def test_image_round_trip(tmp_path, rng):
    image = rng.integers(0, 65535, size=(12, 16), dtype=np.uint16)
    io.write_image_atomic(tmp_path / "sub" / "d.png", image)
    back = io.read_image(tmp_path / "sub" / "d.png")
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, image)
    (tmp_path / "x.png").write_bytes(b"not a png")
    with pytest.raises(FileFormatError, match=r"x\.png"):
        io.read_image(tmp_path / "x.png")
    with pytest.raises(FileFormatError, match="no such file"):
        io.read_image(tmp_path / "none.png")


CAM = {"fx": 500.0, "fy": 510.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}


def test_cameras_json(tmp_path):
    shared = tmp_path / "shared.json"
    shared.write_text(json.dumps(CAM | {"dist": [0.1, -0.01, 0, 0]}))
    cam = io.read_cameras(shared)
    assert cam == Camera(500, 510, 320, 240, 640, 480, (0.1, -0.01, 0, 0))
    listed = tmp_path / "list.json"
    listed.write_text(json.dumps([CAM | {"file": "a.png"}, CAM | {"file": "b.png", "fx": 600.0}]))
    cams = io.read_cameras(listed)
    assert set(cams) == {"a.png", "b.png"} and cams["b.png"].fx == 600.0
    keyed = tmp_path / "keyed.json"
    keyed.write_text(json.dumps({"a.png": CAM, "b.png": CAM}))
    assert io.read_cameras(keyed)["a.png"] == Camera(**CAM)
    data_format = tmp_path / "cameras.json"
    data_format.write_text(
        json.dumps({"images": [CAM | {"file": "rgb_1.png", "distortion": {"coeffs": []}}]})
    )
    assert io.read_cameras(data_format)["rgb_1.png"].fx == 500.0


def test_cameras_json_errors(tmp_path):
    missing = tmp_path / "missing_key.json"
    missing.write_text(json.dumps({k: v for k, v in CAM.items() if k != "cy"}))
    with pytest.raises(FileFormatError, match=r"missing_key\.json.*cy"):
        io.read_cameras(missing)
    per_image = tmp_path / "per_image.json"
    per_image.write_text(json.dumps([CAM | {"file": "a.png"}, {"file": "b.png", "fx": 1.0}]))
    with pytest.raises(FileFormatError, match=r"per_image\.json: b\.png.*fy"):
        io.read_cameras(per_image)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(FileFormatError, match=r"broken\.json"):
        io.read_cameras(broken)


def test_cameras_colmap(tmp_path):
    path = tmp_path / "cameras.txt"
    path.write_text(
        "# Camera list with one line of data per camera:\n"
        "1 PINHOLE 640 480 500 510 320.5 240.5\n"
        "2 SIMPLE_PINHOLE 640 480 500 320.5 240.5\n"
        "3 OPENCV 640 480 500 510 320.5 240.5 0.1 -0.02 0.001 0.002\n"
        "4 SIMPLE_RADIAL 640 480 500 320.5 240.5 0.05\n"
        "5 RADIAL 640 480 500 320.5 240.5 0.05 0.01\n"
    )
    cams = io.read_cameras(path)
    assert cams["1"] == Camera(500, 510, 320, 240, 640, 480)  # COLMAP pixel centres at +0.5
    assert cams["2"].fy == 500
    assert cams["3"].dist == (0.1, -0.02, 0.001, 0.002)
    assert cams["4"].dist == (0.05, 0, 0, 0) and cams["5"].dist == (0.05, 0.01, 0, 0)
    single = tmp_path / "one.txt"
    single.write_text("1 PINHOLE 640 480 500 510 320.5 240.5\n")
    assert isinstance(io.read_cameras(single), Camera)
    bad = tmp_path / "bad.txt"
    bad.write_text("1 FISHEYE_X 640 480 1 2 3\n")
    with pytest.raises(FileFormatError, match=r"bad\.txt:1.*FISHEYE_X"):
        io.read_cameras(bad)
    short = tmp_path / "short.txt"
    short.write_text("1 PINHOLE 640 480 500 510\n")
    with pytest.raises(FileFormatError, match=r"short\.txt:1.*4 parameters"):
        io.read_cameras(short)


@pytest.mark.skipif(not (DATA / "home_kinect" / "cameras.json").exists(), reason="shared data absent")
def test_shared_data_cameras():
    cams = io.read_cameras(DATA / "home_kinect" / "cameras.json")
    assert cams["rgb_1.png"] == Camera(518.0, 519.0, 325.5, 253.5, 640, 480)


def test_json_and_bytes_atomic(tmp_path):
    path = tmp_path / "out" / "r.json"
    io.write_json_atomic(path, {"a": np.arange(3), "b": np.float32(1.5), "c": Path("x")})
    assert json.loads(path.read_text()) == {"a": [0, 1, 2], "b": 1.5, "c": "x"}
    with pytest.raises(TypeError):
        io.write_json_atomic(path, {"bad": object()})
    assert json.loads(path.read_text())["a"] == [0, 1, 2]  # the old file survives a failed write
    assert sorted(p.name for p in path.parent.iterdir()) == ["r.json"]


def test_tum(tmp_path):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    cam_from_world = make_cam_from_world(R, np.array([1.0, 2.0, 3.0]))
    io.write_tum(tmp_path / "t.txt", [2.0, 0.5], [np.eye(4), cam_from_world])
    lines = [
        line.split() for line in (tmp_path / "t.txt").read_text().splitlines() if not line.startswith("#")
    ]
    assert [line[0] for line in lines] == ["0.500000000", "2.000000000"]  # in time order
    values = np.array(lines[0][1:], dtype=np.float64)
    np.testing.assert_allclose(values[:3], camera_center(cam_from_world), atol=1e-8)
    world_from_cam_R = Rotation.from_quat(values[3:]).as_matrix()  # TUM quaternion: x y z w
    np.testing.assert_allclose(world_from_cam_R, R.T, atol=1e-8)
    np.testing.assert_allclose(np.array(lines[1][1:], dtype=float), [0, 0, 0, 0, 0, 0, 1], atol=1e-12)


def test_tum_is_read_by_evo(tmp_path, rng):
    from evo.tools import file_interface
    from scipy.spatial.transform import Rotation

    stamps = [1305031102.175304, 1305031102.211214, 1305031102.243211]
    poses = [
        make_cam_from_world(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3))
        for _ in stamps
    ]
    io.write_tum(tmp_path / "t.tum", stamps, poses)
    trajectory = file_interface.read_tum_trajectory_file(str(tmp_path / "t.tum"))
    np.testing.assert_allclose(trajectory.timestamps, stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(trajectory.positions_xyz, [camera_center(p) for p in poses], atol=1e-8)
    for world_from_cam, cam_from_world in zip(trajectory.poses_se3, poses, strict=True):
        np.testing.assert_allclose(world_from_cam @ cam_from_world, np.eye(4), atol=1e-8)


def test_tum_refuses_file_names_as_timestamps(tmp_path):
    with pytest.raises(InvalidInputError, match="timestamp"):
        io.write_tum(tmp_path / "t.tum", ["img_2.png"], [np.eye(4)])
    with pytest.raises(InvalidInputError, match="timestamp"):
        io.write_tum(tmp_path / "t.tum", [float("nan")], [np.eye(4)])
    assert not (tmp_path / "t.tum").exists()


def test_json_writes_null_for_nan_and_inf(tmp_path):
    path = tmp_path / "r.json"
    record = {"a": float("nan"), "b": [np.float64(np.inf), -np.inf, 1.5], "c": np.array([np.nan, 2.0])}
    io.write_json_atomic(path, record | {"d": {"e": (np.float32(np.nan), np.int64(3))}})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [None, None, 1.5], "c": [None, 2.0], "d": {"e": [None, 3]}}


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield
    os.umask(old)


def test_written_files_follow_the_umask(tmp_path, umask_027):
    from linereg.map.linemap import LineMap

    io.write_json_atomic(tmp_path / "a.json", {"x": 1})
    io.write_tum(tmp_path / "a.tum", [0.0], [np.eye(4)])
    io.write_image_atomic(tmp_path / "a.png", np.zeros((4, 4), np.uint8))
    LineMap.from_segments(np.array([[0.0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0]])).save(tmp_path / "a.linemap")
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in tmp_path.iterdir()}
    assert modes == dict.fromkeys(["a.json", "a.tum", "a.png", "a.linemap"], 0o640)  # 0666 & ~027
    os.umask(0o022)
    io.write_json_atomic(tmp_path / "a.json", {"x": 2})  # a rewrite too
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644


def test_empty_and_directory_inputs_are_named(tmp_path):
    for name in ("empty.ply", "empty.xyz", "empty.png", "empty.json"):
        (tmp_path / name).write_bytes(b"")
    for reader, name in ((io.read_cloud, "empty.ply"), (io.read_cloud, "empty.xyz"),
                         (io.read_image, "empty.png"), (io.read_cameras, "empty.json")):  # fmt: skip
        with pytest.raises(FileFormatError, match=rf"{name}: empty file"):
            reader(tmp_path / name)
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(FileFormatError, match=r"dir\.ply: is a directory"):
        io.read_cloud(tmp_path / "dir.ply")


def test_camera_for_image(tmp_path):
    shared = Camera(**CAM)
    assert io.camera_for_image(shared, "any/where.png") is shared
    other = Camera(**CAM | {"fx": 600.0})
    cameras = {"a.png": shared, "b": other, "sub/c.png": shared}
    assert io.camera_for_image(cameras, tmp_path / "a.png") is shared  # by file name
    assert io.camera_for_image(cameras, tmp_path / "b.jpg") is other  # by stem
    assert io.camera_for_image(cameras, Path("sub/c.png")) is shared  # by path as given
    with pytest.raises(InvalidInputError, match=r"cams\.json: no camera for image d\.png"):
        io.camera_for_image(cameras, tmp_path / "d.png", "cams.json")


def test_intensity_is_read_where_the_file_has_it(tmp_path, cloud, rng):
    import laspy

    from linereg._open3d import open3d

    o3d = open3d()
    value = rng.uniform(0, 1, len(cloud)).astype(np.float32)
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(cloud.astype(np.float32)))
    pcd.point["intensity"] = o3d.core.Tensor(value[:, None])
    for name in ("c.ply", "c.pcd"):
        assert o3d.t.io.write_point_cloud(str(tmp_path / name), pcd)
        points, intensity = io.read_cloud_intensity(tmp_path / name)
        np.testing.assert_allclose(points, cloud, atol=1e-4)
        np.testing.assert_allclose(intensity, value, atol=1e-6)
    np.savetxt(tmp_path / "i.xyz", np.c_[cloud, value])  # x y z i
    np.testing.assert_allclose(io.read_cloud_intensity(tmp_path / "i.xyz")[1], value, atol=1e-6)
    np.savetxt(tmp_path / "rgb.xyz", np.c_[cloud, np.ones((len(cloud), 3))])  # x y z r g b: no intensity
    assert io.read_cloud_intensity(tmp_path / "rgb.xyz")[1] is None
    _write_open3d(tmp_path / "bare.ply", cloud)
    points, intensity = io.read_cloud_intensity(tmp_path / "bare.ply")
    assert intensity is None and len(points) == len(cloud)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets, header.scales = cloud.min(axis=0), np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud[:, 0], cloud[:, 1], cloud[:, 2]
    las.intensity = (value * 1000).astype(np.uint16)
    las.write(tmp_path / "c.las")
    np.testing.assert_array_equal(
        io.read_cloud_intensity(tmp_path / "c.las")[1], (value * 1000).astype(np.uint16)
    )


def test_points_dropped_for_nan_take_their_intensity_along(tmp_path, cloud):
    rows = np.c_[cloud, np.arange(len(cloud), dtype=np.float64)]
    rows[7, 1] = np.nan
    np.savetxt(tmp_path / "n.xyz", rows)
    points, intensity = io.read_cloud_intensity(tmp_path / "n.xyz")
    assert len(points) == len(cloud) - 1 and 7 not in intensity
    np.testing.assert_allclose(points, np.delete(cloud, 7, axis=0))


def test_the_scanner_position_is_read_where_the_file_holds_it(tmp_path, cloud):
    import pye57

    _write_open3d(tmp_path / "c.pcd", cloud)
    assert io.read_sensor_origin(tmp_path / "c.pcd") is None  # open3d writes the identity viewpoint
    text = (
        (tmp_path / "c.pcd")
        .read_bytes()
        .replace(b"VIEWPOINT 0 0 0 1 0 0 0", b"VIEWPOINT 1.5 -2 0.25 1 0 0 0")
    )
    (tmp_path / "v.pcd").write_bytes(text)
    np.testing.assert_allclose(io.read_sensor_origin(tmp_path / "v.pcd"), [1.5, -2.0, 0.25])
    np.testing.assert_allclose(io.read_cloud(tmp_path / "v.pcd"), cloud, atol=1e-4)  # the points as stored
    for count in (1, 2):  # one scan: its pose says where the scanner stood; two scans: two places
        path = tmp_path / f"s{count}.e57"
        e57 = pye57.E57(str(path), mode="w")
        for k in range(count):
            data = {f"cartesian{a}": cloud[:, i].copy() for i, a in enumerate("XYZ")}
            e57.write_scan_raw(
                data, rotation=np.array([1.0, 0, 0, 0]), translation=np.array([3.0 + k, 4.0, 1.5])
            )
        e57.close()
        origin = io.read_sensor_origin(path)
        if count == 1:
            np.testing.assert_allclose(origin, [3.0, 4.0, 1.5])
        else:
            assert origin is None
    _write_open3d(tmp_path / "c.ply", cloud)
    assert io.read_sensor_origin(tmp_path / "c.ply") is None
    with pytest.raises(FileFormatError, match="no such file"):
        io.read_sensor_origin(tmp_path / "missing.pcd")
