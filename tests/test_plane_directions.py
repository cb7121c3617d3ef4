import numpy as np
import pytest

from linereg.config import PlaneDirectionsConfig
from linereg.errors import InvalidInputError
from linereg.geometry import axis_angle_deg
from linereg.map.plane_directions import dominant_normals, map_clusters, plane_directions


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
