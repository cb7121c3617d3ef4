import numpy as np
import pytest

import linereg


@pytest.fixture
def camera() -> linereg.Camera:
    """The paper's synthetic camera: 640x480, f = 800."""
    return linereg.Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def save_box_map(path) -> None:
    """Saves a small LineMap at ``path``: the twelve edges of a 4 x 3 x 2 m box (for CLI input checks)."""
    from linereg.map.linemap import LineMap

    corners = np.array([[x, y, z] for x in (0, 4) for y in (0, 3) for z in (0, 2)], float)
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    LineMap.from_segments(np.array([np.r_[corners[i], corners[j]] for i, j in pairs])).save(path)


def look_at(centre, target):
    """Returns the (4, 4) cam_from_world of a camera at ``centre`` looking at ``target``, its x axis level
    (z up)."""
    from linereg.geometry import make_cam_from_world

    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return make_cam_from_world(R, -R @ centre)
