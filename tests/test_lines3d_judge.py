"""The judge of ``bench lines3d --real`` (``bench.lines3d_judge``): the ceiling of a single sweep."""

import numpy as np
import pytest

from linereg.bench.lines3d_judge import ceiling
from linereg.camera import Camera
from linereg.sim.sweep import SweepConfig, spinning_sweep, street

CAMERA = Camera(fx=500, fy=500, cx=320, cy=240, width=640, height=480)
LOOKING_ALONG_X = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
# at the sensor, looking down the road: the building's near corner (x 10 m, y 2 m) runs up the image at
# u = 220, and its foot along the road's side at v = 325
IMAGE = np.array([[220.0, 130.0, 220.0, 320.0], [5.0, 325.0, 215.0, 325.0]])


@pytest.mark.parametrize("rings, elevation_deg", [(64, (-24.8, 2.0)), (32, (-30.67, 10.67))])
def test_a_sparse_sweeps_ceiling_finds_the_corner_a_dense_one_does(rings, elevation_deg):
    """The building's corner is a depth edge in the photo whether 64 lasers (0.43 deg apart) or 32 (1.33
    deg: ~12 px at this focal length) swept it: the sparse sweep's splats close the gap between its rings
    (it had scored 0.0, no depth edge between the stripes of its rings)."""
    config = SweepConfig(rings=rings, elevation_deg=elevation_deg)
    points, _, _ = spinning_sweep(*street(), np.random.default_rng(0), config)
    found = ceiling(IMAGE, points, CAMERA, LOOKING_ALONG_X)
    corner_share = 190.0 / (190.0 + 210.0)
    assert found["ceiling"] >= 0.8 * corner_share
