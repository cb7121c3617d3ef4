"""lines3d.extract on a sampled box building with a recessed window: recall, precision of positions, offsets."""

import numpy as np
import pytest

from linereg.config import Lines3DConfig
from linereg.errors import InvalidInputError
from linereg.map.lines3d import extract, merge_collinear
from linereg.map.planes import segment_planes

WINDOW = (3.0, 4.5, 2.0, 3.2, 0.2)  # x0, x1, z0, z1, recess depth


def _rect(rng, origin, a, b, density, hole=None):
    """Uniform samples of the rectangle origin + u a + v b (u, v in [0, 1]), minus a hole in metres."""
    origin, a, b = (np.asarray(v, dtype=np.float64) for v in (origin, a, b))
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    uv = rng.uniform(size=(rng.poisson(density * la * lb), 2))
    if hole is not None:
        (u0, u1), (v0, v1) = hole
        u, v = uv[:, 0] * la, uv[:, 1] * lb
        uv = uv[~((u > u0) & (u < u1) & (v > v0) & (v < v1))]
    return origin + uv[:, :1] * a + uv[:, 1:] * b


def box_building(rng, density=400.0, noise_m=0.003):
    """Returns ((P, 3) points, (24, 6) true edges): a 10 x 8 x 6 m box on a ground plane, one recessed window."""
    length, width, height = 10.0, 8.0, 6.0
    x0, x1, z0, z1, depth = WINDOW
    parts = [
        _rect(rng, (0, 0, 0), (length, 0, 0), (0, 0, height), density, hole=((x0, x1), (z0, z1))),
        _rect(rng, (0, width, 0), (length, 0, 0), (0, 0, height), density),
        _rect(rng, (0, 0, 0), (0, width, 0), (0, 0, height), density),
        _rect(rng, (length, 0, 0), (0, width, 0), (0, 0, height), density),
        _rect(rng, (0, 0, height), (length, 0, 0), (0, width, 0), density),
        _rect(
            rng,
            (-5, -5, 0),
            (length + 10, 0, 0),
            (0, width + 10, 0),
            density,
            ((5, 5 + length), (5, 5 + width)),
        ),
        _rect(rng, (x0, 0, z0), (x1 - x0, 0, 0), (0, depth, 0), density),  # reveals
        _rect(rng, (x0, 0, z1), (x1 - x0, 0, 0), (0, depth, 0), density),
        _rect(rng, (x0, 0, z0), (0, 0, z1 - z0), (0, depth, 0), density),
        _rect(rng, (x1, 0, z0), (0, 0, z1 - z0), (0, depth, 0), density),
        _rect(rng, (x0, depth, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), density),  # glass
    ]
    points = np.concatenate(parts)
    points += rng.normal(0.0, noise_m, points.shape)
    corners = np.array([[0, 0], [length, 0], [length, width], [0, width]], dtype=np.float64)
    edges = []
    for i in range(4):
        p, q = corners[i], corners[(i + 1) % 4]
        edges += [[*p, height, *q, height], [*p, 0, *q, 0], [*p, 0, *p, height]]
    for y in (0.0, depth):
        edges += [
            [x0, y, z0, x1, y, z0],
            [x0, y, z1, x1, y, z1],
            [x0, y, z0, x0, y, z1],
            [x1, y, z0, x1, y, z1],
        ]
    return points, np.array(edges, dtype=np.float64)


def recovered(found, truth, distance_m=0.05, angle_deg=2.0, min_cover=0.8):
    """Returns (E,) bool: at least min_cover of the true edge lies within distance_m of found segments
    that are parallel to it within angle_deg."""
    fp, fq = found[:, :3], found[:, 3:]
    fl = np.linalg.norm(fq - fp, axis=1)
    fd = (fq - fp) / fl[:, None]
    out = []
    for edge in truth:
        p, q = edge[:3], edge[3:]
        d = (q - p) / np.linalg.norm(q - p)
        samples = p + np.outer(np.arange(0.0, np.linalg.norm(q - p), 0.02), d)
        par = np.abs(fd @ d) >= np.cos(np.radians(angle_deg))
        t = np.clip(np.einsum("skj,kj->sk", samples[:, None] - fp[par][None], fd[par]), 0, fl[par])
        near = fp[par][None] + t[..., None] * fd[par][None]
        dist = np.linalg.norm(samples[:, None] - near, axis=2)
        out.append(dist.size > 0 and (dist <= distance_m).any(axis=1).mean() >= min_cover)
    return np.array(out)


@pytest.fixture(scope="module")
def scene():
    return box_building(np.random.default_rng(7))


@pytest.fixture(scope="module")
def segments(scene):
    return extract(scene[0])


