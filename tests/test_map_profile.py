import numpy as np
import pytest

from linereg.config import Lines3DConfig, MapProfileConfig
from linereg.errors import InvalidInputError
from linereg.map.profile import lines3d_config_for, point_spacing_m


def grid_points(spacing_m: float, size_m: float = 1.0) -> np.ndarray:
    """Returns a flat square of points on a grid of ``spacing_m``."""
    g = np.arange(0.0, size_m, spacing_m)
    x, y = np.meshgrid(g, g)
    return np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]


def test_spacing_of_a_grid():
    assert point_spacing_m(grid_points(0.01)) == pytest.approx(0.01, rel=1e-6)
    assert point_spacing_m(grid_points(0.05, 5.0)) == pytest.approx(0.05, rel=1e-6)
    assert point_spacing_m(np.zeros((1, 3))) == 0.0


def test_dense_clouds_keep_small_structure_sparse_ones_keep_the_defaults():
    dense = lines3d_config_for(grid_points(0.01))  # RGB-D: 1 cm
    assert dense.min_length_m == pytest.approx(0.15) and dense.min_region_area_m2 == pytest.approx(0.03)
    mid = lines3d_config_for(grid_points(0.02))
    assert mid.min_length_m == pytest.approx(0.24) and mid.min_region_area_m2 == pytest.approx(0.09)
    sparse = lines3d_config_for(grid_points(0.05, 5.0))  # a building scan
    defaults = Lines3DConfig()
    assert sparse.min_length_m == defaults.min_length_m
    assert sparse.min_region_area_m2 == defaults.min_region_area_m2
    base = Lines3DConfig(voxel_m=0.2)
    assert lines3d_config_for(grid_points(0.01), base).voxel_m == 0.2  # everything else is kept


def test_profile_follows_its_config():
    wider = MapProfileConfig(min_length_range_m=(0.1, 0.3), min_area_range_m2=(0.01, 0.1))
    dense = lines3d_config_for(grid_points(0.01), config=wider)
    assert dense.min_length_m == pytest.approx(0.12) and dense.min_region_area_m2 == pytest.approx(0.0225)


def test_bad_input():
    with pytest.raises(InvalidInputError):
        lines3d_config_for(np.zeros((4, 2)))
