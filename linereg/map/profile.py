"""Map-building parameters from the cloud itself: a dense RGB-D room and a sparse LiDAR street need different
smallest regions and segments.

``Lines3DConfig``'s defaults (smallest region 0.1 m^2, shortest segment 0.3 m) suit scans of buildings. In a
dense indoor cloud (Kinect: ~1 cm point spacing) the structure an image shows is furniture, door frames and
shelves: faces of 0.03-0.1 m^2 and edges of 0.15-0.3 m, which those defaults drop, so that few of the
image's lines have a map line at all (docs/measurements.md). Both limits are therefore tied to the median
point spacing ``s`` (``MapProfileConfig``): the shortest segment ``12 s`` and the smallest region
``(15 s)^2`` (a region must span some 15 points a side to give straight contours), clipped to
[0.15, 0.3] m and [0.03, 0.1] m^2 -- a cloud of 2.5 cm spacing or coarser keeps the defaults.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig, MapProfileConfig
from .lines3d import check_points


def point_spacing_m(points: np.ndarray, seed: int = 0, config: MapProfileConfig | None = None) -> float:
    """Returns the median nearest-neighbour distance (m) of (P, 3) points, estimated on a sample of
    ``config.spacing_sample`` of them (0.0 for fewer than two points)."""
    config = config or MapProfileConfig()
    points = check_points(points)
    if len(points) < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    sample = points[rng.choice(len(points), min(config.spacing_sample, len(points)), replace=False)]
    distances, _ = cKDTree(points).query(sample, k=2)
    return float(np.median(distances[:, 1]))


def lines3d_config_for(
    points: np.ndarray, base: Lines3DConfig | None = None, config: MapProfileConfig | None = None
) -> Lines3DConfig:
    """Returns ``base`` (default ``Lines3DConfig()``) with ``min_length_m`` and ``min_region_area_m2`` set
    from the point spacing of (P, 3) points (see the module docstring); the rest is unchanged."""
    base = base or Lines3DConfig()
    config = config or MapProfileConfig()
    spacing = point_spacing_m(points, config=config)
    if spacing <= 0.0:
        return base
    length = float(np.clip(config.length_spacings * spacing, *config.min_length_range_m))
    area = float(np.clip((config.area_spacings * spacing) ** 2, *config.min_area_range_m2))
    return replace(base, min_length_m=length, min_region_area_m2=area)
