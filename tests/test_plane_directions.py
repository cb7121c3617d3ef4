import numpy as np
import pytest

from linereg.config import MapBuildConfig, PlaneDirectionsConfig
from linereg.errors import InvalidInputError
from linereg.geometry import axis_angle_deg
from linereg.map.linemap import LineMap
from linereg.map.plane_directions import dominant_normals, frame_directions, map_clusters, plane_directions


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle_deg(a, b) -> float:
    return axis_angle_deg(a, b)


def jittered(rng, normal, count, jitter_deg) -> np.ndarray:
    return unit(normal + np.radians(jitter_deg) * rng.normal(size=(count, 3)) / np.sqrt(3))


# a room turned about the vertical: floor, two walls
FLOOR, WALL_A, WALL_B = unit([0, 0, 1.0]), unit([1.0, 0.3, 0]), unit([-0.3, 1.0, 0])


def room_regions(rng):
    """Returns ((R, 3) region normals, (R,) areas): three big plane orientations and small clutter."""
    normals = np.vstack(
        [
            jittered(rng, FLOOR, 20, 0.5),
            jittered(rng, WALL_A, 15, 0.5),
            jittered(rng, WALL_B, 15, 0.5),
            unit(rng.normal(size=(30, 3))),
        ]
    )
    areas = np.r_[np.full(20, 1.0), np.full(15, 0.8), np.full(15, 0.6), np.full(30, 0.02)]
    return normals, areas


def test_dominant_normals_of_a_room(rng):
    normals, areas = room_regions(rng)
    found, found_area = dominant_normals(normals, areas)
    assert len(found) == 3
    for got, want in zip(found, [FLOOR, WALL_A, WALL_B], strict=True):  # largest area first
        assert angle_deg(got, want) < 0.5
    assert np.all(np.diff(found_area) <= 0)
    assert found_area[0] == pytest.approx(20.0, rel=0.05)


def test_dominant_normals_follow_the_config(rng):
    normals, areas = room_regions(rng)
    found, _ = dominant_normals(normals, areas, PlaneDirectionsConfig(max_planes=2))
    assert len(found) == 2  # the floor and the larger wall
    assert angle_deg(found[0], FLOOR) < 0.5 and angle_deg(found[1], WALL_A) < 0.5
    few, _ = dominant_normals(normals, areas, PlaneDirectionsConfig(max_regions=20))
    assert len(few) == 1  # only the 20 largest regions (the floor's) vote


def test_plane_directions_are_the_manhattan_axes(rng):
    normals, areas = room_regions(rng)
    directions, support = plane_directions(normals, areas)
    assert len(directions) == 3
    for axis in (FLOOR, WALL_A, WALL_B):  # each wall normal is where the floor meets the other wall
        assert min(angle_deg(d, axis) for d in directions) < 0.5
    assert np.all(support > 0)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)


def test_crease_of_a_non_manhattan_pair():
    # a roof plane at 40 degrees on a wall: their crease is horizontal along the wall; neither normal lies
    # in the other plane, so only the crease is a line direction
    roof = unit([0.0, np.sin(np.radians(40)), np.cos(np.radians(40))])
    wall = unit([0.0, 1.0, 0.0])
    directions, _ = plane_directions(np.array([roof, wall]), np.array([5.0, 5.0]))
    assert len(directions) == 1
    assert angle_deg(directions[0], [1.0, 0.0, 0.0]) < 1e-6


def test_map_clusters_add_what_the_segments_lack(rng):
    # segments only along WALL_A's normal (noisy); the planes also give the vertical and WALL_B's normal
    n = 40
    c = rng.uniform(-3, 3, (n, 3))
    d = jittered(rng, WALL_A, n, 1.0)
    lines3d = np.c_[c - 0.3 * d, c + 0.3 * d]
    normals, areas = room_regions(rng)
    clusters = map_clusters(lines3d, normals, areas)
    assert len(clusters) == 3
    assert angle_deg(clusters.directions[0], WALL_A) < 1.0  # the segments' cluster ranks first
    assert np.mean(clusters.labels == 0) > 0.9
    for axis in (FLOOR, WALL_B):
        assert min(angle_deg(x, axis) for x in clusters.directions) < 0.5
    assert clusters.labels.shape == (n,) and clusters.labels.dtype == np.int64


