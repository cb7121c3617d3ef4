"""Edges found per point (``map.point_edges``) on generated RGB-D-like clouds: a slab over a floor, sampled
on a 1 cm grid with depth noise and a fused cloud's second layer."""

import numpy as np
import pytest

from linereg.config import MapBuildConfig, PointEdgesConfig
from linereg.map import kinds
from linereg.map.build import extract_map
from linereg.map.point_edges import point_edges

SPACING = 0.01
NOISE = 0.002
AXES = np.eye(3)


def face(origin, u, v, spacing=SPACING):
    """Returns points of the parallelogram origin + a u + b v (a, b in [0, 1]) on a grid ``spacing`` apart."""
    origin, u, v = (np.asarray(x, dtype=float) for x in (origin, u, v))
    a = np.arange(0.0, 1.0 + 1e-9, spacing / np.linalg.norm(u))
    b = np.arange(0.0, 1.0 + 1e-9, spacing / np.linalg.norm(v))
    aa, bb = np.meshgrid(a, b, indexing="ij")
    return origin + aa.reshape(-1, 1) * u + bb.reshape(-1, 1) * v


def box_faces(lo, hi):
    """Returns points on the six faces of the axis-aligned box lo..hi."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    out = []
    for k in range(3):
        i, j = [m for m in range(3) if m != k]
        for at in (lo[k], hi[k]):
            origin = lo.copy()
            origin[k] = at
            out.append(face(origin, AXES[i] * size[i], AXES[j] * size[j]))
    return np.concatenate(out)


def box_edges(lo, hi, min_length):
    """Returns (12 or fewer, 6) edges of the box at least min_length long."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    edges = []
    for a in range(8):
        for b in range(a + 1, 8):
            if (corners[a] != corners[b]).sum() == 1 and np.linalg.norm(
                corners[a] - corners[b]
            ) >= min_length:
                edges.append(np.r_[corners[a], corners[b]])
    return np.array(edges)


SLAB = ([0.7, 0.8, 0.5], [1.3, 1.2, 0.54])  # a table top 0.6 x 0.4 m, 4 cm thick, over the floor


def room(seed=0, layered=False):
    """Returns (points, known edges): a 2 x 2 m floor and the slab, with depth noise; ``layered``: the
    floor twice, 1.5 cm apart (a fused cloud's misregistered frames)."""
    rng = np.random.default_rng(seed)
    floor = face([0, 0, 0], [2, 0, 0], [0, 2, 0])
    parts = [floor, box_faces(*SLAB)]
    if layered:
        parts.append(floor[rng.random(len(floor)) < 0.5] + [0, 0, 0.015])
    points = np.concatenate(parts)
    points = points + rng.normal(0.0, NOISE, points.shape)
    floor_edges = np.array(
        [[0, 0, 0, 2, 0, 0], [2, 0, 0, 2, 2, 0], [2, 2, 0, 0, 2, 0], [0, 2, 0, 0, 0, 0]], dtype=float
    )
    return points, np.concatenate([box_edges(*SLAB, 0.15), floor_edges])


def distance_to_line(points, segment):
    p0, p1 = segment[:3], segment[3:]
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    rel = points - p0
    return np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)


def found_along(found, truth, tol_m=0.015, angle_deg=3.0):
    """Returns the share of the true edge's length covered by found segments along it."""
    d = (truth[3:] - truth[:3]) / np.linalg.norm(truth[3:] - truth[:3])
    length = np.linalg.norm(truth[3:] - truth[:3])
    covered = np.zeros(101, dtype=bool)
    for seg in found:
        s = (seg[3:] - seg[:3]) / np.linalg.norm(seg[3:] - seg[:3])
        if abs(s @ d) < np.cos(np.radians(angle_deg)):
            continue
        if distance_to_line(seg.reshape(2, 3), truth).max() > tol_m:
            continue
        t = np.sort((seg.reshape(2, 3) - truth[:3]) @ d) / length
        covered |= (np.linspace(0, 1, 101) >= t[0]) & (np.linspace(0, 1, 101) <= t[1])
    return covered.mean()


@pytest.mark.parametrize("layered", [False, True])
def test_the_slab_and_floor_edges_are_found_and_nothing_else(layered):
    points, truths = room(layered=layered)
    found = point_edges(points, AXES, SPACING, NOISE, 0.15)
    for truth in truths:
        assert found_along(found, truth) >= 0.7, truth
    # every found segment lies along a true edge (no line inside the floor's noise or its second layer)
    for seg in found:
        ends = seg.reshape(2, 3)
        assert min(distance_to_line(ends, t).max() for t in truths) < 0.03, seg


def test_a_flat_noisy_sheet_gives_no_line_inside_it():
    rng = np.random.default_rng(1)
    sheet = face([0, 0, 0], [1.5, 0, 0], [0, 1.5, 0])
    sheet = sheet + rng.normal(0.0, NOISE, sheet.shape)
    found = point_edges(sheet, AXES, SPACING, NOISE, 0.15)
    inside = [s for s in found if (np.abs(s.reshape(2, 3)[:, :2] - 0.75) < 0.6).all()]
    assert not inside


