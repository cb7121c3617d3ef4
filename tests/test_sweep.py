"""A single spinning-LiDAR sweep (``sim.sweep``): its profile, the edges seen from its sensor
(``map.sensor_edges``) and, when asked, the steps of its intensity (``map.intensity_edges``)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from linereg import LineMap
from linereg.config import MapBuildConfig, MapProfileConfig
from linereg.errors import InvalidInputError
from linereg.map import kinds
from linereg.map.profile import profile_cloud, scan_rings
from linereg.sim.sweep import STREET_GROUND, STREET_PAINT_Y, SweepConfig, spinning_sweep, street

GROUND, PAINT_Y = STREET_GROUND, STREET_PAINT_Y


@pytest.fixture(scope="module")
def sweep():
    return spinning_sweep(*street(), np.random.default_rng(0))


def _on_line(segments, point, direction, tol_m, tol_deg):
    """(K,) bool: both ends within tol_m of the line through point along direction, parallel to it."""
    d = direction / np.linalg.norm(direction)
    out = np.ones(len(segments), dtype=bool)
    for end in (segments[:, :3], segments[:, 3:]):
        rel = end - point
        out &= np.linalg.norm(rel - np.outer(rel @ d, d), axis=1) <= tol_m
    u = segments[:, 3:] - segments[:, :3]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return out & (np.abs(u @ d) >= np.cos(np.radians(tol_deg)))


def test_a_sweep_is_profiled_as_one_with_rings_about_its_sensor(sweep):
    points, _, _ = sweep
    profile = profile_cloud(points)
    assert profile.kind == "lidar_sweep"
    np.testing.assert_allclose(profile.sensor_origin, [0.0, 0.0, 0.0], atol=0.05)
    assert profile.rings >= 40  # the lasers that hit something (the highest pass over the roof)


def test_the_buildings_corner_and_foot_are_found(sweep):
    points, _, _ = sweep
    line_map = LineMap.build(points)
    segments = line_map.segments
    corner = _on_line(segments, np.array([10.0, 2.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.05, 3.0)
    foot = _on_line(segments, np.array([10.0, 2.0, GROUND]), np.array([1.0, 0.0, 0.0]), 0.05, 3.0)
    assert corner.any() and foot.any()
    assert not (line_map.kinds == kinds.INTENSITY).any()  # untextured unless asked


def test_intensity_edges_follow_the_paint_when_asked(sweep):
    points, intensity, _ = sweep
    line_map = LineMap.build(points, MapBuildConfig(intensity_edges=True), intensity=intensity)
    found = line_map.segments[line_map.kinds == kinds.INTENSITY]
    along_x = np.array([1.0, 0.0, 0.0])
    for y in PAINT_Y:  # each long edge of the marking, most of its 10 m
        on = _on_line(found, np.array([0.0, y, GROUND]), along_x, 0.05, 2.0)
        assert on.any(), y
        assert np.linalg.norm(found[on, 3:] - found[on, :3], axis=1).max() >= 7.0
    # nothing else: the road's and the walls' own noise is no edge, the walls' foot is a geometric one
    on_paint = _on_line(found, np.array([0.0, PAINT_Y[0], GROUND]), along_x, 0.05, 2.0)
    on_paint |= _on_line(found, np.array([0.0, PAINT_Y[1], GROUND]), along_x, 0.05, 2.0)
    assert on_paint.all()


def test_intensity_edges_say_why_there_are_none(sweep):
    points, intensity, _ = sweep
    no_values = LineMap.build(points, MapBuildConfig(intensity_edges=True))
    assert not (no_values.kinds == kinds.INTENSITY).any()
    assert "no intensity" in " ".join(no_values.metadata["notes"])
    # an evenly sampled patch has no rings to step along
    grid = np.stack(np.meshgrid(np.arange(0, 3, 0.02), np.arange(0, 3, 0.02), [0.0]), -1).reshape(-1, 3)
    flat = LineMap.build(grid, MapBuildConfig(intensity_edges=True), intensity=grid[:, 0] > 1.5)
    assert "rings" in " ".join(flat.metadata["notes"])
    with pytest.raises(InvalidInputError, match="intensity"):
        LineMap.build(points, MapBuildConfig(intensity_edges=True), intensity=intensity[:-1])


def test_map_build_takes_the_scanner_position_from_a_pcd_header(sweep, tmp_path, capsys):
    """A sweep moved into a site's frame: the PCD's VIEWPOINT says where the sensor stood there, and the
    rings, the sensor's edges and the intensity edges are found about it."""
    from linereg._open3d import open3d
    from linereg.cli import main

    points, intensity, _ = sweep
    shift = np.array([100.0, -40.0, 5.0])
    o3d = open3d()
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points + shift))
    cloud.point["intensity"] = o3d.core.Tensor(intensity[:, None])
    assert o3d.t.io.write_point_cloud(str(tmp_path / "raw.pcd"), cloud, write_ascii=True)
    text = (tmp_path / "raw.pcd").read_text()
    assert "VIEWPOINT 0 0 0 1 0 0 0" in text
    (tmp_path / "site.pcd").write_text(text.replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 100 -40 5 1 0 0 0"))
    out = tmp_path / "site.linemap"
    assert main(["map", "build", str(tmp_path / "site.pcd"), "-o", str(out), "--intensity-edges"]) == 0
    line_map = LineMap.load(out)
    np.testing.assert_allclose(line_map.metadata["profile"]["sensor_origin"], shift)
    assert line_map.metadata["profile"]["kind"] == "lidar_sweep"
    found = line_map.segments[line_map.kinds == kinds.INTENSITY] - np.tile(shift, 2)
    assert _on_line(found, np.array([0.0, PAINT_Y[0], GROUND]), np.array([1.0, 0, 0]), 0.05, 2.0).any()


def test_a_sweep_stored_in_firing_order_off_its_frame_origin_is_found_by_its_lasers_cones():
    """The sweep stored as fired, every laser at one azimuth before the next azimuth (no ring runs in the
    file's order; nuScenes' 32-laser sweeps come so), in a frame whose origin lies 23 cm beside the lasers'
    (nuScenes' LIDAR_TOP frame does): the near returns' elevations about the frame origin smear over
    degrees, the far ones do not. The profile finds the lasers' cones, and the sensor where they are
    sharp; the sensor's edges are found about it. (An offset along the axis the lasers turn about blurs
    only rings seeing several ranges: a ring on flat ground keeps one elevation about any point of that
    axis, so the test moves the frame sideways.)"""
    config = SweepConfig()
    points, _, ring = spinning_sweep(*street(), np.random.default_rng(1), config)
    azimuth = np.round(np.degrees(np.arctan2(points[:, 1], points[:, 0])) / config.azimuth_step_deg)
    fired = np.lexsort((ring, azimuth))
    sensor = np.array([0.03, -0.23, 0.0])
    cloud, truth = points[fired] + sensor, ring[fired]
    profile = profile_cloud(cloud)
    assert (profile.kind, profile.ring_source) == ("lidar_sweep", "elevation")
    np.testing.assert_allclose(profile.sensor_origin, sensor, atol=0.01)
    assert profile.ring_gap_deg == pytest.approx(26.8 / 63, abs=0.02)
    found, _, _ = scan_rings(cloud, np.zeros(3))
    labelled = found >= 0
    assert labelled.mean() >= 0.95
    for k in np.unique(found[labelled]):  # each ring found is one laser's
        assert np.bincount(truth[found == k]).max() >= 0.99 * (found == k).sum()
    line_map = LineMap.build(cloud)
    segments = line_map.segments - np.tile(sensor, 2)
    corner = _on_line(segments, np.array([10.0, 2.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.05, 3.0)
    assert corner.any()


def _vehicle_frame(sweep, sensor):
    """The sweep in a frame whose origin lies ``sensor`` below and behind its lasers, its points shuffled
    (no ring runs in the file's order): (points, intensities, true rings)."""
    points, intensity, ring = sweep
    order = np.random.default_rng(7).permutation(len(points))
    return points[order] + sensor, intensity[order], ring[order]


def _write_ply_with_rings(path, points, intensity, rings):
    records = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])  # fmt: skip
    records["x"], records["y"], records["z"] = points.T
    records["intensity"], records["ring"] = intensity, rings
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
    header += "".join(f"property {t} {n}\n" for t, n in (("float", "x"), ("float", "y"), ("float", "z")))
    header += "property float intensity\nproperty ushort ring\nend_header\n"
    path.write_bytes(header.encode("ascii") + records.tobytes())


def test_a_sweep_in_a_vehicles_frame_is_found_by_its_ring_field(sweep, tmp_path, capsys):
    """A sweep stored in a vehicle's frame (its lasers 1.8 m above the frame's origin and 1.2 m ahead, its
    axis leaning 0.7 deg), shuffled: no ring runs in scan order and no sharp cones about any point near the frame's origin, so
    without more it is profiled as a scan and gets no sensor edges. Its PLY's ushort ``ring`` property
    (which open3d skips) gives the rings; the sensor is fitted where each laser's returns share one
    elevation, and the sensor's edges are found about it."""
    from linereg.cli import main
    from linereg.io import read_cloud_fields

    sensor = np.array([1.2, 0.1, 1.8])
    points, intensity, ring = _vehicle_frame(sweep, sensor)
    lean = Rotation.from_euler("xy", [0.6, -0.4], degrees=True)  # the vehicle's frame is not level with it
    points = lean.apply(points - sensor) + sensor
    blind = LineMap.build(points)
    assert blind.metadata["profile"]["kind"] == "scan" and not (blind.kinds == kinds.OCCLUDING).any()
    _write_ply_with_rings(tmp_path / "sweep.ply", points, intensity, ring)
    fields = read_cloud_fields(tmp_path / "sweep.ply")
    np.testing.assert_array_equal(fields.rings, ring)
    assert fields.intensity is None  # not asked for
    out = tmp_path / "sweep.linemap"
    assert main(["map", "build", str(tmp_path / "sweep.ply"), "-o", str(out)]) == 0
    line_map = LineMap.load(out)
    profile = line_map.metadata["profile"]
    assert (profile["kind"], profile["ring_source"], profile["rings"]) == ("lidar_sweep", "field", 64)
    np.testing.assert_allclose(profile["sensor_origin"], sensor, atol=0.01)
    assert (line_map.kinds == kinds.OCCLUDING).any()
    corner = lean.apply(np.array([[10.0, 2.0, 0.0], [0.0, 0.0, 1.0]]))
    assert _on_line(line_map.segments - np.tile(sensor, 2), corner[0], corner[1], 0.05, 3.0).any()
    assert main(["map", "info", str(out)]) == 0
    assert "64 rings" in capsys.readouterr().out


def test_a_ring_field_of_lasers_fitting_no_one_sensor_needs_the_sensor_given(sweep):
    """Lasers whose cones have apexes of their own, up to a metre apart, fit no single sensor position
    (KITTI's HDL-64 sweeps fit none to better than half their ring gap): the field does not place the
    sensor (its rings are looked for as without one, and a note says so). Given the sensor's position, the
    field is taken as it is. (The building's returns only: a ring on flat ground keeps one elevation about
    any point of the axis, whatever its apex.)"""
    from linereg.map.profile import profile_and_rings

    points, _, ring = sweep
    walls = points[:, 2] > GROUND + 0.1
    points, ring = points[walls], ring[walls]
    apex = np.random.default_rng(3).uniform(-0.5, 0.5, ring.max() + 1)
    lifted = points + np.c_[np.zeros((len(points), 2)), apex[ring]]
    shuffled = np.random.default_rng(4).permutation(len(points))
    lifted, ring = lifted[shuffled], ring[shuffled]
    profile, _ = profile_and_rings(lifted, rings=ring)
    assert profile.ring_source != "field"
    line_map = LineMap.build(lifted, rings=ring)
    assert "ring field" in " ".join(line_map.metadata["notes"])
    given, found = profile_and_rings(lifted, sensor_origin=np.zeros(3), rings=ring)
    lasers = (np.bincount(ring) >= MapProfileConfig().min_ring_points).sum()  # those of enough returns
    assert (given.ring_source, given.rings) == ("field", lasers)
    # numbered by their mean elevation from the lowest
    assert (
        np.diff(
            [
                np.median(lifted[found == k, 2] / np.hypot(*lifted[found == k, :2].T))
                for k in range(given.rings)
            ]
        )
        > 0
    ).all()


def test_a_field_that_is_no_lasers_is_not_taken_for_rings(sweep):
    """A field of something else (random values, a column number) has no cones: the profile is the one
    without it, and the map says why the field was left out."""
    from linereg.map.profile import profile_and_rings

    points, _, _ = sweep
    without, _ = profile_and_rings(points)
    for field in (np.random.default_rng(5).integers(0, 64, len(points)), np.arange(len(points)) % 64):
        profile, _ = profile_and_rings(points, rings=field)
        assert profile == without
    line_map = LineMap.build(points, rings=np.arange(len(points)) % 64)
    assert "ring field" in " ".join(line_map.metadata["notes"])


def test_ring_fields_are_read_from_pcd_ascii_ply_and_las_and_bad_ones_named(sweep, tmp_path):
    import laspy

    from linereg.errors import FileFormatError
    from linereg.io import read_cloud_fields

    points, _, ring = sweep
    few, laser = points[:500], ring[:500]
    pcd = tmp_path / "sweep.pcd"
    header = "VERSION 0.7\nFIELDS x y z ring\nSIZE 4 4 4 2\nTYPE F F F U\nCOUNT 1 1 1 1\n"
    header += f"WIDTH {len(few)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(few)}\nDATA ascii\n"
    pcd.write_text(header + "".join(f"{x} {y} {z} {r}\n" for (x, y, z), r in zip(few, laser, strict=True)))
    np.testing.assert_array_equal(read_cloud_fields(pcd).rings, laser)
    ply = tmp_path / "ascii.ply"
    header = f"ply\nformat ascii 1.0\nelement vertex {len(few)}\nproperty float x\nproperty float y\n"
    header += "property float z\nproperty uchar ring\nend_header\n"
    ply.write_text(header + "".join(f"{x} {y} {z} {r}\n" for (x, y, z), r in zip(few, laser, strict=True)))
    np.testing.assert_array_equal(read_cloud_fields(ply).rings, laser)
    las_header = laspy.LasHeader(point_format=3, version="1.2")
    las_header.add_extra_dim(laspy.ExtraBytesParams(name="ring", type=np.uint16))
    las_header.scales, las_header.offsets = np.full(3, 0.001), np.floor(few.min(axis=0))
    las = laspy.LasData(las_header)
    las.x, las.y, las.z = few.T
    las.ring = laser.astype(np.uint16)
    las.write(tmp_path / "sweep.las")
    np.testing.assert_array_equal(read_cloud_fields(tmp_path / "sweep.las").rings, laser)
    assert read_cloud_fields(tmp_path / "sweep.las", rings=False).rings is None
    ply.write_text(
        header + "".join(f"{x} {y} {z} 0.5\n" for x, y, z in few).replace("uchar ring", "float ring")
    )
    with pytest.raises(FileFormatError, match=r"ascii\.ply.*ring"):
        read_cloud_fields(ply)
    with pytest.raises(InvalidInputError, match="rings"):
        LineMap.build(points, rings=ring[:-1])
