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
