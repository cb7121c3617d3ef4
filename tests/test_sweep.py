"""A single spinning-LiDAR sweep (``sim.sweep``): its profile, the edges seen from its sensor
(``map.sensor_edges``) and, when asked, the steps of its intensity (``map.intensity_edges``)."""

import numpy as np
import pytest

from linereg import LineMap
from linereg.config import MapBuildConfig
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
