"""LineMap: build from segments or points, tile queries, visibility, save / load round trip, bad files."""

import json
import zipfile

import numpy as np
import pytest

import linereg
from linereg.errors import FileFormatError, InvalidInputError
from linereg.geometry import make_cam_from_world
from linereg.map.linemap import FORMAT_VERSION, LineMap


def grid_segments(n=6, spacing=4.0, height=3.0):
    """Returns (M, 6): a grid of 'buildings' outlines along x, y and vertical edges, over n x n cells."""
    out = []
    for i in range(n):
        for j in range(n):
            x, y = i * spacing, j * spacing
            out += [[x, y, 0, x + 2, y, 0], [x, y, 0, x, y + 2, 0], [x, y, 0, x, y, height]]
            out += [[x, y, height, x + 2, y, height], [x, y, height, x, y + 2, height]]
    return np.array(out, dtype=np.float64)


@pytest.fixture(scope="module")
def line_map():
    return LineMap.from_segments(grid_segments(), name="grid", tile_m=2.0)


def test_clusters_follow_the_axes(line_map):
    assert len(line_map) == 180
    dirs = np.abs(line_map.clusters.directions[:3])
    assert np.allclose(np.sort(dirs.max(axis=1)), 1.0, atol=1e-6)
    assert (line_map.clusters.labels >= 0).all()


