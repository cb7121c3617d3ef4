import numpy as np
import pytest

from linereg.config import Lines3DConfig, MapProfileConfig
from linereg.errors import InvalidInputError
from linereg.map.profile import lines3d_config_for, point_spacing_m, profile_cloud


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
    with pytest.raises(InvalidInputError, match=r"beyond.*\(point 3\)"):  # a unit gone wrong
        lines3d_config_for(np.r_[grid_points(0.1), [[1e300, 0.0, 0.0]]][-4:])


def test_a_cloud_thinned_at_random_is_even_and_a_scanners_falls_off_with_range():
    rng = np.random.default_rng(0)
    # a room's floor and two walls, points drawn at random with the same density everywhere (a fused
    # cloud thinned to a few percent): its nearest neighbours alone spread as a scanner's do
    floor = np.c_[rng.uniform(0, 4, 6000), rng.uniform(0, 3, 6000), np.zeros(6000)]
    wall = np.c_[rng.uniform(0, 4, 5000), np.zeros(5000), rng.uniform(0, 2.5, 5000)]
    side = np.c_[np.zeros(4000), rng.uniform(0, 3, 4000), rng.uniform(0, 2.5, 4000)]
    room = np.r_[floor, wall, side]
    profile = profile_cloud(room)
    nearest_spread = profile.spacing_p90_m / profile.spacing_p10_m
    assert nearest_spread > MapProfileConfig().uneven_ratio  # the test a density spread replaced
    assert profile.density_spread < 2.5 and profile.kind in ("rgbd", "map")
    # the ground round a scanner (placed far from the frame's origin, so no rings are looked for about
    # it): as many points per metre of range near it as far away, the density falling as 1 / r^2
    r = np.exp(rng.uniform(np.log(1.0), np.log(30.0), 20000))
    azimuth = rng.uniform(0, 2 * np.pi, 20000)
    ground = np.c_[50 + r * np.cos(azimuth), 50 + r * np.sin(azimuth), rng.normal(0, 0.002, 20000)]
    scanned = profile_cloud(ground)
    assert scanned.density_spread > 5 and scanned.kind == "scan"
