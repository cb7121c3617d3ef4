"""A map of copies (``sim.tiled``, ``linereg bench large``): what is copied, and that a repeated map is
answered with its copies as alternatives unless a prior says which copy."""

import numpy as np
import pytest
from test_decide import facade_copies

import linereg
from linereg.geometry import camera_center, rotation_error_deg
from linereg.score import project_clipped
from linereg.sim.synthetic import look_at
from linereg.sim.tiled import tiled_map


def facade_map() -> linereg.LineMap:
    """The facade pattern of ``test_decide.facade_copies`` (its first copy, ground lines leading to it) with
    its walls as surfaces."""
    segments, surfaces = facade_copies()
    return linereg.LineMap.from_segments(segments[: len(segments) // 2], surfaces=surfaces)


def test_the_copies_hold_the_base_map_moved_and_the_middle_one_in_place():
    base = facade_map()
    tiled, offsets = tiled_map(base, 3, gap_m=10.0)
    assert len(tiled) == 9 * len(base) and offsets.shape == (9, 3)
    extent = np.ptp(base.segments.reshape(-1, 3)[:, :2], axis=0).max()
    steps = np.unique(np.round(np.diff(np.unique(offsets[:, 0])), 9))
    assert steps == pytest.approx([extent + 10.0])
    assert np.all(offsets[:, 2] == 0.0)
    middle = int(np.flatnonzero(np.all(offsets == 0.0, axis=1))[0])
    rows = slice(middle * len(base), (middle + 1) * len(base))
    assert np.array_equal(tiled.segments[rows], base.segments)
    assert np.array_equal(tiled.clusters.labels[rows], base.clusters.labels)
    assert np.array_equal(tiled.clusters.directions, base.clusters.directions)
    for k in range(9):  # every copy is the base moved by its offset, surfaces too
        block = tiled.segments[k * len(base) : (k + 1) * len(base)]
        np.testing.assert_allclose(block, base.segments + np.tile(offsets[k], 2), atol=1e-9)
    assert tiled.surfaces is not None and base.surfaces is not None
    assert len(tiled.surfaces) == 9 * len(base.surfaces)
    nv = len(base.surfaces.vertices)
    np.testing.assert_allclose(
        tiled.surfaces.world_vertices()[4 * nv : 5 * nv],
        base.surfaces.world_vertices() + offsets[4],
        atol=1e-4,  # float32 vertices
    )
    assert tiled.metadata["map_id"] != base.metadata["map_id"]
    with pytest.raises(ValueError, match="n >= 1"):
        tiled_map(base, 0)


def test_a_repeated_map_is_ambiguous_without_a_prior_and_answered_with_one():
    base = facade_map()
    tiled, _ = tiled_map(base, 2)
    camera = linereg.Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    truth = look_at(np.array([2.0, 0.0, 1.5]), np.array([20.0, 0.0, 1.5]))
    lines2d, _ = project_clipped(base.segments, camera, truth, 0.05, None)
    alone = linereg.localize_segments(lines2d, base, camera)
    assert alone.success, alone.reason
    anywhere = linereg.localize_segments(lines2d, tiled, camera)
    assert not anywhere.success and anywhere.reason.startswith("ambiguous")
    assert anywhere.alternatives is not None and len(anywhere.alternatives) >= 1
    prior = linereg.Prior(position=camera_center(truth) + np.array([3.0, -2.0, 0.0]), radius_m=8.0)
    near = linereg.localize_segments(lines2d, tiled, camera, prior=prior)
    assert near.success, near.reason
    assert rotation_error_deg(near.cam_from_world[:3, :3], truth[:3, :3]) < 1.0
    assert np.linalg.norm(camera_center(near.cam_from_world) - camera_center(truth)) < 0.3
