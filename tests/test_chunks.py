"""Chunks of nearby map segments: the first cut of what a view sees, never dropping what the exact tests
keep (the occlusion test's pyramid test, the score's projection and clipping), and the search's filter
of map points no camera centre of a box can see inside the image."""

import numpy as np
from conftest import look_at
from plain_visibility import chunks_in_view, in_pyramid

from linereg.camera import Camera
from linereg.chunks import Chunks, kept_chunks
from linereg.score import project_clipped
from linereg.search import in_swept_view

CAMERA = Camera(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)


def maps(rng):
    """Yields ((3,) extent, (20000, 6) segments): random segments over a city-wide box and a thin wall."""
    for extent in ((400.0, 400.0, 30.0), (20.0, 0.01, 5.0)):
        starts = rng.uniform(0.0, 1.0, (20000, 3)) * extent
        yield np.array(extent), np.c_[starts, starts + rng.normal(0.0, 2.0, (20000, 3))]


def test_the_chunk_cut_keeps_every_segment_the_pyramid_test_keeps(rng):
    """``Chunks.rows_in_view`` never drops a segment that the pyramid test of ``visible_parts``' sampling keeps, over random
    poses of a map spread wide (a city) and thin (a wall), and it drops most chunks of the wide one;
    ``index`` keeps its order."""
    near = 0.05
    for extent, segments in maps(rng):
        chunks = Chunks.build(segments)
        index = rng.permutation(len(segments))[:15000]
        cut = []
        for _ in range(20):
            centre = rng.uniform(0.0, 1.0, 3) * extent
            cam = look_at(centre, centre + rng.normal(size=3))
            a = segments[:, :3] @ cam[:3, :3].T + cam[:3, 3]
            b = segments[:, 3:] @ cam[:3, :3].T + cam[:3, 3]
            kept = np.flatnonzero(in_pyramid(a, b, CAMERA, near))
            rows = chunks.rows_in_view(CAMERA, cam, near, None)
            assert np.isin(kept, rows).all()
            sub = chunks.rows_in_view(CAMERA, cam, near, index)
            np.testing.assert_array_equal(sub, index[np.isin(index, rows)])
            np.testing.assert_array_equal(chunks.subset(index).rows_in_view(CAMERA, cam, near, None),
                                          np.flatnonzero(np.isin(index, rows)))  # fmt: skip
            cut.append(1.0 - len(rows) / len(segments))
        if extent[1] > 1.0:
            assert np.median(cut) > 0.5  # a view of the wide map reaches few of its chunks
    assert len(Chunks.build(np.zeros((0, 6))).rows_in_view(CAMERA, np.eye(4), near, None)) == 0
    assert Chunks.of_map(np.zeros((100, 6))) is None  # a small map is not cut


def test_the_projection_with_chunks_is_the_projection_without(rng):
    """``project_clipped`` with the segments' chunks returns the same arrays as without, and the compiled
    per-chunk test keeps exactly the chunks the plain numpy rule keeps (up to rounding at a face: none
    here)."""
    near = 0.05
    intrinsics = np.array([CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy])
    for extent, segments in maps(rng):
        chunks = Chunks.build(segments)
        visible = rng.uniform(size=len(segments)) > 0.1
        for _ in range(20):
            centre = rng.uniform(0.0, 1.0, 3) * extent
            cam = look_at(centre, centre + rng.normal(size=3))
            plain = project_clipped(segments, CAMERA, cam, near, visible)
            cut = project_clipped(segments, CAMERA, cam, near, visible, chunks)
            np.testing.assert_array_equal(plain[0], cut[0])
            np.testing.assert_array_equal(plain[1], cut[1])
            kept = kept_chunks(chunks.centre, chunks.half, cam, intrinsics, 640.0, 480.0, near)
            np.testing.assert_array_equal(kept, chunks_in_view(chunks.centre, chunks.half, CAMERA, cam, near))
            np.testing.assert_array_equal(
                np.flatnonzero(kept[chunks.of]), chunks.rows_in_view(CAMERA, cam, near, None)
            )


def test_the_swept_view_keeps_every_point_a_centre_of_the_box_sees(rng):
    """``search.in_swept_view``: a point that some camera centre inside the box sees along the direction of
    one of the image points (the rays the search votes along) is kept; most of a city-wide spread of
    points, seen from a 40 m box, is not."""
    pixels = rng.uniform([0.0, 0.0], [640.0, 480.0], (300, 2))
    normalized = (pixels - [CAMERA.cx, CAMERA.cy]) / [CAMERA.fx, CAMERA.fy]
    for _ in range(10):
        R = look_at(np.zeros(3), rng.normal(size=3))[:3, :3]
        lo = rng.uniform(-100.0, 100.0, 3)
        hi = lo + rng.uniform(1.0, 80.0, 3)
        # points on the rays of the image points from centres in the box
        centres = rng.uniform(lo, hi, (2000, 3))
        k = rng.integers(0, len(normalized), 2000)
        d = np.c_[normalized[k], np.ones(2000)] @ R  # world directions, R^T (x, y, 1)
        seen = centres + rng.uniform(0.01, 500.0, (2000, 1)) * d
        assert in_swept_view(seen, normalized, R, [(lo, hi)]).all()
        assert in_swept_view(seen, normalized, R, [(lo - 5000.0, lo - 4000.0), (lo, hi)]).all()  # any box
        # on the cone's faces: along the outermost image points' rays from the box's corners
        outer = normalized[[np.argmin(normalized[:, 0]), np.argmax(normalized[:, 0]),
                            np.argmin(normalized[:, 1]), np.argmax(normalized[:, 1])]]  # fmt: skip
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1).reshape(8, 3)
        edges = (corners[:, None] + 300.0 * (np.c_[outer, np.ones(4)] @ R)[None]).reshape(-1, 3)
        assert in_swept_view(edges, normalized, R, [(lo, hi)]).all()
        anywhere = rng.uniform(-1000.0, 1000.0, (20000, 3))
        assert in_swept_view(anywhere, normalized, R, [(lo, hi)]).mean() < 0.5