def test_recovers_facade_and_window_edges(scene, segments):
    _, edges = scene
    ok = recovered(segments, edges)
    assert ok.mean() >= 0.9, f"missed edges {np.flatnonzero(~ok)}"
    assert ok[:12].all()  # the box outline: creases between large planes


def test_output_shape_and_lengths(segments):
    assert segments.dtype == np.float64 and segments.shape[1] == 6
    lengths = np.linalg.norm(segments[:, 3:] - segments[:, :3], axis=1)
    assert (lengths >= Lines3DConfig().min_length_m - 1e-9).all()
    assert len(segments) < 80  # merged: no swarm of fragments


def test_large_offset_gives_same_segments(scene, segments):
    offset = np.array([5e6, 5e6, 100.0])
    shifted = extract(scene[0] + offset) - np.tile(offset, 2)
    assert abs(len(shifted) - len(segments)) <= 2
    flipped = np.concatenate([shifted[:, 3:], shifted[:, :3]], axis=1)
    gap = np.minimum(
        np.abs(segments[:, None] - shifted[None]).max(axis=2),
        np.abs(segments[:, None] - flipped[None]).max(axis=2),
    ).min(axis=1)
    # float64 shifted coordinates round at 1e-9 m: only near-tie decisions on short clutter may differ
    assert (gap <= 1e-3).mean() >= 0.9
    np.testing.assert_array_equal(recovered(shifted, scene[1]), recovered(segments, scene[1]))


def test_regions_are_the_planes(scene):
    planes = segment_planes(scene[0] - scene[0].min(axis=0))
    big = planes.normals[planes.counts > 5000]
    # ground, roof, 4 walls: every large region is axis-aligned
    assert len(big) == 6
    assert np.allclose(np.abs(big).max(axis=1), 1.0, atol=1e-3)


def test_downsampling_keeps_outline(scene):
    found = extract(scene[0], Lines3DConfig(downsample_m=0.05))
    assert recovered(found, scene[1][:12]).all()


def test_merge_collinear_joins_pieces():
    pieces = np.array([[0, 0, 0, 1, 0, 0], [1.05, 0.01, 0, 2, 0.01, 0], [0, 1, 0, 1, 1, 0]], dtype=np.float64)
    merged = merge_collinear(pieces, np.zeros(3), Lines3DConfig())
    assert len(merged) == 2
    longest = merged[np.argmax(np.linalg.norm(merged[:, 3:] - merged[:, :3], axis=1))]
    assert np.linalg.norm(longest[3:] - longest[:3]) == pytest.approx(2.0, abs=0.02)


def test_degenerate_inputs():
    assert extract(np.zeros((0, 3))).shape == (0, 6)
    rng = np.random.default_rng(0)
    assert extract(rng.normal(size=(200, 3))).shape[1] == 6  # noise: no planes, maybe nothing
    with pytest.raises(InvalidInputError):
        extract(np.zeros((10, 2)))
    with pytest.raises(InvalidInputError):
        extract(np.full((10, 3), np.nan))


def test_found_segments_lie_on_true_edges(scene, segments):
    """Precision: junk (contour pieces of ragged patches, raster staircases) would create false matches."""
    _, edges = scene
    mid = 0.5 * (segments[:, :3] + segments[:, 3:])
    near_box = (mid[:, :2] > -0.5).all(axis=1) & (mid[:, :2] < [10.5, 8.5]).all(
        axis=1
    )  # not the ground's end
    on_edge = recovered(edges, segments[near_box], min_cover=0.8)  # roles swapped: found on a true edge
    assert on_edge.all(), f"{(~on_edge).sum()} of {near_box.sum()} segments off every true edge"


def test_ragged_patch_gives_no_lines():
    """A plane whose outline is ragged (vegetation, clutter, a scan's noisy limit) has no straight edges."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(-4.0, 4.0, size=(60_000, 2))
    angle = np.arctan2(xy[:, 1], xy[:, 0])
    wander = np.cumsum(rng.normal(0.0, 0.05, size=721))  # a random walk round the outline
    wander -= np.linspace(0.0, wander[-1], 721)  # closed
    radius = 2.5 + np.interp(angle, np.linspace(-np.pi, np.pi, 721), wander)
    blob = xy[np.linalg.norm(xy, axis=1) < radius]
    points = np.c_[blob, rng.normal(0.0, 0.003, len(blob))]
    found = extract(points)
    # 27 chords before families of directions were required; 11 (0.3-0.8 m chords of a 2.5 m curve, straight
    # within 1.3 cm) since edges sit half a row spacing beyond the last points
    assert len(found) <= 12, found