def test_without_planes_it_is_parallel_clusters(rng):
    c = rng.uniform(-3, 3, (30, 3))
    lines3d = np.c_[c, c + np.array([1.0, 0.0, 0.0])]
    clusters = map_clusters(lines3d, np.zeros((0, 3)), np.zeros(0))
    assert len(clusters) == 1 and np.all(clusters.labels == 0)
    empty = map_clusters(np.zeros((0, 6)), np.zeros((0, 3)), np.zeros(0))
    assert len(empty) == 0 and empty.labels.shape == (0,)


def test_bad_input():
    with pytest.raises(InvalidInputError):
        map_clusters(np.zeros((3, 4)), np.zeros((0, 3)), np.zeros(0))


def rotation_about(axis, angle_deg) -> np.ndarray:
    axis = unit(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.radians(angle_deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def test_frame_directions_leave_tilted_planes_out(rng):
    # a room (floor, two walls 1.5 deg off perpendicular) with two large tilted planes (a sofa's back, a
    # leaning board): their creases with the room are no frame direction
    wall_a = unit(WALL_A + np.array([0, 0, np.tan(np.radians(1.5))]))
    tilted = [unit([1.0, 0.0, 1.2]), unit([0.3, 1.0, -0.5])]
    normals = np.vstack([FLOOR, wall_a, WALL_B, *tilted])
    directions, support = frame_directions(normals, np.array([10.0, 4.0, 3.0, 6.0, 5.0]))
    assert len(directions) == 3 and np.all(support > 0)
    for axis in (FLOOR, WALL_A, WALL_B):
        assert min(angle_deg(d, axis) for d in directions) < 1.6
    assert angle_deg(directions[np.argmin([angle_deg(d, FLOOR) for d in directions])], FLOOR) < 1e-6
    # every horizontal direction is exactly perpendicular to the reference (the floor)
    assert np.sort(np.abs(directions @ FLOOR))[:2] == pytest.approx([0.0, 0.0], abs=1e-12)


def test_frame_directions_need_a_perpendicular_pair():
    roof = unit([0.0, np.sin(np.radians(40)), np.cos(np.radians(40))])
    directions, support = frame_directions(np.array([roof, [0.0, 1.0, 0.0]]), np.array([5.0, 5.0]))
    assert directions.shape == (0, 3) and support.shape == (0,)
    one, _ = frame_directions(np.array([FLOOR]), np.array([5.0]))
    assert len(one) == 0


def test_map_clusters_take_the_planes_directions_not_the_biased_segments(rng):
    # a room turned about a tilted axis; its planes are exact, its segments short, noisy and biased: the
    # "vertical" ones lean 10 deg, and far-range clutter in random directions holds most of the length
    R = rotation_about([0.3, -0.5, 0.8], 25.0)
    floor, wall_a, wall_b = R @ FLOOR, R @ WALL_A, R @ WALL_B
    lean = rotation_about(wall_a, 10.0) @ floor
    parts = []
    for axis, count in ((lean, 60), (wall_a, 25), (np.cross(floor, wall_a), 25)):
        c = rng.uniform(-3, 3, (count, 3))
        d = jittered(rng, axis, count, 2.0)
        parts.append(np.c_[c - 0.2 * d, c + 0.2 * d])
    c, d = rng.uniform(-5, 5, (400, 3)), unit(rng.normal(size=(400, 3)))
    parts.append(np.c_[c - 0.25 * d, c + 0.25 * d])
    lines3d = np.concatenate(parts)
    normals = np.vstack([jittered(rng, n, 10, 0.3) for n in (floor, wall_a, wall_b)])
    areas = np.r_[np.full(10, 2.0), np.full(10, 1.0), np.full(10, 0.8)]
    clusters = map_clusters(lines3d, normals, areas)
    assert len(clusters) == 3
    for axis in (floor, wall_a, wall_b):
        assert min(angle_deg(x, axis) for x in clusters.directions) < 1.0
    # the segments alone give the leaning direction, not the vertical
    alone = map_clusters(lines3d, np.zeros((0, 3)), np.zeros(0))
    assert min(angle_deg(x, floor) for x in alone.directions) > 5.0
    assert clusters.labels.shape == (len(lines3d),) and clusters.labels.dtype == np.int64
    assert np.all(clusters.labels >= -1) and np.all(clusters.labels < 3)


def test_map_clusters_keep_segment_clusters_without_a_frame(rng):
    # one dominant plane (the ground of a sweep): no frame; the poles and curbs keep their clusters
    c = rng.uniform(-10, 10, (40, 3))
    pole, curb = unit([0.05, 0.0, 1.0]), unit([1.0, 0.2, 0.0])
    lines3d = np.concatenate([np.c_[c[:20], c[:20] + 2.0 * pole], np.c_[c[20:], c[20:] + 3.0 * curb]])
    clusters = map_clusters(lines3d, jittered(rng, FLOOR, 10, 0.3), np.full(10, 5.0))
    assert len(clusters) == 2
    assert angle_deg(clusters.directions[0], curb) < 0.1 and angle_deg(clusters.directions[1], pole) < 0.1


def test_build_takes_the_directions_of_a_box_rooms_planes(rng):
    # a box room, turned: its walls' points are exact planes; clutter boxes and noise add short segments
    R = rotation_about([0.2, 1.0, 0.4], 30.0)
    n = 6000
    u = rng.uniform(0, 1, (5, n, 2))
    faces = [
        np.c_[4 * u[0, :, 0], 3 * u[0, :, 1], np.zeros(n)],  # floor 4 x 3
        np.c_[4 * u[1, :, 0], np.zeros(n), 2.5 * u[1, :, 1]],
        np.c_[4 * u[2, :, 0], np.full(n, 3.0), 2.5 * u[2, :, 1]],
        np.c_[np.zeros(n), 3 * u[3, :, 0], 2.5 * u[3, :, 1]],
        np.c_[np.full(n, 4.0), 3 * u[4, :, 0], 2.5 * u[4, :, 1]],
    ]
    clutter = rng.uniform([0.5, 0.5, 0.0], [3.5, 2.5, 1.5], (3000, 3))
    points = (np.concatenate([*faces, clutter]) + rng.normal(0, 0.003, (5 * n + 3000, 3))) @ R.T
    line_map = LineMap.build(points)
    assert len(line_map.clusters) == 3
    for axis in R.T:
        assert min(angle_deg(x, axis) for x in line_map.clusters.directions) < 1.0
    plain = LineMap.build(points, MapBuildConfig(plane_directions=False))
    assert len(plain.clusters) > 0


def test_frame_of_a_street_stands_on_its_ground():
    # a road and a sidewalk sloped 4 deg along the street are one ground: the facade, perpendicular to
    # both, is no reference (the frame is the road's normal, the curb and the facade's normal)
    road, facade = unit([0.0, 0.0, 1.0]), unit([0.0, 1.0, 0.0])
    sidewalk = rotation_about([0.0, 1.0, 0.0], 4.0) @ road
    directions, _ = frame_directions(np.array([road, sidewalk, facade]), np.array([100.0, 80.0, 60.0]))
    assert len(directions) == 3
    for axis in (road, facade, [1.0, 0.0, 0.0]):
        assert min(angle_deg(d, axis) for d in directions) < 1e-6


def test_segments_that_show_the_frame_keep_their_clusters(rng):
    # an exact scan: the segments' clusters lie within the paper's 1 deg of the planes' directions; the map
    # keeps them as they are (members and all)
    parts = []
    for axis in (FLOOR, WALL_A, WALL_B):
        c = rng.uniform(-3, 3, (30, 3))
        d = jittered(rng, axis, 30, 0.2)
        parts.append(np.c_[c - 0.5 * d, c + 0.5 * d])
    lines3d = np.concatenate(parts)
    normals, areas = room_regions(rng)
    clusters, alone = (
        map_clusters(lines3d, normals, areas),
        map_clusters(lines3d, np.zeros((0, 3)), np.zeros(0)),
    )
    np.testing.assert_array_equal(clusters.directions, alone.directions)
    np.testing.assert_array_equal(clusters.labels, alone.labels)