POST = ([0.3, 0.3, 0.7], [0.33, 0.33, 1.3])  # 3 x 3 cm, 0.6 m tall


def test_the_four_edges_of_a_thin_post_are_four_lines():
    rng = np.random.default_rng(3)
    post = box_faces(*POST)
    points = np.concatenate([room()[0], post + rng.normal(0.0, NOISE, post.shape)])
    found = point_edges(points, AXES, SPACING, NOISE, 0.15)
    for truth in box_edges(*POST, 0.5):
        assert found_along(found, truth) >= 0.7, truth


def test_the_map_of_an_rgbd_fusion_holds_point_edges():
    points, truths = room()
    rng = np.random.default_rng(2)
    wall = face([0, 2, 0], [2, 0, 0], [0, 0, 1.5])  # a room's directions come from its floor and walls
    extra = np.concatenate([wall, box_faces(*POST)])  # the post: small structure
    # off the cloud's origin: a floor through it would look like one ring of a sweep there
    shift = np.array([1.3, 0.7, 1.5])
    points = np.concatenate([points, extra + rng.normal(0.0, NOISE, extra.shape)]) - shift
    walls = [[0, 2, 0, 2, 2, 0], [0, 2, 0, 0, 2, 1.5], [2, 2, 0, 2, 2, 1.5]]
    truths = np.concatenate([truths, walls, box_edges(*POST, 0.5)])
    content = extract_map(points)
    assert content.profile.kind == "rgbd"
    edges = content.segments[content.kinds == kinds.POINT_EDGE] + np.tile(shift, 2)
    assert len(edges)
    for seg in edges:
        assert min(distance_to_line(seg.reshape(2, 3), t).max() for t in truths) < 0.03, seg
    off = extract_map(points, MapBuildConfig(point_edges=False))
    assert not (off.kinds == kinds.POINT_EDGE).any()
    # what the planar regions give is kept; point edges only add lines they do not run along
    assert len(content.segments) == len(off.segments) + len(edges)
    assert np.allclose(content.segments[: len(off.segments)], off.segments)


def test_degenerate_input_gives_no_edges():
    assert point_edges(np.zeros((0, 3)), AXES, SPACING, NOISE, 0.15).shape == (0, 6)
    assert point_edges(np.zeros((5, 3)), AXES, SPACING, NOISE, 0.15).shape == (0, 6)
    line = np.c_[np.linspace(0, 1, 200), np.zeros(200), np.zeros(200)]
    assert point_edges(line, np.zeros((0, 3)), SPACING, NOISE, 0.15).shape == (0, 6)
    # a single line of points: every direction, no crash
    found = point_edges(line, AXES, SPACING, NOISE, 0.15, PointEdgesConfig())
    assert found.shape[1] == 6


def scattered(origin, u, v, per_m2, rng):
    """Returns points drawn at random, ``per_m2`` to a square metre, on the parallelogram origin + a u + b v."""
    origin, u, v = (np.asarray(x, dtype=float) for x in (origin, u, v))
    n = int(per_m2 * np.linalg.norm(np.cross(u, v)))
    a, b = rng.random((2, n, 1))
    return origin + a * u + b * v


def test_a_room_sampled_at_random_is_an_rgbd_fusion_with_point_edges():
    # points drawn at random (a cloud thinned, or fused without a grid): their nearest neighbours' distances
    # spread as a scanner's do (by range); the density does not, and the room is profiled as the RGB-D cloud
    # it is, with its point edges
    rng = np.random.default_rng(4)
    lo, hi = np.array(SLAB[0]), np.array(SLAB[1])
    size = hi - lo
    parts = [
        scattered([0, 0, 0], [2, 0, 0], [0, 2, 0], 1200, rng),
        scattered([0, 2, 0], [2, 0, 0], [0, 0, 1.5], 1200, rng),
    ]
    for k in range(3):
        i, j = [m for m in range(3) if m != k]
        for at in (lo[k], hi[k]):
            origin = lo.copy()
            origin[k] = at
            parts.append(scattered(origin, AXES[i] * size[i], AXES[j] * size[j], 1200, rng))
    points = np.concatenate(parts)
    points = points + rng.normal(0.0, NOISE, points.shape) - [1.3, 0.7, 1.5]  # off the origin, as above
    content = extract_map(points)
    assert content.profile.spacing_p90_m > 4 * content.profile.spacing_p10_m
    assert content.profile.kind == "rgbd"
    edges = content.segments[content.kinds == kinds.POINT_EDGE] + np.tile([1.3, 0.7, 1.5], 2)
    assert len(edges)
    # the slab's edges (a table top 4 cm thick: its faces, three spacings apart, also give some lines
    # across them where a point's neighbours reach the other face)
    along = [found_along(edges, truth, tol_m=0.03) for truth in box_edges(*SLAB, 0.15)]
    assert sum(a >= 0.5 for a in along) >= 3, along