def test_segments_near_matches_brute_force(line_map, rng):
    segs = line_map.segments
    for _ in range(20):
        position = rng.uniform([-2, -2, -1], [25, 25, 4])
        radius = rng.uniform(0.5, 6.0)
        got = line_map.segments_near(position, radius)
        a, b = segs[:, :3], segs[:, 3:]
        t = np.clip(np.einsum("ij,ij->i", position - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
        dist = np.linalg.norm(a + t[:, None] * (b - a) - position, axis=1)
        np.testing.assert_array_equal(got, np.flatnonzero(dist <= radius))


def test_tiles_cover_every_segment(line_map):
    members = np.unique(np.concatenate([line_map.tile_segments(t) for t in line_map.tile_ids()]))
    np.testing.assert_array_equal(members, np.arange(len(line_map)))
    assert len(line_map.tile_segments(line_map.tile_of(np.array([1e4, 1e4, 0.0])))) == 0


def test_visible(line_map, camera):
    assert len(line_map.visible(camera, None)) == len(line_map)
    near = line_map.visible(camera, None, prior_position=np.array([0.0, 0, 0]), radius_m=3.0)
    assert 0 < len(near) < len(line_map)
    # looking along +x from behind the grid: camera z = world x, x = -world y, y = -world z
    R = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    cam_from_world = make_cam_from_world(R, -R @ np.array([-10.0, 10.0, 1.5]))
    seen = line_map.visible(camera, cam_from_world)
    assert 0 < len(seen) <= len(line_map)
    behind = make_cam_from_world(R, -R @ np.array([40.0, 10.0, 1.5]))  # past the grid, looking away
    assert len(line_map.visible(camera, behind)) == 0


def test_round_trip(line_map, tmp_path):
    path = tmp_path / "grid.npz"
    line_map.save(path)
    loaded = LineMap.load(path)
    np.testing.assert_array_equal(loaded.segments, line_map.segments)
    np.testing.assert_array_equal(loaded.clusters.labels, line_map.clusters.labels)
    np.testing.assert_array_equal(loaded.clusters.directions, line_map.clusters.directions)
    assert loaded.metadata == line_map.metadata
    np.testing.assert_array_equal(
        loaded.segments_near([4, 4, 0], 3.0), line_map.segments_near([4, 4, 0], 3.0)
    )
    info = loaded.info()
    assert info["name"] == "grid" and info["num_segments"] == 180 and info["format_version"] == FORMAT_VERSION
    json.dumps(info)  # JSON-ready
    assert [p.name for p in tmp_path.iterdir()] == ["grid.npz"]  # no temporary file left behind


def _rewrite_metadata(src, dst, **changes):
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "metadata.npy":
                from io import BytesIO

                meta = json.loads(str(np.load(BytesIO(data))))
                buffer = BytesIO()
                np.save(buffer, np.array(json.dumps(meta | changes)))
                data = buffer.getvalue()
            zout.writestr(item, data)


def test_other_version_is_refused(line_map, tmp_path):
    path = tmp_path / "grid.npz"
    line_map.save(path)
    old = tmp_path / "old.npz"
    _rewrite_metadata(path, old, format_version=FORMAT_VERSION + 1)
    with pytest.raises(
        FileFormatError, match=rf"old\.npz.*version {FORMAT_VERSION + 1}.*supported: 1, 2, {FORMAT_VERSION}"
    ):
        LineMap.load(old)


def test_missing_and_corrupt_files(line_map, tmp_path):
    with pytest.raises(FileFormatError, match="nothere"):
        LineMap.load(tmp_path / "nothere.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"this is not a zip file")
    with pytest.raises(FileFormatError, match="bad"):
        LineMap.load(bad)
    good = tmp_path / "good.npz"
    line_map.save(good)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(FileFormatError, match="truncated"):
        LineMap.load(truncated)
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(FileFormatError, match="other"):
        LineMap.load(tmp_path / "other.npz")


def test_load_says_what_the_file_is_instead(line_map, tmp_path):
    (tmp_path / "folder.linemap").mkdir()
    with pytest.raises(FileFormatError, match=r"folder\.linemap: is a directory"):
        LineMap.load(tmp_path / "folder.linemap")
    (tmp_path / "empty.linemap").write_bytes(b"")
    with pytest.raises(FileFormatError, match=r"empty\.linemap: empty file"):
        LineMap.load(tmp_path / "empty.linemap")
    (tmp_path / "random.linemap").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(FileFormatError, match=r"random\.linemap: not a linereg map file") as info:
        LineMap.load(tmp_path / "random.linemap")
    assert "pickle" not in str(info.value)
    np.save(tmp_path / "array.npy", np.zeros(3))
    with pytest.raises(FileFormatError, match=r"array\.npy: not a linereg map file"):
        LineMap.load(tmp_path / "array.npy")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(FileFormatError, match=r"other\.npz: not a linereg map file"):
        LineMap.load(tmp_path / "other.npz")


def test_build_from_points(rng):
    # two walls meeting at a corner, on a floor: creases along x, y and z
    n = 20000
    wall_a = np.c_[rng.uniform(0, 4, n), np.zeros(n), rng.uniform(0, 3, n)]
    wall_b = np.c_[np.zeros(n), rng.uniform(0, 4, n), rng.uniform(0, 3, n)]
    floor = np.c_[rng.uniform(0, 4, n), rng.uniform(0, 4, n), np.zeros(n)]
    points = np.concatenate([wall_a, wall_b, floor]) + rng.normal(0, 0.002, (3 * n, 3))
    stages = []
    line_map = LineMap.build(points, name="corner", progress=stages.append)
    # even and dense (drawn at random: its nearest neighbours spread, its density does not): a room's cloud
    assert line_map.metadata["profile"]["kind"] == "rgbd"
    assert stages == ["profile", "normals", "regions", "lines", "point edges", "clusters"]
    assert len(line_map) >= 6 and len(line_map.clusters) == 3
    assert line_map.metadata["point_count"] == 3 * n and line_map.metadata["extraction"]["voxel_m"] > 0


def test_a_cloud_of_repeated_points_builds_the_map_of_its_distinct_points(rng):
    """An export that repeats its points (each 3 times in a row, or the whole cloud 10 times over) had a
    spacing of 0: no scale to build by (10 copies of a room gave no line). The copies are dropped, the first
    of each kept in the cloud's order: the map is the distinct points' own, bit for bit, and says so."""
    n = 6000
    wall = np.c_[rng.uniform(0, 3, n), np.zeros(n), rng.uniform(0, 2.5, n)]
    floor = np.c_[rng.uniform(0, 3, n), rng.uniform(0, 3, n), np.zeros(n)]
    points = np.concatenate([wall, floor])
    base = LineMap.build(points)
    assert len(base) >= 4 and "repeated_points" not in base.metadata
    for copies in (np.repeat(points, 3, axis=0), np.tile(points, (10, 1))):
        line_map = LineMap.build(copies)
        np.testing.assert_array_equal(line_map.segments, base.segments)
        assert line_map.metadata["repeated_points"] == len(copies) - len(points)
        assert line_map.metadata["point_count"] == len(points)
        assert line_map.metadata["profile"]["spacing_m"] == base.metadata["profile"]["spacing_m"] > 0


def test_distinct_points_keeps_the_first_of_each_in_order():
    from linereg.map.build import distinct_points

    points = np.array([[1.0, 2, 3], [0.0, 0, 0], [1.0, 2, 3], [-0.0, 0, 0], [5.0, 5, 5], [0.0, 0, 0]])
    assert distinct_points(points).tolist() == [0, 1, 4]
    assert distinct_points(np.zeros((0, 3))).tolist() == []


def test_empty_and_bad_segments(tmp_path):
    empty = LineMap.from_segments(np.zeros((0, 6)))
    assert len(empty) == 0 and len(empty.segments_near([0, 0, 0], 10.0)) == 0
    empty.save(tmp_path / "empty.npz")
    assert len(LineMap.load(tmp_path / "empty.npz")) == 0
    with pytest.raises(InvalidInputError):
        LineMap.from_segments(np.zeros((3, 4)))
    with pytest.raises(InvalidInputError):
        LineMap.from_segments(np.full((3, 6), np.nan))


def test_cli_build_and_info(tmp_path, capsys):
    from linereg.cli import main

    rng = np.random.default_rng(3)
    n = 15000
    points = np.concatenate(
        [
            np.c_[rng.uniform(0, 4, n), np.zeros(n), rng.uniform(0, 3, n)],
            np.c_[np.zeros(n), rng.uniform(0, 4, n), rng.uniform(0, 3, n)],
            np.c_[rng.uniform(0, 4, n), rng.uniform(0, 4, n), np.zeros(n)],
        ]
    )
    cloud = tmp_path / "corner.xyz"
    np.savetxt(cloud, points, fmt="%.5f")
    assert main(["map", "build", str(cloud), "-o", str(tmp_path / "m.npz"), "--name", "corner"]) == 0
    err = capsys.readouterr().err
    for stage in ("read", "normals", "regions", "lines", "clusters", "write"):
        assert stage in err
    assert main(["map", "info", str(tmp_path / "m.npz")]) == 0
    out = capsys.readouterr().out
    assert "corner" in out and "segments" in out and "clusters" in out
    assert main(["map", "info", str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz" in capsys.readouterr().err
    assert linereg.FileFormatError is FileFormatError
